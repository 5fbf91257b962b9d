"""The CAN output schedule: the pack summary and a slice of the cells every period, under a
bus-share cap.

Pure part: :func:`frames_budget` / :class:`CellCycler` decide how many and which cells go out
in a round; the daemon sends them with ``canbus.bus.send_frames`` (ENOBUFS retried).
"""

from __future__ import annotations

import math

from bmsid.canbus.encoder import PACK_PAGES, ParameterEncoder
from bmsid.config.settings import CanSettings
from bmsid.errors import UserError

#: Worst-case bit stuffing adds one bit per 4 after the first 5 of the stuffed region (~20 %).
STUFFING = 1.2


def frame_bits(data_bytes: int, extended_id: bool) -> int:
    """Worst-case bits of one classic data frame on the wire, including interframe space."""
    overhead = 67 if extended_id else 47  # SOF..EOF incl. CRC, ACK; + 3 bits IFS below
    return math.ceil((overhead + 8 * data_bytes) * STUFFING) + 3


def frames_budget(bitrate_bps: int, share: float, period_s: float, bits_per_frame: int) -> int:
    """Frames bmsid may send per period without exceeding ``share`` of the bus."""
    return int(share * bitrate_bps * period_s // bits_per_frame)


class CellCycler:
    """Round-robin over ``n_cells``: each call returns the next ``per_round`` cell indices."""

    def __init__(self, n_cells: int, per_round: int) -> None:
        if per_round < 1:
            raise ValueError("per_round must be >= 1")
        self.n_cells = n_cells
        self.per_round = min(per_round, n_cells)
        self._next = 0

    def next_round(self) -> list[int]:
        cells = [(self._next + k) % self.n_cells for k in range(self.per_round)]
        self._next = (self._next + self.per_round) % self.n_cells
        return cells


def plan_output(
    n_cells: int,
    frames_per_cell: int,
    bits_per_frame: int,
    bitrate_bps: int,
    share: float,
    period_s: float,
) -> CellCycler:
    """The cell cycler for the configured cap; UserError when not even one cell fits."""
    budget = frames_budget(bitrate_bps, share, period_s, bits_per_frame)
    per_round = (budget - len(PACK_PAGES)) // frames_per_cell  # the pack frames come first
    if per_round < 1:
        raise UserError(
            f"can.max_bus_share={share} of {bitrate_bps} bit/s allows {budget} frames per "
            f"{period_s} s; the pack frames and one cell need "
            f"{len(PACK_PAGES) + frames_per_cell}: raise "
            "can.output_period_s or can.max_bus_share"
        )
    return CellCycler(n_cells, per_round)


def output_encoder(can: CanSettings) -> ParameterEncoder:
    """The parameter frames' encoder of ``can.output_dbc`` (None: bmsid's DBC); UserError
    naming the field when that file is missing or lacks bmsid's messages (``check-config``
    passed a missing one that ``run`` then refused as "dbc: file not found")."""
    try:
        return ParameterEncoder(
            can.output_dbc, extended_id=can.output_extended_id, fd=can.output_fd
        )
    except UserError as exc:
        if can.output_dbc is None:
            raise
        raise UserError(f"can.output_dbc: {exc}") from None
