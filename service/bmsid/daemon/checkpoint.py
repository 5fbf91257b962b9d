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
from dataclasses import dataclass, field
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
    #: what the hash covers, part by part (``Settings.config_parts``): saved in the header so
    #: that a mismatch can name the part that changed; not compared itself
    parts: dict[str, str] = field(default_factory=dict, compare=False)


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
        "config": key.parts,
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
    differs = mismatch(header, key)
    if differs is not None:
        log.warning("checkpoint %s is for another setup (%s): starting fresh", path, differs)
        return None
    return Checkpoint(header=header, state=state)


def _part_change(part: str, saved: str, now: str) -> str:
    """One changed part of ``Settings.config_parts`` in words (hashes are never shown)."""
    if part == "variant":
        return f"estimator.variant {saved!r}, not {now!r}"
    if part == "cell":  # "<name> <hash>"
        was, name = saved.rsplit(" ", 1)[0], now.rsplit(" ", 1)[0]
        return (
            f"cell config {was!r}, not {name!r}" if was != name else f"cell config {name!r} changed"
        )
    return f"estimator.{part} changed"


def mismatch(header: dict[str, Any], key: CheckpointKey) -> str | None:
    """What differs between a checkpoint's header and ``key``, for one log line; None: none."""
    found = []
    if header.get("format") != FORMAT_VERSION:
        found.append(f"format {header.get('format')!r}, not {FORMAT_VERSION}")
    for name in ("pack_id", "n_cells"):
        if header.get(name) != getattr(key, name):
            found.append(f"{name} {header.get(name)!r}, not {getattr(key, name)!r}")
    if header.get("config_hash") != key.config_hash:
        saved = header.get("config")
        saved = saved if isinstance(saved, dict) else {}
        changed = [
            _part_change(k, str(saved[k]), v)
            for k, v in key.parts.items()
            if k in saved and saved[k] != v
        ]
        if changed:
            found += changed
        elif not found:  # a checkpoint from before the header named the parts
            found.append("estimator.variant, estimator.tuning or the cell config changed")
    return "; ".join(found) if found else None


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
