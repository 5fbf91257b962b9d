"""``CELL_FIELDS`` is the one list of output fields: every output iterates it.

A field added to the table appears in params.csv, the MQTT cell payload, its JSON schema and
Home Assistant discovery without another edit; a CAN signal the DBC lacks fails loudly. The
existing fields appear in every output with their units, and the shipped schema is current.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import cantools
import jsonschema
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid import docgen
from bmsid.canbus.encoder import CLASSIC_PAGES, DECODED_NAMES, FD_PAGE, ParameterEncoder
from bmsid.canbus.mapping import DEFAULT_DBC_PATH
from bmsid.errors import UserError
from bmsid.estimate import fields
from bmsid.estimate.fields import FieldSpec, HaSensor
from bmsid.estimate.types import EstimateBlock, Estimates
from bmsid.offline.writers import ParamsCsvWriter, write_params_csv
from bmsid.publish import discovery, payloads

REPO = Path(__file__).resolve().parents[2]

#: A field one might add next: a fraction without an HA sensor or CAN signal ...
NIS = FieldSpec("nis", "", "%.6f", "normalised innovation squared (observer)", positive=True)
#: ... and a quantity with a unit and a Home Assistant sensor.
ENERGY = FieldSpec(
    "energy_Wh",
    "Wh",
    "%.5g",
    "identified energy",
    ha=HaSensor("energy", "Wh", digits=2),
    positive=True,
    nullable=True,
)
#: A CAN signal that bmsid.dbc does not define.
DRIFT = FieldSpec("shunt_drift_A", "A", "%.6g", "shunt drift", can_signal="IShuntDrift")

#: Today's Home Assistant sensors of a cell (entity ids users have: must never change).
TODAYS_OBJECT_IDS = {
    f"cell0_{k}"
    for k in (
        "r0_ohm", "r1_ohm", "r2_ohm", "tau1_s", "tau2_s", "c1_f", "c2_f", "soc", "quality",
        "lambda", "h", "v_error_v", "soc_std", "capacity_ah", "capacity_std_ah", "current_offset_a",
    )
}  # fmt: skip

#: params.csv's columns (the first 12 fields were its columns before the table).
TODAYS_HEADER = (
    "t_s,cell,R0_ohm,R1_ohm,C1_F,R2_ohm,C2_F,tau1_s,tau2_s,lambda,h,soc,soc_std,capacity_Ah,"
    "capacity_std_Ah,current_offset_A,v_model_V,v_meas_V,v_error_V,M_V,ocv_offset_V,on_bound,"
    "arx_error_V,"
    "quality"
)


def _typical(spec: FieldSpec, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Values a real run could give: inside the spec's bounds, within CAN signal ranges."""
    lo = spec.lo if spec.lo is not None else 0.0
    hi = spec.hi if spec.hi is not None else (2.0e-3 if spec.positive else 0.01)
    return rng.uniform(lo + 1e-6, hi, shape)


def _block(n_ticks: int, n_cells: int, seed: int = 0) -> EstimateBlock:
    """Every field of the table *as it is now* (a patched table included)."""
    rng = np.random.default_rng(seed)
    return EstimateBlock(
        t_s=1.7e9 + np.arange(n_ticks, dtype=np.float64) * 0.1,
        current_A=rng.uniform(-50, 50, n_ticks),
        cells={s.name: _typical(s, rng, (n_ticks, n_cells)) for s in fields.CELL_FIELDS},
        quality=rng.integers(0, 4, (n_ticks, n_cells)).astype(np.int64),
    )


def _read_csv(path: Path) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(path.read_text(encoding="utf-8"))))


@pytest.fixture
def added(monkeypatch: pytest.MonkeyPatch) -> tuple[FieldSpec, ...]:
    """The table with NIS and ENERGY appended (one patch: consumers read it when called)."""
    new = (NIS, ENERGY)
    monkeypatch.setattr(fields, "CELL_FIELDS", (*fields.CELL_FIELDS, *new))
    return new


# ------------------------------------------------------------------ (1) a field added to the table
def test_added_field_appears_in_params_csv(added: tuple[FieldSpec, ...], tmp_path: Path) -> None:
    block = _block(3, 2)
    write_params_csv(block, ["a", "b"], tmp_path / "params.csv")
    header = (tmp_path / "params.csv").read_text(encoding="utf-8").splitlines()[0]
    assert header == TODAYS_HEADER.replace(",quality", ",nis,energy_Wh,quality")
    rows = _read_csv(tmp_path / "params.csv")
    assert len(rows) == 6 and [r["cell"] for r in rows] == ["a", "b"] * 3
    for spec in added:
        got = [r[spec.out_key] for r in rows]
        assert got == [spec.fmt % v for v in block.cells[spec.name].ravel()]


def test_added_field_appears_in_payload_and_schema(added: tuple[FieldSpec, ...]) -> None:
    est = _block(1, 3).row(0)
    schema = payloads.cell_schema()
    for i in range(3):
        body = json.loads(payloads.encode(payloads.cell_payload(est, i, "p1", seq=i)))
        jsonschema.validate(body, schema)
        for spec in added:
            assert body[spec.out_key] == float(est[spec.name][i])
    props = schema["properties"]
    # every field may be null (a no_data cell), a non-nullable one only then
    assert props["nis"] == {
        "type": ["number", "null"],
        "exclusiveMinimum": 0,
        "description": "normalised innovation squared (observer)",
    }
    assert schema["else"]["properties"]["nis"] == {"type": "number"}
    assert "energy_Wh" not in schema["else"]["properties"]
    assert props["energy_Wh"]["type"] == ["number", "null"]
    assert props["energy_Wh"]["description"] == "identified energy [Wh]"
    assert {"nis", "energy_Wh"} <= set(schema["required"])
    # the shipped file is the table's schema: it is stale now, and docgen says so
    assert json.loads(payloads.CELL_SCHEMA_PATH.read_text()) != schema
    assert payloads.CELL_SCHEMA_PATH in docgen.stale_files(REPO)


def test_added_field_appears_in_home_assistant_discovery(added: tuple[FieldSpec, ...]) -> None:
    assert discovery.cell_sensor_keys()[-3:] == ["v_error_V", "energy_Wh", "quality"]
    msgs = dict(discovery.discovery_messages("homeassistant", "bmsid", "p1", 2, "0"))
    cfg = json.loads(msgs["homeassistant/sensor/bmsid_p1/cell1_energy_wh/config"])
    assert cfg["name"] == "cell 1 energy" and cfg["unit_of_measurement"] == "Wh"
    assert cfg["value_template"] == (
        "{{ (value_json.energy_Wh) | round(2) if value_json.energy_Wh is number else none }}"
    )
    assert cfg["state_topic"] == "bmsid/p1/cell/1" and cfg["state_class"] == "measurement"
    assert not any("nis" in t for t in msgs)  # no ha entry: no sensor


def test_added_field_without_can_signal_leaves_can_frames_alone(
    added: tuple[FieldSpec, ...],
) -> None:
    est = _block(1, 2).row(0)
    for fd in (False, True):
        enc = ParameterEncoder(fd=fd)
        decoded = [enc.decode(f) for f in enc.cell_frames(est, [0, 1])]
        assert all(d is not None and "nis" not in d for d in decoded)


def test_added_can_signal_the_dbc_lacks_fails_loudly(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(fields, "CELL_FIELDS", (*fields.CELL_FIELDS, DRIFT))
    for fd in (False, True):
        with pytest.raises(UserError, match=r"lacks cell signal\(s\) IShuntDrift in BMSID_Cell"):
            ParameterEncoder(fd=fd)


# ------------------------------------------------------------ (2) today's fields, with units
def test_every_key_carries_its_unit() -> None:
    """Units are SI and part of the key (fractions carry none): what every output relies on."""
    assert len({s.name for s in fields.CELL_FIELDS}) == len(fields.CELL_FIELDS)
    assert len({s.out_key for s in fields.CELL_FIELDS}) == len(fields.CELL_FIELDS)
    for s in fields.CELL_FIELDS:
        assert s.name.isidentifier(), s
        assert s.unit == "" or s.out_key.endswith("_" + s.unit), s


def test_params_csv_columns_and_rows(tmp_path: Path) -> None:
    block = _block(4, 3, seed=1)
    names = ["c0", "c1", "c2"]
    # streaming: two appends give the same file as one
    with ParamsCsvWriter(tmp_path / "two.csv", names) as w:
        w.append(block.select(slice(0, 1)))
        w.append(EstimateBlock.empty(3))
        w.append(block.select(slice(1, None)))
    write_params_csv(block, names, tmp_path / "one.csv")
    text = (tmp_path / "one.csv").read_text(encoding="utf-8")
    assert (tmp_path / "two.csv").read_text(encoding="utf-8") == text
    lines = text.splitlines()
    assert lines[0] == TODAYS_HEADER
    # for each tick, every cell; every value with its spec's format
    k, c = 2, 1
    want = [f"{block.t_s[k]:.6f}", names[c]]
    want += [s.fmt % block.cells[s.name][k, c] for s in fields.CELL_FIELDS]
    want.append(str(block.quality[k, c]))
    assert lines[1 + k * 3 + c] == ",".join(want)
    assert len(lines) == 1 + 4 * 3


def test_params_csv_refuses_a_block_it_cannot_write(tmp_path: Path) -> None:
    block = _block(2, 2)
    with (
        ParamsCsvWriter(tmp_path / "p.csv", ["a", "b", "c"]) as w,
        pytest.raises(ValueError, match="2 cells"),
    ):
        w.append(block)
    short = EstimateBlock(block.t_s, block.current_A, {"R0_ohm": block["R0_ohm"]}, block.quality)
    with (
        ParamsCsvWriter(tmp_path / "p.csv", ["a", "b"]) as w,
        pytest.raises(ValueError, match="lacks field"),
    ):
        w.append(short)
    with pytest.raises(ValueError, match="closed"):
        w.append(block)


def test_payload_carries_every_mqtt_field_and_the_schema_their_units() -> None:
    est = _block(1, 2).row(0)
    body = payloads.cell_payload(est, 1, "p1", seq=0)
    mqtt = [s for s in fields.CELL_FIELDS if s.mqtt]
    assert [k for k in body if k in {s.out_key for s in fields.CELL_FIELDS}] == [
        s.out_key for s in mqtt
    ]
    assert "arx_error_V" not in body  # mqtt=False
    props = payloads.cell_schema()["properties"]
    for s in mqtt:
        assert body[s.out_key] == float(est[s.name][1])
        assert props[s.out_key]["description"].endswith(f" [{s.unit}]" if s.unit else "")


def test_shipped_schema_is_the_generated_one() -> None:
    """Regenerate with ``python -m bmsid.docgen`` after editing the table."""
    text = payloads.schema_text(payloads.cell_schema())
    assert payloads.CELL_SCHEMA_PATH.read_text(encoding="utf-8") == text
    assert (REPO / "docs" / "mqtt-schemas" / "cell.json").read_text(encoding="utf-8") == text
    assert docgen.stale_files(REPO) == {}
    jsonschema.Draft202012Validator.check_schema(payloads.cell_schema())


def _payload_value(spec: FieldSpec) -> st.SearchStrategy[float]:
    """Any value the schema must accept: within bounds, or anything not finite where nullable."""
    lo = spec.lo if spec.lo is not None else (0.0 if spec.positive else None)
    finite = st.floats(lo, spec.hi, exclude_min=spec.positive, allow_nan=False,
                       allow_infinity=False)  # fmt: skip
    if spec.nullable:
        return st.one_of(finite, st.sampled_from([math.nan, math.inf, -math.inf]))
    return finite


@settings(max_examples=200, deadline=None)
@given(st.fixed_dictionaries({s.name: _payload_value(s) for s in fields.CELL_FIELDS}))
def test_payload_encodes_values_as_number_or_null_and_validates(values: dict[str, float]) -> None:
    est = Estimates(1.7e9, 0.0, {k: np.array([v]) for k, v in values.items()}, np.array([1]))
    body = json.loads(payloads.encode(payloads.cell_payload(est, 0, "p1", seq=3)))
    jsonschema.validate(body, payloads.cell_schema())
    for s in fields.CELL_FIELDS:
        if s.mqtt:
            v = values[s.name]
            assert body[s.out_key] == (v if math.isfinite(v) else None), s.name


@pytest.mark.parametrize(("key", "bad"), [("R0_ohm", math.nan), ("lambda_", 0.0), ("h", 1.5)])
def test_schema_rejects_what_no_estimate_may_be(key: str, bad: float) -> None:
    est = _block(1, 1).row(0)
    est = Estimates(est.t_s, est.current_A, {**est.cells, key: np.array([bad])}, est.quality)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(payloads.cell_payload(est, 0, "p1", 0), payloads.cell_schema())


def test_discovery_offers_the_table_with_todays_entity_ids() -> None:
    msgs = dict(discovery.discovery_messages("homeassistant", "bmsid", "p1", 1, "0"))
    cfgs = {t.split("/")[-2]: json.loads(p) for t, p in msgs.items() if "/cell0_" in t}
    assert set(cfgs) == TODAYS_OBJECT_IDS
    for spec, ha in discovery.ha_fields():
        cfg = cfgs[f"cell0_{spec.out_key}".lower()]
        assert cfg["unique_id"] == f"bmsid_p1_cell0_{spec.out_key}".lower()
        assert cfg["default_entity_id"] == f"sensor.{cfg['unique_id']}"
        assert cfg.get("unit_of_measurement") == ha.unit
        assert cfg.get("device_class") == ha.device_class
        assert (cfg.get("entity_category") == "diagnostic") == ha.diagnostic
    assert cfgs["cell0_r0_ohm"]["value_template"] == (
        "{{ (value_json.R0_ohm * 1000) | round(4) if value_json.R0_ohm is number else none }}"
    )
    # `lambda` is reserved in the template language: subscripted, as before the table
    assert cfgs["cell0_lambda"]["value_template"] == (
        "{{ (value_json['lambda']) | round(4) if value_json['lambda'] is number else none }}"
    )
    assert cfgs["cell0_quality"]["device_class"] == "enum"


@pytest.mark.parametrize("fd", [False, True])
def test_can_frames_carry_every_can_field_in_its_unit(fd: bool) -> None:
    db = cantools.database.load_file(str(DEFAULT_DBC_PATH))
    assert isinstance(db, cantools.database.can.Database)
    pages = [FD_PAGE] if fd else list(CLASSIC_PAGES)
    signals = {s.name: s for p in pages for s in db.get_message_by_name(f"BMSID_{p}").signals}
    enc = ParameterEncoder(fd=fd)
    est = _block(1, 2, seed=3).row(0)
    got: dict[str, float] = {}
    for frame in enc.cell_frames(est, [1]):
        d = enc.decode(frame)
        assert d is not None
        got |= d
    for spec in fields.CELL_FIELDS:
        if spec.can_signal is None or not (fd or spec.can_classic):
            assert spec.out_key not in got, spec.name
            continue
        sig = signals[spec.can_signal]
        assert (sig.unit or "").lower() == spec.unit.lower(), spec.name  # "Ohm" in the DBC
        assert DECODED_NAMES[spec.can_signal] == spec.out_key
        assert got[spec.out_key] == pytest.approx(float(est[spec.name][1]), abs=sig.scale)
