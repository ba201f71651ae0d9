"""Evaluation metrics on signals with known answers, and the evaluation of a real run."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.stages import adc_read, calibrate
from hdhil.rig.evaluate import (
    COLUMNS,
    Recording,
    calibrated_signals,
    estimate_lag,
    harmonic_amplitude,
)


def test_harmonic_amplitude_recovers_each_component():
    t = np.arange(20000) * 1e-3
    theta = 150.0 * t + 0.3 * np.sin(t)  # a motor angle with a slowly varying speed
    error = (0.6 * np.sin(2 * theta + 0.4) + 0.25 * np.cos(4 * theta + 1.3)
             + 0.1 + 0.02 * np.random.default_rng(1).standard_normal(t.size))  # fmt: skip
    mask = np.ones(t.size, dtype=bool)
    assert harmonic_amplitude(error, theta, 2.0, mask) == pytest.approx(0.6, rel=0.01)
    assert harmonic_amplitude(error, theta, 4.0, mask) == pytest.approx(0.25, rel=0.02)
    assert harmonic_amplitude(error, theta, 3.0, mask) < 0.01
    assert math.isnan(harmonic_amplitude(error, theta, 2.0, np.zeros(t.size, dtype=bool)))


@pytest.mark.parametrize("delay", [0.0, 3.0, 7.4, 22.5])
def test_lag_recovers_a_known_delay(delay):
    t = np.arange(6000) * 1e-3
    truth = 3.0 * np.sign(np.sin(2 * np.pi * 1.0 * t))  # 1 Hz torque steps of +-3 Nm
    truth = np.convolve(truth, np.ones(5) / 5, mode="same")  # a few ms of rise time
    delayed = np.interp(t - delay * 1e-3, t, truth)
    assert estimate_lag(delayed, truth, 1e-3) == pytest.approx(delay, abs=0.3)


def test_calibrated_signals_are_the_firmware_stages_sample_by_sample():
    """The per-count table gives what adc_read and calibrate give for each sample, the
    saturation of out-of-range codes included."""
    cfg = FirmwareConfig()
    rng = np.random.default_rng(3)
    rec = Recording(1e-3)
    codes = rng.integers(-2100, 2100, size=(400, 3)).tolist()
    for torque, tacho, current in codes:
        rec.append_row((torque, tacho, current) + (math.nan,) * (len(COLUMNS) - 3))
    T_meas, vel = calibrated_signals(rec, cfg)
    want = [calibrate(*adc_read(q, tq, cu, cfg.adc), cfg.calibration) for q, tq, cu in codes]
    assert T_meas.tolist() == [w[0] for w in want]
    assert vel.tolist() == [w[1] for w in want]
    assert [len(a) for a in calibrated_signals(Recording(1e-3), cfg)] == [0, 0]


def test_lag_is_undefined_without_torque_variation():
    flat = np.full(5000, 0.1)
    assert estimate_lag(flat, flat, 1e-3) is None


def test_per_minute_blocks_count_from_the_first_frame_whatever_the_clock():
    """Wall-clock timestamps (about 1.8e9 s) must not be walked in 60 s steps."""
    import can

    from hdhil.dbc import codec
    from hdhil.rig.score import TorqueScorer

    tele, truth = codec("control", "CTRL_TPDO1"), codec("truth", "TRUTH_TORQUE")
    scorer = TorqueScorer(block_s=1.0)
    t0 = 1.8e9
    for k in range(2500):  # 2.5 s at 1 kHz: two full blocks
        t = t0 + k * 1e-3
        scorer.on_message_received(
            can.Message(
                timestamp=t,
                arbitration_id=truth.frame_id,
                is_extended_id=True,
                data=truth.encode(0.0, 0.0),
            )
        )
        err = 0.1 if t - t0 < 1.0 else 0.2
        scorer.on_message_received(
            can.Message(
                timestamp=t + 1e-4,
                arbitration_id=tele.frame_id,
                is_extended_id=False,
                data=tele.encode(0.0, err, 0.0, 0.0),
            )
        )
    assert scorer.block_rms == pytest.approx([0.1, 0.2], abs=0.003)


@pytest.mark.slow
def test_a_logged_trace_pairs_each_sample_with_the_truth_sent_after_it(tmp_path) -> None:
    """`hdhil log` in another process receives each sample's truth frames after its sensor
    frame (the drive sends the sensor frame first); `hdhil run`'s tap stamps them at the
    sample instant, before it.  The same run, its truth frames moved behind the sensor
    frame they belong to, is recorded with the same truth per sample when its sidecar says
    `hdhil log` recorded it (and one sample off when it does not say so)."""
    import json

    import can
    import numpy as np

    from hdhil.cli import main
    from hdhil.rig.evaluate import recording_from_trace

    lockstep = tmp_path / "lockstep.blf"
    assert main(["run", "--duration", "0.3", "--trace", str(lockstep), "--quiet"]) == 0
    with can.LogReader(str(lockstep)) as reader:
        frames = list(reader)
    moved, held = [], []
    for msg in frames:  # each truth frame goes right behind the next sensor frame
        if msg.is_extended_id and msg.arbitration_id >> 16 == 0x1F:
            held.append(msg)
            continue
        moved.append(msg)
        if msg.arbitration_id == 0x182 and not msg.is_extended_id and held:
            for i, t in enumerate(held):
                t.timestamp = msg.timestamp + 20e-6 * (i + 1)
            moved += held
            held = []
    meta = json.loads(lockstep.with_name(lockstep.name + ".json").read_text())

    def recorded(name: str, by: str | None) -> np.ndarray:
        path = tmp_path / name
        with can.BLFWriter(str(path)) as writer:
            for msg in moved:
                writer.on_message_received(msg)
        side = {**meta, "recorded_by": by} if by else {k: v for k, v in meta.items()
                                                       if k != "recorded_by"}  # fmt: skip
        path.with_name(path.name + ".json").write_text(json.dumps(side))
        rec, _ = recording_from_trace(path)
        return np.asarray(rec.column("T_true")) + np.asarray(rec.column("T_ripple"))

    rec, _ = recording_from_trace(lockstep)
    truth = np.asarray(rec.column("T_true")) + np.asarray(rec.column("T_ripple"))
    logged = recorded("logged.blf", "hdhil log")
    assert logged.shape == truth.shape and np.array_equal(logged, truth, equal_nan=True)
    unlabelled = recorded("unlabelled.blf", None)
    assert not np.array_equal(unlabelled, truth, equal_nan=True)
    assert np.array_equal(unlabelled[1:], truth[:-1], equal_nan=True)  # one sample late


def test_the_angle_unwraps_past_a_sample_without_truth() -> None:
    """A sample whose truth frames never came has no angle: it stays NaN, and the angle
    unwraps on past it (a NaN carried into the running sum left every later phase NaN,
    and with it the harmonic figures of the whole run)."""
    import numpy as np

    from hdhil.rig.evaluate import _Unwrap

    angle = np.mod(np.linspace(0.0, 40.0, 400), 2 * np.pi)
    holed = angle.copy()
    holed[[3, 150, 151]] = np.nan
    unwrap = _Unwrap()
    got = np.concatenate([unwrap(holed[:200]), unwrap(holed[200:])])  # in two chunks
    expected = np.full(400, np.nan)
    finite = np.isfinite(holed)
    expected[finite] = np.unwrap(holed[finite])
    assert np.allclose(got, expected, equal_nan=True, rtol=0, atol=1e-12)
