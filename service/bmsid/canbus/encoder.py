"""Estimates -> bmsid's output frames (per-cell parameters multiplexed by cell index, pack frames).

Classic CAN: four 8-byte frames per cell (``CellR``, ``CellTau``, ``CellState``,
``CellCapacity``); CAN FD: one 48-byte ``CellParamsFD`` frame per cell. The values sent are the
``CELL_FIELDS`` entries with a ``can_signal`` (those with ``can_classic=False`` only in CAN FD).
Values outside a signal's range are clamped and their bits set in the cell's ``Saturated`` mask
(``dbcgen.SATURATION_BITS``; ``CellState``'s mask has room for bits 0-10, ``CellCapacity``'s and
the FD frame's for all); NaN is sent as the signal's not-available value. Per pack, on both
buses: ``PackSummary`` (R0 spread, weakest cell, health bits 1..16) and ``PackState`` (the
current-sensor offset, every health bit). Ids are 29-bit by default, keeping bmsid out of the
11-bit space most BMSs use; ``extended_id=False`` selects the ``*_11bit`` twins.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import can
import cantools
import numpy as np

from bmsid.canbus.codec import decode_raw, encode_saturating
from bmsid.canbus.dbcgen import SATURATION_BITS
from bmsid.canbus.mapping import DEFAULT_DBC_PATH, load_dbc
from bmsid.errors import UserError
from bmsid.estimate import fields
from bmsid.estimate.types import Estimates

#: DBC signal name -> key of :meth:`ParameterEncoder.decode` (SI units in the key): the cell
#: fields' signals as ``CELL_FIELDS`` names them (their MQTT keys), then the frames' own signals.
DECODED_NAMES: dict[str, str] = {
    "CellIndex": "cell",
    **{s.can_signal: s.out_key for s in fields.CELL_FIELDS if s.can_signal is not None},
    "Quality": "quality",
    "Saturated": "saturated_mask",
    "R0Min": "R0_min_ohm",
    "R0Mean": "R0_mean_ohm",
    "R0Max": "R0_max_ohm",
    "WeakestCell": "weakest_cell",
    "Health": "health",
    "CurrentOffset": "current_offset_A",
}

CLASSIC_PAGES = ("CellR", "CellTau", "CellState", "CellCapacity")
FD_PAGE = "CellParamsFD"
PACK = "PackSummary"
#: The pack frames of one output round, in order (:meth:`ParameterEncoder.pack_frames`).
PACK_PAGES = (PACK, "PackState")
MAX_QUALITY_CLASSIC = 7
#: ``PackSummary`` carries health bits 1..8 in ``Health`` (4 bits) and bit 16 in ``Diverged``;
#: ``PackState``'s ``Health`` carries every bit its DBC signal has room for (16 in bmsid.dbc).
MAX_SUMMARY_HEALTH = 31
_HEALTH_LOW_BITS = 15
_HEALTH_DIVERGED_SHIFT = 4


class ParameterEncoder:
    """Build bmsid's output frames from :class:`Estimates` and decode them back."""

    def __init__(
        self, dbc_path: str | Path | None = None, *, extended_id: bool = True, fd: bool = False
    ) -> None:
        path = Path(dbc_path) if dbc_path is not None else DEFAULT_DBC_PATH
        db = load_dbc(str(path))
        suffix = "" if extended_id else "_11bit"
        try:
            self._pages = [
                db.get_message_by_name(f"BMSID_{p}{suffix}")
                for p in ((FD_PAGE,) if fd else CLASSIC_PAGES)
            ]
            self._pack = db.get_message_by_name(f"BMSID_{PACK}{suffix}")
            self._pack_state = db.get_message_by_name(f"BMSID_{PACK_PAGES[1]}{suffix}")
        except KeyError as exc:
            raise UserError(f"output DBC {path} lacks message {exc}") from None
        # an output DBC older than PackState's Health signal: the frame goes out without it
        state_health = next((s for s in self._pack_state.signals if s.name == "Health"), None)
        #: the health bits ``PackState`` carries (0 when its DBC has no ``Health`` signal)
        self.state_health_mask = 0 if state_health is None else (1 << state_health.length) - 1
        self.extended_id = extended_id
        self.fd = fd
        #: per page: (DBC signal, Estimates field) of the cell fields it carries
        self._page_fields = self._cell_signals(path)
        self._by_key = {
            (int(m.frame_id), bool(m.is_extended_frame)): m
            for m in db.messages
            if m.name.startswith("BMSID_") and m.senders == ["BMSID"]
        }

    def _cell_signals(self, path: Path) -> list[list[tuple[str, str]]]:
        """Map every ``CELL_FIELDS`` entry with a CAN signal (read now, at construction) to the
        page carrying it; a signal that no page has is an error, never a silent drop."""
        wanted = [
            (s.can_signal, s.name)
            for s in fields.CELL_FIELDS
            if s.can_signal is not None and (self.fd or s.can_classic)
        ]
        names = [{sig.name for sig in page.signals} for page in self._pages]
        missing = [sig for sig, _ in wanted if not any(sig in n for n in names)]
        if missing:
            pages = ", ".join(page.name for page in self._pages)
            raise UserError(
                f"output DBC {path} lacks cell signal(s) {', '.join(missing)} in {pages} "
                "(CELL_FIELDS in estimate/fields.py sends them)"
            )
        return [[(sig, name) for sig, name in wanted if sig in n] for n in names]

    def _frame(self, msg: cantools.database.can.Message, data: bytes, t_s: float) -> can.Message:
        return can.Message(
            timestamp=t_s,
            arbitration_id=int(msg.frame_id),
            is_extended_id=bool(msg.is_extended_frame),
            is_fd=bool(msg.is_fd),
            data=data,
        )

    def cell_frames(self, est: Estimates, cells: Sequence[int]) -> list[can.Message]:
        """Per-cell parameter frames for ``cells`` (indices into ``est``), muxed by cell index."""
        frames: list[can.Message] = []
        for i in cells:
            if not 0 <= i < est.n_cells:
                raise ValueError(f"cell {i} not in estimates of {est.n_cells} cells")
            mask = 0
            encoded: list[tuple[cantools.database.can.Message, dict[str, float]]] = []
            for page, page_fields in zip(self._pages, self._page_fields, strict=True):
                page_values = {sig: float(est.cells[name][i]) for sig, name in page_fields}
                page_values["CellIndex"] = float(i)
                _, saturated = encode_saturating(page, page_values)
                for s in saturated:
                    mask |= 1 << SATURATION_BITS[s]
                encoded.append((page, page_values))
            quality = float(min(max(int(est.quality[i]), 0), MAX_QUALITY_CLASSIC))
            for page, page_values in encoded:
                for sig in page.signals:
                    if sig.name == "Saturated":  # the bits this page's mask has room for
                        page_values["Saturated"] = float(mask & ((1 << sig.length) - 1))
                    elif sig.name == "Quality":
                        page_values["Quality"] = quality
                data, _ = encode_saturating(page, page_values)
                frames.append(self._frame(page, data, est.t_s))
        return frames

    def pack_frames(self, est: Estimates, health: int = 0) -> list[can.Message]:
        """The pack frames of an output round (:data:`PACK_PAGES`): :meth:`pack_frame`, then
        ``PackState``: the current-sensor offset (A; the mean of the cells' finite
        ``current_offset_A``, one value per pack, else not available) and every ``health`` bit
        (bits beyond :attr:`state_health_mask` left out, not clamped)."""
        off = np.asarray(est.cells["current_offset_A"], dtype=np.float64)
        off = off[np.isfinite(off)]
        values = {"CurrentOffset": float(off.mean()) if off.size else math.nan}
        if self.state_health_mask:
            values["Health"] = float(max(int(health), 0) & self.state_health_mask)
        _, saturated = encode_saturating(self._pack_state, values)
        values["Saturated"] = 1.0 if saturated else 0.0
        data, _ = encode_saturating(self._pack_state, values)
        return [self.pack_frame(est, health), self._frame(self._pack_state, data, est.t_s)]

    def pack_frame(self, est: Estimates, health: int = 0) -> can.Message:
        """Pack summary: min/mean/max R0 (ohm) over cells with a finite R0, weakest cell = the
        largest R0, ``health`` bits (``publish.payloads.HEALTH_*``: bits 1..8 in ``Health``,
        bit 16 in ``Diverged``; higher bits have no room in the frame and are left out, not
        clamped, which would set every bit: ``PackState`` carries them)."""
        r0 = np.asarray(est.R0_ohm, dtype=np.float64)
        finite = np.isfinite(r0)
        h = max(int(health), 0) & MAX_SUMMARY_HEALTH
        values: dict[str, float] = {
            "Health": float(h & _HEALTH_LOW_BITS),
            "Diverged": float(h >> _HEALTH_DIVERGED_SHIFT),
        }
        if finite.any():
            rf = r0[finite]
            values |= {
                "R0Min": float(rf.min()),
                "R0Mean": float(rf.mean()),
                "R0Max": float(rf.max()),
                "WeakestCell": float(np.flatnonzero(finite)[int(np.argmax(rf))]),
            }
        else:
            values |= dict.fromkeys(("R0Min", "R0Mean", "R0Max", "WeakestCell"), math.nan)
        _, saturated = encode_saturating(self._pack, values)
        values["Saturated"] = 1.0 if saturated else 0.0
        data, _ = encode_saturating(self._pack, values)
        return self._frame(self._pack, data, est.t_s)

    def decode(self, msg: can.Message) -> dict[str, float] | None:
        """Decode one of bmsid's output frames (keys in :data:`DECODED_NAMES`, NaN = not
        available; ``PackSummary``'s ``health`` with ``Diverged`` folded in as bit 16,
        ``PackState``'s every bit); None for any other or malformed frame."""
        if msg.is_error_frame or msg.is_remote_frame:
            return None
        m = self._by_key.get((msg.arbitration_id, bool(msg.is_extended_id)))
        if m is None or len(msg.data) != m.length:
            return None
        try:
            phys = decode_raw(m, bytes(msg.data))
        except Exception:  # malformed frame (unknown mux value): not ours to decode
            return None
        if "Diverged" in phys:
            diverged = phys.pop("Diverged")
            phys["Health"] += diverged * (1 << _HEALTH_DIVERGED_SHIFT)
        return {DECODED_NAMES.get(k, k): v for k, v in phys.items()}
