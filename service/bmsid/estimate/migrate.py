"""Older estimator-bank states brought to the present format (``bank.STATE_FORMAT``).

Format 1 (bmsid 0.1, before the engine was split into stages) kept every array of every
estimator in one flat namespace; format 2 nests one ``state_dict`` per stage. The numbers are
the same, so a format-1 checkpoint restores exactly; anything else is refused with one line.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: format-2 key -> format-1 key, per stage.
_TICKS = {
    "bin_v": "_bin_v", "bin_vn": "_bin_vn", "t_raw": "_t_raw", "i_raw": "_i_raw",
    "t_tick": "_t_tick", "i_tick": "_i_tick", "bin_i": "_bin_i", "bin_n": "_bin_n",
    "i_mean": "_i_mean", "i_var": "_i_var", "dt_nom": "_dt_nom",
}  # fmt: skip
_STATE = {"z": "z", "h": "h", "soc_init_method": "soc_init_method"}
_COMMON = {
    "x1": "x1", "x2": "x2", "tau1": "tau1", "tau2": "tau2", "lam": "lam", "sig_e": "sig_e",
    "arx_err": "arx_err",
}  # fmt: skip
_FUSION = {**_COMMON, "theta": "theta", "P": "P", "fused": "fused"}
_ARX = {
    **_COMMON, "R0": "R0", "R1": "R1", "R2": "R2", "theta_arx": "theta_arx", "P_arx": "P_arx",
    "ue_hist": "_ue_hist", "i_hist": "_i_hist", "arx_ok": "arx_ok", "T_arx": "T_arx",
    "hist_n": "_hist_n",
}  # fmt: skip

#: each variant's parameter stage in format 1 (which of the flat arrays it used).
_V1_PARAMS = {"non-hy-affrls": _ARX, "hy-affrls": _ARX, "hy-affrls-lpso": _FUSION}


def _pick(st: dict[str, Any], names: dict[str, str]) -> dict[str, Any]:
    return {new: st[old] for new, old in names.items()}


def upgrade_state(st: dict[str, Any]) -> dict[str, Any]:
    """``st`` in format 2 (a format-2 state is returned as is); ValueError if unknown."""
    fmt = st.get("format")
    if fmt == 2:
        return st
    if fmt is not None or "z" not in st or "meta" not in st:
        raise ValueError(f"estimator state format {fmt!r} is not one this version reads")
    try:
        names = _V1_PARAMS[st["meta"]["variant"]]
        params = _pick(st, names)
        if names is _FUSION:
            params["schedule"] = {
                "next_swarm": st["_next_swarm"],
                "swarm_count": st["_swarm_count"],
            }
            params["buffer"] = dict(st["buf"])
        n = int(st["meta"]["n_cells"])
        state = _pick(st, _STATE)
        state["pending"] = np.full(n, st["_t_raw"] is None)
        ticks = _pick(st, _TICKS)
        ticks["steps_i"] = ticks["steps_dt"] = np.zeros(0)
    except KeyError as exc:
        raise ValueError(f"format-1 estimator state lacks {exc}") from None
    return {
        "format": 2,
        "meta": st["meta"],
        "ticks": ticks,
        "state": state,
        "params": params,
        "counters": st.get("counters", {}),
    }
