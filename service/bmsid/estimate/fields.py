"""The one table of what the engine reports per cell and tick, and how every output shows it.

``params.csv`` (offline), the MQTT cell payload and its JSON schema, Home Assistant discovery
and the CAN encoder all iterate :data:`CELL_FIELDS`: a field added here appears in each of them
(``tests/estimate/test_fields.py`` proves it). A field's ``name`` is its key in
:class:`~bmsid.estimate.types.Estimates`; ``key`` is what files and payloads call it. Units are
SI and part of the key (``_ohm``, ``_F``, ``_s``, ``_V``); fractions carry no suffix.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class HaSensor:
    """How Home Assistant shows a field: display name and unit, ``scale`` x the SI value."""

    name: str
    unit: str | None = None
    scale: float = 1.0
    device_class: str | None = None
    diagnostic: bool = False
    digits: int = 4


@dataclass(frozen=True, slots=True)
class FieldSpec:
    """One per-cell output field.

    Attributes:
        name: key in ``Estimates`` (a Python identifier).
        unit: SI unit ("" for a fraction or a dimensionless state).
        fmt: printf format in ``params.csv``.
        description: one line for the schema and the docs.
        key: name in params.csv, MQTT and JSON (default ``name``).
        mqtt: published in the MQTT cell payload.
        can_signal: signal of bmsid's CAN cell frames (``dbc/bmsid.dbc``), None if not sent.
        can_classic: also sent in the three 8-byte classic-CAN frames (False: CAN FD only, the
            classic frames have no room; receivers derive it, e.g. C1 = tau1 / R1).
        ha: Home Assistant sensor, None if not offered.
        positive: always > 0 (resistances, capacitances, time constants): the schema says so.
        nullable: may be null in MQTT (a missing measurement) instead of a number.
        lo, hi: closed range the schema enforces (None: open).
    """

    name: str
    unit: str
    fmt: str
    description: str
    key: str = ""
    mqtt: bool = True
    can_signal: str | None = None
    can_classic: bool = True
    ha: HaSensor | None = None
    positive: bool = False
    nullable: bool = False
    lo: float | None = None
    hi: float | None = None

    @property
    def out_key(self) -> str:
        """The field's name outside the engine (CSV column, MQTT key)."""
        return self.key or self.name


#: Per-cell fields, in params.csv order (``t_s`` and ``cell`` come first, ``quality`` last).
CELL_FIELDS: tuple[FieldSpec, ...] = (
    FieldSpec("R0_ohm", "ohm", "%.6g", "ohmic resistance R0 (Eq. 9)", can_signal="R0",
              ha=HaSensor("R0", "mΩ", 1000.0), positive=True),
    FieldSpec("R1_ohm", "ohm", "%.6g", "fast RC branch resistance R1", can_signal="R1",
              ha=HaSensor("R1", "mΩ", 1000.0), positive=True),
    FieldSpec("C1_F", "F", "%.6g", "fast RC branch capacitance C1 = tau1 / R1", can_signal="C1",
              can_classic=False, ha=HaSensor("C1", "F"), positive=True),
    FieldSpec("R2_ohm", "ohm", "%.6g", "slow RC branch resistance R2", can_signal="R2",
              ha=HaSensor("R2", "mΩ", 1000.0), positive=True),
    FieldSpec("C2_F", "F", "%.6g", "slow RC branch capacitance C2 = tau2 / R2", can_signal="C2",
              can_classic=False, ha=HaSensor("C2", "F"), positive=True),
    FieldSpec("tau1_s", "s", "%.6g", "fast time constant R1 C1 (tau1 < tau2)", can_signal="Tau1",
              ha=HaSensor("tau1", "s", device_class="duration"), positive=True),
    FieldSpec("tau2_s", "s", "%.6g", "slow time constant R2 C2", can_signal="Tau2",
              ha=HaSensor("tau2", "s", device_class="duration"), positive=True),
    FieldSpec("lambda_", "", "%.6f", "forgetting factor per second of data (Eq. 21)",
              key="lambda", can_signal="Lambda", ha=HaSensor("lambda", diagnostic=True),
              positive=True, hi=1.0),
    FieldSpec("h", "", "%.5f", "hysteresis state in [-1, 1], -1 after discharge (Eq. 5-6)",
              can_signal="H", ha=HaSensor("hysteresis state", diagnostic=True), lo=-1.0, hi=1.0),
    FieldSpec("soc", "", "%.6f", "state of charge, fraction (coulomb count, Eq. 2)",
              can_signal="SOC", ha=HaSensor("SOC", "%", 100.0, "battery", digits=2),
              nullable=True),
    FieldSpec("soc_std", "", "%.5f", "1-sigma uncertainty of soc (observer covariance), fraction",
              can_signal="SOCStd",
              ha=HaSensor("SOC uncertainty", "%", 100.0, diagnostic=True, digits=2), lo=0.0,
              nullable=True),
    FieldSpec("capacity_Ah", "Ah", "%.5g",
              "capacity from charge throughput between SOC anchors (configured until measured)",
              can_signal="Capacity", ha=HaSensor("capacity", "Ah"), positive=True),
    FieldSpec("capacity_std_Ah", "Ah", "%.4g", "1-sigma uncertainty of capacity_Ah",
              ha=HaSensor("capacity uncertainty", "Ah", diagnostic=True), lo=0.0),
    FieldSpec("current_offset_A", "A", "%.5g",
              "pack current-sensor offset (one per pack, + = reads too much discharge)",
              ha=HaSensor("current offset", "A", diagnostic=True)),
    FieldSpec("v_model_V", "V", "%.6f", "a-priori model terminal voltage (Eq. 9)",
              nullable=True),
    FieldSpec("v_meas_V", "V", "%.6f", "measured terminal voltage (tick mean), null if missing",
              nullable=True),
    FieldSpec("v_error_V", "V", "%.6f", "model error v_meas_V - v_model_V", can_signal="VError",
              ha=HaSensor("model error", "mV", 1000.0, "voltage", diagnostic=True),
              nullable=True),
    FieldSpec("M_V", "V", "%.6g", "hysteresis half-gap at the present SOC (Eq. 32)",
              nullable=True),
    FieldSpec("ocv_offset_V", "V", "%.6g", "identified OCV offset (0 where not identified)",
              nullable=True),
    FieldSpec("on_bound", "", "%d",
              "parameters the estimator holds on a bound, bits 1 R0, 2 R1, 4 R2, 8 tau1, 16 tau2 "
              "(their last good values are published; a finding, estimate/guard.py)", mqtt=False),
    FieldSpec("arx_error_V", "V", "%.6g", "one-step regression prediction error", mqtt=False),
)  # fmt: skip

FIELD_NAMES: tuple[str, ...] = tuple(f.name for f in CELL_FIELDS)
FIELDS_BY_NAME: dict[str, FieldSpec] = {f.name: f for f in CELL_FIELDS}

#: The integer quality code (``estimate.types.Quality``) follows the fields in every output.
QUALITY_KEY = "quality"
