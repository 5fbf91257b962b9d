"""Atomic checkpoints of the estimator state: ``.npz`` of arrays plus one JSON header.

Written as: temp file in the same directory -> flush -> fsync -> rename over the old one ->
fsync the directory, so a crash (kill -9, power loss) leaves either the old or the new
checkpoint, never a torn one. Restored only when pack id, cell count and config hash match.
"""

from __future__ import annotations

import json
import logging
import os
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

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
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with tmp.open("wb") as fh:
            np.savez(fh, **arrays)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


@dataclass(frozen=True)
class Checkpoint:
    header: dict[str, Any]
    state: dict[str, Any]

    @property
    def extra(self) -> dict[str, Any]:
        extra: dict[str, Any] = self.header.get("extra", {})
        return extra


def load_checkpoint(path: Path, key: CheckpointKey) -> Checkpoint | None:
    """The checkpoint at ``path`` if it exists, is readable and matches ``key``; else None
    (the reason is logged: a fresh start is always possible)."""
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
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        log.warning("checkpoint %s unreadable (%s): starting fresh", path, exc)
        return None
    for k, v in scalars.items():
        _insert(state, k, v)
    want = {"pack_id": key.pack_id, "n_cells": key.n_cells, "config_hash": key.config_hash}
    got = {k: header.get(k) for k in want}
    if header.get("format") != FORMAT_VERSION or got != want:
        log.warning("checkpoint %s is for %s, not %s: starting fresh", path, got, want)
        return None
    return Checkpoint(header=header, state=state)
