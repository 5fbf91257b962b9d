"""Atomic checkpoints of the estimator state: ``.npz`` of arrays plus one JSON header.

Written as: temp file in the same directory -> flush -> fsync -> rename over the old one ->
fsync the directory (:func:`~bmsid.daemon.statedir.atomic_write`), so a crash (kill -9, power
loss) leaves either the old or the new checkpoint, never a torn one. Restored only when pack
id, cell count and config hash match.

A checkpoint that cannot be read (empty, truncated, not an ``.npz``) is quarantined beside
itself (:func:`~bmsid.daemon.statedir.quarantine`) and the daemon starts fresh: measured
before, a zero-byte file crashed every start. What it holds is checked against a fresh
bank's state by :func:`state_problem` (same keys and shapes; finite wherever a fresh state is
finite), on load and before every save: a NaN state restored unchecked published ``null`` for
ever and was checkpointed again.
"""

from __future__ import annotations

import json
import logging
import time
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bmsid.daemon.statedir import atomic_write, quarantine

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
_HEADER_KEY = "__header__"
_SCALARS_KEY = "__scalars__"


@dataclass(frozen=True)
class CheckpointKey:
    """What a checkpoint must match to be restored."""

    pack_id: str
    n_cells: int
    config_hash: str


def _split(
    state: dict[str, Any], prefix: str, arrays: dict[str, Any], scalars: dict[str, Any]
) -> None:
    for k, v in state.items():
        key = f"{prefix}{k}"
        if "/" in str(k):
            raise ValueError(f"state key {key!r} contains '/'")
        if isinstance(v, dict):
            _split(v, key + "/", arrays, scalars)
        elif isinstance(v, np.ndarray):
            arrays[key] = v
        elif isinstance(v, np.generic):
            scalars[key] = v.item()
        elif v is None or isinstance(v, bool | int | float | str):
            scalars[key] = v
        else:
            raise TypeError(f"state value {key} has unsupported type {type(v).__name__}")


def _insert(out: dict[str, Any], key: str, value: Any) -> None:
    *parents, leaf = key.split("/")
    node = out
    for p in parents:
        node = node.setdefault(p, {})
    node[leaf] = value


def save_checkpoint(
    path: Path, key: CheckpointKey, state: dict[str, Any], extra: dict[str, Any] | None = None
) -> None:
    """Atomically write ``state`` (nested dicts of arrays and plain scalars) to ``path``."""
    arrays: dict[str, Any] = {}
    scalars: dict[str, Any] = {}
    _split(state, "", arrays, scalars)
    header = {
        "format": FORMAT_VERSION,
        "pack_id": key.pack_id,
        "n_cells": key.n_cells,
        "config_hash": key.config_hash,
        "saved_unix_s": time.time(),
        "extra": extra or {},
    }
    arrays[_HEADER_KEY] = np.array(json.dumps(header))
    arrays[_SCALARS_KEY] = np.array(json.dumps(scalars, allow_nan=True))
    atomic_write(path, lambda fh: np.savez(fh, **arrays))


@dataclass(frozen=True)
class Checkpoint:
    header: dict[str, Any]
    state: dict[str, Any]

    @property
    def extra(self) -> dict[str, Any]:
        extra: dict[str, Any] = self.header.get("extra", {})
        return extra


#: What reading a damaged ``.npz`` raises: empty file (EOFError), truncated or foreign
#: (BadZipFile, ValueError, zlib.error), a missing member (KeyError), a bad header (JSON).
_UNREADABLE = (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zlib.error)


def load_checkpoint(path: Path, key: CheckpointKey) -> Checkpoint | None:
    """The checkpoint at ``path`` if it exists, is readable and matches ``key``; else None
    (the reason is logged: a fresh start is always possible). An unreadable one is
    quarantined; one of another pack or config is left alone (the next checkpoint replaces
    it: restoring the old config before then keeps it)."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as npz:
            header = json.loads(str(npz[_HEADER_KEY]))
            scalars = json.loads(str(npz[_SCALARS_KEY]))
            state: dict[str, Any] = {}
            for name in npz.files:
                if name not in (_HEADER_KEY, _SCALARS_KEY):
                    _insert(state, name, npz[name])
        if not isinstance(header, dict) or not isinstance(scalars, dict):
            raise ValueError("header or scalars are not JSON objects")
    except _UNREADABLE as exc:
        quarantine(path, "checkpoint", f"unreadable: {type(exc).__name__}: {exc}")
        return None
    for k, v in scalars.items():
        _insert(state, k, v)
    want = {"pack_id": key.pack_id, "n_cells": key.n_cells, "config_hash": key.config_hash}
    got = {k: header.get(k) for k in want}
    if header.get("format") != FORMAT_VERSION or got != want:
        log.warning("checkpoint %s is for %s, not %s: starting fresh", path, got, want)
        return None
    return Checkpoint(header=header, state=state)


def _leaves(state: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in state.items():
        if isinstance(v, dict):
            out |= _leaves(v, f"{prefix}{k}/")
        else:
            out[f"{prefix}{k}"] = v
    return out


def _nonfinite(v: Any) -> bool:
    if isinstance(v, np.ndarray):
        return v.dtype.kind in "fc" and not bool(np.all(np.isfinite(v)))
    return isinstance(v, float) and not np.isfinite(v)


def _same_shape(got: tuple[int, ...], ref: tuple[int, ...]) -> bool:
    # A dimension empty in a fresh state is a buffer that grows (current steps seen so far).
    return len(got) == len(ref) and all(r in (0, g) for g, r in zip(got, ref, strict=True))


def state_problem(state: dict[str, Any], reference: dict[str, Any]) -> str | None:
    """Why ``state`` is not a usable estimator state, or None.

    ``reference`` is a fresh bank's ``state_dict()`` of the same config: ``state`` must have
    its keys, array shapes (a dimension empty there may have any length) and kinds, and be
    finite wherever the fresh state is. A fresh state's NaN marks "not yet" (no anchor, no
    previous time), so those may stay NaN; a NaN anywhere else (a parameter, a covariance, a
    SOC) means the state is lost, and restoring or saving it would publish ``null`` for ever.
    """
    got, want = _leaves(state), _leaves(reference)
    if got.keys() != want.keys():
        diff = sorted(got.keys() ^ want.keys())
        more = ", ..." if len(diff) > 3 else ""
        return f"inconsistent: keys differ ({', '.join(diff[:3])}{more})"
    for k, ref in want.items():
        v = got[k]
        if isinstance(ref, np.ndarray):
            if not isinstance(v, np.ndarray) or not _same_shape(v.shape, ref.shape):
                shape = getattr(v, "shape", type(v).__name__)
                return f"inconsistent: {k} is {shape}, not {ref.shape}"
            if ref.dtype.kind in "fc" and v.dtype.kind not in "fciub":
                return f"inconsistent: {k} holds {v.dtype}, not numbers"
        if _nonfinite(v) and not _nonfinite(ref):
            return f"non-finite values in {k}"
    return None
