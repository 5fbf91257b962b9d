"""The SOC observer's checkpoint (``ObserverState.state_dict`` and ``load_state_dict``): what
``observer.py`` keeps between ticks, and what a checkpoint written by an older version lacks.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from bmsid.estimate import rest_anchor as rest
from bmsid.estimate.hysteresis_map import restore_covariance
from bmsid.estimate.statedict import load_arrays

if TYPE_CHECKING:
    from bmsid.estimate.observer import ObserverState

_ARRAYS = ("P", "_g", "_qz", "_learn_gate", "_q_As", "_i_load_A", "_tau_load_s", "_anchored")
_SCALARS = ("b", "_qb", "_since_s", "_rest_s", "_rest_i_A", "_noise_sd_A", "_i_prev_A")
_ARRAYS_MAP = ("d", "_knots")


def save(obs: ObserverState) -> dict[str, Any]:
    """The observer's part of the bank's checkpoint."""
    return {
        **{k.lstrip("_"): np.array(getattr(obs, k)) for k in _ARRAYS},
        **{k.lstrip("_"): float(getattr(obs, k)) for k in _SCALARS},
        **{k.lstrip("_"): np.array(getattr(obs, k)) for k in _ARRAYS_MAP},
        "seen_s": obs._seen_s,
        "lh": obs._lh.copy(),
        "reanchor": obs._reanchor,
        "capacity": obs.capacity.state_dict(),
        "start_relaxation": obs._relax.state_dict(),
    }


def load(obs: ObserverState, saved: dict[str, Any] | None) -> None:
    """Restore ``obs`` from its part of a checkpoint; None (a checkpoint from before the
    observer): its SOC, widened at the next tick."""
    if saved is None:
        obs._widen = True
        return
    renamed = {k: saved[k.lstrip("_")] for k in _ARRAYS}
    # another map (none before it was learnt, another table): the map from its prior; no
    # hysteresis error (before it): its prior
    renamed["P"], same = restore_covariance(obs.P, saved, obs.n, obs._knots)
    if same:
        obs.d = np.asarray(saved["d"], dtype=np.float64).copy()
    load_arrays(obs, renamed, _ARRAYS, "state/observer")
    absent = {"_rest_i_A": rest.NO_REST_A, "_noise_sd_A": 0.0, "_i_prev_A": math.nan}  # older
    for k in _SCALARS:
        setattr(obs, k, float(saved.get(k.lstrip("_"), absent.get(k, math.nan))))
    obs._rest_limit_A = obs._h_rest_A = rest.rest_limit(obs._rest_base_A, obs._noise_sd_A)
    obs._seen_s = float(saved.get("seen_s", obs.tun.unconverged_wait_s))  # older: has run
    obs._lh = np.asarray(saved.get("lh", np.zeros(obs.n)), dtype=np.float64).copy()
    obs._reanchor = bool(saved["reanchor"])
    obs.capacity.load_state_dict(saved["capacity"])
    if "start_relaxation" in saved:  # absent from checkpoints before it: nothing watched
        obs._relax.load_state_dict(saved["start_relaxation"])
    obs._use_capacity()
