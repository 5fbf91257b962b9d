"""The real-parts rule of tests/conftest.py: a missing part FAILS when required, else SKIPS.

Each case runs a small pytest session in a subprocess, with this repository's conftest.py and
a vcan channel name that does not exist (except the realcan case, which needs a usable vcan).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from xml.etree import ElementTree

import pytest

CONFTEST = Path(__file__).resolve().parents[1] / "conftest.py"

PYTEST_INI = """\
[pytest]
markers =
    realcan: needs a real SocketCAN vcan0
"""

CASES = """\
import pytest

@pytest.mark.realcan
def test_uses_vcan(vcan_channel):
    pass

@pytest.mark.realcan
def test_without_fixture():
    pass

def test_needs_a_tool(require_tool):
    require_tool("bmsid-no-such-tool")

@pytest.mark.realcan
def test_skips_itself():
    pytest.skip("skipped from inside")

def test_plain():
    pass
"""


def run_cases(tmp_path: Path, env_overrides: dict[str, str]) -> tuple[dict[str, str], str]:
    """Outcome of each case by test name ("passed", "failed", "error", "skipped"), and stdout."""
    (tmp_path / "conftest.py").write_text(CONFTEST.read_text(encoding="utf-8"), encoding="utf-8")
    (tmp_path / "pytest.ini").write_text(PYTEST_INI, encoding="utf-8")
    (tmp_path / "test_cases.py").write_text(CASES, encoding="utf-8")
    # No CI/BMSID_* from the outer session (e.g. BMSID_REALCAN_FILES_OUT of scripts/test).
    env = {k: v for k, v in os.environ.items() if k != "CI" and not k.startswith("BMSID_")}
    env |= {"BMSID_VCAN_CHANNEL": "bmsidnocan0", "PYTEST_ADDOPTS": "-p no:cacheprovider"}
    env |= env_overrides
    junit = tmp_path / "report.xml"
    result = subprocess.run(
        # Without the hypothesis plugin, whose import takes seconds and is not needed here.
        [
            *(sys.executable, "-m", "pytest", "-rA", "-p", "no:hypothesispytest"),
            *(f"--junitxml={junit}", str(tmp_path)),
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert junit.exists(), result.stdout + result.stderr
    outcomes = {}
    for case in ElementTree.parse(junit).iter("testcase"):
        kinds = [child.tag for child in case if child.tag in {"failure", "error", "skipped"}]
        outcome = kinds[0] if kinds else "passed"
        outcomes[case.attrib["name"]] = "failed" if outcome == "failure" else outcome
    return outcomes, result.stdout


def test_missing_parts_skip_with_the_reason_on_a_developer_machine(tmp_path: Path) -> None:
    # "false"/"0" mean "not set", like an absent variable.
    outcomes, stdout = run_cases(tmp_path, {"CI": "false", "BMSID_REQUIRE_REAL": "0"})
    assert outcomes == {
        "test_uses_vcan": "skipped",
        "test_without_fixture": "skipped",
        "test_needs_a_tool": "skipped",
        "test_skips_itself": "skipped",
        "test_plain": "passed",
    }, stdout
    assert "bmsidnocan0" in stdout
    assert "scripts/uml-run" in stdout


@pytest.mark.parametrize("variable", ["CI", "BMSID_IN_UML"])
def test_missing_parts_fail_when_real_parts_are_required(tmp_path: Path, variable: str) -> None:
    outcomes, stdout = run_cases(tmp_path, {variable: "true"})
    # Failing in setup is pytest's "error": it fails the run like a failed test does.
    expected = {
        "test_uses_vcan": "error",
        "test_without_fixture": "error",
        "test_skips_itself": "error",
    }
    if variable != "BMSID_IN_UML":  # inside UML only realcan tests are selected
        expected |= {"test_needs_a_tool": "failed", "test_plain": "passed"}
    assert outcomes == expected, stdout
    assert "scripts/uml-run" in stdout


@pytest.mark.realcan
def test_a_realcan_test_that_skips_itself_fails_when_required(
    tmp_path: Path, vcan_channel: str
) -> None:
    # Needs a usable vcan so that the case gets past setup and reaches its own pytest.skip.
    outcomes, stdout = run_cases(
        tmp_path, {"BMSID_REQUIRE_REAL": "1", "BMSID_VCAN_CHANNEL": vcan_channel}
    )
    assert outcomes["test_uses_vcan"] == "passed", stdout
    assert outcomes["test_skips_itself"] == "failed", stdout
    assert "skipped from inside" in stdout
