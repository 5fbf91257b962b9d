"""Shared fixtures for tests that need real parts: SocketCAN vcan, Mosquitto and can-utils.

One rule for every real part: when it is missing, the test FAILS if real parts are required
(env ``CI``, ``BMSID_REQUIRE_REAL`` or ``BMSID_IN_UML`` set to anything but "", "0", "false",
"no") and is SKIPPED with the reason otherwise (a developer laptop without vcan).

Fixtures other tests use:

- ``vcan_channel`` (session) -> "vcan0" (name from env ``BMSID_VCAN_CHANNEL``), checked by
  opening a raw CAN socket on it.
- ``vcan_channels`` (session) -> ("vcan0", "vcan1") for tests that need two buses.
- ``require_tool`` -> callable ``(name) -> absolute path`` of candump, canplayer, cansend,
  mosquitto_sub, ...
- ``mosquitto_broker`` (function scope: each test gets a fresh broker with no retained
  messages or sessions, and starting one costs ~20 ms) -> ``BrokerAddress(host, port)``.
- ``mosquitto_factory`` (function scope) -> callable ``(config, *, port=None) ->
  MosquittoBroker`` that starts a broker from extra config text, with ``stop()``, ``start()``
  and ``restart()`` on the SAME port (outage tests). All brokers stop at teardown.
- ``real_part_missing`` -> callable ``(what) -> NoReturn`` applying the fail/skip rule.

Hooks:

- a ``realcan`` test is skipped/failed (rule above) before setup when vcan0 is unusable, so it
  never errors on a socket call in the middle;
- when real parts are required, a ``realcan`` test that ends up skipped anyway (importorskip,
  skipif, pytest.skip) is reported as FAILED;
- inside UML (``BMSID_IN_UML=1``, set by scripts/uml-run) only ``realcan`` tests are selected:
  the rest already ran on the host at host speed, and a realcan phase that selects nothing exits
  with pytest's "no tests collected" status, which scripts/test treats as a failure.
"""

from __future__ import annotations

import logging
import os
import pwd
import random
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Generator, Iterator
from functools import cache
from pathlib import Path
from typing import NamedTuple, NoReturn

import pytest

from bmsid.threads import one_blas_thread

HOW_TO_GET_REAL_PARTS = (
    "run ./scripts/test (it boots User-Mode Linux when the kernel has no CAN), or "
    "scripts/uml-run pytest -m realcan ..., or on a kernel with CAN: "
    "ip link add dev vcan0 type vcan && ip link set up vcan0; "
    "packages: can-utils mosquitto mosquitto-clients"
)
_FALSE_WORDS = frozenset({"", "0", "false", "no"})
_SBIN_DIRS = ("/usr/local/sbin", "/usr/sbin", "/sbin")  # mosquitto lives in /usr/sbin
BROKER_START_TIMEOUT_S = 15.0  # generous: UML syscalls are slow
BROKER_STOP_TIMEOUT_S = 5.0


@pytest.fixture(autouse=True)
def _restore_root_logger() -> Iterator[None]:
    """``bmsid.cli.main`` sets the root logger's level and handler (the CLI and fault tests
    call it in-process): leave them as found for later tests."""
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    yield
    root.setLevel(level)
    root.handlers[:] = handlers


def _env_flag(name: str) -> bool:
    return os.environ.get(name, "").strip().lower() not in _FALSE_WORDS


def real_parts_required() -> bool:
    """True when a missing real part must fail the test instead of skipping it."""
    return any(_env_flag(name) for name in ("CI", "BMSID_REQUIRE_REAL", "BMSID_IN_UML"))


def in_uml() -> bool:
    return _env_flag("BMSID_IN_UML")


def missing_real_part(what: str) -> NoReturn:
    """Fail (real parts required) or skip (developer machine) because `what` is missing."""
    message = f"real part missing: {what}; {HOW_TO_GET_REAL_PARTS}"
    if real_parts_required():
        pytest.fail(
            f"{message} [failing, not skipping: real parts are required, env CI, "
            "BMSID_REQUIRE_REAL or BMSID_IN_UML is set]",
            pytrace=False,
        )
    pytest.skip(message)


def vcan_name(index: int = 0) -> str:
    """Name of the index-th test bus: env BMSID_VCAN_CHANNEL (default vcan0), then vcan1."""
    first = os.environ.get("BMSID_VCAN_CHANNEL", "vcan0")
    return first if index == 0 else f"vcan{index}"


@cache
def can_socket_problem(channel: str) -> str | None:
    """Why a raw CAN socket cannot be bound to `channel`, or None when it can."""
    if not hasattr(socket, "AF_CAN"):
        return "this Python has no socket.AF_CAN (not Linux?)"
    try:
        with socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW) as sock:
            sock.bind((channel,))
    except OSError as exc:
        return f"cannot bind a raw CAN socket to {channel!r}: {exc}"
    return None


def require_vcan(channel: str) -> str:
    problem = can_socket_problem(channel)
    if problem is not None:
        missing_real_part(problem)
    return channel


def find_tool(name: str) -> str | None:
    """Absolute path of executable `name` on PATH or in the sbin directories, or None."""
    found = shutil.which(name)
    if found is None:
        found = shutil.which(name, path=os.pathsep.join(_SBIN_DIRS))
    return found


def require_tool(name: str) -> str:
    """Absolute path of executable `name`; fails or skips (rule above) when it is missing."""
    path = find_tool(name)
    if path is None:
        missing_real_part(f"executable {name!r} not found on PATH or in {':'.join(_SBIN_DIRS)}")
    return path


def _ephemeral_port_range() -> tuple[int, int]:
    try:
        low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(low), int(high)
    except (OSError, ValueError):
        return 32768, 60999  # Linux's default


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago, outside the ephemeral range.

    Why outside: while a broker is down, a client reconnecting to a port in the kernel's
    ephemeral range can be given that same port as its source port and connect to itself (a TCP
    simultaneous open; paho then reads its own CONNECT: "Unrecognised command 16"), and then holds
    the port the broker is restarted on ("Address already in use"). The kernel never picks a
    source port outside the range, so such a port stays the broker's.
    """
    low, high = _ephemeral_port_range()
    candidates = [p for p in range(10000, 65536) if not low <= p <= high]
    rng = random.Random()  # independent of any test's seeded random state
    for _ in range(200):
        port = rng.choice(candidates)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"no free loopback port outside the ephemeral range {low}-{high}")


def port_accepts(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=1.0):
            return True
    except OSError:
        return False


def _current_user() -> str:
    return pwd.getpwuid(os.geteuid()).pw_name


class BrokerAddress(NamedTuple):
    host: str
    port: int


class MosquittoBroker:
    """Debian's mosquitto on a fixed loopback port, from generated config, stoppable/restartable.

    The config file is ``listener PORT 127.0.0.1``, ``persistence false`` (nothing written to
    the working directory), ``user <whoever runs the tests>`` (as root, mosquitto would drop to
    user "mosquitto" before reading password files and fail on pytest's private tmp dirs), then
    `extra_config`: its per-listener options (certfile, keyfile, cafile, require_certificate,
    ...) apply to that listener; global ones (allow_anonymous, password_file, ...) work too.
    """

    def __init__(self, executable: str, workdir: Path, port: int, extra_config: str) -> None:
        self.executable = executable
        self.workdir = workdir
        self.address = BrokerAddress("127.0.0.1", port)
        self.config_path = workdir / "mosquitto.conf"
        self.log_path = workdir / "mosquitto.log"
        self.config_path.write_text(
            f"listener {port} 127.0.0.1\npersistence false\nuser {_current_user()}\n"
            f"{extra_config.strip()}\n",
            encoding="utf-8",
        )
        self._process: subprocess.Popen[bytes] | None = None

    @property
    def host(self) -> str:
        return self.address.host

    @property
    def port(self) -> int:
        return self.address.port

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def log_text(self) -> str:
        return self.log_path.read_text(encoding="utf-8", errors="replace")

    def start(self) -> BrokerAddress:
        """Start the broker and wait until its port accepts connections."""
        if self.running:
            raise RuntimeError(f"mosquitto on port {self.port} is already running")
        with self.log_path.open("ab") as log:
            self._process = subprocess.Popen(
                [self.executable, "-c", str(self.config_path)],
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        deadline = time.monotonic() + BROKER_START_TIMEOUT_S
        while not port_accepts(*self.address):
            if self._process.poll() is not None:
                raise RuntimeError(
                    f"mosquitto exited with {self._process.returncode} on port {self.port}; "
                    f"log:\n{self.log_text()}"
                )
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(
                    f"mosquitto did not accept on port {self.port} within "
                    f"{BROKER_START_TIMEOUT_S} s; log:\n{self.log_text()}"
                )
            time.sleep(0.02)
        return self.address

    def stop(self) -> None:
        """Stop the broker (SIGTERM, then SIGKILL); a no-op when it is not running."""
        process, self._process = self._process, None
        if process is None or process.poll() is not None:
            return
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=BROKER_STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()

    def restart(self) -> BrokerAddress:
        self.stop()
        return self.start()


@pytest.fixture
def restore_kernel() -> Iterator[None]:
    """Put back the process's kernel choice (``jit.select``) that a kernel test changes."""
    from bmsid.estimate import jit  # here: numba only for the tests that use it

    before = jit.MODE
    yield
    jit.restore(before)


#: Tests count every message their subscriber (another process) gets. Under load it can fall
#: behind a burst, and Mosquitto's default then drops all past 1000 queued for it, silently:
#: the broker's loss, not the daemon's, so the test brokers queue without a limit.
DEFAULT_BROKER_CONFIG = "allow_anonymous true\nmax_queued_messages 0\n"

BrokerFactory = Callable[..., MosquittoBroker]


@pytest.fixture
def mosquitto_factory(tmp_path_factory: pytest.TempPathFactory) -> Iterator[BrokerFactory]:
    """Callable ``(extra_config=DEFAULT_BROKER_CONFIG, *, port=None) -> MosquittoBroker``.

    The broker is started before it is returned; `port` None picks a free loopback port.
    """
    executable = require_tool("mosquitto")
    brokers: list[MosquittoBroker] = []

    def start(
        extra_config: str = DEFAULT_BROKER_CONFIG, *, port: int | None = None
    ) -> MosquittoBroker:
        # A free port can be taken between probe and bind: retry on a fresh one if not pinned.
        attempts = 1 if port is not None else 3
        for attempt in range(attempts):
            workdir = tmp_path_factory.mktemp("mosquitto")
            broker = MosquittoBroker(
                executable, workdir, port or free_loopback_port(), extra_config
            )
            brokers.append(broker)
            try:
                broker.start()
            except RuntimeError:
                if attempt == attempts - 1 or "Address already in use" not in broker.log_text():
                    raise
            else:
                return broker
        raise AssertionError("unreachable")

    yield start
    for broker in brokers:
        broker.stop()


@pytest.fixture
def mosquitto_broker(mosquitto_factory: BrokerFactory) -> BrokerAddress:
    """A fresh anonymous, non-persistent mosquitto on 127.0.0.1; yields (host, port)."""
    return mosquitto_factory().address


@pytest.fixture(scope="session")
def vcan_channel() -> str:
    """Name of the first test bus ("vcan0" or $BMSID_VCAN_CHANNEL), checked by binding to it."""
    return require_vcan(vcan_name(0))


@pytest.fixture(scope="session")
def vcan_channels() -> tuple[str, str]:
    """Two independent buses, ("vcan0", "vcan1"), both checked."""
    return require_vcan(vcan_name(0)), require_vcan(vcan_name(1))


@pytest.fixture(name="require_tool")
def require_tool_fixture() -> Callable[[str], str]:
    """``require_tool("candump")`` -> absolute path; fails/skips when the tool is missing."""
    return require_tool


@pytest.fixture
def real_part_missing() -> Callable[[str], NoReturn]:
    """``real_part_missing("what")`` fails or skips the test by the real-parts rule."""
    return missing_real_part


#: Measured cell data (``shared/data/real`` beside the clone, as in CI), never copied here.
REAL_DATA_DIR = Path(
    os.environ.get("BMSID_REAL_DATA", Path(__file__).resolve().parents[1].parent / "shared"
                   / "data" / "real")
)  # fmt: skip


@pytest.fixture
def real_data_dir() -> Path:
    """The measured-data folder (``$BMSID_REAL_DATA`` or ``../shared/data/real``); a missing
    one fails or skips the test by the real-parts rule."""
    if not REAL_DATA_DIR.is_dir():
        missing_real_part(f"measured cell data at {REAL_DATA_DIR} (set BMSID_REAL_DATA)")
    return REAL_DATA_DIR


# ---------------------------------------------------------------------------------------------
# Hooks
# ---------------------------------------------------------------------------------------------


def pytest_report_header(config: pytest.Config) -> str:
    channel = vcan_name(0)
    vcan = can_socket_problem(channel) or f"{channel} usable"
    mosquitto = find_tool("mosquitto") or "mosquitto missing"
    return (
        f"bmsid real parts: {vcan}; {mosquitto}; required={real_parts_required()}; "
        f"in_uml={in_uml()}"
    )


_REALCAN_FILES_KEY = pytest.StashKey[set[str]]()


def pytest_itemcollected(item: pytest.Item) -> None:
    """Note the files holding realcan tests, before -m/-k deselect anything."""
    if item.get_closest_marker("realcan") is not None:
        item.config.stash.setdefault(_REALCAN_FILES_KEY, set()).add(str(item.path))


def pytest_collection_finish(session: pytest.Session) -> None:
    """Write the realcan test files to $BMSID_REALCAN_FILES_OUT (one per line) if set.

    scripts/test collects everything once on the host (`-m "not realcan"` phase) and hands this
    list to the realcan phase, so the slow UML guest imports only the modules it needs.
    """
    out = os.environ.get("BMSID_REALCAN_FILES_OUT")
    if out:
        files = sorted(session.config.stash.get(_REALCAN_FILES_KEY, None) or ())
        # Under pytest-xdist every worker collects (the same items) and writes: each its own
        # file, renamed over the list, so no reader ever sees a half-written one.
        part = Path(f"{out}.{os.getpid()}")
        part.write_text("".join(f"{file}\n" for file in files), encoding="utf-8")
        part.replace(out)


class _XdistPlan:
    """The order in which a pytest-xdist worker's tests are handed out. scripts/test runs the
    host phase with ``-n 2 --dist loadfile --no-loadscope-reorder``: a module's tests run on one
    worker, so a module-scoped fixture (a CLI run, a Dask cluster) is set up once, and modules
    go out in collection order, here with the ``slow`` tests' modules first (the 7-day daemon
    replay takes minutes: handed out late, it would run on one worker long after the other had
    finished everything else). Every worker collects the same items and sorts them alike.
    """

    @pytest.hookimpl(tryfirst=True)
    def pytest_collection_modifyitems(self, items: list[pytest.Item]) -> None:
        items.sort(key=lambda item: item.get_closest_marker("slow") is None)  # stable


def pytest_configure(config: pytest.Config) -> None:
    if hasattr(config, "workerinput"):  # a pytest-xdist worker
        config.pluginmanager.register(_XdistPlan(), "bmsid-xdist-plan")


def pytest_sessionstart(session: pytest.Session) -> None:
    """Under pytest-xdist, before the workers start (xdist's own hook runs last): compile the
    engine's kernels into numba's cache, once (about a minute after a fresh clone or an edit of
    a kernel, a second or two to load them otherwise). Serially the first test that needs them
    compiles them; in parallel every worker would, at once, and inside whatever test came
    first: a daemon's start then outlasted its tests' wait for the bus (20 s)."""
    if not session.config.pluginmanager.hasplugin("dsession"):  # not the xdist controller
        return
    import importlib
    import pkgutil

    import bmsid.estimate
    from bmsid.estimate import jit

    for module in pkgutil.iter_modules(bmsid.estimate.__path__):  # each kernel's module
        importlib.import_module(f"bmsid.estimate.{module.name}")
    jit.select(None)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Inside UML keep only realcan tests (the host runs the rest at host speed)."""
    if not in_uml():
        return
    host_only = [item for item in items if item.get_closest_marker("realcan") is None]
    if host_only:
        config.hook.pytest_deselected(items=host_only)
        items[:] = [item for item in items if item.get_closest_marker("realcan") is not None]


def pytest_runtest_setup(item: pytest.Item) -> None:
    if item.get_closest_marker("realcan") is not None:
        require_vcan(vcan_name(0))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    report = yield
    if (
        report.skipped
        and not hasattr(report, "wasxfail")
        and item.get_closest_marker("realcan") is not None
        and real_parts_required()
    ):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else report.longrepr
        report.outcome = "failed"
        report.longrepr = (
            f"realcan test skipped while real parts are required (CI/BMSID_REQUIRE_REAL/"
            f"BMSID_IN_UML): {reason}"
        )
    return report


one_blas_thread()  # as the CLI and the benchmarks run the engine (bmsid/threads.py)
