"""The checks a record gets before it is identified: one run's, and each input's of a fleet.

``bmsid identify`` of one file prints the findings and stops at the first error; a fleet task
turns that error into its input's failure and keeps the warnings in the input's metrics.json.
Before, a fleet ran no checks: a record in minutes, one with a flipped current sign and one in
milliseconds all came out ``ok``, the flipped one ranked as the healthiest cell (a sweep).
Pure over the record's head (``plausibility.check_head_samples``); nothing is printed here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from bmsid.config.cell import CellConfig, paper_cell
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.gates import GateConfig
from bmsid.offline import plausibility
from bmsid.offline.plausibility import Finding
from bmsid.offline.record_cell import accepted_readings, capacity_as_recorded, cell_from_record
from bmsid.samples import SampleBlock


@dataclass(frozen=True)
class CheckOptions:
    """What the user gave, as the checks need it (picklable: a fleet's workers get it)."""

    cell_config_given: bool = False
    capacity_given: bool = False  # --capacity-ah
    soc0: float | None = None
    charge_positive: bool = False
    ocv_coeffs: tuple[float, ...] | None = None
    #: the time column as read (``--columns t_s=SOURCE*SCALE``): the fixes the messages name
    t_source: str = "t_s"
    t_scale: float = 1.0

    def time_fix(self, factor: float = 0.001) -> str:
        """The option that would give t_s in seconds (the file's unit x ``factor``)."""
        return f"--columns t_s={self.t_source}*{factor * self.t_scale:g}"


@dataclass(frozen=True)
class CheckedRecord:
    """The cell to run with (a capacity read off the record when nothing else gives one), its
    note (None: the given cell), and the findings (the first error is to be raised)."""

    cell: CellConfig
    note: str | None
    findings: list[Finding]

    @property
    def error(self) -> Finding | None:
        return plausibility.first_error(self.findings)


def check_record(
    head: SampleBlock, cell: CellConfig, opts: CheckOptions, tuning: EstimatorTuning,
    gates: GateConfig | None = None,
) -> CheckedRecord:  # fmt: skip
    """Plausibility of a record's ``head`` (its first samples) for ``cell``: time unit, the
    capacity, the current sign, excitation, a start still relaxing (``plausibility``)."""
    t, i, v = head.t_s, head.current_A, head.cell_voltages_V
    findings = plausibility.check_time_unit(t, i, cell.capacity_Ah, opts.time_fix(), tuning.gap_s)
    if not plausibility.first_error(findings):
        findings += plausibility.check_sample_period(t, i, tuning.id_period_s)
    note = None
    record_chemistry = None
    pseudo_text: str | None = None
    capacity_from: Literal["cell", "option", "record"] = "cell"
    given = opts.capacity_given or opts.cell_config_given
    if not plausibility.first_error(findings):
        # minutes or hours compress the record whatever capacity is given: read on the given
        # cell's OCV curve where there is one
        est = capacity_as_recorded(t, i, v, tuning.gap_s, opts.ocv_coeffs, cell if given else None)
        findings += plausibility.check_time_compressed(
            t, i, est, (gates or GateConfig()).i_max_C, opts.time_fix
        )
        if given and not plausibility.first_error(findings):
            source = "--capacity-ah" if opts.capacity_given else "the cell config"
            findings += plausibility.check_capacity_given(est, cell.capacity_Ah, source)
            if opts.cell_config_given:
                findings += plausibility.check_cell_fit(est, cell.chemistry, cell.name)
    if opts.capacity_given:
        capacity_from = "option"
    elif not opts.cell_config_given and not plausibility.first_error(findings):
        found = cell_from_record(t, i, v, tuning.gap_s, opts.ocv_coeffs, gates)
        if found is not None:
            cell, note, capacity_from = found.cell, found.note, "record"
            record_chemistry, pseudo_text = found.record_chemistry, found.pseudo_ocv_text
    if not opts.cell_config_given:
        if capacity_from == "cell" and not plausibility.first_error(findings):
            findings.append(plausibility.capacity_not_read(cell.capacity_Ah))
        assumed = plausibility.assumed_cell(
            cell.name, cell.capacity_Ah, capacity_from=capacity_from,
            chemistry=paper_cell().chemistry, record_chemistry=record_chemistry,
            ocv_from_record=pseudo_text,
        )  # fmt: skip
        findings.insert(0, assumed)
    if not plausibility.first_error(findings):
        # what the run's gates refuse (a current glitch, a dead channel) is no evidence here
        i_ok, v = accepted_readings(t, i, v, cell, tuning.gap_s, gates)
        i = plausibility.held(i_ok, 0.0)
        findings += plausibility.check_consistency(
            t, i, v, capacity_Ah=cell.capacity_Ah,
            capacity_assumed=not opts.cell_config_given and capacity_from == "cell",
            soc0=opts.soc0, charge_positive=opts.charge_positive,
            excitation_C=tuning.excitation_C, excitation_window_s=tuning.excitation_window_s,
            gap_s=tuning.gap_s,
        )  # fmt: skip
        if opts.soc0 is None and cell.soc_init.policy == "ocv_at_rest":
            r0 = cell.initial_parameters().R0_ohm
            findings += plausibility.check_start_relaxation(
                t, i, v, cell.capacity_Ah, r0, cell.soc_init.rest_current_C
            )
        findings += plausibility.check_ocv_temperature(head.temperature_C, cell.ocv.temperature_C)
    return CheckedRecord(cell, note, findings)
