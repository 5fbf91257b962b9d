"""Fixtures of the estimator's tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from bmsid.estimate import jit


@pytest.fixture
def restore_kernel() -> Iterator[None]:
    """Put back the process's kernel choice (``jit.select``) that a test changes."""
    before = jit.MODE
    yield
    jit.restore(before)
