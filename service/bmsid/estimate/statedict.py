"""Restoring a stage's arrays from a checkpoint: shape-checked, dtype kept."""

from __future__ import annotations

from typing import Any

import numpy as np


def load_arrays(obj: object, st: dict[str, Any], names: tuple[str, ...], stage: str) -> None:
    """Set ``obj.<name>`` from ``st[name]`` for each name, checking shape and keeping dtype."""
    for k in names:
        cur = np.asarray(getattr(obj, k))
        arr = np.asarray(st[k], dtype=cur.dtype)
        if arr.shape != cur.shape:
            raise ValueError(
                f"checkpoint field {stage}/{k} has shape {arr.shape}, need {cur.shape}"
            )
        setattr(obj, k, arr.copy())
