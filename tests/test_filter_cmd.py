"""Tests of ``hdhil filter`` (tools/hdhil/filter_cmd.py): the firmware's filter chain run
offline over a signal CSV or a trace, with the same numbers as the firmware itself."""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import can
import numpy as np
import pytest

from hdhil.can.traces.writer import open_writer
from hdhil.cli import main
from hdhil.dbc import codec
from hdhil.firmware.config import FirmwareConfig, paper_config
from hdhil.firmware.isr import AdcSample, InterruptHandler, TorqueFilterChain
from hdhil.rig.offline import OUTPUT_COLUMNS

HEADER = "time_s,T_meas_Nm,acceleration_radps2,T_expected_Nm,ripple_Nm,T_filtered_Nm"


def _signal(n: int = 1500, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 1e-3
    vel = 40.0 + 100.0 * t + rng.normal(0.0, 0.1, n)
    theta = np.cumsum(vel) * 1e-3
    T = 1.0 + 0.6 * np.sin(2 * theta) + 0.2 * np.sin(4 * theta + 1) + rng.normal(0.0, 0.02, n)
    enc = np.floor(theta * 8000 / (2 * np.pi)).astype(np.int64) % 65536
    return t, T, vel, enc


def _write_csv(path: Path, columns: dict[str, list], header: str | None = None) -> Path:
    names = list(columns)
    with path.open("w") as fh:
        fh.write((header if header is not None else ",".join(names)) + "\n")
        for row in zip(*columns.values(), strict=True):
            fh.write(",".join(str(v) for v in row) + "\n")
    return path


def _read_output(path: Path) -> tuple[list[str], np.ndarray]:
    with path.open() as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(v) for v in r] for r in rows[1:]])


def _chain_rows(cfg: FirmwareConfig, t, T, vel, enc) -> np.ndarray:
    chain = TorqueFilterChain(cfg)
    rows = []
    for ti, Ti, vi, ei in zip(t, T, vel, enc, strict=True):
        acc, T_exp, _dT, T_f, ripple = chain.step(Ti, vi, ei)
        rows.append((ti, Ti, acc, T_exp, ripple, T_f))
    return np.array(rows)


@pytest.fixture
def signal_csv(tmp_path: Path) -> tuple[Path, tuple[np.ndarray, ...]]:
    t, T, vel, enc = _signal()
    path = _write_csv(
        tmp_path / "in.csv",
        {
            "time": [repr(v) for v in t.tolist()],
            "T_meas": [repr(v) for v in T.tolist()],
            "velocity": [repr(v) for v in vel.tolist()],
            "encoder": enc.tolist(),
        },
    )
    return path, (t, T, vel, enc)


# ------------------------------------------------------------------ signal CSV
def test_csv_output_is_the_chain_exactly(signal_csv, tmp_path, capsys) -> None:
    path, (t, T, vel, enc) = signal_csv
    out = tmp_path / "out.csv"
    assert main(["filter", str(path), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "1500 samples" in err and "0 skipped" in err and "phase from encoder" in err
    assert len(err.strip().splitlines()) == 1
    assert out.read_text().splitlines()[0] == HEADER
    header, rows = _read_output(out)
    assert tuple(header) == OUTPUT_COLUMNS
    expected = _chain_rows(FirmwareConfig(), t.tolist(), T.tolist(), vel.tolist(), enc.tolist())
    np.testing.assert_array_equal(rows, expected)  # bit for bit: the same code path
    np.testing.assert_array_equal(rows[:, 5], rows[:, 1] - rows[:, 4])  # T_f = T_meas - ripple
    # and the filter did something: the ripple is largely gone at the end
    assert np.std(rows[-500:, 5] - 1.0) < 0.2 * np.std(rows[-500:, 1] - 1.0)


def test_csv_with_paper_flag_and_with_config_file(signal_csv, tmp_path) -> None:
    path, (t, T, vel, enc) = signal_csv
    expected = _chain_rows(
        paper_config(FirmwareConfig()), t.tolist(), T.tolist(), vel.tolist(), enc.tolist()
    )
    out = tmp_path / "paper.csv"
    assert main(["filter", str(path), "--out", str(out), "--paper"]) == 0
    np.testing.assert_array_equal(_read_output(out)[1], expected)
    # a scenario-style file ([firmware.*] tables) ...
    scenario = tmp_path / "scn.toml"
    scenario.write_text(
        '[scenario]\nname = "x"\n[plant.ripple]\namp2_Nm = 0.1\n[firmware.ripple]\nmode = "paper"\n'
    )
    assert main(["filter", str(path), "--out", str(out), "--config", str(scenario)]) == 0
    np.testing.assert_array_equal(_read_output(out)[1], expected)
    # ... or the firmware tables at top level
    bare = tmp_path / "fw.toml"
    bare.write_text('[ripple]\nmode = "paper"\n')
    assert main(["filter", str(path), "--out", str(out), "--config", str(bare)]) == 0
    np.testing.assert_array_equal(_read_output(out)[1], expected)


def test_csv_without_encoder_uses_the_tacho_phase(tmp_path, capsys) -> None:
    t, T, vel, _ = _signal()
    path = _write_csv(
        tmp_path / "noenc.csv",
        {"T_meas": T.tolist(), "extra": [0] * len(t), "velocity": vel.tolist(), "time": t.tolist()},
    )
    out = tmp_path / "out.csv"
    assert main(["filter", str(path), "--out", str(out)]) == 0
    assert "phase from tacho" in capsys.readouterr().err
    cfg = FirmwareConfig()
    cfg = dataclasses.replace(cfg, ripple=dataclasses.replace(cfg.ripple, phase_source="tacho"))
    expected = _chain_rows(cfg, t.tolist(), T.tolist(), vel.tolist(), [None] * len(t))
    np.testing.assert_array_equal(_read_output(out)[1], expected)


def test_non_finite_values_are_filtered_skipped_and_counted(tmp_path, capsys) -> None:
    t, T, vel, enc = _signal(300)
    T_text = [repr(v) for v in T.tolist()]
    vel_text = [repr(v) for v in vel.tolist()]
    T_text[100], T_text[150], vel_text[200] = "nan", "inf", "-inf"
    path = _write_csv(
        tmp_path / "nan.csv",
        {"time": t.tolist(), "T_meas": T_text, "velocity": vel_text, "encoder": enc.tolist()},
    )
    out = tmp_path / "out.csv"
    assert main(["filter", str(path), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "300 samples" in err and "3 skipped (non-finite)" in err
    _, rows = _read_output(out)
    assert len(rows) == 300
    assert math.isnan(rows[100, 5]) and math.isinf(rows[150, 5])
    assert np.all(np.isfinite(rows[201:, 5]))  # the filter went on


def test_output_to_stdout(signal_csv, capsys) -> None:
    path, _ = signal_csv
    assert main(["filter", str(path), "--out", "-"]) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert lines[0] == HEADER and len(lines) == 1501
    assert "wrote stdout" in captured.err


# ------------------------------------------------------------------ traces
def _trace_frames(n: int = 800) -> tuple[list[can.Message], list[tuple[int, int, int, int]]]:
    """Frames as ``hdhil run`` logs them: SYNC, the drive's sensor frame, the controller's
    telemetry on the control bus (channel 0), truth on channel 1."""
    sensor = codec("control", "DRIVE_TPDO1")
    sync = codec("control", "SYNC")
    tele = codec("control", "CTRL_TPDO1")
    truth = codec("truth", "TRUTH_TORQUE")
    rng = np.random.default_rng(7)
    frames, counts = [], []
    for k in range(n):
        t0 = k * 1e-3
        theta = 120.0 * t0
        torque = round((1.0 + 0.6 * math.sin(2 * theta)) / 6.6 / (10 / 2048))
        c = (
            torque + int(rng.integers(-2, 3)),
            round(120.0 / 56.2565 / (10 / 2048)) + int(rng.integers(-1, 2)),
            int(rng.integers(-50, 50)),
            math.floor(theta * 8000 / (2 * math.pi)) % 65536,
        )
        counts.append(c)
        frames += [
            can.Message(timestamp=t0, arbitration_id=sync.frame_id, is_extended_id=False,
                        data=sync.encode(k % 240 + 1), channel=0),
            can.Message(timestamp=t0 + 1e-4, arbitration_id=sensor.frame_id,
                        is_extended_id=False, data=sensor.encode(*c), channel=0),
            can.Message(timestamp=t0 + 2e-4, arbitration_id=truth.frame_id, is_extended_id=True,
                        data=truth.encode(1.0, 0.5), channel=1),
            can.Message(timestamp=t0 + 3e-4, arbitration_id=tele.frame_id, is_extended_id=False,
                        data=tele.encode(9.0, 9.0, 9.0, 9.0), channel=0),
        ]  # fmt: skip
    return frames, counts


def _isr_rows(cfg: FirmwareConfig, counts) -> np.ndarray:
    isr = InterruptHandler(cfg)
    rows = []
    for c in counts:
        o = isr(AdcSample(*c))
        rows.append((o.T_meas, o.acceleration, o.T_expected, o.ripple, o.T_filtered))
    return np.array(rows)


@pytest.mark.parametrize("suffix", [".blf", ".asc", ".csv", ".log", ".trc"])
def test_trace_is_filtered_exactly_as_the_firmware_did(tmp_path, suffix, capsys) -> None:
    frames, counts = _trace_frames()
    trace = tmp_path / f"run{suffix}"
    writer = open_writer(trace)
    for msg in frames:
        writer.on_message_received(msg)
    writer.stop()
    for paper, cfg in ((False, FirmwareConfig()), (True, paper_config(FirmwareConfig()))):
        out = tmp_path / "out.csv"
        argv = ["filter", str(trace), "--out", str(out)] + (["--paper"] if paper else [])
        assert main(argv) == 0
        err = capsys.readouterr().err
        assert "800 samples from DRIVE_TPDO1 frames" in err
        header, rows = _read_output(out)
        assert tuple(header) == OUTPUT_COLUMNS
        np.testing.assert_array_equal(rows[:, 1:], _isr_rows(cfg, counts))
        np.testing.assert_allclose(rows[:, 0], np.arange(800) * 1e-3 + 1e-4, atol=2e-6)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["paper", "recommended"])
def test_a_run_s_trace_is_replayed_from_the_firmware_s_first_interrupt(tmp_path, mode, capsys):
    """The firmware leaves out the sensor frames before its first interrupt (the drive's
    start-up and, in paper mode, the listing's settling pause): the replay does too, so
    every filtered sample equals the telemetry's T_filtered from the first one on (within
    half the telemetry's resolution)."""
    config = tmp_path / "fw.toml"
    config.write_text(f'[firmware.ripple]\nmode = "{mode}"\n')
    trace = tmp_path / "t.blf"
    argv = ["run", "--scenario", "free-motion", "--duration", "0.2", "--override", str(config),
            "--trace", str(trace)]  # fmt: skip
    assert main(argv) == 0
    out = tmp_path / "o.csv"
    paper = ["--paper"] if mode == "paper" else []
    assert main(["filter", str(trace), "--out", str(out), "--config", str(config), *paper]) == 0
    err = capsys.readouterr().err
    assert "sensor frames before the firmware's first interrupt left out" in err
    tele = codec("control", "CTRL_TPDO1")
    with can.LogReader(str(trace)) as reader:
        filtered = [tele.decode(m.data)[1] for m in reader
                    if m.arbitration_id == tele.frame_id and not m.is_extended_id]  # fmt: skip
    _, rows = _read_output(out)
    assert len(rows) >= len(filtered) == 200
    lsb = tele.message.get_signal_by_name("T_filtered").scale
    np.testing.assert_allclose(rows[: len(filtered), 5], filtered, rtol=0, atol=lsb / 2 + 1e-9)


def _real_time_trace(n: int = 300) -> tuple[list[can.Message], list[tuple[float, float, int]]]:
    """Frames as a real-time run over udp_multicast logs them (every control frame twice,
    the logger joined to both groups), with the firmware's cycle as it runs there: at each
    SYNC it reads the frames that came, runs its interrupt on the first and ignores the
    others; with none it takes the first to come in the cycle, and a frame coming after its
    answer waits for the next SYNC.  The drive stalls once (three frames late, in a burst:
    the firmware answers a cycle behind) and the firmware reads late once (it catches up,
    one frame ignored).  Returns the frames and, per interrupt, (sensor frame time, the
    telemetry's T_filtered, periods skipped before it)."""
    sensor = codec("control", "DRIVE_TPDO1")
    sync = codec("control", "SYNC")
    tele = codec("control", "CTRL_TPDO1")
    command = codec("control", "DRIVE_RPDO1")
    isr = InterruptHandler(FirmwareConfig())
    ms = 1e-3
    arrival = [k * ms + 0.12 * ms for k in range(n)]
    for i, k in enumerate((100, 101, 102)):  # the drive's process held up
        arrival[k] = 102.3 * ms + 0.02 * ms * i
    read_late = {110: 0.5 * ms}  # the firmware's process held up
    counts = []
    for k in range(n):
        theta = 120.0 * k * ms
        counts.append((
            round((1.0 + 0.6 * math.sin(2 * theta)) / 6.6 / (10 / 2048)) + k % 3 - 1,
            round(120.0 / 56.2565 / (10 / 2048)) + k % 2,
            k % 7,
            math.floor(theta * 8000 / (2 * math.pi)) % 65536,
        ))  # fmt: skip
    events: list[tuple[float, can.Message]] = []

    def add(t: float, frame_id: int, data: bytes) -> None:
        events.append((t, can.Message(timestamp=t, arbitration_id=frame_id,
                                      is_extended_id=False, data=data, channel=0)))  # fmt: skip

    interrupts: list[tuple[float, float, int]] = []
    next_frame = 0  # the first frame the firmware has not read
    missed = 0
    for k in range(n):
        add(k * ms, sync.frame_id, sync.encode(k % 240 + 1))
        add(arrival[k], sensor.frame_id, sensor.encode(*counts[k]))
        read = k * ms + read_late.get(k, 0.05 * ms)
        came = [j for j in range(next_frame, n) if arrival[j] < read]
        if came:
            taken, at = came[0], read
            next_frame = came[-1] + 1  # the others read in this cycle: ignored
        elif next_frame < n and arrival[next_frame] < (k + 1) * ms:
            taken, at = next_frame, arrival[next_frame]
            next_frame += 1
        else:
            missed += 1
            continue
        for _ in range(missed):
            isr.sample_missed()
        o = isr(AdcSample(*counts[taken]))
        add(at + 0.08 * ms, command.frame_id, command.encode(o.dac_counts, 15, k % 256))
        data = tele.encode(o.T_meas, o.T_filtered, o.velocity, o.current)
        add(at + 0.1 * ms, tele.frame_id, data)
        interrupts.append((arrival[taken], tele.decode(data)[1], missed))
        missed = 0
    frames = []
    for _, msg in sorted(events, key=lambda e: e[0]):
        frames.append(msg)
        twin = msg.__copy__()
        twin.channel = 1
        frames.append(twin)
    return frames, interrupts


def test_a_real_time_trace_is_replayed_as_the_firmware_ran(tmp_path, capsys) -> None:
    """In real time the firmware's cycles are not the frames' timestamps: a late frame is
    answered a cycle later, a burst loses all but one frame.  The replay takes the samples
    the firmware took (its telemetry names them) and the periods it skipped, so every
    filtered sample equals the telemetry's T_filtered (within half its resolution)."""
    frames, interrupts = _real_time_trace()
    assert sum(m for _, _, m in interrupts) == 2  # the stall: two periods without a sample
    trace = tmp_path / "rt.blf"
    writer = open_writer(trace)
    for msg in frames:
        writer.on_message_received(msg)
    writer.stop()
    out = tmp_path / "o.csv"
    assert main(["filter", str(trace), "--out", str(out)]) == 0
    capsys.readouterr()
    _, rows = _read_output(out)
    # 300 periods, two skipped; 300 frames, two ignored (one after the stall, one late read)
    assert len(rows) == len(interrupts) == 300 - 2
    np.testing.assert_allclose(rows[:, 0], [t for t, _, _ in interrupts], atol=2e-6)
    lsb = codec("control", "CTRL_TPDO1").message.get_signal_by_name("T_filtered").scale
    np.testing.assert_allclose(
        rows[:, 5], [f for _, f, _ in interrupts], rtol=0, atol=lsb / 2 + 1e-9
    )


def test_trace_without_sensor_frames_is_an_error(tmp_path, capsys) -> None:
    trace = tmp_path / "truth_only.asc"
    writer = open_writer(trace)
    truth = codec("truth", "TRUTH_TORQUE")
    for k in range(5):
        writer.on_message_received(
            can.Message(timestamp=k * 1e-3, arbitration_id=truth.frame_id, is_extended_id=True,
                        data=truth.encode(1.0, 0.0), channel=1)
        )  # fmt: skip
    writer.stop()
    assert main(["filter", str(trace), "--out", str(tmp_path / "o.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert "no DRIVE_TPDO1 frames" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o.csv").exists()


# ------------------------------------------------------------------ user errors
def _one_line_error(argv: list[str], capsys) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hdhil: error: ") and "Traceback" not in err
    assert len(err.splitlines()) == 1, err
    return err


def test_user_errors_are_one_line(tmp_path, capsys) -> None:
    out = str(tmp_path / "out.csv")
    err = _one_line_error(["filter", str(tmp_path / "missing.csv"), "--out", out], capsys)
    assert "no such file" in err
    (tmp_path / "x.txt").write_text("time,T_meas,velocity\n0,1,2\n")
    err = _one_line_error(["filter", str(tmp_path / "x.txt"), "--out", out], capsys)
    assert "unsupported input format '.txt'" in err
    (tmp_path / "empty.csv").write_text("")
    assert "empty" in _one_line_error(["filter", str(tmp_path / "empty.csv"), "--out", out], capsys)
    (tmp_path / "head.csv").write_text("time,T_meas,velocity\n")
    err = _one_line_error(["filter", str(tmp_path / "head.csv"), "--out", out], capsys)
    assert "no samples" in err
    (tmp_path / "cols.csv").write_text("time,torque,speed\n0,1,2\n")
    err = _one_line_error(["filter", str(tmp_path / "cols.csv"), "--out", out], capsys)
    assert "missing column(s) T_meas, velocity" in err
    (tmp_path / "word.csv").write_text("time,T_meas,velocity\n0,1,2\n0.001,abc,2\n")
    err = _one_line_error(["filter", str(tmp_path / "word.csv"), "--out", out], capsys)
    assert "word.csv:3" in err and "'T_meas'" in err and "'abc'" in err
    # An empty cell is a missing sample (a cycle without its frame in a per-cycle export):
    # skipped and counted by the filter, not an error; an empty time is one.
    (tmp_path / "blank.csv").write_text("time,T_meas,velocity\n0,1,\n0.001,1,2\n")
    ok = str(tmp_path / "ok.csv")
    assert main(["filter", str(tmp_path / "blank.csv"), "--out", ok]) == 0
    assert "1 skipped" in capsys.readouterr().err
    (tmp_path / "notime.csv").write_text("time,T_meas,velocity\n,1,2\n")
    err = _one_line_error(["filter", str(tmp_path / "notime.csv"), "--out", out], capsys)
    assert "notime.csv:2" in err and "'time'" in err
    (tmp_path / "short.csv").write_text("time,T_meas,velocity\n0,1\n")
    err = _one_line_error(["filter", str(tmp_path / "short.csv"), "--out", out], capsys)
    assert "short.csv:2: expected 3 fields, got 2" in err
    (tmp_path / "enc.csv").write_text("time,T_meas,velocity,encoder\n0,1,2,3.5\n")
    err = _one_line_error(["filter", str(tmp_path / "enc.csv"), "--out", out], capsys)
    assert "enc.csv:2" in err and "encoder" in err
    assert not (tmp_path / "out.csv").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".out.csv")] == []


def test_bad_output_and_config_are_one_line(signal_csv, tmp_path, capsys) -> None:
    path, _ = signal_csv
    err = _one_line_error(["filter", str(path), "--out", str(tmp_path / "no" / "o.csv")], capsys)
    assert "does not exist" in err
    err = _one_line_error(["filter", str(path), "--out", str(path)], capsys)
    assert "overwrite the input" in err
    bad = tmp_path / "bad.toml"
    bad.write_text("[firmware.ripple]\nmode = 'fast'\n")
    err = _one_line_error(["filter", str(path), "--out", "-", "--config", str(bad)], capsys)
    assert "ripple.mode" in err
    bad.write_text("[firmware\n")
    err = _one_line_error(["filter", str(path), "--out", "-", "--config", str(bad)], capsys)
    assert "invalid TOML" in err
    err = _one_line_error(
        ["filter", str(path), "--out", "-", "--config", str(tmp_path / "none.toml")], capsys
    )
    assert "no such file" in err
