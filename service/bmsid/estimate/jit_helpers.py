"""Scalar functions that compiled kernels (``jit.Kernel``) call: plain Python, compiled into
the kernels that call them.

numba compiles a kernel's source only if every global it calls is compiled too. A helper is
marked ``@helper`` (it stays the plain Python function: the kernel's source still runs
uncompiled, as its reference does); a kernel's ``warm`` calls ``register()`` before its first
call, which hands every marked helper to ``numba.extending.register_jitable`` (numba is imported
only then: it stays optional). Keep a kernel's helpers in the kernel's own file: numba's cache
is invalidated by a change to the compiled function's file only, not to the files it calls.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

_HELPERS: list[Callable[..., Any]] = []
_REGISTERED: set[int] = set()


def helper(fn: F) -> F:
    """Mark a scalar function that kernels call (see the module docstring)."""
    _HELPERS.append(fn)
    return fn


def register() -> None:
    """Make every marked helper callable from compiled code (once each per process)."""
    from numba.extending import register_jitable  # noqa: PLC0415 (numba is optional)

    for fn in _HELPERS:
        if id(fn) not in _REGISTERED:
            register_jitable(fn)
            _REGISTERED.add(id(fn))
