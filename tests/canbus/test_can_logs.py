"""candump logs: both text formats in, -l format out, and a log reproduces its CSV."""

from __future__ import annotations

import gzip
import logging
import tempfile
from pathlib import Path

import numpy as np
import pytest
from can_helpers import frames, synthetic
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.canbus.frames_to_samples import FrameToSamples
from bmsid.canbus.logs import (
    csv_to_messages,
    is_candump_path,
    iter_samples_from_log,
    read_log,
    samples_from_log,
    summarize_log,
    write_log,
)
from bmsid.canbus.mapping import default_mapping, load_mapping
from bmsid.errors import UserError

REPO = Path(__file__).resolve().parents[2]

LOGFILE = """\
(1700000000.000100) vcan0 100#E80300000500
(1700000000.000200) vcan0 18FF5101#0102030405060708 R
(1700000000.000300) vcan0 123#R
(1700000000.000400) vcan0 20000004#0004000000000000
(1700000000.000500) vcan0 310##1AABBCCDDEEFF00112233
this line is garbage
(1700000000.000600) vcan0 12#00
"""

CONSOLE = """\
  vcan0  100   [6]  E8 03 00 00 05 00
 (1700000000.000200)  vcan0  18FF5101   [8]  01 02 03 04 05 06 07 08   '........'
  vcan0  123   [0]  remote request
  vcan0  20000004   [8]  00 04 00 00 00 00 00 00   ERRORFRAME
  vcan0  310  [12]  AA BB CC DD EE FF 00 11 22 33 44 55
  vcan0  100   [3]  E8 03
"""


def _check(msgs: list) -> None:
    assert msgs[0].arbitration_id == 0x100 and not msgs[0].is_extended_id
    assert bytes(msgs[0].data) == bytes.fromhex("E80300000500")
    assert msgs[1].arbitration_id == 0x18FF5101 and msgs[1].is_extended_id
    assert msgs[2].is_remote_frame and msgs[2].arbitration_id == 0x123
    assert msgs[3].is_error_frame
    assert msgs[4].is_fd and len(msgs[4].data) in (10, 12)


def test_read_candump_logfile(tmp_path: Path) -> None:
    p = tmp_path / "a.log"
    p.write_text(LOGFILE)
    msgs = list(read_log(p))
    assert len(msgs) == 5  # garbage and the 2-digit id are skipped
    _check(msgs)
    assert msgs[0].timestamp == pytest.approx(1700000000.0001)


def test_read_candump_console(tmp_path: Path) -> None:
    p = tmp_path / "a.txt"
    p.write_text(CONSOLE)
    msgs = list(read_log(p))
    assert len(msgs) == 5  # the last line says [3] but carries 2 bytes
    _check(msgs)
    assert msgs[0].timestamp == 0.0 and msgs[1].timestamp == pytest.approx(1700000000.0002)


def test_missing_log_is_a_user_error(tmp_path: Path) -> None:
    with pytest.raises(UserError):
        list(read_log(tmp_path / "nope.log"))


def test_write_then_read_is_identity(tmp_path: Path) -> None:
    msgs = frames(default_mapping(), n=5)
    write_log(tmp_path / "x.log", msgs, channel="vcan0")
    back = list(read_log(tmp_path / "x.log"))
    assert [(m.arbitration_id, m.is_extended_id, bytes(m.data), m.timestamp) for m in back] == [
        (m.arbitration_id, m.is_extended_id, bytes(m.data), pytest.approx(m.timestamp))
        for m in msgs
    ]


def test_a_gzipped_log_reads_as_the_log_and_a_cut_one_up_to_its_cut(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A rotated or archived candump log is often gzipped (``.log.gz``): it was read as a CSV
    ("missing column(s) t_s ..."). Its frames are the log's; a gzip cut short (archived while
    still written) gives the frames before the cut and a warning; no gzip at all is an error
    that says what to do."""
    msgs = frames(default_mapping(), n=400)
    write_log(tmp_path / "x.log", msgs, channel="vcan0")
    raw = (tmp_path / "x.log").read_bytes()
    (tmp_path / "x.log.gz").write_bytes(gzip.compress(raw))
    plain = [(m.arbitration_id, bytes(m.data), m.timestamp) for m in read_log(tmp_path / "x.log")]
    zipped = [
        (m.arbitration_id, bytes(m.data), m.timestamp) for m in read_log(tmp_path / "x.log.gz")
    ]
    assert zipped == plain and len(plain) == len(msgs)
    assert is_candump_path(tmp_path / "x.log.gz") and not is_candump_path(tmp_path / "x.csv.gz")
    cut = gzip.compress(raw)
    (tmp_path / "cut.log.gz").write_bytes(cut[: len(cut) // 2])
    with caplog.at_level(logging.WARNING, logger="bmsid.canbus.logs"):
        part = [
            (m.arbitration_id, bytes(m.data), m.timestamp)
            for m in read_log(tmp_path / "cut.log.gz")
        ]
    assert 0 < len(part) < len(plain) and part == plain[: len(part)]
    assert any("gzip file cut short after line" in r.getMessage() for r in caplog.records)
    (tmp_path / "plain.log.gz").write_bytes(raw)
    with pytest.raises(UserError, match=r"not a gzip file .*: a plain log is named \.log"):
        list(read_log(tmp_path / "plain.log.gz"))


def test_a_log_read_in_several_passes_tells_each_finding_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An offline run reads a log in three to five passes; each pass repeated every skipped
    line and every decoder note (a sweep: 17 stale-current lines for one log). Now each count
    is told once per process, and a log whose current frames come every 5 s (60 % of the
    cycles dropped on a CALCE log, 18.9 mV against 2.3) gets one line that says so."""
    mapping = default_mapping()
    current_id = min(m.arbitration_id for m in frames(mapping, n=1))
    msgs = [m for m in frames(mapping, n=200)
            if m.arbitration_id != current_id or round(m.timestamp) % 5 == 0]  # fmt: skip
    write_log(tmp_path / "slow.log", msgs)
    with (tmp_path / "slow.log").open("a") as fh:
        fh.write("this line is garbage\n")
    with caplog.at_level(logging.WARNING):
        for _ in range(3):
            n = sum(1 for _ in iter_samples_from_log(tmp_path / "slow.log", mapping, 6))
    lines = [r.getMessage() for r in caplog.records]
    assert 100 <= n <= 140  # 2 of every 5 cycles: the held current older than 2 s
    share = [x for x in lines if "dropped for a stale current" in x]
    assert len(share) == 1 and "cell-voltage cycles (" in share[0], lines
    assert sum("stale_current: " in x and "(1 so far)" in x for x in lines) == 1
    assert sum("skipped (not a candump line)" in x for x in lines) == 1
    assert sum("malformed lines skipped in total" in x for x in lines) == 1


@pytest.mark.parametrize("mapping_file", ["bmsid_mapping.toml", "example_bms_mapping.toml"])
def test_samples_from_log_reproduce_the_csv(tmp_path: Path, mapping_file: str) -> None:
    mapping = load_mapping(REPO / "dbc" / mapping_file)
    t, i, v = synthetic(200, 6)
    write_log(tmp_path / "x.log", frames(mapping, n=200, n_cells=6))
    samples = samples_from_log(tmp_path / "x.log", mapping, 6)
    assert len(samples) == 200
    np.testing.assert_allclose([s.current_A for s in samples], i, atol=0.05)
    np.testing.assert_allclose(np.array([s.cell_voltages_V for s in samples]), v, atol=5e-4)
    np.testing.assert_allclose([s.t_s for s in samples], t + 1000.0)


def test_a_log_holding_each_frame_twice_gives_each_sample_once(tmp_path: Path) -> None:
    """A sweep: every line twice (a log recorded or merged twice) gave 1600 samples of a
    800-tick log in the header; the repeats are dropped, counted and said now."""
    mapping = default_mapping()
    msgs = frames(mapping, n=50, n_cells=6)
    write_log(tmp_path / "x.log", [m for m in msgs for _ in range(2)])
    assert len(samples_from_log(tmp_path / "x.log", mapping, 6)) == 50
    text = summarize_log(tmp_path / "x.log", mapping).text()
    assert f"{2 * len(msgs)} frames" in text
    assert f"{len(msgs)} decoded by the mapping ({len(msgs)} repeated at the same timestamp" in text


def test_frames_of_a_wrong_dlc_are_counted_as_dropped_not_decoded(tmp_path: Path) -> None:
    """A sweep: with every 10th cell frame cut to 6 bytes the summary said "2400 decoded by
    the mapping" while the decoder dropped 80 of them; it counts and says them now."""
    mapping = default_mapping()
    msgs = frames(mapping, n=50, n_cells=4)
    cut = [m for m in msgs if m.arbitration_id == 0x110][::10]
    for m in cut:
        m.data = m.data[:6]
        m.dlc = 6
    write_log(tmp_path / "x.log", msgs)
    f2s = FrameToSamples(mapping, 4)
    for m in read_log(tmp_path / "x.log"):
        f2s.feed(m)
    s = summarize_log(tmp_path / "x.log", mapping)
    can0 = s.channels["can0"]
    assert (can0.wrong_dlc, f2s.counters["wrong_dlc"]) == (len(cut), len(cut))
    assert can0.decoded == f2s.counters["decoded"] == len(msgs) - len(cut)
    text = s.text()
    assert f"{len(msgs) - len(cut)} decoded by the mapping ({len(cut)} with a wrong DLC" in text


def test_error_frames_are_filed_under_their_channel(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A sweep: python-can's reader drops an error frame's channel, and the summary filed such
    frames under a channel "None"; they keep the log's channel, class and data now."""
    mapping = default_mapping()
    write_log(tmp_path / "x.log", frames(mapping, n=20, n_cells=4), channel="can1")
    with (tmp_path / "x.log").open("a") as fh:
        fh.write("(1030.000000) can1 20000004#0004000000000000\n")
        fh.write("(1030.100000) can1 20000080#0000000000000000\n")
    errors = [m for m in read_log(tmp_path / "x.log") if m.is_error_frame]
    assert [(m.channel, m.arbitration_id) for m in errors] == [("can1", 0x4), ("can1", 0x80)]
    assert bytes(errors[0].data) == bytes.fromhex("0004000000000000")
    s = summarize_log(tmp_path / "x.log", mapping)
    assert list(s.channels) == ["can1"] and "None" not in s.text()
    assert s.channels["can1"].frames == 20 * 2 + 2  # current and cell frames, 2 errors
    with caplog.at_level(logging.WARNING):
        samples_from_log(tmp_path / "x.log", mapping, 4, channel="can1")
    assert any("error frame on can1 id=0x4 (1 so far)" in r.getMessage() for r in caplog.records)


def _stamped(msgs: list, jitter_s: list[float]) -> list:
    """``msgs`` (a tick's frames share a time) with each tick late by its jitter, s."""
    ticks = sorted({m.timestamp for m in msgs})
    late = dict(zip(ticks, jitter_s * len(ticks), strict=False))
    for m in msgs:
        m.timestamp += late[m.timestamp]
    return msgs


def _relative(text: str, delta: bool) -> str:
    """A ``candump -l`` log's lines as ``-td`` (delta) or ``-tz`` (zero-based) prints them."""
    out, prev, first = [], None, None
    for line in text.splitlines():
        stamp, rest = line[1:].split(")", 1)
        us = int(stamp.replace(".", ""))
        first = us if first is None else first
        t = us - (prev if delta and prev is not None else first)
        out.append(f"({t // 10**6:03d}.{t % 10**6:06d}){rest}")
        prev = us
    return "\n".join(out) + "\n"


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(0.0, 0.4), min_size=1, max_size=7), st.integers(3, 40))
def test_delta_timestamps_are_summed_not_stepped_back(jitter_s: list[float], n: int) -> None:
    """A sweep: ``candump -td`` stamps (the time since the previous frame) gave a
    time_backwards note per tick (799 on an 800-tick log) and times off by the absorbed steps.
    They are told once and summed now; ``-tz`` stamps read as they are."""
    mapping = default_mapping()
    with tempfile.TemporaryDirectory(dir="/tmp") as d:
        tmp = Path(d)
        write_log(tmp / "abs.log", _stamped(frames(mapping, n=n, n_cells=4), jitter_s))
        ref = samples_from_log(tmp / "abs.log", mapping, 4)
        t0 = next(read_log(tmp / "abs.log")).timestamp
        for name, delta in (("td.log", True), ("tz.log", False)):
            (tmp / name).write_text(_relative((tmp / "abs.log").read_text(), delta))
            f2s = FrameToSamples(mapping, 4)
            got = [s for m in read_log(tmp / name) for s in f2s.feed(m)] + f2s.flush()
            assert f2s.counters["time_backwards"] == 0, name
            np.testing.assert_allclose([s.t_s for s in got], [s.t_s - t0 for s in ref], atol=1e-6)
            np.testing.assert_array_equal(
                [s.cell_voltages_V for s in got], [s.cell_voltages_V for s in ref]
            )


def test_delta_timestamps_are_told_once_and_a_clock_step_is_no_delta(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    mapping = default_mapping()
    write_log(tmp_path / "abs.log", frames(mapping, n=30, n_cells=4, t0=0.0))
    (tmp_path / "td.log").write_text(_relative((tmp_path / "abs.log").read_text(), True))
    with caplog.at_level(logging.WARNING):
        for _ in range(3):  # an offline run's passes
            assert len(samples_from_log(tmp_path / "td.log", mapping, 4)) == 30
    lines = [r.getMessage() for r in caplog.records]
    assert sum("relative timestamps (candump -td" in x for x in lines) == 1, lines
    assert not any("time_backwards" in x for x in lines)
    stepped = frames(mapping, n=30, n_cells=4, t0=0.0)
    for m in stepped[20:]:
        m.timestamp -= 5.0  # one clock step back on a log from 0 s: no delta stamps
    write_log(tmp_path / "step.log", stepped)
    assert [m.timestamp for m in read_log(tmp_path / "step.log")] == [m.timestamp for m in stepped]


def test_log_without_timestamps_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "a.txt"
    p.write_text(
        "  can0  100   [8]  E8 03 00 00 05 00 00 00\n  can0  110   [8]  00 00 00 00 00 00 00 00\n"
    )
    mapping = default_mapping()
    with pytest.raises(UserError):
        samples_from_log(p, mapping, 4)


def test_real_a123_profile_survives_the_log(tmp_path: Path, real_data_dir: Path) -> None:
    from bmsid.canbus.logs import csv_to_messages

    real = real_data_dir / "a123_lfp_25C" / "a123_25C_DYN50.csv.gz"

    data = np.loadtxt(real, delimiter=",", skiprows=1, max_rows=3000)
    t, i, v = data[:, 0], data[:, 1], data[:, 2]
    write_log(tmp_path / "r.log", csv_to_messages(t, i, v, default_mapping(), t0_s=1.7e9))
    samples = samples_from_log(tmp_path / "r.log", default_mapping(), 1)
    assert len(samples) == len(t)
    np.testing.assert_allclose([s.current_A for s in samples], i, atol=5e-4 + 1e-9)
    np.testing.assert_allclose([s.cell_voltages_V[0] for s in samples], v, atol=5e-4 + 1e-9)
    np.testing.assert_allclose([s.t_s - 1.7e9 for s in samples], t, atol=2e-6)


# ----------------------------------------------------------------------------- what a log holds
DEMO_LOG = REPO / "service" / "bmsid" / "data" / "demo_pack.log"


def _two_channel_log(path: Path, n: int = 400) -> Path:
    """can0 carries a 3-cell pack, can1 a 2-cell pack, interleaved by time as candump -l
    writes a capture of both buses."""
    mapping = default_mapping()
    t, i, v = synthetic(n, 3)
    lines: list[str] = []
    for name, cells, scale in (("can0", 3, 1.0), ("can1", 2, 0.5)):
        part = path.with_suffix(f".{name}")
        write_log(part, csv_to_messages(t, scale * i, v[:, :cells], mapping, t0_s=1.7e9), name)
        lines += part.read_text().splitlines()
    lines.sort(key=lambda line: float(line[1 : line.index(")")]))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_summary_counts_channels_ids_and_cells(tmp_path: Path) -> None:
    s = summarize_log(_two_channel_log(tmp_path / "two.log"), default_mapping())
    assert s.mapped_channels == ["can0", "can1"]
    can0, can1 = s.channels["can0"], s.channels["can1"]
    assert (can0.frames, can1.frames) == (800, 800)
    assert can0.ids == {(0x100, False): 400, (0x110, False): 400}
    assert (can0.n_cells, can1.n_cells) == (3, 2)  # padding slots are not-available: no cell
    text = s.text()
    assert text.startswith("two.log holds can0: 800 frames, 2 id(s) (0x100 x400, 0x110 x400)")
    assert "can1: 800 frames" in text and "2 cell(s)" in text


def test_two_channels_are_refused_unless_one_is_chosen(tmp_path: Path) -> None:
    log = _two_channel_log(tmp_path / "two.log")
    with pytest.raises(UserError) as err:
        samples_from_log(log, default_mapping(), 2)
    msg = str(err.value)
    assert "on 2 CAN channels (can0: 800, can1: 800)" in msg and "pass --channel NAME" in msg
    one = samples_from_log(log, default_mapping(), 2, channel="can1")
    assert len(one) == 400  # not 800 (or more) samples of two buses interleaved
    _, i, _ = synthetic(400, 3)
    np.testing.assert_allclose([s.current_A for s in one], 0.5 * i, atol=1e-3)
    with pytest.raises(UserError, match="on channel 'can7'"):
        samples_from_log(log, default_mapping(), 2, channel="can7")


def test_bundled_demo_log_carries_eight_cells() -> None:
    s = summarize_log(DEMO_LOG, default_mapping())
    assert list(s.channels) == ["can0"]
    assert s.channels["can0"].n_cells == 8
    assert s.channels["can0"].cells == list(range(8))


def test_listed_layout_cells_are_counted(tmp_path: Path) -> None:
    mapping = load_mapping(REPO / "dbc" / "example_bms_mapping.toml")
    write_log(tmp_path / "x.log", frames(mapping, n=30, n_cells=6))
    assert summarize_log(tmp_path / "x.log", mapping).channels["can0"].n_cells == 6
