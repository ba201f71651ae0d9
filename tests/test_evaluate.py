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
