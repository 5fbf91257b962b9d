"""The cell configuration: everything bmsid must know about a cell type before identifying it.

One pydantic model, stored as TOML or JSON (``load_cell_config`` / ``save_cell_config``), written by
``bmsid fit-ocv`` and read by ``bmsid identify`` and the daemon.
"""

from __future__ import annotations

import itertools
import json
import math
import tomllib
from pathlib import Path
from typing import Annotated, Literal, Self

import numpy as np
import tomli_w
from pydantic import BaseModel, ConfigDict, Field, model_validator

from bmsid.model.ocv import OcvModel, end_segment, eval_ocv

Coeffs = Annotated[list[float], Field(min_length=6, max_length=6)]
#: Largest |dU| (V) of an OCV correction table: a table corrects what Eq. 4's six terms miss of
#: the same cell's curve (6-18 mV on the C/20 tests measured, tens of mV at a staging step);
#: 0.2 V is a tenth of a Li-ion cell's whole OCV span and catches a table in mV or from another
#: cell.
MAX_CORRECTION_V = 0.2
#: An LFP plateau (``CellConfig.hysteresis_law`` of an unlabelled cell): the mean OCV within
#: this span (V) over SOC 20-80 %, its median in this range (V); as ``offline.plausibility``
#: reads a record's discharge (LFP: a plateau within 0.15 V, full at rest 3.40-3.65 V).
LFP_PLATEAU_SPAN_V = 0.15
LFP_PLATEAU_V = (3.1, 3.5)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class OcvCurve(_Strict):
    """OCV(z) of the paper's Eq. 4 per branch, in volts, with z the SOC as a fraction in (0, 1).

    ``U(z) = a0 + a1 z + a2 z^2 + a3/z + a4 ln z + a5 ln(1-z)``. ``mean`` is the curve the model
    uses (Eq. 9); ``charge`` and ``discharge`` are kept for reporting and for M(z). ``soc_min`` and
    ``soc_max`` bound the range where the Eq. 4 fit is valid (it is singular at 0 and 1).

    ``v_empty_V`` / ``v_full_V`` (optional): the cell's rested voltage (V) at SOC 0 / 1 as the OCV
    test measured it. When given, the mean curve continues beyond ``soc_min`` / ``soc_max`` by a
    monotone cubic that is C1 with Eq. 4 at the join and reaches that voltage at the end
    (``bmsid.model.ocv.end_segment``), and SOC may run to 0 / 1. When absent, z is clamped to
    [soc_min, soc_max] as before. ``discharge``/``charge`` are never extended (reporting only).

    ``correction_soc`` / ``correction_V`` (optional, written by ``fit-ocv`` when Eq. 4 misses
    the test's mean OCV by more than its noise): a table dU(z) added to ``mean`` on
    [soc_min, soc_max], knots as SOC fractions (strictly increasing in [0, 1], at least 3) and
    values in V (|dU| <= 0.2 V). The mean curve is then Eq. 4 + dU, a C1 piecewise cubic through
    the knots (Fritsch-Carlson slopes, ``bmsid.model.ocv``), held at its end values beyond them;
    the end segments join it, and it must increase over [soc_min, soc_max]. Without the table
    the curve is Eq. 4 exactly as before.
    """

    mean: Coeffs
    charge: Coeffs | None = None
    discharge: Coeffs | None = None
    soc_min: float = Field(0.01, gt=0.0, lt=0.5)
    soc_max: float = Field(0.99, gt=0.5, lt=1.0)
    v_empty_V: float | None = Field(None, gt=0.0, lt=10.0)
    v_full_V: float | None = Field(None, gt=0.0, lt=10.0)
    correction_soc: list[float] | None = None
    correction_V: list[float] | None = None
    temperature_C: float | None = Field(None, ge=-60.0, le=120.0)
    """The OCV test's temperature, degC (``fit-ocv``: the median of the test files' temperature
    column, or ``--temperature-c``); None: not known. ``identify`` warns when a record runs
    more than 10 K away from it: the OCV moves with temperature (its entropic coefficient),
    and a PyBaMM NMC cell read through its 25 degC curve at -10 and 50 degC ran 2-5 SOC points
    off with a SOC std of 0.03-1.4 points and nothing said."""

    @model_validator(mode="after")
    def _ends(self) -> Self:
        if self.correction_soc is not None or self.correction_V is not None:
            self._check_correction()
            return self
        for v_end, join, end in (
            (self.v_empty_V, self.soc_min, 0.0),
            (self.v_full_V, self.soc_max, 1.0),
        ):
            if v_end is not None:
                end_segment(self.mean, join, end, v_end)  # ValueError: no monotone C1 segment
        return self

    def _check_correction(self) -> None:
        zs, dus = self.correction_soc, self.correction_V
        if zs is None or dus is None:
            raise ValueError("ocv.correction_soc and ocv.correction_V must be given together")
        if len(zs) != len(dus) or len(zs) < 3:
            raise ValueError(
                "ocv.correction_soc and ocv.correction_V need the same length, at least 3 "
                f"(got {len(zs)} and {len(dus)})"
            )
        if not all(math.isfinite(z) and 0.0 <= z <= 1.0 for z in zs) or any(
            b <= a for a, b in itertools.pairwise(zs)
        ):
            raise ValueError("ocv.correction_soc must increase strictly within [0, 1] (fractions)")
        if not all(math.isfinite(d) and abs(d) <= MAX_CORRECTION_V for d in dus):
            raise ValueError(
                f"ocv.correction_V must lie within +-{MAX_CORRECTION_V} V (volts, not mV)"
            )
        try:  # the corrected curve must increase and join its ends monotonically
            OcvModel.from_coeffs(
                self.mean, self.soc_min, self.soc_max, [0.0, 1.0], [0.0, 0.0],
                v_empty_V=self.v_empty_V, v_full_V=self.v_full_V,
                corr_soc=zs, corr_V=dus,
            )  # fmt: skip
        except ValueError as exc:
            raise ValueError(f"ocv.correction_V: {exc}") from None


class HysteresisTable(_Strict):
    """Hysteresis half-gap M(z) in volts as a piecewise-linear table (Eq. 10 / Eq. 32 form).

    ``soc`` must be increasing; outside it the end values hold. ``gamma`` is Plett's dimensionless
    hysteresis rate: h relaxes by a factor e for every 1/gamma of SOC moved (Eq. 5), i.e. the
    paper's decay factor kappa = eta * gamma / Q with Q in ampere-seconds (Eq. 6).
    ``M_ci95_V`` (optional, written by ``fit-ocv``): half-width (V) of the 95 % confidence
    interval of each ``M_V`` value, the prior's uncertainty for online learning of M; knots that
    were not measured (the ends that an OCV test pins to 0) carry 0. It belongs to the stored
    value: where ``fit-ocv`` stored a knot other than its fit (raised to the test's pooled lower
    bound because hysteresis is present, or 0 because none is resolved; its report says which),
    ``M_V +- M_ci95_V`` covers the fitted knot's own interval clipped at 0. It includes the
    polarisation's uncertainty and the knot's sensitivity to ``gamma`` (not fitted).

    ``law``: how h moves with charge. ``"plett"`` (Eq. 5): exponentially toward the current's
    branch, so under a drive's mixed current h settles at the charge-weighted mean of the signs
    (-0.3 on a cycle with regeneration) and a rest after it sits between the branches.
    ``"play"``: a play (backlash) operator, ``h -= 2 kappa i dt`` clipped to [-1, 1] (a full
    swing over 1/gamma of SOC, Plett's initial rate): a reversal smaller than the swing leaves
    h near its branch, the minor loops of a two-phase electrode (LFP). None (default): ``"play"``
    where ``chemistry`` names LFP (``LFP``, ``LiFePO4``, any case) or, unlabelled (``unknown``,
    as ``fit-ocv`` writes without ``--chemistry``), the OCV curve is an LFP plateau; else
    ``"plett"``. Measured
    on the A123 LFP DYN50 record (count SOC, the config's curve and M, its 17 rests of 12-15
    min): the rested voltage's residual 19.3 mV RMS (mean -16.5) with Plett's h, 8.4 mV (mean
    -4.5) with the play.
    """

    soc: list[float] = Field(default_factory=lambda: [0.0, 1.0], min_length=1)
    M_V: list[float] = Field(default_factory=lambda: [0.0, 0.0], min_length=1)
    gamma: float = Field(30.0, ge=0.0, le=10_000.0)
    M_ci95_V: list[float] | None = None
    law: Literal["plett", "play"] | None = None

    @model_validator(mode="after")
    def _check(self) -> Self:
        if len(self.soc) != len(self.M_V):
            raise ValueError("hysteresis.soc and hysteresis.M_V must have the same length")
        if any(b <= a for a, b in zip(self.soc, self.soc[1:], strict=False)):
            raise ValueError("hysteresis.soc must be strictly increasing")
        if any(m < 0 or m > 0.5 for m in self.M_V):
            raise ValueError("hysteresis.M_V must lie in [0, 0.5] V")
        if self.M_ci95_V is not None and (
            len(self.M_ci95_V) != len(self.soc)
            or any(not (math.isfinite(c) and c >= 0) for c in self.M_ci95_V)
        ):
            raise ValueError("hysteresis.M_ci95_V needs one finite value >= 0 per knot")
        return self


class Range(_Strict):
    """A closed interval [lo, hi] in the unit its field names."""

    lo: float
    hi: float

    @model_validator(mode="after")
    def _check(self) -> Self:
        if not (math.isfinite(self.lo) and math.isfinite(self.hi)) or self.hi <= self.lo:
            raise ValueError(f"range needs finite lo < hi, got [{self.lo}, {self.hi}]")
        return self


class ParameterBounds(_Strict):
    """Physical bounds for the identified parameters. Estimates never leave them.

    Defaults are wide enough for 18650 cells (tens of mOhm) and large prismatic cells (~1 mOhm,
    time constants of thousands of seconds).
    """

    R0_ohm: Range = Range(lo=1e-5, hi=0.5)
    R1_ohm: Range = Range(lo=1e-6, hi=0.5)
    R2_ohm: Range = Range(lo=1e-6, hi=0.5)
    tau1_s: Range = Range(lo=0.5, hi=200.0)
    tau2_s: Range = Range(lo=20.0, hi=8000.0)
    M_scale: Range = Range(lo=0.0, hi=3.0)
    ocv_offset_V: Range = Range(lo=-0.15, hi=0.15)

    @model_validator(mode="after")
    def _positive(self) -> Self:
        for name in ("R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "tau2_s"):
            if getattr(self, name).lo <= 0:
                raise ValueError(f"bounds.{name}.lo must be > 0")
        return self


class InitialParameters(_Strict):
    """Starting values before anything is identified (ohm, s)."""

    R0_ohm: float = Field(gt=0)
    R1_ohm: float = Field(gt=0)
    tau1_s: float = Field(gt=0)
    R2_ohm: float = Field(gt=0)
    tau2_s: float = Field(gt=0)


class SocInit(_Strict):
    """How the initial SOC is chosen.

    ``ocv_at_rest``: invert the OCV at each cell's first valid voltage (at rest when |current|
    <= ``rest_current_C`` x capacity, else corrected by the start R0 x current); a cell starts
    at its own first valid voltage, never from a default. ``fixed``: use ``soc0`` for every cell.
    """

    policy: Literal["ocv_at_rest", "fixed"] = "ocv_at_rest"
    soc0: float | None = Field(None, ge=0.0, le=1.0)
    rest_current_C: float = Field(0.01, ge=0.0)


class CellConfig(_Strict):
    """Everything bmsid needs to know about a cell type (units in the field names)."""

    name: str = "cell"
    chemistry: str = "unknown"
    capacity_Ah: float = Field(gt=0.0, le=10_000.0)
    #: Charge-counting factor (Eq. 2, applied on charge): SOC moves eta x the measured charge Ah.
    #: A physical coulombic efficiency is <= 1 (> 0.99 for Li-ion); a value above 1 is what a
    #: closed OCV test measures when the tester counts charge low (more Ah out than back in to
    #: the same rested voltage): a counting correction for that sensor, so it is accepted.
    #: (0.5, 2] only rejects unit slips (a percentage, 0); fit-ocv reports anything beyond
    #: [0.98, 1.02] as a counting mismatch.
    coulombic_efficiency: float = Field(1.0, gt=0.5, le=2.0)
    ocv: OcvCurve
    hysteresis: HysteresisTable = HysteresisTable()
    bounds: ParameterBounds | None = None
    """Parameter bounds; None: derived from the record around its measured R0 when one is
    available (``estimate/startvalues.py``), else ``ParameterBounds()``'s wide defaults."""
    initial: InitialParameters | None = None
    """Start values; None: from the record (its current steps) when one is available."""
    soc_init: SocInit = SocInit()

    @property
    def hysteresis_law(self) -> Literal["plett", "play"]:
        """``hysteresis.law``, or by chemistry where it is not set (see ``HysteresisTable``)."""
        if self.hysteresis.law is not None:
            return self.hysteresis.law
        label = self.chemistry.strip().upper()
        if "LFP" in label or "LIFEPO4" in label:
            return "play"
        return "play" if label in ("", "UNKNOWN") and self._ocv_looks_lfp() else "plett"

    def _ocv_looks_lfp(self) -> bool:
        """An unlabelled cell whose mean OCV (Eq. 4) is an LFP plateau: within
        ``LFP_PLATEAU_SPAN_V`` over SOC 20-80 %, its median in ``LFP_PLATEAU_V`` (the shipped
        A123 curve: 0.092 V around 3.30 V; the NMC configs span 0.39-0.57 V)."""
        v = eval_ocv(self.ocv.mean, np.linspace(0.2, 0.8, 13))
        lo, hi = LFP_PLATEAU_V
        return bool(np.ptp(v) < LFP_PLATEAU_SPAN_V and lo <= float(np.median(v)) <= hi)

    def parameter_bounds(self) -> ParameterBounds:
        """The configured bounds, or the wide defaults (see ``bounds``)."""
        return self.bounds if self.bounds is not None else ParameterBounds()

    def initial_parameters(self) -> InitialParameters:
        """Configured starting values, or a capacity-scaled guess (R0 ~ 0.1 ohm Ah / Q): the
        last resort when neither the config nor a record gives them (callers say so)."""
        if self.initial is not None:
            return self.initial
        b = self.parameter_bounds()
        r0 = min(max(0.1 / self.capacity_Ah, b.R0_ohm.lo), b.R0_ohm.hi)
        return InitialParameters(
            R0_ohm=r0, R1_ohm=0.5 * r0, tau1_s=10.0, R2_ohm=0.5 * r0, tau2_s=300.0
        )


def load_cell_config(path: str | Path) -> CellConfig:
    """Read a cell config from ``.toml`` or ``.json`` (pydantic validation errors propagate)."""
    p = Path(path)
    text = p.read_text(encoding="utf-8")
    data = tomllib.loads(text) if p.suffix.lower() == ".toml" else json.loads(text)
    return CellConfig.model_validate(data)


def save_cell_config(cfg: CellConfig, path: str | Path) -> None:
    """Write a cell config as TOML (``.toml``) or JSON (anything else)."""
    p = Path(path)
    data = cfg.model_dump(mode="json", exclude_none=True)
    if p.suffix.lower() == ".toml":
        p.write_text(tomli_w.dumps(data), encoding="utf-8")
    else:
        p.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


#: The paper's cell (Table 1 OCV, 70 Ah ternary) with the test parameters of the issue tracker.
PAPER_OCV_MEAN = [4.041, -1.107, 1.348, -0.002527, 0.1998, 0.02058]


def paper_cell(M_V: float = 0.015, gamma: float = 30.0) -> CellConfig:
    """The 70 Ah cell of the paper: Table 1 OCV, constant hysteresis half-gap ``M_V``."""
    return CellConfig(
        name="paper-70Ah-NMC",
        chemistry="NMC",
        capacity_Ah=70.0,
        coulombic_efficiency=1.0,
        ocv=OcvCurve(mean=PAPER_OCV_MEAN, soc_min=0.02, soc_max=0.98),
        hysteresis=HysteresisTable(soc=[0.0, 1.0], M_V=[M_V, M_V], gamma=gamma),
        initial=InitialParameters(R0_ohm=2e-3, R1_ohm=1e-3, tau1_s=10.0, R2_ohm=1e-3, tau2_s=300.0),
        bounds=ParameterBounds(),
    )
