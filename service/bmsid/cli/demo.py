"""``bmsid demo``: the whole daemon with no hardware and no broker to install.

A bundled candump log (an 8-cell pack of 70 Ah NMC cells under DST, one weak cell) is replayed on
python-can's ``virtual`` bus at ``--speed`` x real time; ``bmsid run``'s daemon decodes it,
identifies every cell online and publishes CAN frames and MQTT messages (to a Mosquitto the demo
starts when one is installed; otherwise MQTT is off and says so). A live table shows the cells'
parameters; at the end a short report compares them with the true values and saves plots.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np
from pydantic import ValidationError

from bmsid.cli.outputs import output_dir, positive
from bmsid.config.settings import ReplaySettings, Settings
from bmsid.daemon import demo_data
from bmsid.daemon.local_broker import start_mosquitto
from bmsid.errors import UserError
from bmsid.estimate.types import Estimates, Quality

if TYPE_CHECKING:
    from bmsid.daemon.core import Daemon

REFRESH_S = 0.25


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "demo", help="run the daemon on a bundled log: no hardware, no broker", description=__doc__
    )
    p.add_argument(
        "--duration-s",
        type=float,
        default=None,
        help="stop after this many seconds of wall time (default: the whole log)",
    )
    p.add_argument("--speed", type=float, default=30.0, help="replay speed (default 30x)")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="directory for the report, plots and state (default: a temp dir)",
    )
    p.add_argument("--no-mqtt", action="store_true", help="do not start a broker")
    p.set_defaults(func=run)


@dataclass
class History:
    t_s: list[float] = field(default_factory=list)
    R0_ohm: list[np.ndarray[Any, np.dtype[np.float64]]] = field(default_factory=list)
    tau1_s: list[np.ndarray[Any, np.dtype[np.float64]]] = field(default_factory=list)
    tau2_s: list[np.ndarray[Any, np.dtype[np.float64]]] = field(default_factory=list)
    soc: list[np.ndarray[Any, np.dtype[np.float64]]] = field(default_factory=list)

    def add(self, e: Estimates) -> None:
        self.t_s.append(e.t_s)
        self.R0_ohm.append(e.R0_ohm)
        self.tau1_s.append(e.tau1_s)
        self.tau2_s.append(e.tau2_s)
        self.soc.append(e.soc)


def _live_view(out: TextIO, e: Estimates, daemon: Daemon, first: bool) -> None:
    lines = [
        f"bmsid demo  t = {e.t_s - demo_data.T0_S:7.0f} s  I = {e.current_A:8.2f} A  "
        f"frames {daemon.f2s.counters['frames']}  MQTT {daemon.seq} msgs",
        " cell    R0 mOhm  R1 mOhm  tau1 s   R2 mOhm  tau2 s    SOC %   quality",
    ]
    for c in range(e.n_cells):
        q = Quality(int(e.quality[c])).name.lower()
        lines.append(
            f" {c:4d}  {e.R0_ohm[c] * 1e3:8.3f} {e.R1_ohm[c] * 1e3:8.3f} {e.tau1_s[c]:7.1f}  "
            f"{e.R2_ohm[c] * 1e3:8.3f} {e.tau2_s[c]:7.1f}  {e.soc[c] * 100:6.2f}   {q}"
        )
    if not first:
        out.write(f"\x1b[{len(lines)}F")
    out.write("".join(f"{line}\x1b[K\n" for line in lines))
    out.flush()


def _report(h: History, out_dir: Path) -> Path | None:
    if not h.t_s:
        return None
    # matplotlib is imported only here: every other `bmsid` command would pay for it.
    matplotlib = importlib.import_module("matplotlib")
    matplotlib.use("Agg")
    plt = importlib.import_module("matplotlib.pyplot")

    t = (np.asarray(h.t_s) - h.t_s[0]) / 60.0
    fig, ax = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for a, data, scale, name, truth in (
        (ax[0, 0], h.R0_ohm, 1e3, "R0 / mOhm", demo_data.R0_OHM * 1e3),
        (ax[0, 1], h.tau1_s, 1.0, "tau1 / s", demo_data.TAU1_S),
        (ax[1, 0], h.tau2_s, 1.0, "tau2 / s", demo_data.TAU2_S),
        (ax[1, 1], h.soc, 100.0, "SOC / %", None),
    ):
        arr = np.asarray(data) * scale
        for c in range(arr.shape[1]):
            a.plot(t, arr[:, c], lw=1.0, label=f"cell {c}")
            if truth is not None:
                a.axhline(truth[c], color=a.lines[-1].get_color(), ls=":", lw=0.8)
        a.set_ylabel(name)
        a.grid(alpha=0.3)
    ax[1, 0].set_xlabel("time / min")
    ax[1, 1].set_xlabel("time / min")
    ax[0, 0].legend(fontsize=7, ncol=2)
    fig.suptitle("bmsid demo: online identification (dotted: true values)")
    fig.tight_layout()
    path = out_dir / "demo_report.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


async def _run_demo(
    settings: Settings, duration_s: float | None, out: TextIO
) -> tuple[Daemon, History]:
    h = History()
    tty = out.isatty()
    state = {"last": 0.0, "first": True}

    def on_estimates(e: Estimates) -> None:
        h.add(e)
        now = time.monotonic()
        if tty and now - state["last"] >= REFRESH_S:
            _live_view(out, e, daemon, bool(state["first"]))
            state["last"], state["first"] = now, False

    core = importlib.import_module("bmsid.daemon.core")
    daemon: Daemon = core.Daemon(settings, on_estimates=on_estimates, shutdown_timeout_s=5.0)
    task = asyncio.create_task(daemon.run())
    t0: float | None = None  # the duration counts from the first frame source running
    while not task.done():
        await asyncio.sleep(0.1)
        if t0 is None and daemon.reading:
            t0 = time.monotonic()
        ran_s = 0.0 if t0 is None else time.monotonic() - t0
        if daemon.idle() or (duration_s is not None and ran_s >= duration_s):
            daemon.request_stop()
            break
    await task
    if tty and daemon.latest is not None:
        _live_view(out, daemon.latest, daemon, bool(state["first"]))
    return daemon, h


def run(args: argparse.Namespace) -> int:
    # The daemon pulls in the estimator stack (scipy): imported only when the demo runs.
    core = importlib.import_module("bmsid.daemon.core")
    positive(args.speed, "--speed")
    positive(args.duration_s, "--duration-s")
    try:
        ReplaySettings(log=demo_data.DEMO_LOG, speed=args.speed)
    except ValidationError as exc:
        raise UserError(f"--speed {args.speed:g}: {exc.errors()[0]['msg'].lower()}") from None
    if not demo_data.DEMO_LOG.exists():
        raise UserError(f"the bundled demo log is missing: {demo_data.DEMO_LOG}")
    out_dir = output_dir(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bmsid-demo-"))
    broker = None if args.no_mqtt else start_mosquitto(out_dir)
    if broker is None:
        why = "--no-mqtt" if args.no_mqtt else "no mosquitto installed (apt install mosquitto)"
        print(f"MQTT disabled: {why}; CAN output and the live view still run.")
    else:
        print(
            f"MQTT: mosquitto on 127.0.0.1:{broker[1]}  "
            f"(watch: mosquitto_sub -p {broker[1]} -t 'bmsid/#' -v)"
        )
    settings = Settings(
        pack_id="demo",
        systemd_notify=False,
        status_period_s=5.0,
        can={
            "interface": "virtual",
            "channel": "bmsid-demo",
            "n_cells": demo_data.N_CELLS,
            "replay": {"log": demo_data.DEMO_LOG, "speed": args.speed, "start_delay_s": 0.2},
        },
        estimator={"tuning": {"min_window_s": 300.0, "window_s": 900.0, "swarm_period_s": 300.0}},
        mqtt={
            "enabled": broker is not None,
            "url": f"mqtt://127.0.0.1:{broker[1] if broker else 1883}",
            "homeassistant": {"enabled": True},
        },
        state={"directory": out_dir / "state", "restore": False},
    )
    sys.setswitchinterval(core.SWITCH_INTERVAL_S)
    print(
        "starting the estimator (the first run after an install compiles its kernels: about a "
        "minute; later runs start in seconds)",
        flush=True,
    )
    try:
        daemon, history = asyncio.run(_run_demo(settings, args.duration_s, sys.stdout))
    finally:
        if broker is not None:
            broker[0].terminate()
            broker[0].wait(5)
    e = daemon.latest
    print("\nreport")
    snap = daemon.snapshot()
    print(
        f"  frames {snap['frames']}, samples {snap['samples']}, decode errors "
        f"{snap['decode_errors']}, CAN frames sent {snap['can_frames_sent']}, "
        f"MQTT messages {snap.get('publishes', 0)}, loop lag max {snap['loop_lag_max_ms']} ms"
    )
    if e is None:
        print("  no estimate yet: run longer (--duration-s)")
        return 0
    print(f"  after {e.t_s - demo_data.T0_S:.0f} s of data (true values of the simulation):")
    print("  cell   R0 mOhm (true)    tau1 s (true)   tau2 s (true)   quality")
    for c in range(e.n_cells):
        print(
            f"  {c:4d}  {e.R0_ohm[c] * 1e3:6.3f} ({demo_data.R0_OHM[c] * 1e3:5.2f})  "
            f"{e.tau1_s[c]:7.1f} ({demo_data.TAU1_S[c]:4.0f})  "
            f"{e.tau2_s[c]:7.0f} ({demo_data.TAU2_S[c]:4.0f})   "
            f"{Quality(int(e.quality[c])).name.lower()}"
        )
    weakest = int(np.argmax(e.R0_ohm))
    print(
        f"  weakest cell (largest R0): {weakest} (the simulated weak cell is {demo_data.WEAK_CELL})"
    )
    plot = _report(history, out_dir)
    if plot is not None:
        print(f"  plots: {plot}")
    return 0
