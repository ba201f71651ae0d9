"""Tests of the torque-ripple Kalman filter (firmware/ripple.py; [Taghirad97], Eqs. 5-10,
listing A.1 / A.2 ``Kalman``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from listing_ports import ListingKF
from scipy.linalg import block_diag

from hdhil.firmware.config import (
    LISTING_A1_RIPPLE,
    LISTING_A2_RIPPLE,
    SECTION5_RIPPLE,
    Oscillator,
    RippleFilterConfig,
)
from hdhil.firmware.ripple import RippleKalman

T = 1e-3
GEAR = 100.0


def one_block(q: float = 0.5, r: float = 1.0, p0: float = 1.0) -> RippleKalman:
    cfg = RippleFilterConfig(oscillators=(Oscillator("motor", 2.0, q),), r=r, p0=p0, mode="paper")
    return RippleKalman(cfg, T, GEAR)


# ------------------------------------------------------------------ hand-worked cases
def test_hand_worked_two_state_filter_at_zero_velocity() -> None:
    # velocity 0 -> Phi = I.  p0 = 1, q = 0.5, R = 1, C = [1 0].
    kf = one_block()
    # Call 1, y = 2: init x = [2, 0], P = I.
    #   PC = P C' = [1, 0]; CPC = 1; pPC = Phi PC = [1, 0]; K = [1, 0] / (1 + 1) = [0.5, 0]
    #   Phi - K C = [[0.5, 0], [0, 1]]
    #   P = Q + (Phi - KC) P Phi' = 0.5 I + diag(0.5, 1) = diag(1.0, 1.5)
    #   x = (Phi - KC) x + K y = [1, 0] + [1, 0] = [2, 0];  output C x = 2
    assert kf.step(2.0, 0.0) == pytest.approx(2.0)
    np.testing.assert_allclose(kf.K, [0.5, 0.0])
    np.testing.assert_allclose(kf.P, np.diag([1.0, 1.5]))
    np.testing.assert_allclose(kf.x, [2.0, 0.0])
    # Call 2, y = 4: PC = [1, 0]; CPC = 1; K = [0.5, 0]
    #   P = 0.5 I + diag(0.5, 1) diag(1, 1.5) = diag(1.0, 2.0)
    #   x = [0.5 * 2, 0] + [0.5 * 4, 0] = [3, 0]
    assert kf.step(4.0, 0.0) == pytest.approx(3.0)
    np.testing.assert_allclose(kf.P, np.diag([1.0, 2.0]))
    np.testing.assert_allclose(kf.x, [3.0, 0.0])


def test_hand_worked_two_state_filter_quarter_turn() -> None:
    # 2 * velocity * T = pi/2 -> Phi = [[0, 1], [-1, 0]].  p0 = 1, q = 0.5, R = 1.
    vel = (math.pi / 2) / (2 * T)
    kf = one_block()
    # Call 1, y = 2: x = [2, 0], P = I.  PC = [1, 0]; CPC = 1; pPC = Phi [1, 0] = [0, -1]
    #   K = [0, -0.5];  Phi - KC = [[0, 1], [-0.5, 0]]
    #   P Phi' = [[0, -1], [1, 0]];  (Phi - KC) P Phi' = [[1, 0], [0, 0.5]]
    #   P = [[1.5, 0], [0, 1.0]]
    #   x = (Phi - KC) [2, 0] + K 2 = [0, -1] + [0, -1] = [0, -2];  output 0
    assert kf.step(2.0, vel) == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(kf.K, [0.0, -0.5], atol=1e-12)
    np.testing.assert_allclose(kf.P, [[1.5, 0.0], [0.0, 1.0]], atol=1e-12)
    np.testing.assert_allclose(kf.x, [0.0, -2.0], atol=1e-12)
    # Call 2, y = 0.5: PC = [1.5, 0]; CPC = 1.5; pPC = [0, -1.5]; K = [0, -0.6]
    #   Phi - KC = [[0, 1], [-0.4, 0]];  P Phi' = [[0, -1.5], [1, 0]]
    #   (Phi - KC) P Phi' = [[1, 0], [0, 0.6]];  P = [[1.5, 0], [0, 1.1]]
    #   x = (Phi - KC) [0, -2] + K 0.5 = [-2, 0] + [0, -0.3] = [-2, -0.3];  output -2
    assert kf.step(0.5, vel) == pytest.approx(-2.0)
    np.testing.assert_allclose(kf.K, [0.0, -0.6], atol=1e-12)
    np.testing.assert_allclose(kf.P, [[1.5, 0.0], [0.0, 1.1]], atol=1e-12)
    np.testing.assert_allclose(kf.x, [-2.0, -0.3], atol=1e-12)


# ------------------------------------------------------------------ reference transcriptions
def rot(wt: float) -> np.ndarray:
    return np.array([[math.cos(wt), math.sin(wt)], [-math.sin(wt), math.cos(wt)]])


class EquationsKF:
    """[Taghirad97], Eqs. 5-10 written the textbook way (Eq. 8 in innovation form)."""

    def __init__(self, cfg: RippleFilterConfig, sample_period: float, gear: float) -> None:
        self.w = [o.multiple / (gear if o.source == "output" else 1.0) for o in cfg.oscillators]
        n = 2 * len(self.w)
        self.T = sample_period
        self.Q = np.diag(np.repeat([o.q for o in cfg.oscillators], 2))
        self.R = cfg.r
        self.p0 = cfg.p0
        self.C = np.tile([1.0, 0.0], n // 2)
        self.x: np.ndarray | None = None
        self.P = np.eye(n) * cfg.p0

    def step(self, y: float, vel: float) -> float:
        if self.x is None:
            self.x = np.tile([y, 0.0], len(self.w))
        phi = block_diag(*[rot(w * vel * self.T) for w in self.w])  # Eq. 5, 6
        K = phi @ self.P @ self.C / (self.R + self.C @ self.P @ self.C)  # Eq. 9
        self.x = phi @ self.x + K * (y - self.C @ self.x)  # Eq. 8
        self.P = self.Q + (phi - np.outer(K, self.C)) @ self.P @ phi.T  # Eq. 10
        return float(self.C @ self.x)


def _inputs(n: int, seed: int) -> list[tuple[float, float]]:
    rng = np.random.default_rng(seed)
    vel = 50.0 + 150.0 * np.sin(np.linspace(0.0, 3.0, n)) + rng.normal(0.0, 5.0, n)
    y = rng.normal(0.0, 1.0, n)
    return list(zip(y.tolist(), vel.tolist(), strict=True))


@pytest.mark.parametrize("cfg", [LISTING_A1_RIPPLE, LISTING_A2_RIPPLE, SECTION5_RIPPLE])
def test_matches_equations_8_to_10(cfg: RippleFilterConfig) -> None:
    kf = RippleKalman(cfg, T, GEAR)
    ref = EquationsKF(cfg, T, GEAR)
    for y, vel in _inputs(400, seed=1):
        assert kf.step(y, vel) == pytest.approx(ref.step(y, vel), rel=1e-9, abs=1e-9)
    np.testing.assert_allclose(kf.P, ref.P, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(kf.x, ref.x, rtol=1e-9, atol=1e-9)


def test_first_step_4th_order_against_numpy_transcription() -> None:
    y, vel = 0.8, 156.0
    kf = RippleKalman(LISTING_A1_RIPPLE, T, GEAR)
    out = kf.step(y, vel)
    x = np.array([y, 0.0, y, 0.0])
    P = np.eye(4)
    C = np.array([1.0, 0.0, 1.0, 0.0])
    phi = block_diag(rot(2 * vel * T), rot(4 * vel * T))
    K = phi @ P @ C / (1.0 + C @ P @ C)
    P1 = 1e3 * np.eye(4) + (phi - np.outer(K, C)) @ P @ phi.T
    x1 = phi @ x + K * (y - C @ x)
    np.testing.assert_allclose(kf.phi, phi, rtol=1e-12)
    np.testing.assert_allclose(kf.K, K, rtol=1e-12)
    np.testing.assert_allclose(kf.P, P1, rtol=1e-12)
    np.testing.assert_allclose(kf.x, x1, rtol=1e-12)
    assert out == pytest.approx(x1[0] + x1[2], rel=1e-12)


class ListingNumpyKF:
    """Listing A.1's update order (Eqs. 9, 10, 8) with numpy matrices, every product in
    full: the form the generated kernel unrolls."""

    def __init__(self, cfg: RippleFilterConfig, sample_period: float, gear: float) -> None:
        self.ref = EquationsKF(cfg, sample_period, gear)

    def step(self, y: float, vel: float) -> float:
        r = self.ref
        if r.x is None:
            r.x = np.tile([y, 0.0], len(r.w))
        phi = block_diag(*[rot(w * vel * r.T) for w in r.w])
        PC = r.P @ r.C
        K = phi @ PC / (r.R + r.C @ PC)
        p_KC = phi - np.outer(K, r.C)
        r.P = r.Q + p_KC @ (r.P @ phi.T)
        r.x = p_KC @ r.x + K * y
        return float(r.C @ r.x)


@pytest.mark.parametrize("cfg", [LISTING_A1_RIPPLE, LISTING_A2_RIPPLE, SECTION5_RIPPLE])
def test_kernel_is_the_numpy_listing_to_round_off(cfg: RippleFilterConfig) -> None:
    """Over a long run the unrolled step and the same update with full numpy products
    differ only by the order of additions: round-off, which the filter does not grow."""
    kf = RippleKalman(cfg, T, GEAR)
    ref = ListingNumpyKF(cfg, T, GEAR)
    pairs = [(kf.step(y, vel), ref.step(y, vel)) for y, vel in _inputs(1000, seed=5)]
    got, want = [p[0] for p in pairs], [p[1] for p in pairs]
    scale = max(abs(v) for v in want)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * scale)
    np.testing.assert_allclose(kf.P, ref.ref.P, rtol=1e-13, atol=1e-13 * np.abs(ref.ref.P).max())
    assert "import" not in kf.kernel_source and kf.kernel_source.startswith("def step(")


@pytest.mark.parametrize(("cfg", "a2"), [(LISTING_A1_RIPPLE, False), (LISTING_A2_RIPPLE, True)])
def test_matches_the_listing_loop_for_loop(cfg: RippleFilterConfig, a2: bool) -> None:
    kf = RippleKalman(cfg, T, GEAR)
    listing = ListingKF(a2=a2)
    for y, vel in _inputs(150, seed=2):
        assert kf.step(y, vel) == pytest.approx(listing(y, vel, T), rel=1e-9, abs=1e-9)


def test_output_block_frequency_uses_gear_ratio() -> None:
    cfg = RippleFilterConfig(
        oscillators=(Oscillator("motor", 2.0), Oscillator("output", 3.0)), mode="paper"
    )
    kf = RippleKalman(cfg, T, gear_ratio=50.0)
    kf.step(0.0, 200.0)
    phi = kf.phi
    assert phi[0, 1] == pytest.approx(math.sin(2.0 * 200.0 * T))
    assert phi[2, 2] == pytest.approx(math.cos(3.0 * 200.0 * T / 50.0))
    assert phi[3, 2] == pytest.approx(-math.sin(3.0 * 200.0 * T / 50.0))
    assert phi[0, 2] == 0.0 and phi[1, 3] == 0.0


# ------------------------------------------------------------------ behaviour
def _ripple(theta: float) -> float:
    return 0.5 * math.sin(2 * theta + 0.3) + 0.2 * math.sin(4 * theta + 1.1)


def test_converges_on_pure_ripple_at_constant_velocity() -> None:
    kf = RippleKalman(LISTING_A1_RIPPLE, T, GEAR)
    vel = 156.0  # [Taghirad97] §4: peaks at 312 and 624 rad/s at 156 rad/s
    errors = []
    for k in range(1000):
        predicted_next = kf.step(_ripple(vel * k * T), vel)
        errors.append(abs(predicted_next - _ripple(vel * (k + 1) * T)))
    assert max(errors[:10]) > 1e-2  # it starts wrong ...
    assert max(errors[-200:]) < 1e-9  # ... and locks on


def test_tracks_ripple_through_a_velocity_ramp() -> None:
    kf = RippleKalman(LISTING_A1_RIPPLE, T, GEAR)
    theta = 0.0
    errors = []
    for k in range(2000):
        vel = 20.0 + 0.1 * k  # rad/s, ramping up to 220 rad/s
        y = _ripple(theta)
        theta += vel * T  # the model's rotation: theta(k+1) = theta(k) + vel(k) T
        errors.append(abs(kf.step(y, vel) - _ripple(theta)))
    assert max(errors[-500:]) < 1e-8


def test_sixth_order_model_also_removes_misalignment() -> None:
    kf = RippleKalman(SECTION5_RIPPLE, T, GEAR)
    vel = 150.0

    def signal(k: int) -> float:
        theta = vel * k * T
        return _ripple(theta) + 1.0 * math.sin(theta / GEAR + 0.4)  # 2 Nm p-p, §5

    errors = [abs(kf.step(signal(k), vel) - signal(k + 1)) for k in range(20000)]
    assert max(errors[-1000:]) < 1e-3 * max(errors[:100])


def test_state_persists_between_calls() -> None:
    kf = RippleKalman(LISTING_A1_RIPPLE, T, GEAR)
    kf.step(1.0, 100.0)
    second = kf.step(0.3, 100.0)
    fresh = RippleKalman(LISTING_A1_RIPPLE, T, GEAR).step(0.3, 100.0)
    assert second != pytest.approx(fresh)
    assert kf.steps == 2


def test_non_finite_input_is_skipped_and_counted() -> None:
    kf = RippleKalman(LISTING_A1_RIPPLE, T, GEAR)
    assert kf.step(float("nan"), 100.0) == 0.0  # nothing predicted yet
    assert not kf.initialized
    first = kf.step(1.0, 100.0)
    x, P = kf.x, kf.P
    assert kf.step(float("nan"), 100.0) == first
    assert kf.step(0.5, float("inf")) == first
    assert kf.step(0.5, float("-inf")) == first
    assert kf.skipped == 4
    np.testing.assert_array_equal(kf.x, x)
    np.testing.assert_array_equal(kf.P, P)
    # and the filter goes on as if the bad samples had never come
    clean = RippleKalman(LISTING_A1_RIPPLE, T, GEAR)
    clean.step(1.0, 100.0)
    assert kf.step(0.2, 110.0) == clean.step(0.2, 110.0)


def test_reset_restores_fresh_state() -> None:
    kf = RippleKalman(LISTING_A1_RIPPLE, T, GEAR)
    for y, vel in _inputs(20, seed=3):
        kf.step(y, vel)
    kf.step(float("nan"), 0.0)
    kf.reset()
    assert kf.skipped == 0 and kf.steps == 0 and kf.prediction == 0.0
    fresh = RippleKalman(LISTING_A1_RIPPLE, T, GEAR)
    assert kf.step(0.7, 80.0) == fresh.step(0.7, 80.0)


def test_exposed_arrays_are_copies() -> None:
    kf = RippleKalman(LISTING_A1_RIPPLE, T, GEAR)
    before = kf.step(1.0, 100.0)
    kf.x[:] = 99.0
    kf.P[:] = 99.0
    kf.K[:] = 99.0
    assert kf.x[0] != 99.0 and kf.P[0, 0] != 99.0 and kf.K[0] != 99.0
    assert kf.prediction == before


def test_covariance_stays_bounded_and_symmetric_over_a_long_run() -> None:
    kf = RippleKalman(SECTION5_RIPPLE, T, GEAR)
    for y, vel in _inputs(20000, seed=4):
        kf.step(y, vel)
    P = kf.P
    assert np.all(np.isfinite(P))
    np.testing.assert_allclose(P, P.T, rtol=1e-9, atol=1e-9)
    assert np.all(np.linalg.eigvalsh((P + P.T) / 2) > 0)


def test_paper_presets_are_the_listings() -> None:
    # Listing A.1: Q = 1000 I, R = 1, P = I, 2x and 4x; A.2: Q[2][2] = Q[3][3] = 5e-2, 1x output.
    assert LISTING_A1_RIPPLE.mode == LISTING_A2_RIPPLE.mode == SECTION5_RIPPLE.mode == "paper"
    assert [(o.source, o.multiple, o.q) for o in LISTING_A1_RIPPLE.oscillators] == [
        ("motor", 2.0, 1e3),
        ("motor", 4.0, 1e3),
    ]
    assert [(o.source, o.multiple, o.q) for o in LISTING_A2_RIPPLE.oscillators] == [
        ("motor", 2.0, 1e3),
        ("output", 1.0, 5e-2),
    ]
    assert SECTION5_RIPPLE.order == 6
    for cfg in (LISTING_A1_RIPPLE, LISTING_A2_RIPPLE, SECTION5_RIPPLE):
        assert cfg.r == 1.0 and cfg.p0 == 1.0
    kf = RippleKalman(LISTING_A1_RIPPLE, T, GEAR)
    np.testing.assert_array_equal(kf.Q, 1e3 * np.eye(4))
    np.testing.assert_array_equal(kf.C, [1.0, 0.0, 1.0, 0.0])


def test_paper_filter_refuses_a_recommended_config() -> None:
    with pytest.raises(ValueError, match="paper"):
        RippleKalman(RippleFilterConfig(), T, GEAR)
