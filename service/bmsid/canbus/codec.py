"""Physical <-> raw conversion of DBC signals that saturates instead of wrapping around.

cantools' own ``encode`` raises on out-of-range values (``strict=True``) or wraps them
(``strict=False``); bmsid instead clamps to the declared [minimum, maximum], reports that it did,
and writes the signal's "not available" raw value for NaN (see ``dbcgen``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import cantools


@dataclass(frozen=True, slots=True)
class RawRange:
    """Valid raw values of a signal and its not-available value (None when it has none)."""

    lo: int
    hi: int
    sna: int | None


def raw_range(sig: cantools.database.can.Signal) -> RawRange:
    n = int(sig.length)
    bit_lo, bit_hi = (-(1 << (n - 1)), (1 << (n - 1)) - 1) if sig.is_signed else (0, (1 << n) - 1)
    scale, offset = float(sig.scale), float(sig.offset)
    lo, hi = bit_lo, bit_hi
    if sig.minimum is not None and sig.maximum is not None:
        a = (float(sig.minimum) - offset) / scale
        b = (float(sig.maximum) - offset) / scale
        a, b = min(a, b), max(a, b)
        lo = max(bit_lo, math.ceil(a - 1e-6))
        hi = min(bit_hi, math.floor(b + 1e-6))
    sna: int | None = None
    if sig.is_signed and bit_lo < lo:
        sna = bit_lo
    elif not sig.is_signed and bit_hi > hi:
        sna = bit_hi
    return RawRange(lo, hi, sna)


def to_raw(sig: cantools.database.can.Signal, value: float) -> tuple[int, bool]:
    """Raw value for ``value`` (physical, the DBC's unit) and whether it saturated.

    NaN becomes the not-available value (or raises ``ValueError`` when the signal has none).
    """
    r = raw_range(sig)
    if math.isnan(value):
        if r.sna is None:
            raise ValueError(f"signal {sig.name} has no not-available value for NaN")
        return r.sna, False
    x = (value - float(sig.offset)) / float(sig.scale)
    if x < r.lo - 0.5:
        return r.lo, True
    if x > r.hi + 0.5:
        return r.hi, True
    return min(max(round(x), r.lo), r.hi), False


def to_physical(sig: cantools.database.can.Signal, raw: int) -> float:
    """Physical value of ``raw``; NaN for the not-available value or anything outside the range."""
    r = raw_range(sig)
    if not (r.lo <= raw <= r.hi):
        return math.nan
    return raw * float(sig.scale) + float(sig.offset)


def encode_saturating(
    message: cantools.database.can.Message, values: Mapping[str, float]
) -> tuple[bytes, list[str]]:
    """Encode physical ``values`` of one message; returns the data and the saturated signals.

    Signals of ``message`` missing from ``values`` are sent as their not-available value, or 0 /
    the nearest valid value when they have none. For a multiplexed message, ``values`` must hold
    the multiplexer; only signals present under its value are encoded.
    """
    raw: dict[str, int] = {}
    saturated: list[str] = []
    for sig in message.signals:
        if sig.name in values:
            r, sat = to_raw(sig, float(values[sig.name]))
            if sat:
                saturated.append(sig.name)
        else:
            rr = raw_range(sig)
            r = rr.sna if rr.sna is not None else min(max(0, rr.lo), rr.hi)
        raw[sig.name] = r
    if message.is_multiplexed():
        raw = _select_mux(message, raw)
    data = message.encode(raw, scaling=False, padding=False, strict=False)
    return bytes(data), saturated


def _select_mux(message: cantools.database.can.Message, raw: dict[str, int]) -> dict[str, int]:
    keep: dict[str, int] = {}
    for sig in message.signals:
        mux = sig.multiplexer_signal
        if mux is None or (sig.multiplexer_ids and raw.get(mux) in sig.multiplexer_ids):
            keep[sig.name] = raw[sig.name]
    return keep


def decode_raw(message: cantools.database.can.Message, data: bytes) -> dict[str, float]:
    """Decode ``data`` to physical values, NaN for not-available/out-of-range raw values.

    Raises cantools' ``DecodeError`` on a wrong length or an unknown multiplexer value.
    """
    raw = message.decode(data, decode_choices=False, scaling=False)
    if not isinstance(raw, dict):  # only container messages decode to a list
        raise TypeError(f"{message.name} is a container message")
    out: dict[str, float] = {}
    for name, value in raw.items():
        sig = message.get_signal_by_name(name)
        out[name] = to_physical(sig, int(value))  # type: ignore[arg-type]
    return out
