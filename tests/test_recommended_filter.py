"""Tests of the recommended ripple filter (firmware/ripple.py ``HarmonicKalman``, the
angle-locked harmonic regression Kalman filter) and of the torque transfer function
(firmware/response.py) that shows why it replaces the paper filter as the default."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hdhil.firmware.config import (
    RECOMMENDED_RIPPLE,
    RECOMMENDED_SECTION5_RIPPLE,
    FirmwareConfig,
    Oscillator,
    RippleFilterConfig,
    paper_config,
)
from hdhil.firmware.isr import TorqueFilterChain
from hdhil.firmware.response import torque_response, torque_transfer
from hdhil.firmware.ripple import HarmonicKalman

Ts = 1e-3
GEAR = 100.0
CPR = 8000


# ------------------------------------------------------------------ reference transcription
class ReferenceKF:
    """The recommended filter written the textbook way with numpy (prediction form):
    ripple = C_h x_h; S = C P C' + R; K = P C' / S; moving: x += K e, P -= K C P;
    standstill: Schmidt gain (harmonic rows of K zeroed) with the Joseph-form covariance
    update; then P += Q."""

    def __init__(self, cfg: RippleFilterConfig, gear: float) -> None:
        self.w = [o.multiple / (gear if o.source == "output" else 1.0) for o in cfg.oscillators]
        self.n = 2 * len(self.w) + 1
        self.Q = np.diag([o.q for o in cfg.oscillators for _ in range(2)] + [cfg.residual_q])
        self.R = cfg.r
        self.standstill = cfg.standstill_radps
        self.x: np.ndarray | None = None
        self.P = np.eye(self.n) * cfg.p0

    def step(self, y: float, vel: float, angle: float) -> float:
        if self.x is None:
            self.x = np.zeros(self.n)
            self.x[-1] = y
        C = np.ones(self.n)
        for i, w in enumerate(self.w):
            C[2 * i], C[2 * i + 1] = math.cos(w * angle), math.sin(w * angle)
        ripple = float(C[:-1] @ self.x[:-1])
        S = C @ self.P @ C + self.R
        K = self.P @ C / S
        e = y - C @ self.x
        if abs(vel) >= self.standstill:
            self.x = self.x + K * e
            self.P = self.P - np.outer(K, C @ self.P)
        else:
            Ks = np.zeros(self.n)
            Ks[-1] = K[-1]
            A = np.eye(self.n) - np.outer(Ks, C)
            self.x = self.x + Ks * e
            self.P = A @ self.P @ A.T + self.R * np.outer(Ks, Ks)
        self.P = self.P + self.Q
        return ripple


@pytest.mark.parametrize(
    "cfg",
    [
        RippleFilterConfig(oscillators=(Oscillator("motor", 2.0),)),
        RECOMMENDED_RIPPLE,
        RECOMMENDED_SECTION5_RIPPLE,
        dataclasses.replace(RECOMMENDED_RIPPLE, r=0.3, p0=2.0, residual_q=1e-3),
        RippleFilterConfig(oscillators=(Oscillator("output", 3.0, 1e-4),), p0=0.5),
    ],
    ids=["1 harmonic", "2 harmonics", "3 harmonics", "other tuning", "output only"],
)
def test_matches_the_textbook_equations_including_standstill(cfg: RippleFilterConfig) -> None:
    kf = HarmonicKalman(cfg, GEAR)
    ref = ReferenceKF(cfg, GEAR)
    rng = np.random.default_rng(1)
    angle = 0.3
    for k in range(600):
        vel = 0.0 if 200 <= k < 300 else float(rng.normal(80.0, 40.0))  # incl. standstill
        vel = 1.5 if k == 350 else vel  # just under the threshold
        angle += vel * Ts
        y = float(rng.normal(1.0, 0.5))
        # different but equivalent algebra (P - u u'/S against P - K C P): rounding only
        assert kf.step(y, vel, angle) == pytest.approx(ref.step(y, vel, angle), rel=1e-9, abs=1e-9)
    np.testing.assert_allclose(kf.x, ref.x, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(kf.P, ref.P, rtol=1e-8, atol=1e-12)
    assert kf.steps == 600 and kf.skipped == 0 and kf.covariance_resets == 0


def test_first_step_initialises_the_residual_and_subtracts_nothing() -> None:
    kf = HarmonicKalman(RECOMMENDED_RIPPLE, GEAR)
    assert kf.step(2.5, 100.0, 0.7) == 0.0
    assert kf.residual == 2.5  # r = y, innovation 0
    np.testing.assert_array_equal(kf.x[:-1], 0.0)


def test_ripple_is_the_map_at_the_measured_angle_before_the_update() -> None:
    # prediction form: ripple(k) = C_ripple(k) x(k|k-1), evaluated at the angle of k
    kf = HarmonicKalman(RECOMMENDED_RIPPLE, GEAR)
    rng = np.random.default_rng(2)
    angle = 0.0
    for _ in range(200):
        angle += 0.15
        expected = kf.ripple_at(angle)  # before the update
        assert kf.step(float(rng.normal()), 150.0, angle) == expected
        assert kf.prediction == expected


def test_initial_covariance() -> None:
    # 1 Nm^2; 25 Nm^2 with an output harmonic ([Taghirad97] §5: up to 10 Nm p-p misalignment)
    np.testing.assert_array_equal(HarmonicKalman(RECOMMENDED_RIPPLE, GEAR).P, np.eye(5))
    np.testing.assert_array_equal(
        HarmonicKalman(RECOMMENDED_SECTION5_RIPPLE, GEAR).P, 25.0 * np.eye(7)
    )


def test_output_harmonic_phase_is_the_output_angle() -> None:
    kf = HarmonicKalman(RECOMMENDED_SECTION5_RIPPLE, gear_ratio=50.0)
    assert kf.phase_gains == (2.0, 4.0, 1.0 / 50.0)
    np.testing.assert_allclose(
        kf.regressor(1.0),
        [math.cos(2), math.sin(2), math.cos(4), math.sin(4), math.cos(0.02), math.sin(0.02), 1],
    )


def test_refuses_a_paper_config() -> None:
    with pytest.raises(ValueError, match="recommended"):
        HarmonicKalman(paper_config(FirmwareConfig()).ripple, GEAR)


# ------------------------------------------------------------------ synthetic drive signal
def _synthetic(seed: int = 0, duration_s: float = 12.0, misalignment_Nm: float = 0.0):
    """True torque with an offset, slow variation and steps; ripple at 2x and 4x the motor
    angle; sensor noise; motor angle from a speed profile; encoder counts from the angle."""
    rng = np.random.default_rng(seed)
    n = round(duration_s / Ts)
    t = np.arange(n) * Ts
    speed = np.where(t < 1.0, 120.0 * t, 120.0 + 60.0 * np.sin(2 * np.pi * 0.1 * (t - 1.0)))
    theta = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * Ts)])
    T_true = 1.5 + 0.8 * np.sin(2 * np.pi * 0.3 * t) + np.where(t % 4.0 < 2.0, 1.0, -1.0)
    ripple = 0.6 * np.sin(2 * theta + 0.4) + 0.25 * np.sin(4 * theta + 1.3)
    ripple += misalignment_Nm * np.sin(theta / GEAR + 0.4)
    T_meas = T_true + ripple + rng.normal(0.0, 0.02, n)
    encoder = np.floor(theta * CPR / (2 * np.pi)).astype(np.int64) % 65536
    velocity = speed + rng.normal(0.0, 0.05, n)
    return theta, T_true, T_meas, velocity, encoder


def _filtered(cfg: FirmwareConfig, T_meas, velocity, encoder) -> np.ndarray:
    step = TorqueFilterChain(cfg).step
    return np.array(
        [
            step(T, v, e)[3]
            for T, v, e in zip(T_meas.tolist(), velocity.tolist(), encoder.tolist(), strict=True)
        ]
    )


def _harmonic_amplitude(err: np.ndarray, phase: np.ndarray) -> float:
    """Amplitude of the component of ``err`` locked to ``phase`` (demodulation)."""
    return float(abs(2.0 * np.mean(err * np.exp(-1j * phase))))


@pytest.fixture(scope="module")
def drive_signal():
    return _synthetic()


@pytest.mark.parametrize("phase_source", ["encoder", "tacho"])
def test_removes_the_ripple_and_keeps_the_true_torque(drive_signal, phase_source) -> None:
    theta, T_true, T_meas, velocity, encoder = drive_signal
    ripple_cfg = dataclasses.replace(RECOMMENDED_RIPPLE, phase_source=phase_source)
    T_f = _filtered(FirmwareConfig(ripple=ripple_cfg), T_meas, velocity, encoder)
    m = slice(2000, None)  # after the first 2 s
    err, raw = T_f[m] - T_true[m], T_meas[m] - T_true[m]
    assert np.sqrt(np.mean(err**2)) <= 0.10 * np.sqrt(np.mean(raw**2))
    for multiple in (2, 4):
        reduction_dB = 20 * np.log10(
            _harmonic_amplitude(raw, multiple * theta[m])
            / _harmonic_amplitude(err, multiple * theta[m])
        )
        assert reduction_dB >= 20.0, multiple


def test_paper_filter_fails_the_same_signal(drive_signal) -> None:
    # the comparison that motivates the recommended mode: the paper filter cancels the
    # ripple too, but also the true low-frequency torque (offset, slow sine, steps)
    _theta, T_true, T_meas, velocity, encoder = drive_signal
    T_f = _filtered(paper_config(FirmwareConfig()), T_meas, velocity, encoder)
    m = slice(2000, None)
    err, raw = T_f[m] - T_true[m], T_meas[m] - T_true[m]
    assert np.sqrt(np.mean(err**2)) > 1.0 * np.sqrt(np.mean(raw**2))


@pytest.mark.slow
def test_output_harmonic_removes_misalignment() -> None:
    # [Taghirad97] §5: a torque signature at the output angle; 1 Nm amplitude (2 Nm p-p, the
    # text's value after re-assembly), motor at 120 rad/s, so 0.19 Hz: it takes a few
    # output revolutions to tell it from the slowly varying true torque
    rng = np.random.default_rng(3)
    n = 70_000
    t = np.arange(n) * Ts
    theta = 120.0 * t
    T_true = 1.0 + 0.5 * np.sin(2 * np.pi * 0.05 * t)
    misalignment = 1.0 * np.sin(theta / GEAR + 0.4)
    ripple = 0.6 * np.sin(2 * theta + 0.4) + 0.25 * np.sin(4 * theta + 1.3)
    T_meas = T_true + misalignment + ripple + rng.normal(0.0, 0.02, n)
    encoder = np.floor(theta * CPR / (2 * np.pi)).astype(np.int64) % 65536
    velocity = np.full(n, 120.0)
    m = slice(50_000, None)
    T_f = _filtered(FirmwareConfig(ripple=RECOMMENDED_SECTION5_RIPPLE), T_meas, velocity, encoder)
    assert _harmonic_amplitude(T_f[m] - T_true[m], theta[m] / GEAR) < 0.03
    # without the output harmonic it stays
    T_f = _filtered(FirmwareConfig(), T_meas, velocity, encoder)
    assert _harmonic_amplitude(T_f[m] - T_true[m], theta[m] / GEAR) > 0.9


# ------------------------------------------------------------------ transfer functions
FREQS_LOW = [0.0, 0.5, 1.0, 2.0, 5.0]


def _ripple_freqs(speed: float) -> list[float]:
    return [m * speed / (2 * np.pi) for m in (2.0, 4.0)]


@pytest.mark.slow
@pytest.mark.parametrize("speed", [20.0, 156.0])
def test_recommended_mode_passes_low_frequency_torque(speed: float) -> None:
    gains = torque_transfer(FirmwareConfig(), speed, FREQS_LOW)
    np.testing.assert_allclose(gains, 1.0, atol=0.02)


@pytest.mark.parametrize(("speed", "limit"), [(20.0, 0.2), (156.0, 0.7)])
def test_paper_mode_attenuates_low_frequency_torque(speed: float, limit: float) -> None:
    gains = torque_transfer(paper_config(FirmwareConfig()), speed, [0.0, 0.5], settle_s=3.0)
    assert np.all(gains < limit)  # measured: 0.05 at 20 rad/s, 0.53 at 156 rad/s


@pytest.mark.slow
@pytest.mark.parametrize("speed", [20.0, 156.0])
@pytest.mark.parametrize("mode", ["paper", "recommended"])
def test_both_modes_notch_the_ripple_frequencies(speed: float, mode: str) -> None:
    cfg = FirmwareConfig() if mode == "recommended" else paper_config(FirmwareConfig())
    gains = torque_transfer(cfg, speed, _ripple_freqs(speed))
    assert np.all(gains < 0.05)


def test_transfer_measurement_is_exact_for_a_pass_through() -> None:
    # a filter that can learn nothing (q = 0 and P0 tiny) leaves T_filtered = T_meas: the
    # measurement itself must then give gain 1 and phase 0 at any frequency
    ripple = RippleFilterConfig(
        oscillators=(Oscillator("motor", 2.0, 0.0),), p0=1e-300, residual_q=1e-2
    )
    H = torque_response(
        FirmwareConfig(ripple=ripple), 50.0, [0.0, 3.0, 40.0], settle_s=0.5, measure_s=2.0
    )
    np.testing.assert_allclose(H, 1.0, atol=1e-4)  # Hann-window leakage only


def test_transfer_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="frequencies"):
        torque_transfer(FirmwareConfig(), 20.0, [600.0])
    with pytest.raises(ValueError, match="speed"):
        torque_transfer(FirmwareConfig(), math.nan, [1.0])


# ------------------------------------------------------------------ robustness
def test_non_finite_inputs_are_skipped_and_counted() -> None:
    kf = HarmonicKalman(RECOMMENDED_RIPPLE, GEAR)
    clean = HarmonicKalman(RECOMMENDED_RIPPLE, GEAR)
    assert kf.step(math.nan, 100.0, 0.1) == 0.0  # nothing learned yet
    assert not kf.initialized
    angle = 0.0
    for k in range(300):
        angle += 0.1
        y = math.sin(2 * angle)
        assert kf.step(y, 100.0, angle) == clean.step(y, 100.0, angle)
        if k == 150:
            x, P = kf.x, kf.P
            assert kf.step(math.nan, 100.0, angle + 0.05) == kf.ripple_at(angle + 0.05)
            assert kf.step(0.5, math.inf, angle) == kf.ripple_at(angle)
            last = kf.prediction
            assert kf.step(0.5, 100.0, math.nan) == last  # no angle: the last ripple
            assert kf.step(0.5, 100.0, -math.inf) == last
            np.testing.assert_array_equal(kf.x, x)
            np.testing.assert_array_equal(kf.P, P)
    assert kf.skipped == 5
    assert kf.steps == clean.steps == 300
    np.testing.assert_array_equal(kf.x, clean.x)


def test_a_broken_covariance_is_reset_and_counted() -> None:
    kf = HarmonicKalman(RECOMMENDED_RIPPLE, GEAR)
    kf.step(1.0, 100.0, 0.0)
    x = kf.x
    n = kf.n
    # corrupt P (as a bit flip would): a negative diagonal makes S negative
    kf._P = tuple(-5.0 if i == j else 0.0 for i in range(n) for j in range(i, n))
    kf.step(1.0, 100.0, 0.1)
    assert kf.covariance_resets == 1
    np.testing.assert_array_equal(kf.P, np.eye(n) * RECOMMENDED_RIPPLE.p0)  # P(0)
    np.testing.assert_array_equal(kf.x, x)  # the bad update was discarded
    kf._P = tuple(
        math.nan if i == j == 0 else (1.0 if i == j else 0.0) for i in range(n) for j in range(i, n)
    )
    kf.step(1.0, 100.0, 0.2)
    assert kf.covariance_resets == 2
    assert np.all(np.isfinite(kf.P)) and np.all(np.isfinite(kf.x))


@pytest.mark.slow
def test_covariance_stays_symmetric_positive_definite_over_200000_steps() -> None:
    rng = np.random.default_rng(4)
    n = 200_000
    t = np.arange(n) * Ts
    # forwards, standstill, backwards, slow crawl through the threshold, fast
    vel = 150.0 * np.sin(2 * np.pi * t / 40.0) * (np.abs(np.sin(2 * np.pi * t / 13.0)) > 0.2)
    vel += rng.normal(0.0, 0.3, n)
    theta = np.cumsum(vel) * Ts
    y = (
        0.5 * np.sin(2 * theta)
        + 0.2 * np.sin(4 * theta + 1.0)
        + 0.3 * np.sin(theta / GEAR)
        + 2.0 * np.sin(2 * np.pi * 0.05 * t)
        + rng.normal(0.0, 0.03, n)
    )
    kf = HarmonicKalman(RECOMMENDED_SECTION5_RIPPLE, GEAR)
    step = kf.step
    for args in zip(y.tolist(), vel.tolist(), theta.tolist(), strict=True):
        step(*args)
    P = kf.P
    assert kf.covariance_resets == 0 and kf.skipped == 0
    assert np.all(np.isfinite(P)) and np.all(np.isfinite(kf.x))
    np.testing.assert_array_equal(P, P.T)
    assert np.all(np.linalg.eigvalsh(P) > 0.0)
    assert np.all(np.diag(P) < 10.0)  # bounded: not drifting off


# ------------------------------------------------------------------ standstill
def test_standstill_freezes_the_ripple_map_but_still_applies_it() -> None:
    cfg = RECOMMENDED_RIPPLE
    kf = HarmonicKalman(cfg, GEAR)

    def ripple(a: float) -> float:
        return 0.6 * math.sin(2 * a + 0.4) + 0.25 * math.sin(4 * a + 1.3)

    angle = 0.0
    for _ in range(20_000):  # learn at 100 rad/s, true torque 1 Nm
        angle += 100.0 * Ts
        kf.step(1.0 + ripple(angle), 100.0, angle)
    assert kf.ripple_at(angle) == pytest.approx(ripple(angle), abs=0.01)
    coefficients = kf.x[:-1]
    P_h = kf.P[:-1, :-1]
    # stop at this angle; the true torque steps to 3 Nm (a load), velocity below threshold
    outputs = []
    for k in range(3000):
        vel = 1.9 if k % 2 else -1.9
        outputs.append(kf.step(3.0 + ripple(angle), vel, angle))
    np.testing.assert_array_equal(kf.x[:-1], coefficients)  # the map did not absorb the step
    Q_h = np.diag([o.q for o in cfg.oscillators for _ in range(2)])
    np.testing.assert_allclose(kf.P[:-1, :-1], P_h + 3000 * Q_h, rtol=1e-9)
    assert outputs[-1] == kf.ripple_at(angle)  # the learned ripple is still subtracted
    T_filtered = 3.0 + ripple(angle) - outputs[-1]
    assert T_filtered == pytest.approx(3.0, abs=0.01)
    assert kf.residual == pytest.approx(3.0, abs=0.01)  # r took the step
    # at the threshold the coefficients are updated again (by a non-zero innovation)
    kf.step(3.5 + ripple(angle), cfg.standstill_radps, angle)
    assert not np.array_equal(kf.x[:-1], coefficients)


def test_paper_filter_absorbs_a_standstill_offset_the_recommended_keeps() -> None:
    # at standstill the paper filter has Phi = I and takes any torque for ripple
    T_true = 2.0
    for cfg, expected in ((paper_config(FirmwareConfig()), 0.0), (FirmwareConfig(), T_true)):
        chain = TorqueFilterChain(cfg)
        for _ in range(2000):
            T_f = chain.step(T_true, 0.0, 1000)[3]
        assert T_f == pytest.approx(expected, abs=0.01)
