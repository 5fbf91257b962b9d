"""Validated configuration models (pydantic): the cell description and, later, daemon settings."""
