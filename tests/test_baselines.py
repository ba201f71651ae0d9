"""Tests of the baseline torque filters (firmware/baselines.py): the listing's Butterworth
low-pass (revision note "01/11/95 hdt Butterworth filter for torque") and a notch bank
tracking 2x/4x motor velocity."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from hdhil.firmware.baselines import ButterworthLowPass, TrackingNotchBank, butterworth_lowpass

Ts = 1e-3
FS = 1.0 / Ts


# ------------------------------------------------------------------ Butterworth
@pytest.mark.parametrize(("cutoff", "order"), [(10.0, 2), (20.0, 2), (50.0, 4), (5.0, 1)])
def test_butterworth_coefficients_are_scipys(cutoff: float, order: int) -> None:
    lp = ButterworthLowPass(cutoff, Ts, order)
    b, a = signal.butter(order, cutoff, fs=FS)
    np.testing.assert_array_equal(lp.b, b)
    np.testing.assert_array_equal(lp.a, a)
    # -3 dB at the cut-off, unity at DC
    _, h = signal.freqz(lp.b, lp.a, worN=[0.0, cutoff], fs=FS)
    assert abs(h[0]) == pytest.approx(1.0, abs=1e-12)
    assert abs(h[1]) == pytest.approx(1 / math.sqrt(2), rel=1e-9)


@pytest.mark.parametrize("order", range(1, 9))
def test_butterworth_design_is_scipys_for_every_order(order: int) -> None:
    for cutoff in (0.5, 10.0, 100.0, 333.0, 499.0):
        b, a = butterworth_lowpass(order, cutoff, FS)
        b_ref, a_ref = signal.butter(order, cutoff, fs=FS)
        np.testing.assert_allclose(b, b_ref, rtol=1e-12, atol=0)
        np.testing.assert_allclose(a, a_ref, rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_butterworth_step_and_filter_agree_and_share_the_state(order: int) -> None:
    x = np.random.default_rng(1).normal(1.0, 0.5, 3000)
    a, b = ButterworthLowPass(10.0, Ts, order), ButterworthLowPass(10.0, Ts, order)
    by_step = np.array([a.step(v) for v in x.tolist()])
    by_array = np.concatenate([b.filter(x[:1234]), b.filter(x[1234:])])  # resumes
    np.testing.assert_allclose(by_step, by_array, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.state, b.state, rtol=0, atol=1e-12)
    np.testing.assert_allclose(by_array, signal.lfilter(a.b, a.a, x), rtol=0, atol=1e-12)
    # and mixed: step after filter continues where filter stopped
    assert a.step(0.3) == pytest.approx(b.step(0.3), abs=1e-12)


def test_butterworth_reset_and_steady_start() -> None:
    lp = ButterworthLowPass(10.0, Ts)
    first = lp.step(1.0)
    lp.step(2.0)
    lp.reset()
    assert lp.step(1.0) == first
    lp.reset(5.0)  # steady state of a constant 5 Nm: no start-up transient
    np.testing.assert_allclose(lp.filter(np.full(100, 5.0)), 5.0, rtol=1e-12)


@pytest.mark.parametrize("order", [1, 2, 3])
def test_butterworth_steady_start_is_lfilter_zis(order: int) -> None:
    lp = ButterworthLowPass(20.0, Ts, order)
    lp.reset(-3.0)
    zi = signal.lfilter_zi(lp.b, lp.a) * -3.0
    np.testing.assert_allclose(lp.state, zi, rtol=1e-9, atol=0)
    x = np.random.default_rng(2).normal(-3.0, 0.5, 500)
    np.testing.assert_allclose(
        lp.filter(x), signal.lfilter(lp.b, lp.a, x, zi=zi)[0], rtol=0, atol=1e-11
    )


def test_butterworth_removes_ripple_above_cutoff_and_lags() -> None:
    t = np.arange(4000) * Ts
    slow = np.sin(2 * np.pi * 1.0 * t)
    ripple = 0.5 * np.sin(2 * np.pi * 100.0 * t)
    y = ButterworthLowPass(10.0, Ts).filter(slow + ripple)[1000:]
    residual = abs(2 * np.mean(y * np.exp(-2j * np.pi * 100.0 * t[1000:])))
    assert residual < 0.02 * 0.5  # ripple at 100 Hz down by more than 34 dB ...
    lag = ButterworthLowPass(10.0, Ts).filter(slow)[1000:] - slow[1000:]
    assert np.max(np.abs(lag)) > 0.1  # ... at the price of lag at 1 Hz


def test_butterworth_rejects_bad_parameters() -> None:
    with pytest.raises(ValueError, match="cutoff_Hz"):
        ButterworthLowPass(500.0, Ts)
    with pytest.raises(ValueError, match="cutoff_Hz"):
        ButterworthLowPass(0.0, Ts)
    with pytest.raises(ValueError, match="order"):
        ButterworthLowPass(10.0, Ts, order=0)
    with pytest.raises(ValueError, match="sample_period_s"):
        ButterworthLowPass(10.0, -1.0)
    with pytest.raises(ValueError, match="1-D"):
        ButterworthLowPass(10.0, Ts).filter(np.zeros((2, 2)))


# ------------------------------------------------------------------ tracking notches
def test_notch_coefficients_are_the_standard_second_order_notch() -> None:
    bank = TrackingNotchBank((2.0, 4.0), Ts, bandwidth_Hz=2.0)
    speed = 100.0
    for (b, a), multiple in zip(bank.coefficients(speed), (2.0, 4.0), strict=True):
        f0 = multiple * speed / (2 * np.pi)
        b_ref, a_ref = signal.iirnotch(f0, f0 / 2.0, fs=FS)  # Q = f0 / bandwidth
        np.testing.assert_allclose(b, b_ref, rtol=1e-12)
        np.testing.assert_allclose(a, a_ref, rtol=1e-12)
        # zeros on the unit circle at w0, poles at radius rho = sqrt(2 beta - 1) inside
        w0T = multiple * speed * Ts
        np.testing.assert_allclose(b / b[0], [1.0, -2 * math.cos(w0T), 1.0], rtol=1e-12)
        np.testing.assert_allclose(np.angle(np.roots(b)), [w0T, -w0T], rtol=1e-6)
        np.testing.assert_allclose(np.abs(np.roots(a)), bank.pole_radius, rtol=1e-12)
        # unity gain at DC and Nyquist, zero at the centre
        _, h = signal.freqz(b, a, worN=[0.0, f0, FS / 2 - 1e-9], fs=FS)
        np.testing.assert_allclose(np.abs(h), [1.0, 0.0, 1.0], atol=1e-9)
    assert bank.coefficients(1.0) == [None, None]  # below min_speed_radps


@pytest.mark.parametrize("speed", [30.0, 156.0])
def test_notch_removes_a_tracked_sinusoid_and_passes_dc(speed: float) -> None:
    n = 6000
    theta = speed * np.arange(n) * Ts
    offset = 1.7  # true torque: DC
    ripple = 0.6 * np.sin(2 * theta + 0.4) + 0.25 * np.sin(4 * theta + 1.3)
    y = TrackingNotchBank((2.0, 4.0), Ts).filter(offset + ripple, np.full(n, speed))
    settled = y[3000:] - offset
    for multiple, amplitude in ((2, 0.6), (4, 0.25)):
        residual = abs(2 * np.mean(settled * np.exp(-1j * multiple * theta[3000:])))
        assert 20 * np.log10(amplitude / residual) >= 30.0
    assert np.mean(y[3000:]) == pytest.approx(offset, abs=1e-3)


def test_notch_bypassed_near_standstill_and_above_nyquist() -> None:
    x = np.random.default_rng(2).normal(size=500)
    slow = TrackingNotchBank((2.0, 4.0), Ts, min_speed_radps=5.0)
    np.testing.assert_array_equal(slow.filter(x, np.full(500, 4.9)), x)
    np.testing.assert_array_equal(slow.filter(x, np.full(500, -4.9)), x)
    np.testing.assert_array_equal(slow.filter(x, np.full(500, np.nan)), x)
    # 4x of 1000 rad/s is 4 rad/sample > pi: that notch is bypassed, the 2x one is not
    fast = TrackingNotchBank((2.0, 4.0), Ts)
    two_only = TrackingNotchBank((2.0,), Ts)
    np.testing.assert_array_equal(
        fast.filter(x, np.full(500, 1000.0)), two_only.filter(x, np.full(500, 1000.0))
    )


def test_notch_step_and_filter_agree_exactly() -> None:
    rng = np.random.default_rng(3)
    n = 3000
    x = rng.normal(size=n)
    vel = 80.0 * np.sin(np.arange(n) / 300.0) + rng.normal(0.0, 1.0, n)  # incl. slow, reversing
    vel[100] = np.nan
    a, b = TrackingNotchBank((2.0, 4.0), Ts), TrackingNotchBank((2.0, 4.0), Ts)
    by_step = np.array([a.step(xi, vi) for xi, vi in zip(x.tolist(), vel.tolist(), strict=True)])
    by_array = np.concatenate([b.filter(x[:777], vel[:777]), b.filter(x[777:], vel[777:])])
    np.testing.assert_array_equal(by_step, by_array)
    assert a.step(0.5, 60.0) == b.step(0.5, 60.0)
    a.reset()
    fresh = TrackingNotchBank((2.0, 4.0), Ts)
    assert a.step(1.0, 60.0) == fresh.step(1.0, 60.0)


def test_notch_rejects_bad_parameters() -> None:
    with pytest.raises(ValueError, match="multiples"):
        TrackingNotchBank((), Ts)
    with pytest.raises(ValueError, match="multiples"):
        TrackingNotchBank((2.0, -4.0), Ts)
    with pytest.raises(ValueError, match="bandwidth_Hz"):
        TrackingNotchBank((2.0,), Ts, bandwidth_Hz=0.0)
    with pytest.raises(ValueError, match="min_speed_radps"):
        TrackingNotchBank((2.0,), Ts, min_speed_radps=-1.0)
    with pytest.raises(ValueError, match="equal length"):
        TrackingNotchBank((2.0,), Ts).filter(np.zeros(3), np.zeros(4))
