"""hdhil with the CAN tools its users already have: python-can's bus options and
configuration, every trace format python-can writes and reads (MF4 through asammdf,
gzip), can-utils' log2asc/asc2log, and real dates in the traces."""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import json
import subprocess
import sys
from pathlib import Path

import can
import numpy as np
import pytest
from conftest import require_tools, skip_covered_elsewhere

from hdhil.cli import main
from hdhil.commands.options import NO_INTERFACE, add_bus_options, open_bus
from hdhil.dbc import CHANNEL_NUMBER, database

PINNED = "2026-01-02T03:04:05Z"
PINNED_UNIX = 1767323045.0


def _run(tmp_path: Path, trace: str, *extra: str) -> Path:
    path = tmp_path / trace
    args = ["run", "--duration", "0.2", "--seed", "1", "--no-evaluate", "--json",
            "--trace", str(path), "--start-time", PINNED, *extra]  # fmt: skip
    assert main(args) == 0
    return path


def _frames(path: Path) -> list[tuple[int, bool, bytes, float]]:
    """(id, extended, data, time since the first frame) of every frame python-can reads."""
    with can.LogReader(str(path)) as reader:
        msgs = list(reader)
    t0 = msgs[0].timestamp
    return [(m.arbitration_id, m.is_extended_id, bytes(m.data), round(m.timestamp - t0, 6))
            for m in msgs]  # fmt: skip


# ------------------------------------------------------------------ bus options


def _parsed(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_bus_options(p)
    return p.parse_args(argv)


@pytest.fixture
def no_can_config(tmp_path, monkeypatch):
    """No python-can configuration from the environment or a real home directory."""
    for name in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setattr(can.util, "CONFIG_FILES", [str(home / ".canrc")])
    return home


def test_bitrate_from_can_bitrate_reaches_the_bus(no_can_config, monkeypatch):
    """CAN_BITRATE is python-can's; the bus opened from hdhil's options runs at it (the
    simulated bus times frames by its bit rate, so the rate it reports is the one used)."""
    monkeypatch.setenv("CAN_BITRATE", "500000")
    bus, resolved = open_bus(_parsed(["-i", "simbus", "-c", "bitrate-env"]))
    try:
        assert resolved["bitrate"] == 500000
        assert bus.channel_info.endswith("at 500000 bit/s")
    finally:
        bus.shutdown()
    # The command line wins over the environment.
    bus, resolved = open_bus(_parsed(["-i", "simbus", "-c", "bitrate-cli", "-b", "250000"]))
    try:
        assert resolved["bitrate"] == 250000
        assert bus.channel_info.endswith("at 250000 bit/s")
    finally:
        bus.shutdown()


def test_interface_and_bitrate_from_the_configuration_file(no_can_config):
    (no_can_config / ".canrc").write_text(
        "[default]\ninterface = simbus\nchannel = from-file\nbitrate = 125000\n"
    )
    bus, resolved = open_bus(_parsed([]))
    try:
        assert resolved["interface"] == "simbus" and resolved["channel"] == "from-file"
        assert bus.channel_info.endswith("at 125000 bit/s")
    finally:
        bus.shutdown()


def test_without_any_bit_rate_the_system_rate_is_used(no_can_config):
    bus, resolved = open_bus(_parsed(["-i", "simbus", "-c", "default-rate"]))
    try:
        assert resolved["bitrate"] == 1_000_000
        assert bus.channel_info.endswith("at 1000000 bit/s")
    finally:
        bus.shutdown()


def test_missing_interface_is_one_line_saying_how_to_name_one(no_can_config, capsys):
    assert main(["nmt", "start", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"hdhil: error: {NO_INTERFACE}"
    assert "--interface" in err and "CAN_INTERFACE" in err and "\n" not in err


def test_bus_kwargs_and_filters_reach_python_can(no_can_config):
    args = _parsed(["-i", "virtual", "-c", "kw", "--filter", "181:7FF",
                    "--bus-kwargs", "receive_own_messages=True"])  # fmt: skip
    bus, _ = open_bus(args)
    try:
        bus.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\x01"))
        bus.send(can.Message(arbitration_id=0x182, is_extended_id=False, data=b"\x02"))
        got = bus.recv(0.5)
        assert got is not None and got.arbitration_id == 0x181  # own frame, filtered
        assert bus.recv(0.1) is None  # 0x182 filtered out
    finally:
        bus.shutdown()


# ------------------------------------------------------------------ trace formats

FORMATS = [".blf", ".asc", ".log", ".csv", ".trc", ".asc.gz", ".log.gz", ".csv.gz",
           ".trc.gz"]  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("suffix", FORMATS)
def test_every_format_round_trips_through_python_can(tmp_path, suffix):
    """What ``run`` writes, python-can's LogReader reads back frame for frame, and
    ``dump`` decodes with no unknown or damaged frame."""
    reference = _frames(_run(tmp_path, "ref.blf"))
    path = _run(tmp_path, f"t{suffix}")
    assert _frames(path) == reference
    assert main(["dump", str(path), "--stats", "--json"]) == 0


def test_mf4_round_trip(tmp_path, capsys):
    skip_covered_elsewhere(
        importlib.util.find_spec("asammdf") is not None,
        "asammdf (the mf4 extra)",
        "HDHIL_MF4_ELSEWHERE",
        "the MF4 step of .ci/run, in a venv of its own",
    )
    reference = _frames(_run(tmp_path, "ref.blf"))
    path = _run(tmp_path, "t.mf4")
    assert _frames(path) == reference
    from asammdf import MDF

    mdf = MDF(str(path))
    # The file's start is the trace's start, and its time axis starts at 0, not 1.8e9 s.
    assert abs(mdf.header.start_time.timestamp() - PINNED_UNIX) < 1e-3
    assert main(["evaluate", str(path)]) == 0
    capsys.readouterr()


def test_mf4_rig_databases_decode_every_joint_by_name(tmp_path):
    """asammdf decodes an MF4 trace of a bus with two joints by the .dbc file written
    from the generated rig database (:mod:`hdhil.canopen.rigdb`): each joint's
    telemetry and truth under its own message name."""
    skip_covered_elsewhere(
        importlib.util.find_spec("asammdf") is not None,
        "asammdf (the mf4 extra)",
        "HDHIL_MF4_ELSEWHERE",
        "the MF4 step of .ci/run, in a venv of its own",
    )
    import cantools
    from asammdf import MDF

    from hdhil.canopen.rigdb import RigDrive, rig_databases

    drives = [RigDrive("J3", 4, "can1", mapping="cst-sensor"), RigDrive("J4", 5, "can1")]
    db = rig_databases(drives)["can1"]
    dbc = tmp_path / "can1.dbc"
    cantools.database.dump_file(db, str(dbc))
    path = tmp_path / "rig.mf4"
    writer = can.MF4Writer(str(path))
    for k in range(5):
        for name, values in (
            ("J3_CTRL_TPDO1", {"T_meas": 0.5 * k, "T_filtered": 0, "velocity": 0, "current": 0}),
            ("J4_CTRL_TPDO1", {"T_meas": -0.5 * k, "T_filtered": 0, "velocity": 0, "current": 0}),
            ("J4_TRUTH_TORQUE", {"T_true": 1.5 * k, "T_ripple": 0}),
        ):
            message = db.get_message_by_name(name)
            writer.on_message_received(can.Message(
                timestamp=1.0 + k * 1e-3, arbitration_id=message.frame_id, channel=0,
                is_extended_id=message.is_extended_frame, data=message.encode(values)))  # fmt: skip
    writer.stop()
    decoded = MDF(str(path)).extract_bus_logging({"CAN": [(str(dbc), 0)]})
    steps = np.arange(5)
    assert np.allclose(decoded.get("J3_CTRL_TPDO1.T_meas").samples, 0.5 * steps)
    assert np.allclose(decoded.get("J4_CTRL_TPDO1.T_meas").samples, -0.5 * steps)
    assert np.allclose(decoded.get("J4_TRUTH_TORQUE.T_true").samples, 1.5 * steps)


@pytest.mark.slow
@pytest.mark.subprocess
def test_truncated_mf4_is_one_error_line(tmp_path):
    """A cut MF4 file: asammdf raises in its constructor and the half-built object's
    finaliser raises again when collected ("Exception ignored in ..."); both end as the
    one line ``hdhil: error: ...``, exit 2, in every command that reads a trace."""
    skip_covered_elsewhere(
        importlib.util.find_spec("asammdf") is not None,
        "asammdf (the mf4 extra)",
        "HDHIL_MF4_ELSEWHERE",
        "the MF4 step of .ci/run, in a venv of its own",
    )
    whole = _run(tmp_path, "whole.mf4").read_bytes()
    for keep in (len(whole) // 8, len(whole) - 512):
        cut = tmp_path / f"cut{keep}.mf4"
        cut.write_bytes(whole[:keep])
        for argv in (["dump", str(cut)], ["evaluate", str(cut)]):
            proc = subprocess.run(
                [sys.executable, "-m", "hdhil", *argv], capture_output=True, text=True,
                timeout=120,
            )  # fmt: skip
            lines = proc.stderr.splitlines()
            assert proc.returncode == 2, (argv, proc.returncode, proc.stderr)
            assert len(lines) == 1 and lines[0].startswith("hdhil: error: "), proc.stderr
            assert "not a readable MF4 trace" in lines[0]


@pytest.mark.slow
def test_mf4_without_asammdf_is_a_clear_error(tmp_path, monkeypatch, capsys):
    import hdhil.can.traces.formats as formats

    monkeypatch.setattr(formats, "mf4_available", lambda: False)
    assert main(["run", "--duration", "0.05", "--trace", str(tmp_path / "x.mf4")]) == 2
    err = capsys.readouterr().err
    assert "asammdf" in err and "hdhil[mf4]" in err and not (tmp_path / "x.mf4").exists()


def test_sqlite_is_refused_rather_than_losing_frames(tmp_path, capsys):
    assert main(["run", "--duration", "0.05", "--trace", str(tmp_path / "x.db")]) == 2
    assert "unsupported trace format '.db'" in capsys.readouterr().err


def test_blf_cannot_be_gzipped_and_says_what_can(tmp_path, capsys):
    assert main(["run", "--duration", "0.05", "--trace", str(tmp_path / "x.blf.gz")]) == 2
    assert ".asc" in capsys.readouterr().err


def test_sidecar_and_header_dates(tmp_path):
    path = _run(tmp_path, "d.blf")
    meta = json.loads((tmp_path / "d.blf.json").read_text())
    assert (
        meta["start_time"] == PINNED_UNIX and meta["start_time_utc"] == "2026-01-02T03:04:05.000Z"
    )
    assert meta["scenario"] == "free-motion" and meta["seed"] == 1
    with can.BLFReader(str(path)) as reader:
        assert abs(reader.start_timestamp - PINNED_UNIX) < 1e-3
        first = next(iter(reader))
    assert PINNED_UNIX <= first.timestamp < PINNED_UNIX + 1e-3


def test_bad_start_time_is_one_line(capsys):
    assert main(["run", "--start-time", "yesterday", "--trace", ""]) == 2
    assert "--start-time" in capsys.readouterr().err


# ------------------------------------------------------------------ can-utils


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.canutils
def test_can_utils_log2asc_asc2log_round_trip(tmp_path):
    """candump log -> log2asc -> asc2log gives back every frame, in order, with the same
    times relative to the first frame and one ASC header."""
    require_tools("log2asc", "asc2log", package="can-utils")
    log = _run(tmp_path, "t.log")
    asc, back = tmp_path / "t.asc", tmp_path / "back.log"
    subprocess.run(["log2asc", "-I", str(log), "-O", str(asc), "can0", "can1"], check=True,
                   capture_output=True)  # fmt: skip
    text = asc.read_text()
    assert text.count("\ndate ") + text.startswith("date ") == 1
    subprocess.run(["asc2log", "-I", str(asc), "-O", str(back)], check=True,
                   capture_output=True)  # fmt: skip
    original, returned = _frames(log), _frames(back)
    assert len(returned) == len(original)
    assert [f[:3] for f in returned] == [f[:3] for f in original]
    assert max(abs(a[3] - b[3]) for a, b in zip(original, returned, strict=True)) < 2e-6
    # And python-can reads log2asc's ASC: the same frames.
    assert [f[:3] for f in _frames(asc)] == [f[:3] for f in original]


def test_truth_and_control_decode_with_the_databases(tmp_path):
    """Channel numbers survive in the formats that store them (ASC, BLF, candump)."""
    path = _run(tmp_path, "c.asc")
    with can.LogReader(str(path)) as reader:
        for msg in reader:
            bus = "truth" if msg.is_extended_id else "control"
            assert can.util.channel2int(msg.channel) in (CHANNEL_NUMBER[bus], None)
            database(bus).get_message_by_frame_id(msg.arbitration_id)


# ------------------------------------------------------------------ tidy data


def _csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    import csv

    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], [dict(zip(rows[0], r, strict=True)) for r in rows[1:]]


def test_dump_csv_is_one_row_per_cycle_with_units(tmp_path, capsys):
    trace = _run(tmp_path, "t.blf")
    out, frames = tmp_path / "cycles.csv", tmp_path / "frames.csv"
    assert main(["dump", str(trace), "--csv", str(out)]) == 0
    assert main(["dump", str(trace), "--csv", str(frames), "--per-frame"]) == 0
    capsys.readouterr()
    header, rows = _csv(out)
    assert header[:2] == ["time_s", "sample"]
    for column in ("T_meas_Nm", "T_filtered_Nm", "velocity_radps", "current_A", "T_true_Nm",
                   "omega_motor_radps", "ADC_torque_count", "ENC_count"):  # fmt: skip
        assert column in header
    # Only the signals present: free motion runs no control law, so no CTRL_TPDO2 columns.
    assert not any(c.startswith(("tau_lgd_hat", "e_hat", "dtau_s_hat")) for c in header)
    # One row per sample: as many rows as sensor frames, numbered from 0.
    fheader, frows = _csv(frames)
    sensor = [r for r in frows if r["id"] == "0x182"]
    telemetry = [r for r in frows if r["id"] == "0x181"]
    assert len(rows) == len(sensor) and [int(r["sample"]) for r in rows] == list(range(len(rows)))
    # The cells are the frames' values: the k-th telemetry frame answers a sample.
    answered = [r for r in rows if r["T_meas_Nm"] != ""]
    assert len(answered) == len(telemetry)
    for r, f in zip(answered[::50], telemetry[::50], strict=True):
        assert float(r["T_meas_Nm"]) == float(f["CTRL_TPDO1.T_meas"])
        assert float(r["velocity_radps"]) == float(f["CTRL_TPDO1.velocity"])
    # Mostly full: per frame, most cells are empty.
    empty = sum(v == "" for r in rows for v in r.values()) / (len(rows) * len(header))
    fempty = sum(v == "" for r in frows for v in r.values()) / (len(frows) * len(fheader))
    assert empty < 0.02 < 0.8 < fempty
    # Times (of each sample's sensor frame) are seconds since the trace's start, rising
    # by the 1 ms period; a heartbeat on the wire delays a sensor frame by a frame time.
    times = [float(r["time_s"]) for r in rows]
    steps = [b - a for a, b in itertools.pairwise(times)]
    assert 0 <= times[0] < 0.01 and all(0.8e-3 < d < 1.2e-3 for d in steps)
    assert abs((times[-1] - times[0]) / len(steps) - 1e-3) < 1e-6


def test_dump_csv_has_the_control_law_columns_when_one_runs(tmp_path, capsys):
    trace = _run(tmp_path, "lqg.blf", "--scenario", "lqg-tracking")
    out = tmp_path / "lqg.csv"
    assert main(["dump", str(trace), "--csv", str(out), "--id", "CTRL_TPDO2"]) == 0
    capsys.readouterr()
    header, rows = _csv(out)
    assert header[:2] == ["time_s", "sample"]
    assert {"dtau_s_hat_Nmps", "tau_lgd_hat_Nm", "tau_sD_Nm", "e_hat_Nm"} <= set(header)
    assert len(header) == 6 and rows  # --id keeps only that message's columns


@pytest.mark.slow
def test_filter_reads_the_per_cycle_csv_and_writes_units(tmp_path, capsys):
    trace = _run(tmp_path, "t.blf")
    cycles, filtered = tmp_path / "cycles.csv", tmp_path / "filtered.csv"
    assert main(["dump", str(trace), "--csv", str(cycles)]) == 0
    assert main(["filter", str(cycles), "--out", str(filtered)]) == 0
    capsys.readouterr()
    header, rows = _csv(filtered)
    assert header == ["time_s", "T_meas_Nm", "acceleration_radps2", "T_expected_Nm",
                      "ripple_Nm", "T_filtered_Nm"]  # fmt: skip
    assert len(rows) == len(_csv(cycles)[1])


# ------------------------------------------------------------------ progress


def _on_a_terminal(args: list[str]) -> tuple[int, str, str]:
    """Run ``python -m hdhil ARGS`` with standard error on a pseudo-terminal; return the
    exit code, standard output and what reached the terminal."""
    import os
    import pty

    master, slave = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-m", "hdhil", *args], stdout=subprocess.PIPE,
                            stderr=slave, stdin=subprocess.DEVNULL)  # fmt: skip
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:  # EIO: the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    out = proc.stdout.read().decode() if proc.stdout else ""
    code = proc.wait(timeout=300)
    os.close(master)
    return code, out, b"".join(chunks).decode(errors="replace")


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize(
    "args",
    [
        ["run", "--duration", "1", "--trace", "", "--no-evaluate"],
        ["calibrate", "--positions", "4"],
    ],
    ids=["run", "calibrate"],
)
def test_progress_on_a_terminal_and_none_with_json_or_quiet(args):
    code, out, tty = _on_a_terminal(args)
    assert code == 0, tty
    assert f"hdhil {args[0]}" in tty and "%|" in tty and "<" in tty  # bar with an ETA
    assert "%|" not in out  # the result itself is clean
    for flag in ("--json", "--quiet"):
        code, out, tty = _on_a_terminal([*args, flag])
        assert code == 0 and "%|" not in tty and "%|" not in out
    # Not a terminal (a pipe): no progress either.
    proc = subprocess.run([sys.executable, "-m", "hdhil", *args], capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0 and "%|" not in proc.stderr


def test_soak_blocks_adapt_to_short_runs():
    from hdhil.analysis.soak import SoakLimits, default_block_s

    limits = SoakLimits(settle_s=40.0)
    assert default_block_s(120.0, limits) == 20.0  # 4 blocks from 40 s
    assert default_block_s(3600.0, limits) == 60.0
    assert default_block_s(30.0, limits) == 60.0  # nothing after settling: the verdict says so


# ------------------------------------------------------------------ one DBC view


@pytest.mark.slow
@pytest.mark.subprocess
def test_dbc_export_decodes_a_whole_trace_with_cantools(tmp_path, capsys):
    """``hdhil dbc export`` gives one database for both buses: cantools decodes every
    frame of a candump log (none unknown), with the value tables and units."""
    merged = tmp_path / "hdhil.dbc"
    assert main(["dbc", "export", str(merged)]) == 0
    capsys.readouterr()
    log = _run(tmp_path, "t.log")
    proc = subprocess.run([sys.executable, "-m", "cantools", "decode", "--single-line",
                           str(merged)], input=log.read_text(), capture_output=True, text=True,
                          timeout=120, check=True)  # fmt: skip
    lines = proc.stdout.splitlines()
    assert len(lines) == len(log.read_text().splitlines())
    assert not [line for line in lines if "Unknown" in line]
    assert any("TRUTH_TORQUE(T_true:" in line and " Nm" in line for line in lines)
    assert any("controlword: enable operation" in line for line in lines)
    assert any("statusword: operation enabled" in line for line in lines)
    assert any("sync_counter: 2 cycle" in line for line in lines)
    import cantools

    db = cantools.database.load_file(str(merged), strict=True)
    assert db.dbc.attributes["Baudrate"].value == 1_000_000
    for name in ("TRUTH_TORQUE", "TRUTH_MOTION", "TRUTH_JOINT"):
        assert db.get_message_by_name(name).comment
    emcy = db.get_message_by_name("EMCY_DRIVE").get_signal_by_name("error_code").choices
    assert str(emcy[0x8130]) == "heartbeat lost"
    sdo = db.get_message_by_name("SDO_RX_DRIVE").get_signal_by_name("sdo_cs").choices
    assert str(sdo[0x40]) == "upload request"
    assert db.get_message_by_name("DRIVE_RPDO1").get_signal_by_name("cycle").unit == "cycle"


def test_dbc_export_refuses_a_directory(tmp_path, capsys):
    assert main(["dbc", "export", str(tmp_path)]) == 2
    assert "not a regular file" in capsys.readouterr().err


# ------------------------------------------------------------------ the Python API


@pytest.mark.slow
@pytest.mark.subprocess
def test_the_readme_python_api_example_runs_and_prints_what_the_readme_says(tmp_path):
    """The README's "Python API" example, run as it stands in a fresh interpreter (in an
    empty directory), prints exactly the lines the README shows."""
    import re

    readme = (Path(__file__).parent.parent / "README.md").read_text(encoding="utf-8")
    section = readme[readme.index("## Python API") :]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    claimed = re.search(r"It prints:\n\n```\n(.*?)```", section, re.S).group(1)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=True, cwd=tmp_path).stdout  # fmt: skip
    assert out.strip() == claimed.strip()
    assert (tmp_path / "api-run.blf").is_file() and (tmp_path / "api-run.blf.json").is_file()


@pytest.mark.slow
def test_api_arrays_match_the_trace(tmp_path):
    """The run's per-cycle arrays (samples in operation) are a stretch of the trace's
    per-cycle table (every sample, start-up included), value for value."""
    import hdhil.api as hd

    trace = tmp_path / "a.blf"
    result = hd.run("free-motion", duration_s=0.3, seed=2, trace=trace)
    run_arrays, trace_arrays = hd.cycle_arrays(result), hd.read_trace(trace)
    n = len(run_arrays["time_s"])
    assert n >= 300 and len(trace_arrays["time_s"]) > n
    enc_run, enc_trace = run_arrays["ENC_count"], trace_arrays["ENC_count"]
    adc_run, adc_trace = run_arrays["ADC_torque_count"], trace_arrays["ADC_torque_count"]
    offsets = [o for o in range(len(enc_trace) - n + 1)
               if np.array_equal(adc_trace[o : o + n], adc_run)
               and np.array_equal(enc_trace[o : o + n], enc_run)]  # fmt: skip
    assert len(offsets) == 1
    o = offsets[0]
    told, tnew = trace_arrays["T_meas_Nm"][o : o + n], run_arrays["T_meas_Nm"]
    both = np.isfinite(told) & np.isfinite(tnew)
    assert both.sum() > 0.95 * n and np.array_equal(told[both], tnew[both])
    assert np.array_equal(trace_arrays["T_true_Nm"][o : o + n], run_arrays["T_true_Nm"])
    with pytest.raises(ValueError, match="evaluate=True"):
        hd.cycle_arrays(hd.run("free-motion", duration_s=0.05, evaluate=False))


def test_compare_laws_traces_keep_the_whole_format_extension():
    from hdhil.rig.laws import _suffixed

    assert _suffixed(Path("d/run.asc.gz"), "jtf1") == Path("d/run-jtf1.asc.gz")
    assert _suffixed(Path("run.blf"), "jtf2") == Path("run-jtf2.blf")


@pytest.mark.parametrize("name", ["x.txt", "x.blf.gz"])
def test_log_refuses_a_bad_trace_name_in_one_line(tmp_path, capsys, name):
    args = ["log", str(tmp_path / name), "-i", "virtual", "-c", "log-bad", "--duration", "0.1"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hdhil: error: unsupported trace format") and "\n" not in err
