"""Exceptions a user can act on. The CLI prints them as one line, without a traceback."""


class UserError(Exception):
    """Bad input or configuration, with a message that says what and where."""
