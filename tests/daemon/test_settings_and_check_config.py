"""Settings (TOML + BMSID_ environment) and ``bmsid check-config``."""

from __future__ import annotations

from pathlib import Path

import pytest

from bmsid.cli.main import main
from bmsid.config.settings import load_settings
from bmsid.errors import UserError

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "configs" / "bmsid.example.toml"

GOOD = """
pack_id = "p1"
[can]
channel = "vcan0"
n_cells = 4
[mqtt]
url = "mqtts://broker.example:8884"
username = "bmsid"
password = "hunter2-secret"
topic_prefix = "site/bms"
[state]
directory = "state"
"""


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "bmsid.toml"
    p.write_text(text, encoding="utf-8")
    return p


def test_example_config_is_valid() -> None:
    s = load_settings(EXAMPLE)
    assert s.can.n_cells == 16 and s.mqtt.endpoint() == ("localhost", 1883, False)


def test_good_file_paths_and_endpoint(tmp_path: Path) -> None:
    s = load_settings(_write(tmp_path, GOOD))
    assert s.mqtt.endpoint() == ("broker.example", 8884, True)
    assert s.state.directory == (tmp_path / "state").resolve()  # relative to the file
    assert s.mqtt.password_value() == "hunter2-secret"


def test_environment_overrides_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BMSID_CAN__N_CELLS", "12")
    monkeypatch.setenv("BMSID_MQTT__QOS", "0")
    monkeypatch.setenv("BMSID_ESTIMATOR__TUNING__LAMBDA_MIN", "0.97")
    s = load_settings(_write(tmp_path, GOOD))
    assert (s.can.n_cells, s.mqtt.qos, s.estimator.tuning.lambda_min) == (12, 0, 0.97)
    assert s.mqtt.username == "bmsid"  # untouched keys of the same section survive


def test_password_file(tmp_path: Path) -> None:
    (tmp_path / "pw").write_text("from-file\n")
    text = GOOD.replace('password = "hunter2-secret"', 'password_file = "pw"')
    assert load_settings(_write(tmp_path, text)).mqtt.password_value() == "from-file"


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (('topic_prefix = "site/bms"', 'topic_prefix = "site/+/bms"'), "mqtt.topic_prefix"),
        (('topic_prefix = "site/bms"', 'topic_prefix = "site//bms"'), "mqtt.topic_prefix"),
        (('topic_prefix = "site/bms"', 'topic_prefix = "site/bms/"'), "mqtt.topic_prefix"),
        (('topic_prefix = "site/bms"', 'topic_prefix = "#"'), "mqtt.topic_prefix"),
        (("n_cells = 4", "n_cells = 0"), "can.n_cells"),
        (("n_cells = 4", "n_cells = 4\nbogus = 1"), "can.bogus"),
        (('url = "mqtts://broker.example:8884"', 'url = "http://x"'), "mqtt"),
        (('pack_id = "p1"', 'pack_id = "a b"'), "pack_id"),
        (("[state]", '[estimator]\nvariant = "kalman"\n[state]'), "estimator.variant"),
    ],
)
def test_bad_file_names_the_field(tmp_path: Path, edit: tuple[str, str], field: str) -> None:
    path = _write(tmp_path, GOOD.replace(*edit))
    with pytest.raises(UserError, match=rf"field {field}"):
        load_settings(path)


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (("n_cells = 4", 'n_cells = "8"'), "can.n_cells"),
        (("n_cells = 4", 'n_cells = 4\nstaleness_s = "2"'), "can.staleness_s"),
        (("n_cells = 4", 'n_cells = 4\noutput = "false"'), "can.output"),
        (("[state]", '[gates]\ni_max_C = "30"\n[state]'), "gates.i_max_C"),
        (("[state]", '[estimator.tuning]\nn_particles = "12"\n[state]'), "estimator.tuning"),
        (("[state]", '[estimator.tuning.observer]\nenabled = "no"\n[state]'), "estimator"),
        (('username = "bmsid"', "username = 7"), "mqtt.username"),
    ],
)
def test_wrong_toml_type_is_refused(tmp_path: Path, edit: tuple[str, str], field: str) -> None:
    """A quoted number is a mistake to name, not a value to guess (pydantic's lax mode took it)."""
    with pytest.raises(UserError, match=rf"field {field}\S*: .*\(got "):
        load_settings(_write(tmp_path, GOOD.replace(*edit)))


def test_int_in_float_field_and_paths_still_load(tmp_path: Path) -> None:
    text = GOOD.replace("n_cells = 4", 'n_cells = 4\nstaleness_s = 2\nmapping = "map.toml"')
    text += "checkpoint_period_s = 30\n[gates]\ni_max_C = 20\n[estimator.tuning]\nwindow_s = 900\n"
    s = load_settings(_write(tmp_path, text))
    assert (s.can.staleness_s, s.state.checkpoint_period_s) == (2.0, 30.0)
    assert (s.gates.i_max_C, s.estimator.tuning.window_s) == (20.0, 900.0)
    assert s.can.mapping == tmp_path / "map.toml"


def test_check_config_names_a_quoted_number(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _write(tmp_path, GOOD.replace("n_cells = 4", 'n_cells = "8"'))
    assert main(["check-config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith(
        "field can.n_cells: Input should be a valid integer "
        "(got the string '8': write it without quotes)"
    )
    assert len(err.splitlines()) == 1


def test_check_config_prints_effective_redacted(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["check-config", str(_write(tmp_path, GOOD))]) == 0
    out = capsys.readouterr().out
    assert "hunter2-secret" not in out and "**********" in out
    assert 'topic_prefix = "site/bms"' in out and "lambda_min = 0.98" in out  # defaults shown


def test_check_config_bad_file_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _write(tmp_path, GOOD.replace("n_cells = 4", "n_cells = -3"))
    assert main(["check-config", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "can.n_cells" in err and "Traceback" not in err


def test_check_config_missing_and_unparsable(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["check-config", str(tmp_path / "nope.toml")]) == 2
    assert main(["check-config", str(_write(tmp_path, "pack_id = "))]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "not found" in err[0] and "not valid TOML" in err[1]


def test_check_config_replay_needs_virtual_bus(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _write(tmp_path, GOOD.replace("n_cells = 4", "n_cells = 4\nreplay = 3"))
    assert main(["check-config", str(path)]) == 2
    assert "can.replay" in capsys.readouterr().err
