"""The README's generated tables (CAN contract, configuration reference) are current."""

from __future__ import annotations

import re
from pathlib import Path

import cantools

from bmsid import docgen
from bmsid.config.settings import Settings

REPO = Path(__file__).resolve().parents[2]
README = REPO / "README.md"


def test_generated_tables_in_readme_are_current() -> None:
    text = README.read_text(encoding="utf-8")
    assert docgen.render(text) == text, "README is stale: run python -m bmsid.docgen"
    assert docgen.main(["--check", "--readme", str(README)]) == 0


def test_stale_readme_is_detected(tmp_path: Path) -> None:
    stale = README.read_text(encoding="utf-8").replace("| `can.channel` |", "| `can.chanel` |")
    path = tmp_path / "README.md"
    path.write_text(stale, encoding="utf-8")
    assert docgen.main(["--check", "--readme", str(path)]) == 1
    assert docgen.main(["--readme", str(path)]) == 0
    assert docgen.main(["--check", "--readme", str(path)]) == 0


def test_config_reference_covers_every_field_with_a_meaning() -> None:
    table = docgen.config_reference_table()
    keys = {k for k, _, section in docgen._fields(Settings, "") if not section}
    rows = [r for r in table.splitlines() if r.startswith("| `")]
    assert {re.match(r"\| `([^`]+)`", r).group(1) for r in rows} == keys  # type: ignore[union-attr]
    for r in rows:
        meaning = r.rstrip(" |").rsplit(" | ", 1)[1]
        assert meaning and not meaning.startswith("`BMSID_"), f"no description: {r}"
    assert "mqtt.password" in table and "secret" in table


def test_can_contract_lists_every_signal_of_the_dbc() -> None:
    db = cantools.database.load_file(str(REPO / "dbc" / "bmsid.dbc"))
    assert isinstance(db, cantools.database.can.Database)
    table = docgen.can_contract_table(REPO / "dbc" / "bmsid.dbc")
    for m in db.messages:
        if m.name.endswith("_11bit"):
            assert f"(0x{m.frame_id:03X})" in table
            continue
        for s in m.signals:
            assert re.search(rf"\| {m.name} \|[^\n]*\| {s.name}[ |]", table), (m.name, s.name)
