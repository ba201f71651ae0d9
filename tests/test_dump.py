"""Tests of ``hdhil dump``: reading traces of every format, decoding, CSV, stats, damage."""

from __future__ import annotations

import csv
import gzip
import json
import math
import os
import re
import stat
from pathlib import Path

import can
import numpy as np
import pytest
from runs import lockstep

from hdhil.can.traces import export
from hdhil.can.traces.clock import TraceClock
from hdhil.can.traces.decode import (
    DecodedFrame,
    FrameKind,
    classify_frame,
    decode_frame,
    default_decoder,
)
from hdhil.can.traces.reader import _CSV_HEADER, MAX_DAMAGE, TraceError, read_trace
from hdhil.can.traces.stats import StatsAccumulator, compute_stats
from hdhil.cli import main
from hdhil.dbc import database

CTRL = database("control")
TRUTH = database("truth")
FORMATS = [".blf", ".asc", ".log", ".csv", ".trc"]
UNKNOWN_ID = 0x7EF
UNKNOWN_DATA = bytes.fromhex("DEADBEEF")


def _msg(t: float, name: str, values: dict[str, float], channel: int | None) -> can.Message:
    db = TRUTH if name.startswith("TRUTH") else CTRL
    m = db.get_message_by_name(name)
    return can.Message(
        timestamp=t,
        arbitration_id=m.frame_id,
        is_extended_id=m.is_extended_frame,
        data=m.encode(values),
        channel=channel,
        is_rx=True,
    )


def cycle_values(k: int) -> dict[str, dict[str, float]]:
    """Physical values sent in cycle ``k`` (within each signal's range)."""
    return {
        "SYNC": {"sync_counter": k % 240 + 1},
        "DRIVE_TPDO1": {
            "ADC_torque": (37 * k) % 4000 - 2000,
            "ADC_tacho": -k % 2000,
            "ADC_current": 5,
            "ENC_count": (13 * k) % 65536,
        },
        "CTRL_TPDO1": {
            "T_meas": 0.013 * k - 5.0,
            "T_filtered": -0.007 * k + 1.0,
            "velocity": 0.37 * (k % 1000) - 100.0,
            "current": 0.0011 * k,
        },
        "TRUTH_TORQUE": {"T_true": 1.1 + 0.001 * k, "T_ripple": -0.25 * math.sin(k)},
    }


def make_frames(cycles: int, extras: bool = True) -> list[can.Message]:
    """``cycles`` 1 kHz cycles of SYNC, DRIVE_TPDO1, CTRL_TPDO1 (control) and TRUTH_TORQUE
    (truth); with ``extras`` one unknown-ID frame and one malformed CTRL_TPDO1 in cycle 1."""
    frames = []
    for k in range(cycles):
        t = k * 1e-3
        values = cycle_values(k)
        frames.append(_msg(t, "SYNC", values["SYNC"], 0))
        frames.append(_msg(t + 100e-6, "DRIVE_TPDO1", values["DRIVE_TPDO1"], 0))
        frames.append(_msg(t + 250e-6, "CTRL_TPDO1", values["CTRL_TPDO1"], 0))
        frames.append(_msg(t + 300e-6, "TRUTH_TORQUE", values["TRUTH_TORQUE"], 1))
        if extras and k == 1:
            frames.append(
                can.Message(
                    timestamp=t + 400e-6,
                    arbitration_id=UNKNOWN_ID,
                    is_extended_id=False,
                    data=UNKNOWN_DATA,
                    channel=0,
                )
            )
            frames.append(
                can.Message(
                    timestamp=t + 500e-6,
                    arbitration_id=0x181,
                    is_extended_id=False,
                    data=bytes(range(5)),
                    channel=0,
                )
            )
    return frames


def write_trace(path: Path, frames: list[can.Message]) -> Path:
    with can.Logger(str(path)) as writer:
        for msg in frames:
            writer.on_message_received(msg)
    return path


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    rc = main(["dump", *[str(a) for a in argv]])
    out, err = capsys.readouterr()
    return rc, out, err


SUMMARY = re.compile(
    r"(\d+) frames: (\d+) decoded, (\d+) unknown, (\d+) malformed, (\d+) error, (\d+) remote"
)


def summary_counts(text: str) -> tuple[int, ...]:
    match = SUMMARY.search(text)
    assert match, text
    return tuple(int(g) for g in match.groups())


# ------------------------------------------------------------------------------ table


def test_table_shows_decoded_signals_unknown_and_malformed(tmp_path, capsys):
    trace = write_trace(tmp_path / "t.blf", make_frames(5))
    rc, out, err = run_cli(capsys, trace)
    assert rc == 0, err
    assert err == ""
    lines = out.splitlines()
    ctrl = [line for line in lines if "CTRL_TPDO1" in line and "T_meas=" in line]
    assert len(ctrl) == 5
    # cycle 0: T_meas = -5.000, T_filtered = 1.000, velocity = -100.00, current = 0.000
    assert "T_meas=-5.000 Nm" in ctrl[0]
    assert "T_filtered=1.000 Nm" in ctrl[0]
    assert "velocity=-100.00 rad/s" in ctrl[0]
    assert "current=0.000 A" in ctrl[0]
    assert "control" in ctrl[0] and " 181 " in ctrl[0]
    truth = [line for line in lines if "TRUTH_TORQUE" in line]
    assert len(truth) == 5 and "T_true=1.100000 Nm" in truth[0] and "truth" in truth[0]
    assert "001F0001" in truth[0]
    unknown = [line for line in lines if "UNKNOWN" in line]
    assert len(unknown) == 1 and "7EF" in unknown[0] and "DE AD BE EF" in unknown[0]
    malformed = [line for line in lines if "MALFORMED" in line]
    assert len(malformed) == 1 and "00 01 02 03 04" in malformed[0]
    assert re.match(r"\s+0\.001500\s", malformed[0])  # time with 6 decimals
    assert summary_counts(lines[-1]) == (22, 20, 1, 1, 0, 0)
    assert "duration 0.004300 s" in lines[-1]


def test_error_and_remote_frames_are_flagged(tmp_path, capsys):
    frames = make_frames(2, extras=False)
    frames.append(can.Message(timestamp=0.0025, is_error_frame=True, channel=0))
    frames.append(
        can.Message(
            timestamp=0.0026,
            arbitration_id=0x181,
            is_extended_id=False,
            is_remote_frame=True,
            dlc=8,
            channel=0,
        )
    )
    for suffix in (".blf", ".asc"):
        trace = write_trace(tmp_path / f"t{suffix}", frames)
        rc, out, _ = run_cli(capsys, trace)
        assert rc == 0
        assert "ERROR FRAME" in out
        assert re.search(r"181\s+CTRL_TPDO1\s+REMOTE", out)
        assert summary_counts(out) == (10, 8, 0, 0, 1, 1)


def test_limit_prints_n_frames_but_counts_all(tmp_path, capsys):
    trace = write_trace(tmp_path / "t.blf", make_frames(50))
    rc, out, _ = run_cli(capsys, trace, "--limit", "7")
    assert rc == 0
    lines = out.splitlines()
    assert len(lines) == 1 + 7 + 1  # header, frames, summary
    assert summary_counts(lines[-1])[0] == 202
    assert "7 shown" in lines[-1]


def test_id_filter_by_name_and_hex(tmp_path, capsys):
    trace = write_trace(tmp_path / "t.csv", make_frames(10))
    rc, out, _ = run_cli(capsys, trace, "--id", "TRUTH_TORQUE", "--id", "0x7ef")
    assert rc == 0
    body = out.splitlines()[1:-1]
    assert len(body) == 11
    assert all("TRUTH_TORQUE" in line or "UNKNOWN" in line for line in body)
    assert "11 selected by --id" in out
    rc, out, err = run_cli(capsys, trace, "--id", "NOPE!")
    assert rc == 2 and "--id" in err


# ------------------------------------------------------------------ formats round trip


@pytest.mark.parametrize("suffix", FORMATS)
def test_every_format_round_trips(tmp_path, suffix):
    cycles = 30
    frames = make_frames(cycles)
    trace = write_trace(tmp_path / f"trace{suffix}", frames)
    decoded: dict[str, list[DecodedFrame]] = {}
    kinds: dict[FrameKind, int] = {}
    with read_trace(trace) as result:
        for msg in result:
            frame = classify_frame(msg)
            kinds[frame.kind] = kinds.get(frame.kind, 0) + 1
            if decode_frame(msg) is not None:
                decoded.setdefault(frame.message, []).append(frame)
    assert not result.damage
    assert result.frame_count == len(frames)
    assert kinds == {
        FrameKind.DECODED: 4 * cycles,
        FrameKind.UNKNOWN: 1,
        FrameKind.MALFORMED: 1,
    }
    for name in ("SYNC", "DRIVE_TPDO1", "CTRL_TPDO1", "TRUTH_TORQUE"):
        got = decoded[name]
        assert len(got) == cycles
        message = (TRUTH if name.startswith("TRUTH") else CTRL).get_message_by_name(name)
        sent_times = [
            m.timestamp
            for m in frames
            if m.arbitration_id == message.frame_id and len(m.data) == message.length
        ]
        for k, frame in enumerate(got):
            assert frame.bus == ("truth" if name.startswith("TRUTH") else "control")
            assert frame.time == pytest.approx(sent_times[k], abs=2e-6)
            for signal in message.signals:
                sent = cycle_values(k)[name][signal.name]
                value = frame.signals[signal.name]
                if signal.is_float:
                    assert value == pytest.approx(float(np.float32(sent)), rel=1e-7)
                else:
                    assert abs(value - sent) <= signal.scale / 2 + 1e-9, (name, signal.name)


def test_gzip_compressed_trace(tmp_path, capsys):
    plain = write_trace(tmp_path / "t.asc", make_frames(5))
    packed = tmp_path / "t.asc.gz"
    packed.write_bytes(gzip.compress(plain.read_bytes()))
    rc, out, _ = run_cli(capsys, packed)
    assert rc == 0
    assert summary_counts(out) == (22, 20, 1, 1, 0, 0)


# -------------------------------------------------------------------------------- CSV


def test_csv_output(tmp_path, capsys):
    cycles = 20
    trace = write_trace(tmp_path / "t.blf", make_frames(cycles))
    out_csv = tmp_path / "out.csv"
    rc, out, err = run_cli(capsys, trace, "--csv", out_csv, "--per-frame")
    assert rc == 0
    assert out == ""
    assert summary_counts(err) == (4 * cycles + 2, 4 * cycles, 1, 1, 0, 0)
    assert not (tmp_path / "out.csv.tmp").exists()
    rows = out_csv.read_text().splitlines()
    header = rows[0].split(",")
    assert header[:3] == ["time", "bus", "id"]
    for column in (
        "CTRL_TPDO1.T_meas",
        "CTRL_TPDO1.T_filtered",
        "CTRL_TPDO1.velocity",
        "TRUTH_TORQUE.T_true",
        "SYNC.sync_counter",
    ):
        assert column in header
    assert len(rows) - 1 == 4 * cycles  # one row per decoded frame, unknown/malformed left out
    table = [dict(zip(header, row.split(","), strict=True)) for row in rows[1:]]
    ctrl = [r for r in table if r["CTRL_TPDO1.T_meas"]]
    assert len(ctrl) == cycles
    k = 7
    expected = cycle_values(k)["CTRL_TPDO1"]
    assert float(ctrl[k]["time"]) == pytest.approx(k * 1e-3 + 250e-6, abs=1e-9)
    assert ctrl[k]["bus"] == "control" and ctrl[k]["id"] == "0x181"
    assert float(ctrl[k]["CTRL_TPDO1.T_meas"]) == pytest.approx(expected["T_meas"], abs=0.002)
    assert float(ctrl[k]["CTRL_TPDO1.velocity"]) == pytest.approx(expected["velocity"], abs=0.005)
    assert ctrl[k]["TRUTH_TORQUE.T_true"] == ""  # other messages' cells stay empty
    truth = [r for r in table if r["TRUTH_TORQUE.T_true"]]
    # float32 signals are written as the shortest text that reads back to the same float32
    assert np.float32(truth[k]["TRUTH_TORQUE.T_true"]) == np.float32(1.1 + 0.001 * k)
    assert truth[k]["id"] == "0x001F0001" and truth[k]["bus"] == "truth"


def test_csv_is_not_left_half_written(tmp_path, capsys, monkeypatch):
    trace = write_trace(tmp_path / "t.blf", make_frames(20))
    out_csv = tmp_path / "out.csv"
    original = export.FrameCsv.add
    calls = {"n": 0}

    def failing_add(self, frame):
        calls["n"] += 1
        if calls["n"] == 30:
            raise KeyboardInterrupt
        original(self, frame)

    monkeypatch.setattr(export.FrameCsv, "add", failing_add)
    rc, _, err = run_cli(capsys, trace, "--csv", out_csv, "--per-frame")
    assert rc == 130 and "interrupted" in err
    assert not out_csv.exists()
    assert not (tmp_path / "out.csv.tmp").exists()


def test_csv_to_stdout_and_to_a_fifo(tmp_path, capsys):
    trace = write_trace(tmp_path / "t.asc", make_frames(10))
    rc, out, err = run_cli(capsys, trace, "--csv", "-", "--per-frame")
    assert rc == 0
    rows = out.splitlines()
    assert rows[0].startswith("time,bus,id,") and len(rows) == 1 + 40
    assert "wrote 40 rows to stdout" in err
    # a FIFO is refused (only regular files are written; '-' is the way to a pipe), and
    # it is still a FIFO afterwards
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    rc, _, err = run_cli(capsys, trace, "--csv", fifo, "--per-frame")
    assert rc == 2 and "a FIFO" in err and len(err.strip().splitlines()) == 1
    assert stat.S_ISFIFO(fifo.stat().st_mode)


def test_csv_refuses_to_overwrite_the_trace(tmp_path, capsys):
    trace = write_trace(tmp_path / "t.csv", make_frames(3))
    before = trace.read_bytes()
    rc, _, err = run_cli(capsys, trace, "--csv", trace)
    assert rc == 2 and "overwrite" in err
    assert trace.read_bytes() == before


# ------------------------------------------------------------------------------ stats


def schedule(cycles: int, jitter_s: np.ndarray | None = None) -> list[can.Message]:
    """SYNC (1 byte) + three 8-byte frames per 1 ms cycle on the control bus."""
    frames = []
    for k in range(cycles):
        t = k * 1e-3 + (0.0 if jitter_s is None else float(jitter_s[k]))
        frames.append(_msg(t, "SYNC", {"sync_counter": 1}, 0))
        for i, name in enumerate(("DRIVE_TPDO1", "CTRL_TPDO1")):
            values = {s.name: 0 for s in CTRL.get_message_by_name(name).signals}
            frames.append(_msg(t + (i + 1) * 100e-6, name, values, 0))
        frames.append(
            can.Message(
                timestamp=t + 300e-6,
                arbitration_id=0x381,
                is_extended_id=False,
                data=bytes(8),
                channel=0,
            )
        )
    return frames


def test_stats_of_1khz_schedule():
    stats = compute_stats(schedule(1000), bitrate=1_000_000)
    assert stats["frames"] == 4000 and stats["unknown"] == 1000
    by_id = {s["id"]: s for s in stats["ids"]}
    assert set(by_id) == {0x80, 0x181, 0x182, 0x381}
    for s in by_id.values():
        assert s["count"] == 1000
        assert s["rate_hz"] == pytest.approx(1000.0, rel=1e-9)
        assert s["period_ms"] == pytest.approx(1.0, rel=1e-9)
        assert s["jitter_std_us"] == pytest.approx(0.0, abs=1e-6)
        assert s["jitter_max_us"] == pytest.approx(0.0, abs=1e-6)
    # each identifier at its own worst case (docs/design.md, "Frame budget"): 62 bits for
    # the 1-byte SYNC, 132 for these 8-byte frames, a few below the bounds for any
    # identifier (65, 135)
    assert by_id[0x80]["worst_case_bits"] == 62 and by_id[0x80]["frame_time_us"] == 62.0
    assert by_id[0x181]["worst_case_bits"] == 132 and by_id[0x181]["payload_bytes"] == 8
    assert by_id[0x381]["name"] is None
    control = stats["buses"]["control"]
    assert control["load_percent"] == pytest.approx((62 + 3 * 132) / 1000 * 100, rel=1e-9)
    assert control["frames"] == 4000
    assert control["unknown_ids"] == 1 and control["unknown_frames"] == 1000
    assert control["duration"] == pytest.approx(0.999 + 300e-6)
    assert not control["over_limit"]
    slow = compute_stats(schedule(100), bitrate=500_000)
    assert slow["buses"]["control"]["load_percent"] == pytest.approx(2 * (62 + 3 * 132) / 10)
    assert slow["buses"]["control"]["over_limit"]


def test_a_burst_of_sdo_frames_counts_spread_over_the_bus_duration():
    """A DCF's configuration writes at boot: 100 SDO request/response pairs within 20 ms,
    then the 1 kHz schedule for 1 s.  The bus's worst-case load is the schedule's plus
    the burst's 200 frames spread over the second, not the burst's own rate."""
    burst = []
    for i in range(100):
        for k, cob in enumerate((0x602, 0x582)):
            burst.append(
                can.Message(
                    timestamp=i * 200e-6 + k * 100e-6,
                    arbitration_id=cob,
                    is_extended_id=False,
                    data=bytes(8),
                    channel=0,
                )
            )
    cyclic = [
        can.Message(
            timestamp=m.timestamp + 0.02,
            arbitration_id=m.arbitration_id,
            is_extended_id=m.is_extended_id,
            data=m.data,
            channel=m.channel,
        )
        for m in schedule(1000)
    ]
    stats = compute_stats(burst + cyclic, bitrate=1_000_000)
    control = stats["buses"]["control"]
    by_id = {s["id"]: s for s in stats["ids"]}
    assert by_id[0x602]["load_percent"] > 60  # the burst's own rate: 5 kHz of 132 us
    cyclic_load = (62 + 3 * 132) / 1000 * 100
    burst_load = 200 * 132e-6 / control["duration"] * 100
    assert control["load_percent"] == pytest.approx(cyclic_load + burst_load, rel=2e-3)
    assert control["load_percent"] < 60 and not control["over_limit"]


def test_stats_jitter_matches_numpy():
    rng = np.random.default_rng(7)
    jitter = rng.normal(0.0, 20e-6, 500)
    stats = compute_stats(schedule(500, jitter))
    sync = next(s for s in stats["ids"] if s["name"] == "SYNC")
    times = np.arange(500) * 1e-3 + jitter
    periods = np.diff(times)
    assert sync["period_ms"] == pytest.approx(periods.mean() * 1e3, rel=1e-9)
    assert sync["jitter_std_us"] == pytest.approx(periods.std() * 1e6, rel=1e-6)
    expected_max = np.max(np.abs(periods - periods.mean())) * 1e6
    assert sync["jitter_max_us"] == pytest.approx(expected_max, rel=1e-6)
    assert sync["jitter_std_us"] > 20.0  # differences of two N(0, 20 us) draws


def test_stats_cli_text_and_json(tmp_path, capsys):
    trace = write_trace(tmp_path / "s.blf", schedule(200) + make_frames(3)[-1:])
    rc, out, _ = run_cli(capsys, trace, "--stats")
    assert rc == 0
    assert re.search(r"bus control: .* worst-case load 45\.8 % of 1000 kbit/s", out)
    assert re.search(r"control\s+080\s+SYNC\s+200\s+1000\.00", out)
    assert "unknown IDs 1 (200 frames)" in out
    rc, out, err = run_cli(capsys, trace, "--json", "--bitrate", "500000")
    assert rc == 0
    data = json.loads(out)
    assert data["bitrate"] == 500_000
    assert data["buses"]["control"]["load_percent"] == pytest.approx(2 * 45.8, rel=1e-3)
    assert data["buses"]["truth"]["frames"] == 1
    assert data["damage"] == [] and data["trace"].endswith("s.blf")
    assert {"id", "id_hex", "name", "count", "rate_hz", "jitter_std_us", "load_percent"} <= set(
        data["ids"][0]
    )
    assert summary_counts(err)[0] == 801


# -------------------------------------------------------------------------- bad files


def _bad_files(tmp_path: Path) -> dict[str, Path]:
    files = {
        "missing": tmp_path / "missing.blf",
        "directory": tmp_path / "dir.blf",
        "empty_blf": tmp_path / "empty.blf",
        "empty_csv": tmp_path / "empty.csv",
        "text_as_blf": tmp_path / "text.blf",
        "random_blf": tmp_path / "random.blf",
        "random_csv": tmp_path / "random.csv",
        "text_as_asc": tmp_path / "text.asc",
        "header_only_csv": tmp_path / "header.csv",
        "unsupported": tmp_path / "trace.txt",
    }
    files["directory"].mkdir()
    files["empty_blf"].write_bytes(b"")
    files["empty_csv"].write_bytes(b"")
    files["text_as_blf"].write_text("this is not a BLF file\n" * 20)
    random = np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes()
    files["random_blf"].write_bytes(random)
    files["random_csv"].write_bytes(random)
    files["text_as_asc"].write_text("hello\nworld\n")
    files["header_only_csv"].write_text(_CSV_HEADER)
    files["unsupported"].write_text("0.0 1 181 Rx d 8 00 00 00 00 00 00 00 00\n")
    return files


@pytest.mark.parametrize(
    "kind",
    [
        "missing",
        "directory",
        "empty_blf",
        "empty_csv",
        "text_as_blf",
        "random_blf",
        "random_csv",
        "text_as_asc",
        "header_only_csv",
        "unsupported",
    ],
)
def test_bad_files_are_a_one_line_error(tmp_path, capsys, kind):
    path = _bad_files(tmp_path)[kind]
    rc, _, err = run_cli(capsys, path)
    assert rc == 2
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("hdhil: error: ")
    assert str(path) in lines[0]
    with pytest.raises(TraceError):
        read_trace(path)


# ----------------------------------------------------------------------- damaged files


WARNING = re.compile(
    r"^hdhil: warning: (?P<path>\S+): damaged after frame (?P<n>\d+) \(t=(?P<t>[\d.]+)s\): "
    r"(?P<reason>.+)$"
)


UNREADABLE = re.compile(r"^hdhil: warning: \S+: (\d+) unreadable lines?, the first at line (\d+)$")


def _warnings(err: str) -> list[re.Match[str]]:
    lines = err.splitlines()
    summary = [UNREADABLE.match(line) for line in lines if UNREADABLE.match(line)]
    matches = [WARNING.match(line) for line in lines if not UNREADABLE.match(line)]
    assert all(matches), err
    lined = [m for m in matches if m and "line " in m["reason"]]
    if lined:  # text formats: the count and the first line number are summarised
        assert len(summary) == 1 and int(summary[0][1]) >= len(lined), err
    return matches  # type: ignore[return-value]


def test_truncated_blf(tmp_path, capsys):
    frames = make_frames(2000, extras=False)
    trace = write_trace(tmp_path / "t.blf", frames)
    data = trace.read_bytes()
    cut = tmp_path / "cut.blf"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    rc, out, err = run_cli(capsys, cut)
    assert rc == 1
    (warning,) = _warnings(err)
    assert "file truncated" in warning["reason"]
    total, decoded, *_ = summary_counts(out)
    assert 0 < total < len(frames) and decoded == total
    assert int(warning["n"]) == total
    last_line = out.splitlines()[-2]
    assert float(warning["t"]) == pytest.approx(float(last_line.split()[0]), abs=1e-6)
    assert sum("T_meas=" in line for line in out.splitlines()) > 0


def test_corrupted_blf_container(tmp_path, capsys):
    trace = write_trace(tmp_path / "t.blf", make_frames(3000, extras=False))
    data = bytearray(trace.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(b ^ 0x55 for b in data[middle : middle + 64])
    trace.write_bytes(bytes(data))
    rc, out, err = run_cli(capsys, trace)
    assert rc == 1
    warnings = _warnings(err)
    assert len(warnings) == 1
    total = summary_counts(out)[0]
    assert 0 < total < 12000 and int(warnings[0]["n"]) == total


@pytest.mark.slow
def test_blf_never_closed_by_its_writer(tmp_path, capsys):
    """A logger that died: containers were flushed but the header was never finalised."""
    path = tmp_path / "crashed.blf"
    frames = make_frames(4000, extras=False)
    writer = can.BLFWriter(str(path))
    for msg in frames:
        writer.on_message_received(msg)
    writer.file.flush()  # what reached the disk; no stop(): the header keeps its placeholder
    rc, out, err = run_cli(capsys, path, "--limit", "0")
    writer.stop()
    assert rc == 1
    (warning,) = _warnings(err)
    assert "never finalised" in warning["reason"]
    assert 0 < summary_counts(out)[0] < len(frames)


@pytest.mark.slow
def test_cut_gzip_stream(tmp_path, capsys):
    plain = write_trace(tmp_path / "t.log", make_frames(3000, extras=False))
    packed = gzip.compress(plain.read_bytes())
    cut = tmp_path / "t.log.gz"
    cut.write_bytes(packed[: len(packed) // 2])
    rc, out, err = run_cli(capsys, cut, "--limit", "0")
    assert rc == 1
    (warning,) = _warnings(err)
    assert "EOFError" in warning["reason"] and "line" not in warning["reason"]
    assert 0 < summary_counts(out)[0] < 12000


def _corrupt_line(path: Path, index: int, replacement: str) -> None:
    lines = path.read_text().splitlines(keepends=True)
    lines[index] = replacement
    path.write_text("".join(lines))


@pytest.mark.parametrize(
    ("suffix", "replacement"),
    [
        (".asc", " 1.000100 1  181             Rx   d 8 ZZ 00 7D 00 00 00 64 00\n"),
        (".asc", "this line is garbage\n"),  # the ASC reader would skip it silently
        (".csv", "0.5,0x181,0,0\n"),
        (".csv", "0.5,0x18Z,0,0,0,8,AAAAAAAAAAA=\n"),
        (".log", "(0.5) can0 18X#00\n"),
        (".trc", "garbage in a trc file\n"),
    ],
)
def test_corrupted_line_in_text_trace(tmp_path, capsys, suffix, replacement):
    frames = make_frames(500, extras=False)
    trace = write_trace(tmp_path / f"t{suffix}", frames)
    lines = trace.read_text().splitlines()
    index = len(lines) // 2
    _corrupt_line(trace, index, replacement)
    rc, out, err = run_cli(capsys, trace)
    assert rc == 1
    (warning,) = _warnings(err)
    assert f"line {index + 1}:" in warning["reason"] and "resumed" in warning["reason"]
    total = summary_counts(out)[0]
    assert total == len(frames) - 1  # only the corrupted line is lost
    assert 0 < int(warning["n"]) < total


@pytest.mark.parametrize("suffix", [".csv", ".asc", ".log", ".trc"])
def test_text_trace_cut_mid_line(tmp_path, capsys, suffix):
    frames = make_frames(300, extras=False)
    trace = write_trace(tmp_path / f"t{suffix}", frames)
    text = trace.read_bytes()
    cut = int(len(text) * 0.6)
    while text[cut - 1 : cut] in (b"\n", b"\r"):
        cut -= 3  # make sure the cut is inside a line
    trace.write_bytes(text[:cut])
    rc, out, err = run_cli(capsys, trace)
    assert rc == 1
    warnings = _warnings(err)
    assert len(warnings) == 1
    total = summary_counts(out)[0]
    assert 0 < total < len(frames)


def test_many_damaged_lines_stop_reading(tmp_path):
    trace = write_trace(tmp_path / "t.csv", make_frames(400, extras=False))
    lines = trace.read_text().splitlines(keepends=True)
    for i in range(100, 400):
        lines[i] = "broken\n"
    trace.write_text("".join(lines))
    with read_trace(trace) as result:
        count = sum(1 for _ in result)
    assert count == 99
    assert len(result.damage) == MAX_DAMAGE + 1
    assert "stopped reading" in result.damage[-1].reason


def test_clean_read_has_no_damage_and_streams(tmp_path):
    trace = write_trace(tmp_path / "t.log", make_frames(10))
    result = read_trace(trace)
    first = next(iter(result))
    assert first.channel == 0 and first.arbitration_id == 0x80
    rest = list(result)
    assert len(rest) == 41 and result.frame_count == 42
    assert not result.damaged
    truth = [m for m in rest if m.is_extended_id]
    assert truth and all(m.channel == 1 for m in truth)


# ---------------------------------------------------------------------------- decoding


def test_decode_frame_api():
    msg = _msg(0.5, "CTRL_TPDO1", cycle_values(3)["CTRL_TPDO1"], None)
    frame = decode_frame(msg)
    assert frame is not None
    assert frame.message == "CTRL_TPDO1" and frame.bus == "control" and frame.id_text == "181"
    assert frame.signals["T_meas"] == pytest.approx(0.013 * 3 - 5.0, abs=0.002)
    unknown = can.Message(arbitration_id=0x181, is_extended_id=True, data=bytes(8))
    assert decode_frame(unknown) is None
    assert classify_frame(unknown).kind is FrameKind.UNKNOWN
    assert classify_frame(unknown).bus == "?"
    short = can.Message(arbitration_id=0x181, is_extended_id=False, data=bytes(7), channel=0)
    assert decode_frame(short) is None
    assert classify_frame(short).kind is FrameKind.MALFORMED
    truth_on_control = _msg(0.0, "TRUTH_TORQUE", {"T_true": 1.0, "T_ripple": 0.0}, 0)
    frame = classify_frame(truth_on_control)
    assert frame.kind is FrameKind.DECODED and frame.on_wrong_bus
    assert "WRONG BUS" in default_decoder().describe(frame)


@pytest.mark.slow
def test_stats_report_actual_load_and_cycle_counter_gaps(tmp_path, capsys):
    """A run's trace with frames removed: the counters' gaps show exactly what is missing."""
    from hdhil.rig.scenario import load_scenario

    full = tmp_path / "full.blf"
    lockstep(load_scenario("free-motion"), duration_s=0.5, trace=full, evaluate=False)
    with can.LogReader(str(full)) as reader:
        frames = list(reader)
    syncs = [i for i, m in enumerate(frames) if m.arbitration_id == 0x080 and not m.is_extended_id]
    cmds = [i for i, m in enumerate(frames) if m.arbitration_id == 0x202 and not m.is_extended_id]
    drop = {syncs[100], syncs[101], syncs[300], cmds[50], cmds[51], cmds[52], cmds[400]}
    cut = tmp_path / "cut.blf"
    with can.Logger(str(cut)) as writer:
        for i, m in enumerate(frames):
            if i not in drop:
                writer(m)
    assert main(["dump", str(full), "--stats", "--json"]) == 0
    clean = json.loads(capsys.readouterr().out)
    assert main(["dump", str(cut), "--stats", "--json"]) == 0
    gaps = json.loads(capsys.readouterr().out)["counter_gaps"]
    assert clean["counter_gaps"]["SYNC.sync_counter"] == {
        "gaps": 0,
        "missing": 0,
        "reordered": 0,
        "repeats": 0,
    }
    assert gaps["SYNC.sync_counter"] == {"gaps": 2, "missing": 3, "reordered": 0, "repeats": 0}
    assert gaps["DRIVE_RPDO1.cycle"] == {"gaps": 2, "missing": 4, "reordered": 0, "repeats": 0}
    control = clean["buses"]["control"]
    assert 0 < control["actual_load_percent"] < control["load_percent"]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("fault", "kind", "field"),
    [
        ("control.loss_rate=0.05", "loss", "missing"),
        ("control.duplicate_rate=0.02", "duplicate", "repeats"),
        ("control.reorder_rate=0.02", "reorder", None),
    ],
)
def test_stats_tell_lost_duplicated_and_reordered_counts_apart(tmp_path, capsys, fault, kind,
                                                               field):  # fmt: skip
    """A faulty run's trace: the SYNC counter's lost and duplicated counts equal the
    faults injected on SYNC (fault log), and reordering is never counted as loss."""
    trace, log = tmp_path / "t.blf", tmp_path / "faults.jsonl"
    args = ["run", "--duration", "1.5", "--fault", fault, "--trace", str(trace)]
    assert main([*args, "--fault-log", str(log), "--no-evaluate"]) == 0
    capsys.readouterr()
    records = [json.loads(line) for line in log.read_text().splitlines()]
    injected = sum(r["kind"] == kind and r["frame_id"] == 0x080 for r in records)
    assert injected > 3
    assert main(["dump", str(trace), "--stats", "--json"]) == 0
    stats = json.loads(capsys.readouterr().out)
    (sync,) = [g for g in stats["counter_gaps_by_channel"] if g["sender"] == "080"]
    others = {"missing", "repeats", "reordered"} - {field}
    if field is None:  # reordering: swapped neighbours, nothing lost or duplicated
        assert sync["reordered"] >= 1 and sync["missing"] == 0 and sync["repeats"] == 0
    else:
        assert sync[field] == injected
        assert all(sync[k] == 0 for k in others)


@pytest.mark.slow
@pytest.mark.parametrize("suffix", [".asc", ".trc"])
def test_a_flipped_byte_in_a_frame_line_is_reported(tmp_path, capsys, suffix):
    """Every single-bit flip that loses a frame of an ASC/TRC file is reported: exit 1,
    the count of unreadable lines and the first line number (seeded sample of flips)."""
    import random

    trace = tmp_path / f"t{suffix}"
    assert main(["run", "--duration", "0.2", "--trace", str(trace), "--no-evaluate"]) == 0
    capsys.readouterr()
    src = trace.read_bytes()
    assert main(["dump", str(trace), "--stats", "--json"]) == 0
    frames = json.loads(capsys.readouterr().out)["frames"]
    rng = random.Random(7)
    lost_and_reported = 0
    for _ in range(120):
        data = bytearray(src)
        pos = rng.randrange(len(data))
        data[pos] ^= 1 << rng.randrange(8)
        damaged = tmp_path / f"d{suffix}"
        damaged.write_bytes(bytes(data))
        rc = main(["dump", str(damaged), "--stats", "--json"])
        out, err = capsys.readouterr()
        assert "Traceback" not in err
        if rc == 2:
            continue  # the header itself is gone: not a trace (one-line error)
        if json.loads(out)["frames"] < frames:  # a frame line was lost...
            assert rc == 1, (pos, bytes(src[pos - 20 : pos + 20]))  # ...and reported
            assert "unreadable line" in err and ", the first at line " in err
            lost_and_reported += 1
    assert lost_and_reported >= 10


# ------------------------------------------------------- the library, without argparse


def _decoder(trace: Path):
    from hdhil.canopen.mapping import trace_decoder

    return trace_decoder(trace)


def test_export_writes_the_table_dump_prints(tmp_path, capsys):
    trace = write_trace(tmp_path / "t.asc", make_frames(20))
    decoder = _decoder(trace)
    id_filter, _ = export.parse_id_filter(["CTRL_TPDO1", "0x7EF"], decoder)
    lines: list[str] = []
    result = export.export(read_trace(trace), decoder, table=lines.append, limit=5,
                           id_filter=id_filter)  # fmt: skip
    clock = TraceClock(0.0)
    assert lines[0] == export.table_header(decoder, clock) + "\n" and len(lines) == 1 + 5
    assert (result.selected, result.printed, result.counts.total) == (22, 5, 82)
    rc, out, err = run_cli(capsys, trace, "--limit", "5", "--id", "CTRL_TPDO1", "--id", "7EF")
    assert rc == 0 and err == ""
    note = f"{result.selected} selected by --id, {result.printed} shown"
    assert out == "".join(lines) + result.counts.line(note, clock) + "\n"


@pytest.mark.parametrize("per_frame", [False, True], ids=["per-cycle", "per-frame"])
def test_export_writes_the_csv_dump_writes(tmp_path, capsys, per_frame):
    trace = write_trace(tmp_path / "t.blf", make_frames(20))
    decoder = _decoder(trace)
    id_filter, names = export.parse_id_filter(["181"], decoder)
    kind = export.FrameCsv if per_frame else export.CycleCsv
    ours = tmp_path / "library.csv"
    csv_out = kind(str(ours), decoder, names)
    result = export.export(read_trace(trace), decoder, id_filter=id_filter, csv_out=csv_out)
    assert result.printed == 0 and csv_out.rows == 20
    theirs = tmp_path / "command.csv"
    rc, out, err = run_cli(capsys, trace, "--csv", theirs, "--id", "181",
                           *(["--per-frame"] if per_frame else []))  # fmt: skip
    assert rc == 0 and out == ""
    assert f"hdhil: wrote {csv_out.rows} rows to" in err
    assert ours.read_bytes() == theirs.read_bytes()


def test_export_gives_the_statistics_dump_prints(tmp_path, capsys):
    trace = write_trace(tmp_path / "s.blf", schedule(50) + make_frames(3))
    decoder = _decoder(trace)
    stats = StatsAccumulator(500_000, decoder)
    result = export.export(read_trace(trace), decoder, stats=stats)
    rc, out, err = run_cli(capsys, trace, "--json", "--bitrate", "500000")
    assert rc == 0
    printed = json.loads(out)
    assert printed.pop("trace") == str(trace) and printed.pop("damage") == []
    assert printed == json.loads(json.dumps(stats.result()))
    assert err == result.counts.line() + "\n"


def test_export_refusals_are_value_errors(tmp_path):
    trace = write_trace(tmp_path / "t.csv", make_frames(2))
    decoder = _decoder(trace)
    with pytest.raises(ValueError, match=r"'nope': neither a message name \("):
        export.parse_id_filter(["nope"], decoder)
    with pytest.raises(ValueError, match=r"'20000000': identifier out of range"):
        export.parse_id_filter(["20000000"], decoder)
    with pytest.raises(ValueError, match="would overwrite the trace being read"):
        export.check_csv_target(str(trace), trace)
    with pytest.raises(ValueError, match="is a directory"):
        export.check_csv_target(str(tmp_path), trace)
    export.check_csv_target("-", trace)


# ------------------------------------------------- value tables, hex, columns, times

T0 = 1714564800.25  # 2024-05-01T12:00:00.25Z


def _control_frames() -> list[can.Message]:
    """Frames whose signals have value tables, bit-field words and object indices."""
    return [
        _msg(T0 + 0.000, "HEARTBEAT_DRIVE", {"nmt_state": 5}, 0),
        _msg(T0 + 0.001, "DRIVE_TPDO2", {"statusword": 0x0270}, 0),
        _msg(T0 + 0.002, "DRIVE_TPDO2", {"statusword": 0x1234}, 0),
        _msg(T0 + 0.003, "DRIVE_RPDO1", {"DAC_cmd": -3, "controlword": 0x000F, "cycle": 7}, 0),
        _msg(T0 + 0.004, "SDO_RX_DRIVE",
             {"sdo_cs": 0x40, "sdo_index": 0x6041, "sdo_sub": 2, "sdo_data": 0}, 0),
        _msg(T0 + 0.005, "CTRL_TPDO1",
             {"T_meas": 1.0, "T_filtered": 0.5, "velocity": 2.0, "current": 0.1}, 0),
        _msg(T0 + 0.0061, "TRUTH_TORQUE", {"T_true": 1.0, "T_ripple": 0.0}, 1),
    ]  # fmt: skip


def _expected_text(msg: can.Message) -> dict[str, str]:
    """What cantools decodes (``decode_choices=True``), as the table must print it."""
    db = TRUTH if msg.is_extended_id else CTRL
    message = db.get_message_by_frame_id(msg.arbitration_id)
    named = db.decode_message(msg.arbitration_id, msg.data, decode_choices=True)
    plain = db.decode_message(msg.arbitration_id, msg.data, decode_choices=False)
    texts = {}
    for sig in message.signals:
        value = plain[sig.name]
        hexed = sig.name.endswith("word") or "index" in sig.name
        number = f"0x{value:04X}" if hexed else None
        if sig.choices and value in sig.choices:
            name = str(named[sig.name])
            assert name == str(sig.choices[value])
            shown = name if " " not in name else f'"{name}"'
            texts[sig.name] = f"{shown}({number or value})"
        elif number is not None:
            texts[sig.name] = number
    return texts


def test_table_names_value_table_entries_as_cantools_decodes_them(tmp_path, capsys):
    frames = _control_frames()
    trace = write_trace(tmp_path / "v.blf", frames)
    rc, out, _ = run_cli(capsys, trace)
    assert rc == 0
    lines = out.splitlines()[1:-1]
    for msg, line in zip(frames, lines, strict=True):
        for signal, text in _expected_text(msg).items():
            assert f"{signal}={text}" in line, line
    assert "nmt_state=operational(5)" in lines[0]
    assert 'statusword="switch on disabled"(0x0270)' in lines[1]
    assert re.search(r"statusword=0x1234(\s|$)", lines[2])  # no value-table entry: hex alone
    assert 'controlword="enable operation"(0x000F)' in lines[3]
    assert "sdo_index=0x6041  sdo_sub=2" in lines[4]
    assert 'sdo_cs="upload request"(64)' in lines[4]


def test_table_columns_are_aligned(tmp_path, capsys):
    frames = [*_control_frames(), *make_frames(2)]
    frames.append(can.Message(timestamp=T0 + 0.01, is_error_frame=True, channel=0))
    trace = write_trace(tmp_path / "a.blf", frames)
    rc, out, _ = run_cli(capsys, trace)
    assert rc == 0
    lines = out.splitlines()[:-1]
    column = lines[0].index("signals")
    for line in lines[1:]:
        if "ERROR FRAME" in line and len(line) <= column:
            continue  # an error frame without data has no signals column
        assert line[column - 2 : column] == "  " and line[column] != " ", line
    ids = {line[lines[0].index("id") :].split()[0] for line in lines[1:]}
    assert {"702", "282", "602", "001F0001", "-"} <= ids


def test_asc_and_blf_of_the_same_run_print_the_same_times(tmp_path, capsys):
    frames = [*_control_frames()]
    outs = {}
    for suffix in (".blf", ".asc", ".log"):
        trace = write_trace(tmp_path / f"r{suffix}", frames)
        rc, outs[suffix], _ = run_cli(capsys, trace)
        assert rc == 0
    assert outs[".blf"] == outs[".asc"] == outs[".log"]
    first = outs[".blf"].splitlines()[1]
    assert first.startswith("    0.000000  control")
    assert "0.000000 .. 0.006100 s" in outs[".blf"]


def test_absolute_prints_iso_utc_times_in_every_format(tmp_path, capsys):
    frames = _control_frames()
    outs = {}
    for suffix in (".blf", ".asc"):
        trace = write_trace(tmp_path / f"w{suffix}", frames)
        rc, outs[suffix], err = run_cli(capsys, trace, "--absolute")
        assert rc == 0, err
    assert outs[".blf"] == outs[".asc"]
    lines = outs[".blf"].splitlines()
    assert lines[1].startswith("2024-05-01T12:00:00.250000Z  control  702")
    assert lines[-2].startswith("2024-05-01T12:00:00.256100Z  truth")
    column = lines[0].index("signals")
    assert all(line[column - 2 : column] == "  " for line in lines[1:-1])


def test_absolute_asc_without_header_date_uses_the_sidecar_or_refuses(tmp_path, capsys):
    trace = write_trace(tmp_path / "n.asc", _control_frames())
    text = "".join(
        line
        for line in trace.read_text().splitlines(keepends=True)
        if not line.lower().startswith(("date", "begin triggerblock"))
    )
    trace.write_text(text)
    rc, out, err = run_cli(capsys, trace, "--absolute")
    assert rc == 2 and out == "" and "--absolute" in err and "no start date" in err
    (tmp_path / "n.asc.json").write_text(json.dumps({"time_offset_s": T0}))
    rc, out, err = run_cli(capsys, trace, "--absolute")
    assert rc == 0, err
    assert out.splitlines()[1].startswith("2024-05-01T12:00:00.250000Z")


def test_csv_stays_numeric_with_value_tables(tmp_path, capsys):
    trace = write_trace(tmp_path / "c.blf", _control_frames())
    out_csv = tmp_path / "c.csv"
    rc, _, err = run_cli(capsys, trace, "--csv", out_csv, "--per-frame")
    assert rc == 0, err
    rows = list(csv.DictReader(out_csv.open()))
    assert rows[0]["HEARTBEAT_DRIVE.nmt_state"] == "5"
    assert rows[1]["DRIVE_TPDO2.statusword"] == "624"
    assert rows[4]["SDO_RX_DRIVE.sdo_index"] == str(0x6041)
