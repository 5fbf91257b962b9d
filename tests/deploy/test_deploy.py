"""The gateway deployment files in ``deploy/``: systemd unit, networkd files, scripts, installer,
Mosquitto ACL, Node-RED flow and the replay recipe, each checked with the real tool where one
runs offline (systemd-analyze, shellcheck, mosquitto + mosquitto_pub/mosquitto_sub, bash).

Tools (Debian packages): systemd-analyze and /lib/systemd/systemd-networkd (``systemd``),
shellcheck (``shellcheck``), mosquitto and mosquitto_passwd (``mosquitto``), mosquitto_pub and
mosquitto_sub (``mosquitto-clients``), ip (``iproute2``). A missing one fails the test when real
parts are required (CI) and skips it otherwise (conftest rule).
"""

from __future__ import annotations

import json
import os
import queue
import re
import shutil
import signal
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn

import pytest

from bmsid.config.settings import Settings, load_settings
from bmsid.publish.payloads import topic

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
UNIT = DEPLOY / "systemd" / "bmsid.service"
NETWORKD = DEPLOY / "networkd"
EXAMPLE_CONFIG = REPO / "configs" / "bmsid.example.toml"
SCHEMAS = REPO / "service" / "bmsid" / "publish" / "schemas"
DEMO_LOG = REPO / "service" / "bmsid" / "data" / "demo_pack.log"
NETWORKD_BINARY = Path("/lib/systemd/systemd-networkd")

UNIT_BMSID = "/opt/bmsid/venv/bin/bmsid"
UNIT_RUN = f"exec {UNIT_BMSID} run --config /etc/bmsid/bmsid.toml"
#: ``systemd-analyze security`` overall exposure (0 best .. 10 worst) the unit must not exceed.
#: Measured 1.3 with systemd 252; the rest is the host network, AF_CAN/INET/UNIX/NETLINK sockets
#: and no IP allow-list, which bmsid needs (deploy/README.md).
MAX_EXPOSURE = 1.5

ToolFinder = Callable[[str], str]


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def unit_entries(text: str) -> list[tuple[str, str, str]]:
    """(section, key, value) of a systemd-style file, in order, repeated keys kept."""
    entries: list[tuple[str, str, str]] = []
    section = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1]
            continue
        key, sep, value = line.partition("=")
        assert sep, f"not a key=value line: {raw!r}"
        assert section, f"key before any section: {raw!r}"
        entries.append((section, key.strip(), value.strip()))
    return entries


def values(entries: list[tuple[str, str, str]], section: str, key: str) -> list[str]:
    return [v for s, k, v in entries if s == section and k == key]


def the_value(entries: list[tuple[str, str, str]], section: str, key: str) -> str:
    found = values(entries, section, key)
    assert len(found) == 1, f"[{section}] {key}= expected once, found {found}"
    return found[0]


def unit_environment(entries: list[tuple[str, str, str]]) -> dict[str, str]:
    env: dict[str, str] = {}
    for value in values(entries, "Service", "Environment"):
        name, _, val = value.partition("=")
        env[name] = val
    return env


def exec_start_script(entries: list[tuple[str, str, str]]) -> str:
    """The shell script of ``ExecStart=/bin/sh -c '...'``."""
    exec_start = the_value(entries, "Service", "ExecStart")
    match = re.fullmatch(r"/bin/sh -c '([^']*)'", exec_start)
    assert match, f"ExecStart is not /bin/sh -c '...': {exec_start}"
    return match.group(1)


def dev_bmsid() -> str:
    """The ``bmsid`` entry point of the environment running the tests."""
    candidate = Path(sys.executable).parent / "bmsid"
    found = str(candidate) if candidate.exists() else shutil.which("bmsid")
    assert found, "no bmsid executable beside the test interpreter or on PATH"
    return found


def verifiable_unit(tmp_path: Path, text: str | None = None) -> Path:
    """The unit with the venv path made real, for systemd-analyze (it checks that ExecStart's
    program exists); nothing else changes."""
    text = UNIT.read_text(encoding="utf-8") if text is None else text
    assert text.count(UNIT_BMSID) == 1
    path = tmp_path / "bmsid.service"
    path.write_text(text.replace(UNIT_BMSID, dev_bmsid()), encoding="utf-8")
    return path


def run(cmd: list[str], **kwargs: Any) -> subprocess.CompletedProcess[str]:
    kwargs.setdefault("timeout", 120)
    return subprocess.run(cmd, capture_output=True, text=True, check=False, **kwargs)


def verify_problems(analyze: str, unit: Path) -> list[str]:
    """Lines ``systemd-analyze verify`` prints about `unit` (nothing = clean)."""
    result = run([analyze, "verify", "--man=no", str(unit)], cwd=unit.parent)
    lines = [line for line in (result.stdout + result.stderr).splitlines() if line.strip()]
    ours = [line for line in lines if unit.name in line or str(unit.parent) in line]
    for line in lines:
        if line not in ours:
            print(f"systemd-analyze verify (not about our unit): {line}")
    if result.returncode != 0 and not ours:
        ours = [f"exit code {result.returncode}", *lines]
    return ours


# ---------------------------------------------------------------------------------------------
# systemd unit
# ---------------------------------------------------------------------------------------------


def test_unit_verifies_without_any_message(require_tool: ToolFinder, tmp_path: Path) -> None:
    analyze = require_tool("systemd-analyze")
    unit = verifiable_unit(tmp_path)
    assert verify_problems(analyze, unit) == []
    # The check is not blind: a bad line in the same unit is reported.
    broken_dir = tmp_path / "broken"
    broken_dir.mkdir()
    broken = verifiable_unit(
        broken_dir,
        UNIT.read_text(encoding="utf-8").replace("[Service]\n", "[Service]\nSetCredential=x:\n"),
    )
    problems = verify_problems(analyze, broken)
    assert any("Invalid syntax" in line for line in problems), problems


def test_unit_security_exposure(require_tool: ToolFinder, tmp_path: Path) -> None:
    analyze = require_tool("systemd-analyze")
    unit = verifiable_unit(tmp_path)
    result = run([analyze, "security", "--offline=yes", "--no-pager", str(unit)], cwd=tmp_path)
    output = result.stdout + result.stderr
    match = re.search(r"Overall exposure level for bmsid\.service: (\d+\.\d+) (\w+)", output)
    assert match, f"no exposure figure in:\n{output}"
    exposure, label = float(match.group(1)), match.group(2)
    print(f"systemd-analyze security --offline=yes: bmsid.service exposure {exposure} {label}")
    assert label == "OK"
    assert exposure <= MAX_EXPOSURE, output
    # The items that still cost points are the ones deploy/README.md explains, no others.
    costly = {
        m.group(1) for m in re.finditer(r"^✗ (\S+)\s.*\s(\d+\.\d+)\s*$", output, flags=re.MULTILINE)
    }
    assert costly <= {
        "RootDirectory=/RootImage=",
        "RestrictAddressFamilies=~AF_NETLINK",
        "RestrictAddressFamilies=~AF_UNIX",
        "RestrictAddressFamilies=~…",
        "RestrictAddressFamilies=~AF_(INET|INET6)",
        "PrivateNetwork=",
        "DeviceAllow=",
        "IPAddressDeny=",
    }, costly


def test_unit_settings_fit_the_daemon() -> None:
    entries = unit_entries(UNIT.read_text(encoding="utf-8"))
    service = {k: v for s, k, v in entries if s == "Service"}
    assert service["Type"] == "notify"
    assert service["NotifyAccess"] == "main"
    assert service["WatchdogSec"] == "30s"
    assert service["Restart"] == "on-failure"
    assert service["DynamicUser"] == "yes"
    assert service["StateDirectory"] == "bmsid"
    assert service["ConfigurationDirectory"] == "bmsid"
    assert service["CapabilityBoundingSet"] == ""
    assert service["PrivateUsers"] == "yes"
    assert set(service["RestrictAddressFamilies"].split()) == {
        "AF_CAN", "AF_INET", "AF_INET6", "AF_UNIX", "AF_NETLINK"
    }  # fmt: skip
    assert values(entries, "Service", "LoadCredential") == [
        "mqtt-password:/etc/bmsid/mqtt.password"
    ]
    assert exec_start_script(entries).endswith(UNIT_RUN)
    # Wanted and ordered, never bound to the CAN device: bmsid reopens the bus itself.
    assert "sys-subsystem-net-devices-can0.device" in values(entries, "Unit", "Wants")
    assert "sys-subsystem-net-devices-can0.device" in values(entries, "Unit", "After")
    for key in ("BindsTo", "Requires", "PartOf"):
        assert values(entries, "Unit", key) == [], key
    assert the_value(entries, "Install", "WantedBy") == "multi-user.target"


def test_unit_restart_prevent_status_is_bmsids_config_error(tmp_path: Path) -> None:
    """RestartPreventExitStatus=2 must be what bmsid exits with on a configuration error."""
    entries = unit_entries(UNIT.read_text(encoding="utf-8"))
    assert the_value(entries, "Service", "RestartPreventExitStatus") == "2"
    bad = tmp_path / "bad.toml"
    bad.write_text('pack_id = "p1"\n[can]\nn_cells = 4\nno_such_key = 1\n', encoding="utf-8")
    result = run([dev_bmsid(), "run", "--config", str(bad)])
    assert result.returncode == 2, result
    assert "can.no_such_key" in result.stderr


def test_unit_environment_names_are_real_settings(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The unit's BMSID_* variables, with %S and %d as systemd expands them, load into the
    settings model on top of the example config and land where the unit means them to."""
    entries = unit_entries(UNIT.read_text(encoding="utf-8"))
    env = unit_environment(entries)
    state_root, cred_dir = tmp_path / "var-lib", tmp_path / "credentials"
    cred_dir.mkdir()
    (cred_dir / "mqtt-password").write_text("s3cret\n", encoding="utf-8")
    expanded = {
        name: value.replace("%S", str(state_root)).replace("%d", str(cred_dir))
        for name, value in env.items()
        if name.startswith("BMSID_")
    }
    assert expanded == {
        "BMSID_STATE__DIRECTORY": f"{state_root}/bmsid",
        "BMSID_ESTIMATOR__KERNELS": "numpy",  # no JIT under MemoryDenyWriteExecute
    }
    # what ExecStart exports when the credential is not empty
    script = exec_start_script(entries)
    exported = re.findall(r'export (BMSID_\w+)="([^"]*)"', script)
    assert exported == [("BMSID_MQTT__PASSWORD_FILE", "%d/mqtt-password")]
    expanded["BMSID_MQTT__PASSWORD_FILE"] = f"{cred_dir}/mqtt-password"
    config = tmp_path / "bmsid.toml"
    config.write_text(
        EXAMPLE_CONFIG.read_text(encoding="utf-8").replace(
            '# username = "bmsid"', 'username = "bmsid"'
        ),
        encoding="utf-8",
    )
    for name, value in expanded.items():
        monkeypatch.setenv(name, value)
    settings: Settings = load_settings(config)
    assert settings.state.directory == state_root / "bmsid"
    assert settings.estimator.kernels == "numpy"
    assert settings.mqtt.password_file == cred_dir / "mqtt-password"
    assert settings.mqtt.password_value() == "s3cret"
    assert settings.systemd_notify is True  # READY/WATCHDOG reach Type=notify


@pytest.mark.parametrize(
    ("content", "exported"),
    [("s3cret\n", True), ("", False), (None, False)],
    ids=["password", "empty-file", "no-file"],
)
def test_exec_start_passes_the_password_file_only_when_not_empty(
    tmp_path: Path, content: str | None, exported: bool
) -> None:
    """ExecStart's shell part, run by /bin/sh as systemd would (%d expanded), with a stand-in
    for bmsid that prints its arguments and environment."""
    script = exec_start_script(unit_entries(UNIT.read_text(encoding="utf-8")))
    cred_dir = tmp_path / "credentials"
    cred_dir.mkdir()
    if content is not None:
        (cred_dir / "mqtt-password").write_text(content, encoding="utf-8")
    fake = tmp_path / "bmsid"
    fake.write_text(
        '#!/bin/sh\necho "args: $*"\necho "pw: ${BMSID_MQTT__PASSWORD_FILE-unset}"\n'
        'echo "pid: $$"\n',
        encoding="utf-8",
    )
    fake.chmod(0o755)
    shell = script.replace("%d", str(cred_dir)).replace(UNIT_BMSID, str(fake))
    env = {k: v for k, v in os.environ.items() if k != "BMSID_MQTT__PASSWORD_FILE"}
    proc = subprocess.Popen(["/bin/sh", "-c", shell], stdout=subprocess.PIPE, text=True, env=env)
    out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0
    assert "args: run --config /etc/bmsid/bmsid.toml" in out
    expected = f"{cred_dir}/mqtt-password" if exported else "unset"
    assert f"pw: {expected}" in out
    # exec: bmsid is the process systemd started (NotifyAccess=main, watchdog PID)
    assert f"pid: {proc.pid}" in out


# ---------------------------------------------------------------------------------------------
# systemd-networkd files
# ---------------------------------------------------------------------------------------------


def networkd_keys(real_part_missing: Callable[[str], NoReturn]) -> set[str]:
    """``Section.Key`` names systemd-networkd's config parser accepts, read from the gperf
    tables compiled into the binary (there is no offline "verify" for .network files)."""
    if not NETWORKD_BINARY.exists():
        real_part_missing(f"{NETWORKD_BINARY} (Debian package systemd)")
    data = NETWORKD_BINARY.read_bytes()
    keys = {
        m.decode()
        for m in re.findall(rb"(?<=\x00)([A-Z][A-Za-z0-9]*\.[A-Z][A-Za-z0-9]*)\x00", data)
    }
    assert {"Match.Name", "CAN.BitRate", "NetDev.Kind", "Link.RequiredForOnline"} <= keys
    return keys


@pytest.mark.parametrize("name", ["80-can0.network", "80-vcan0.netdev", "80-vcan0.network"])
def test_networkd_file_keys_are_known_to_networkd(
    name: str, real_part_missing: Callable[[str], NoReturn]
) -> None:
    known = networkd_keys(real_part_missing)
    entries = unit_entries((NETWORKD / name).read_text(encoding="utf-8"))
    assert entries
    unknown = [f"{s}.{k}" for s, k, _ in entries if f"{s}.{k}" not in known]
    assert unknown == [], f"{name}: keys systemd-networkd does not know: {unknown}"
    # A CAN link has no address: it must not hold up network-online.target (bmsid's After=).
    if name.endswith(".network"):
        assert the_value(entries, "Link", "RequiredForOnline") == "no"


def test_networkd_values_and_consistency() -> None:
    can0 = unit_entries((NETWORKD / "80-can0.network").read_text(encoding="utf-8"))
    assert the_value(can0, "Match", "Name") == "can0"
    bitrate = the_value(can0, "CAN", "BitRate")
    assert re.fullmatch(r"\d+[KM]?", bitrate), bitrate  # systemd.network: SI prefixes, base 1000
    bitrate_bps = int(bitrate.rstrip("KM")) * {"K": 1000, "M": 1_000_000}.get(bitrate[-1], 1)
    sample_point = the_value(can0, "CAN", "SamplePoint")
    assert re.fullmatch(r"\d{1,2}(\.\d)?%", sample_point), sample_point
    restart = the_value(can0, "CAN", "RestartSec")
    assert restart == "100ms"
    # the same numbers as vcan-setup.sh's defaults and the example config's bus bit rate
    script = (DEPLOY / "vcan-setup.sh").read_text(encoding="utf-8")
    assert f"BITRATE={bitrate_bps}\n" in script
    assert "RESTART_MS=100\n" in script
    assert f"SAMPLE_POINT={float(sample_point.rstrip('%')) / 100:g}\n" in script
    assert re.search(rf"^bitrate_bps = {bitrate_bps}\b", EXAMPLE_CONFIG.read_text(), re.M)
    netdev = unit_entries((NETWORKD / "80-vcan0.netdev").read_text(encoding="utf-8"))
    vcan_network = unit_entries((NETWORKD / "80-vcan0.network").read_text(encoding="utf-8"))
    assert the_value(netdev, "NetDev", "Kind") == "vcan"
    assert the_value(netdev, "NetDev", "Name") == the_value(vcan_network, "Match", "Name")


# ---------------------------------------------------------------------------------------------
# shell scripts
# ---------------------------------------------------------------------------------------------

SCRIPTS = ["install.sh", "vcan-setup.sh"]


@pytest.mark.parametrize("name", SCRIPTS)
def test_script_is_clean_for_bash_and_shellcheck(name: str, require_tool: ToolFinder) -> None:
    path = DEPLOY / name
    assert path.stat().st_mode & stat.S_IXUSR, f"{name} is not executable"
    assert run(["bash", "-n", str(path)]).returncode == 0
    result = run([require_tool("shellcheck"), "--severity=style", str(path)])
    assert result.returncode == 0, result.stdout + result.stderr
    help_run = run([str(path), "--help"])
    assert help_run.returncode == 0
    assert "Usage:" in help_run.stdout


def test_vcan_setup_dry_run_and_errors() -> None:
    script = str(DEPLOY / "vcan-setup.sh")
    absent = "vcan97"  # no such interface on any test machine
    dry = run([script, "--dry-run", absent])
    assert dry.returncode == 0, dry.stderr
    assert f"+ ip link add dev {absent} type vcan\n+ ip link set up {absent}\n" in dry.stdout
    if not Path("/sys/module/vcan").exists():
        assert dry.stdout.startswith("+ modprobe vcan\n")
    missing = run([script, "--dry-run", "can97"])
    assert missing.returncode == 1
    assert "no interface can97" in missing.stderr
    for bad in (["--bitrate", "fast"], ["--sample-point", "87.5"], ["a", "b"], ["--nope"]):
        result = run([script, *bad])
        assert result.returncode == 2, bad
        assert "see --help" in result.stderr


@pytest.mark.realcan
def test_vcan_setup_creates_and_keeps_a_real_vcan(vcan_channel: str) -> None:
    """In User-Mode Linux (root, real SocketCAN): create, re-run, refuse a vcan as real CAN."""
    script = str(DEPLOY / "vcan-setup.sh")
    name = "vcan5"
    impostor = "can9"  # a vcan called like a real controller
    try:
        first = run([script, name])
        assert first.returncode == 0, first.stderr
        assert f"{name} is up" in first.stdout
        shown = run(["ip", "-details", "link", "show", "dev", name])
        assert "UP" in shown.stdout.split("\n")[0]
        assert "vcan" in shown.stdout
        again = run([script, name])
        assert again.returncode == 0
        assert "nothing to do" in again.stdout
        assert "nothing to do" in run([script, vcan_channel]).stdout
        assert run(["ip", "link", "add", "dev", impostor, "type", "vcan"]).returncode == 0
        refused = run([script, impostor])
        assert refused.returncode == 1
        assert "is a vcan interface" in refused.stderr
    finally:
        for dev in (name, impostor):
            run(["ip", "link", "del", "dev", dev])


# ---------------------------------------------------------------------------------------------
# install.sh
# ---------------------------------------------------------------------------------------------


def install(root: Path, *args: str) -> subprocess.CompletedProcess[str]:
    venv = Path(dev_bmsid()).parent.parent
    result = run(
        [str(DEPLOY / "install.sh"), "--root", str(root), "--no-systemctl",
         "--link-venv", str(venv), *args]
    )  # fmt: skip
    print(result.stdout, result.stderr)
    return result


def test_install_twice_keeps_an_edited_config(tmp_path: Path) -> None:
    root = tmp_path / "root"
    root.mkdir()
    first = install(root, "--networkd", "--networkd-vcan")
    assert first.returncode == 0, first.stderr
    etc = root / "etc" / "bmsid"
    config = etc / "bmsid.toml"
    assert config.read_bytes() == EXAMPLE_CONFIG.read_bytes()
    assert stat.S_IMODE(config.stat().st_mode) == 0o644
    password = etc / "mqtt.password"
    assert password.read_bytes() == b""
    assert stat.S_IMODE(password.stat().st_mode) == 0o600
    unit = root / "etc" / "systemd" / "system" / "bmsid.service"
    assert unit.read_bytes() == UNIT.read_bytes()
    doc = root / "usr" / "share" / "doc" / "bmsid"
    for rel in ("README.md", "examples/mosquitto/bmsid.acl", "examples/mosquitto/bmsid.conf",
                "examples/dashboard/node-red-flow.json", "examples/networkd/80-can0.network",
                "examples/bmsid.example.toml"):  # fmt: skip
        assert (doc / rel).is_file(), rel
    assert os.access(root / "opt" / "bmsid" / "bin" / "vcan-setup.sh", os.X_OK)
    network = root / "etc" / "systemd" / "network"
    assert sorted(p.name for p in network.iterdir()) == [
        "80-can0.network", "80-vcan0.netdev", "80-vcan0.network"
    ]  # fmt: skip

    # The installed bmsid accepts the installed config (with the unit's state directory).
    bmsid = root / "opt" / "bmsid" / "venv" / "bin" / "bmsid"
    env = {**os.environ, "BMSID_STATE__DIRECTORY": str(tmp_path / "state")}
    check = run([str(bmsid), "check-config", str(config)], env=env)
    assert check.returncode == 0, check.stderr
    assert "valid" in check.stdout

    # Second run, after the operator edited the config and wrote a password.
    edited = config.read_text(encoding="utf-8").replace('pack_id = "pack-01"', 'pack_id = "site-7"')
    assert edited != EXAMPLE_CONFIG.read_text(encoding="utf-8")
    config.write_text(edited, encoding="utf-8")
    password.write_text("pw\n", encoding="utf-8")
    can0 = network / "80-can0.network"
    can0.write_text(can0.read_text(encoding="utf-8").replace("BitRate=500K", "BitRate=250K"))
    unit.write_text("stale\n", encoding="utf-8")
    second = install(root, "--networkd")
    assert second.returncode == 0, second.stderr
    assert config.read_text(encoding="utf-8") == edited
    assert (etc / "bmsid.toml.new").read_bytes() == EXAMPLE_CONFIG.read_bytes()
    assert "bmsid.toml.new" in second.stdout
    assert password.read_text(encoding="utf-8") == "pw\n"
    assert "BitRate=250K" in can0.read_text(encoding="utf-8")
    assert (network / "80-can0.network.new").read_bytes() == (
        NETWORKD / "80-can0.network"
    ).read_bytes()
    assert unit.read_bytes() == UNIT.read_bytes()  # ours: always replaced
    check = run([str(bmsid), "check-config", str(config)], env=env)
    assert check.returncode == 0, check.stderr
    assert 'pack_id = "site-7"' in check.stdout

    # Third run with the config back to the example's: the stale .new goes away.
    config.write_bytes(EXAMPLE_CONFIG.read_bytes())
    assert install(root).returncode == 0
    assert not (etc / "bmsid.toml.new").exists()


def test_install_refuses_bad_arguments(tmp_path: Path) -> None:
    script = str(DEPLOY / "install.sh")
    cases = [
        (["--root", str(tmp_path / "missing")], "no such directory"),
        (["--root", str(tmp_path), "--link-venv", str(tmp_path)], "no bin/bmsid"),
        (["--root", str(tmp_path), str(tmp_path / "nope.whl")], "no such file"),
        (["--root", str(tmp_path), "--bogus"], "unknown option"),
    ]
    for args, message in cases:
        result = run([script, *args])
        assert result.returncode != 0, args
        assert message in result.stderr, (args, result.stderr)
    assert not (tmp_path / "etc").exists()  # refused before writing anything


# ---------------------------------------------------------------------------------------------
# Mosquitto: the example ACL on a real broker
# ---------------------------------------------------------------------------------------------

PASSWORDS = {"bmsid": "gw-pw-1", "dashboard": "dash-pw-2", "homeassistant": "ha-pw-3",
             "monitor": "mon-pw-4"}  # fmt: skip


class Subscriber:
    """mosquitto_sub in the background; messages as lines ``=MSG= topic payload``."""

    def __init__(self, exe: str, host: str, port: int, user: str, topics: list[str]) -> None:
        # stdbuf: mosquitto_sub's stdout is block-buffered into a pipe
        cmd = ["stdbuf", "-oL", exe, "-h", host, "-p", str(port), "-u", user,
               "-P", PASSWORDS[user], "-d", "-q", "1", "-F", "=MSG= %t %p"]  # fmt: skip
        for t in topics:
            cmd += ["-t", t]
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()
        try:
            self.wait_for(lambda line: "received SUBACK" in line, 10.0, "SUBACK")
        except AssertionError:
            self.close()
            raise

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))

    def wait_for(self, pred: Callable[[str], bool], timeout: float, what: str) -> str:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(
                    f"no {what} within {timeout} s; saw {len(self.seen)} lines, the last: "
                    f"{self.seen[-6:]}"
                )
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                continue
            self.seen.append(line)
            if pred(line):
                return line

    def next_message(self, timeout: float = 10.0) -> str:
        return self.wait_for(lambda line: line.startswith("=MSG= "), timeout, "message")[6:]

    def messages_until(self, last: str, timeout: float = 10.0) -> list[str]:
        """Messages up to and including `last`."""
        got: list[str] = []
        while not got or got[-1] != last:
            got.append(self.next_message(timeout))
        return got

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=5)


@pytest.fixture
def acl_broker(
    mosquitto_factory: Callable[..., Any], require_tool: ToolFinder, tmp_path: Path
) -> Iterator[tuple[str, int]]:
    """A real Mosquitto with bmsid.conf's authentication settings and bmsid.acl verbatim (plus
    a test-only user ``monitor`` that reads everything); listener: the fixture's loopback port
    (the TLS listener is another test's business)."""
    passwd_tool = require_tool("mosquitto_passwd")
    passwd = tmp_path / "passwd"
    for i, (user, password) in enumerate(PASSWORDS.items()):
        create = ["-c"] if i == 0 else []
        result = run([passwd_tool, *create, "-b", str(passwd), user, password])
        assert result.returncode == 0, result.stderr
    acl = tmp_path / "acl"
    acl.write_text(
        (DEPLOY / "mosquitto" / "bmsid.acl").read_text(encoding="utf-8")
        + "\n# test only\nuser monitor\ntopic read #\n",
        encoding="utf-8",
    )
    globals_: list[str] = []
    for line in (DEPLOY / "mosquitto" / "bmsid.conf").read_text(encoding="utf-8").splitlines():
        if line.startswith("listener"):
            break  # the listeners follow the global part
        if not line.strip() or line.startswith("#"):
            continue
        key = line.split()[0]
        value = {"password_file": str(passwd), "acl_file": str(acl)}.get(key)
        globals_.append(f"{key} {value}" if value else line)
    assert {g.split()[0] for g in globals_} == {
        "allow_anonymous",
        "password_file",
        "acl_file",
        "max_queued_messages",
    }
    assert "allow_anonymous false" in globals_
    broker = mosquitto_factory("\n".join(globals_))
    yield broker.host, broker.port


def test_mosquitto_acl_allows_and_refuses_what_it_says(
    acl_broker: tuple[str, int], require_tool: ToolFinder
) -> None:
    host, port = acl_broker
    sub_exe, pub_exe = require_tool("mosquitto_sub"), require_tool("mosquitto_pub")

    def publish(user: str | None, t: str, payload: str) -> subprocess.CompletedProcess[str]:
        auth = ["-u", user, "-P", PASSWORDS[user]] if user else []
        cmd = [pub_exe, "-h", host, "-p", str(port), *auth, "-q", "1", "-t", t, "-m", payload]
        return run(cmd, timeout=15)

    cell = topic("bmsid", "p1", "cell", 0)
    discovery = "homeassistant/sensor/bmsid_p1/cell0_r0/config"
    subscribers: list[Subscriber] = []

    def subscribe(user: str, topics: list[str]) -> Subscriber:
        subscribers.append(Subscriber(sub_exe, host, port, user, topics))
        return subscribers[-1]

    try:
        dashboard = subscribe("dashboard", ["bmsid/#"])
        monitor = subscribe("monitor", ["#"])
        bmsid = subscribe("bmsid", ["homeassistant/status", "bmsid/#"])
        ha = subscribe("homeassistant", ["homeassistant/#", "bmsid/#"])
        # bmsid publishes its topics; the dashboard and Home Assistant read them.
        assert publish("bmsid", cell, "c0").returncode == 0
        assert dashboard.next_message() == f"{cell} c0"
        assert ha.next_message() == f"{cell} c0"
        assert monitor.next_message() == f"{cell} c0"
        # Each refused publish is followed by an allowed marker: the first message a reader
        # sees next must be the marker, so the refused one was dropped, not merely late.
        refused = [
            ("bmsid", "other/x"),  # outside bmsid's prefixes
            ("bmsid", "homeassistant/status"),  # HA's birth message is HA's
            ("dashboard", cell),  # dashboards only read
            ("homeassistant", cell),
        ]
        for n, (user, t) in enumerate(refused):
            result = publish(user, t, f"refused-{n}")
            assert result.returncode == 0, result.stderr  # Mosquitto 2 drops it silently
            assert publish("bmsid", cell, f"marker-{n}").returncode == 0
            assert monitor.next_message() == f"{cell} marker-{n}", (user, t)
        # bmsid reads nothing of its own topics (write-only), but HA's birth message and it
        # writes discovery configs that Home Assistant reads.
        assert publish("homeassistant", "homeassistant/status", "online").returncode == 0
        assert bmsid.next_message() == "homeassistant/status online"
        assert publish("bmsid", discovery, "{}").returncode == 0
        seen_by_ha = ha.messages_until(f"{discovery} {{}}")
        assert f"{cell} marker-0" in seen_by_ha
        assert not any("refused-" in m for m in seen_by_ha), seen_by_ha
        # the dashboard saw only bmsid's own messages, in order
        expected = [f"{cell} marker-{n}" for n in range(len(refused))]
        assert [dashboard.next_message() for _ in expected] == expected
        for sub in (bmsid, dashboard):
            assert not any("refused-" in line for line in sub.seen)
    finally:
        for sub in subscribers:
            sub.close()
    # No anonymous clients, no wrong passwords.
    anonymous = publish(None, cell, "anon")
    assert anonymous.returncode != 0
    assert "not authori" in anonymous.stderr.lower()
    wrong = run(
        [pub_exe, "-h", host, "-p", str(port), "-u", "bmsid", "-P", "wrong", "-t", cell, "-m", "x"]
    )
    assert wrong.returncode != 0


def test_mosquitto_config_keeps_a_backlog_for_a_dashboard_that_falls_behind(
    acl_broker: tuple[str, int], require_tool: ToolFinder
) -> None:
    """bmsid delivers its outbox after an outage as fast as the broker takes it. A dashboard
    that cannot keep up (here: stopped) must get all of it, in order; with Mosquitto's default
    it would get the first 1020 only."""
    host, port = acl_broker
    n = 3000
    cell = topic("bmsid", "p1", "cell", 0)
    dashboard = Subscriber(require_tool("mosquitto_sub"), host, port, "dashboard", ["bmsid/#"])
    try:
        dashboard.proc.send_signal(signal.SIGSTOP)
        try:
            pub = [require_tool("mosquitto_pub"), "-h", host, "-p", str(port), "-u", "bmsid",
                   "-P", PASSWORDS["bmsid"], "-q", "1", "-t", cell, "-l"]  # fmt: skip
            result = run(pub, input="".join(f"m{i}\n" for i in range(n)), timeout=60)
            assert result.returncode == 0, result.stderr
        finally:
            dashboard.proc.send_signal(signal.SIGCONT)
        got = dashboard.messages_until(f"{cell} m{n - 1}", timeout=30.0)
        assert got == [f"{cell} m{i}" for i in range(n)]
    finally:
        dashboard.close()


# ---------------------------------------------------------------------------------------------
# Node-RED flow
# ---------------------------------------------------------------------------------------------


def mqtt_topic_matches(pattern: str, name: str) -> bool:
    p, n = pattern.split("/"), name.split("/")
    for i, level in enumerate(p):
        if level == "#":
            return True
        if i >= len(n) or (level != "+" and level != n[i]):
            return False
    return len(p) == len(n)


def payload_fields(code: str) -> set[str]:
    """Fields a function node reads from the payload: ``p.x`` with ``const p = msg.payload``,
    and ``c.y`` with ``const c = p.x`` (reported as ``x.y``)."""
    assert "const p = msg.payload;" in code
    aliases = dict(re.findall(r"const (\w+) = p\.(\w+);", code))
    fields = set(re.findall(r"\bmsg\.payload\.(\w+)", code))
    fields |= set(re.findall(r"(?<![\w.])p\.(\w+)", code))
    for alias, parent in aliases.items():
        fields |= {f"{parent}.{f}" for f in re.findall(rf"(?<![\w.]){alias}\.(\w+)", code)}
    return fields


def documented_status_counters() -> set[str]:
    """Counter names from the status example in docs/mqtt.md."""
    doc = (REPO / "docs" / "mqtt.md").read_text(encoding="utf-8")
    section = doc.split("## Status", 1)[1]
    block = section.split("```json", 1)[1].split("```", 1)[0]
    counters: dict[str, Any] = json.loads(block)["counters"]
    return set(counters)


def schema_fields(schema: dict[str, Any]) -> set[str]:
    fields: set[str] = set()
    for name, spec in schema["properties"].items():
        fields.add(name)
        for sub in spec.get("properties", {}):
            fields.add(f"{name}.{sub}")
        for sub in spec.get("required", []):
            fields.add(f"{name}.{sub}")
    return fields


def test_node_red_flow_reads_only_published_topics_and_fields() -> None:
    flow: list[dict[str, Any]] = json.loads(
        (DEPLOY / "dashboard" / "node-red-flow.json").read_text(encoding="utf-8")
    )
    by_id = {node["id"]: node for node in flow}
    assert len(by_id) == len(flow), "duplicate node ids"
    # every wire and config reference points at a node of the flow
    for node in flow:
        for outputs in node.get("wires", []):
            for target in outputs:
                assert target in by_id, f"{node['id']} wired to missing {target}"
        for ref in ("broker", "group", "tab", "z", "page", "ui", "theme"):
            if ref in node and not (node["type"] == "mqtt-broker" and ref == "broker"):
                assert node[ref] in by_id, f"{node['id']}.{ref} -> missing {node[ref]}"
    # the daemon's topics (publish/payloads.py) for a sample pack
    published = {
        "cell": topic("bmsid", "p1", "cell", 3),
        "pack": topic("bmsid", "p1", "pack"),
        "status": topic("bmsid", "p1", "status"),
    }
    schemas = {k: json.loads((SCHEMAS / f"{k}.json").read_text()) for k in published}
    allowed = {k: schema_fields(s) for k, s in schemas.items()}
    allowed["status"] |= {f"counters.{c}" for c in documented_status_counters()}
    covered: set[str] = set()
    widgets: set[str] = set()
    for node in (n for n in flow if n["type"] == "mqtt in"):
        kinds = [k for k, t in published.items() if mqtt_topic_matches(node["topic"], t)]
        assert len(kinds) == 1, f"{node['topic']} matches {kinds} of bmsid's topics"
        kind = kinds[0]
        covered.add(kind)
        assert node["broker"] in by_id
        assert by_id[node["broker"]]["type"] == "mqtt-broker"
        # mqtt in -> json -> function(s) that read the payload
        (parse_id,) = (t for outs in node["wires"] for t in outs)
        parse = by_id[parse_id]
        assert parse["type"] == "json"
        assert parse["property"] == "payload"
        functions = [by_id[t] for outs in parse["wires"] for t in outs]
        assert functions
        assert all(f["type"] == "function" for f in functions)
        for fn in functions:
            fields = payload_fields(fn["func"])
            assert fields, fn["name"]
            unknown = fields - allowed[kind]
            assert not unknown, f"{fn['name']} reads {sorted(unknown)}, not in {kind}.json"
            assert fn["outputs"] == len(fn["wires"])
            widgets |= {by_id[t]["type"] for outs in fn["wires"] for t in outs}
    assert covered == set(published)
    # FlowFuse Dashboard 2's widgets (the deprecated node-red-dashboard's were ui_chart, ...)
    assert {"ui-chart", "ui-gauge", "ui-text"} <= widgets
    # the quantities the dashboard promises
    cell_fn = next(n for n in flow if n["type"] == "function" and "cell" in n["name"])
    assert {"R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "tau2_s", "soc", "v_error_V"} <= (
        payload_fields(cell_fn["func"])
    )


# ---------------------------------------------------------------------------------------------
# Replay recipe
# ---------------------------------------------------------------------------------------------


def test_replay_block_matches_the_log_and_the_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    readme = (DEPLOY / "README.md").read_text(encoding="utf-8")
    section = readme.split("## Replay a log on a virtual bus", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```sh\n(.*?)```", section, flags=re.DOTALL)
    assert len(blocks) == 1, "the replay section has exactly one copy-paste block"
    block = blocks[0]
    match = re.search(r"canplayer -I (\S+) vcan0=(\w+)", block)
    assert match, block
    log = REPO / match.group(1)
    assert log == DEMO_LOG
    channels = {line.split()[1] for line in log.read_text().splitlines()[:50]}
    assert channels == {match.group(2)}
    # the overrides are settings the daemon knows, and the config is the example
    overrides = dict(re.findall(r"\b(BMSID_\w+)=(\S+)", block))
    assert overrides["BMSID_CAN__CHANNEL"] == "vcan0"
    assert "--config configs/bmsid.example.toml" in block
    for name, value in overrides.items():
        monkeypatch.setenv(name, value)
    settings = load_settings(EXAMPLE_CONFIG)
    assert settings.can.channel == "vcan0"
    assert settings.can.n_cells == 8  # the demo log's pack
    assert "deploy/vcan-setup.sh vcan0" in block
    assert "mosquitto_sub -t 'bmsid/#' -v" in block
