"""Tests of the ported interrupt body (firmware/isr.py; [Taghirad97], listing A.1 ``c_int10``),
and of its [Vertechy] torque-control stage."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hdhil.core.converter import Converter
from hdhil.firmware.config import (
    ControlConfig,
    DesiredTorqueConfig,
    FirmwareConfig,
    Law,
    PlausibilityConfig,
    ReferenceConfig,
    Wave,
    paper_config,
)
from hdhil.firmware.isr import AdcSample, InterruptHandler, IsrOutput, TorqueFilterChain
from hdhil.firmware.lqg import LqgController
from hdhil.firmware.lqg_design import (
    ControlLaw,
    Feedforward,
    JointParams,
    LqgWeights,
    design_lq,
    design_lqg,
)
from hdhil.firmware.ripple import HarmonicKalman, RippleKalman
from hdhil.firmware.stages import Differentiator

LSB = 10.0 / 2048
PAPER = paper_config(FirmwareConfig())  # listing A.1
RECOMMENDED = FirmwareConfig()  # the default
#: The stage order with the plausibility stage off: the random velocities below change by
#: more per sample than a joint can, which that stage would replace.
UNCHECKED = PlausibilityConfig(enabled=False)


def _samples(n: int, seed: int = 0) -> list[AdcSample]:
    rng = np.random.default_rng(seed)
    return [
        AdcSample(
            torque=int(rng.integers(-300, 300)),
            tacho=int(200 + 20 * math.sin(k / 5)),
            current=int(rng.integers(-100, 100)),
            encoder=17 * k,
        )
        for k in range(n)
    ]


def test_default_is_the_recommended_filter_and_paper_is_listing_a1() -> None:
    assert isinstance(TorqueFilterChain(RECOMMENDED).kalman, HarmonicKalman)
    assert isinstance(TorqueFilterChain(PAPER).kalman, RippleKalman)


def test_paper_chain_follows_the_listing_order() -> None:
    cfg = dataclasses.replace(PAPER, plausibility=UNCHECKED)
    chain = TorqueFilterChain(cfg)
    diff = Differentiator(cfg.diff_tau_s, cfg.sample_period_s)
    kalman = RippleKalman(cfg.ripple, cfg.sample_period_s, cfg.gear_ratio)
    rng = np.random.default_rng(5)
    previous_prediction = 0.0  # listing: float T_ripple = 0.0;
    for k in range(50):
        T_meas, vel = float(rng.normal(1.0, 0.3)), float(rng.normal(120.0, 10.0))
        acc, T_exp, dT, T_f, ripple = chain.step(T_meas, vel, 12345 * k)  # encoder ignored
        assert acc == diff.step(vel)
        assert T_exp == pytest.approx(1.725e-2 * acc / 100.0)
        assert dT == pytest.approx(T_meas - T_exp)
        assert ripple == previous_prediction  # Torque_f = T_meas - T_ripple (previous)
        assert T_f == T_meas - previous_prediction
        nxt = kalman.step(dT, vel)  # T_ripple = Kalman(Delta_T, vel, sample_period)
        assert chain.T_ripple == nxt
        previous_prediction = nxt


def test_recommended_chain_subtracts_the_ripple_at_the_measured_angle() -> None:
    cfg = dataclasses.replace(RECOMMENDED, plausibility=UNCHECKED)
    chain = TorqueFilterChain(cfg)
    kalman = HarmonicKalman(cfg.ripple, cfg.gear_ratio)
    diff = Differentiator(cfg.diff_tau_s, cfg.sample_period_s)
    rad_per_count = 2 * math.pi / cfg.calibration.encoder_counts_per_rev
    rng = np.random.default_rng(6)
    count = 65000  # wraps within the run
    for _ in range(300):
        T_meas, vel = float(rng.normal(1.0, 0.3)), float(rng.normal(120.0, 10.0))
        count += 150
        acc, T_exp, dT, T_f, ripple = chain.step(T_meas, vel, count % 65536)
        assert acc == diff.step(vel)
        assert dT == T_meas - T_exp
        angle = count * rad_per_count  # the unwrapped count, started at the first count
        assert chain.angle == pytest.approx(angle, rel=1e-12)
        assert ripple == kalman.step(dT, vel, chain.angle)
        assert T_f == T_meas - ripple


def test_recommended_chain_needs_the_encoder_unless_phase_from_tacho() -> None:
    chain = TorqueFilterChain(RECOMMENDED)
    with pytest.raises(ValueError, match="encoder"):
        chain.step(1.0, 100.0)
    ripple = dataclasses.replace(RECOMMENDED.ripple, phase_source="tacho")
    tacho = TorqueFilterChain(dataclasses.replace(RECOMMENDED, ripple=ripple))
    tacho.step(1.0, 100.0)
    tacho.step(1.0, 100.0)
    assert tacho.angle == pytest.approx(100.0 * 1e-3)  # trapezoidal integral of the tacho


@pytest.mark.parametrize("cfg", [PAPER, RECOMMENDED], ids=["paper", "recommended"])
def test_chain_first_filtered_torque_is_the_measurement(cfg: FirmwareConfig) -> None:
    chain = TorqueFilterChain(cfg)
    _, _, _, T_f, ripple = chain.step(3.25, 100.0, 0)
    assert T_f == 3.25 and ripple == 0.0
    chain.step(3.0, 100.0, 25)
    chain.reset()
    assert chain.step(3.25, 100.0, 0)[3] == 3.25


@pytest.mark.parametrize("cfg", [PAPER, RECOMMENDED], ids=["paper", "recommended"])
def test_handler_outputs_are_consistent_with_the_stages(cfg: FirmwareConfig) -> None:
    cfg = dataclasses.replace(
        cfg,
        reference=ReferenceConfig(wave=Wave.SINE, bias_V=1.0, amplitude_V=2.0, frequency_Hz=5.0),
    )
    isr = InterruptHandler(cfg)
    previous_ripple = 0.0
    for k, s in enumerate(_samples(120)):
        out = isr(s)
        assert out.samplecount == k
        assert out.T_meas == pytest.approx(s.torque * LSB * 6.6)
        assert out.velocity == pytest.approx(s.tacho * LSB * 56.2565)
        assert out.current == pytest.approx(s.current * LSB)
        assert out.T_expected == pytest.approx(1.725e-2 * out.acceleration / 100.0)
        assert out.delta_T == pytest.approx(out.T_meas - out.T_expected)
        assert out.T_filtered == out.T_meas - out.ripple
        if cfg.ripple.mode == "paper":
            assert out.ripple == previous_ripple  # predicted at the previous interrupt
            previous_ripple = isr.chain.T_ripple
        ref = 1.0 + 2.0 * math.sin(2 * math.pi * 5.0 * k * 1e-3)
        assert out.reference_V == pytest.approx(ref)
        assert out.dac_counts == round(ref / LSB)
        assert out.encoder == (17 * k) & 0xFFFF
    assert isr.samplecount == 120


@pytest.mark.parametrize("cfg", [PAPER, RECOMMENDED], ids=["paper", "recommended"])
def test_handler_is_the_chain_on_calibrated_signals(cfg: FirmwareConfig) -> None:
    # the offline path (chain over calibrated values) gives the online numbers exactly
    isr = InterruptHandler(cfg)
    chain = TorqueFilterChain(cfg)
    for s in _samples(60, seed=1):
        out = isr(s)
        assert chain.step(out.T_meas, out.velocity, s.encoder) == (
            out.acceleration,
            out.T_expected,
            out.delta_T,
            out.T_filtered,
            out.ripple,
        )


def test_handler_returns_one_reused_output_object() -> None:
    isr = InterruptHandler(FirmwareConfig())
    a = isr(AdcSample(100, 200, 0, 0))
    kept = dataclasses.replace(a)
    b = isr(AdcSample(-100, 200, 0, 1))
    assert a is b
    assert isinstance(b, IsrOutput)
    assert kept.samplecount == 0 and b.samplecount == 1
    assert kept.T_meas != b.T_meas


def test_done_flag_and_run_until_stopped() -> None:
    isr = InterruptHandler(FirmwareConfig(num_samples=3))
    flags = []
    for s in _samples(4):
        flags.append(isr.done)
        isr(s)
    flags.append(isr.done)
    assert flags == [False, False, False, True, True]
    forever = InterruptHandler(FirmwareConfig(num_samples=0))
    for s in _samples(10):
        forever(s)
    assert not forever.done


def test_encoder_is_masked_to_16_bits() -> None:
    isr = InterruptHandler(FirmwareConfig())
    assert isr(AdcSample(0, 0, 0, 70000)).encoder == 70000 - 65536
    assert isr(AdcSample(0, 0, 0, -1)).encoder == 0xFFFF


def test_dac_saturates_a_large_reference() -> None:
    cfg = FirmwareConfig(
        reference=ReferenceConfig(wave=Wave.STEP, bias_V=-12.0, amplitude_V=24.0, step_time_s=0.002)
    )
    isr = InterruptHandler(cfg)
    codes = [isr(s).dac_counts for s in _samples(4)]
    assert codes == [-2048, -2048, 2047, 2047]
    assert isr.startup_dac_counts == -2048  # main(): write_dac0(Vbias)
    assert isr.shutdown_dac_counts == 0  # main(): write_dac0(0.0)


def test_dac_code_follows_the_reference_and_a_new_converter() -> None:
    cfg = FirmwareConfig(
        reference=ReferenceConfig(wave=Wave.STEP, bias_V=1.0, amplitude_V=0.5, step_time_s=0.003)
    )
    isr = InterruptHandler(cfg)
    codes = [isr(s).dac_counts for s in _samples(5)]
    assert codes == [205, 205, 205, 307, 307]  # round(V / LSB) before and after the step
    isr.cfg = dataclasses.replace(cfg, dac=Converter(bits=16, full_scale_V=10.0))
    assert isr(_samples(1)[0]).dac_counts == round(1.5 / (10.0 / 32768))  # same volts


def test_handler_uses_configured_converters_and_calibration() -> None:
    cfg = FirmwareConfig(adc=Converter(bits=16, full_scale_V=5.0))
    isr = InterruptHandler(cfg)
    out = isr(AdcSample(torque=16384, tacho=-8192, current=0, encoder=0))
    assert out.T_meas == pytest.approx(2.5 * 6.6)
    assert out.velocity == pytest.approx(-1.25 * 56.2565)


def test_reset_starts_over() -> None:
    isr = InterruptHandler(FirmwareConfig())
    samples = _samples(30, seed=2)
    first = [dataclasses.astuple(isr(s)) for s in samples]
    isr.reset()
    assert isr.samplecount == 0
    again = [dataclasses.astuple(isr(s)) for s in samples]
    assert again == first


def _free_motion_at_constant_speed(cfg: FirmwareConfig, n: int) -> tuple[list, list]:
    """Free motion at 156 rad/s with a meshing ripple on the bridge: the drive's counts
    (torque, tacho, encoder) into the handler; returns (T_meas, T_filtered)."""
    isr = InterruptHandler(cfg)
    adc = cfg.adc
    vel = 156.0
    tacho = adc.to_counts(vel / 56.2565)
    vel_q = adc.to_volts(tacho) * 56.2565
    meas, filt = [], []
    for k in range(n):
        theta = vel_q * k * 1e-3
        ripple_Nm = 0.8 * math.sin(2 * theta) + 0.3 * math.sin(4 * theta + 0.5)
        encoder = math.floor(theta * 8000 / (2 * math.pi)) % 65536
        out = isr(AdcSample(adc.to_counts(ripple_Nm / 6.6), tacho, 0, encoder))
        meas.append(out.T_meas)
        filt.append(out.T_filtered)
    return meas, filt


@pytest.mark.parametrize("cfg", [PAPER, RECOMMENDED], ids=["paper", "recommended"])
def test_handler_cancels_ripple_from_adc_counts(cfg: FirmwareConfig) -> None:
    # [Taghirad97], Fig. 9: the filtered torque keeps far less ripple than the measured one
    meas, filt = _free_motion_at_constant_speed(cfg, 3000)
    rms_meas = float(np.sqrt(np.mean(np.square(meas[-1000:]))))
    rms_filt = float(np.sqrt(np.mean(np.square(filt[-1000:]))))
    assert rms_meas > 0.5
    assert rms_filt < 0.1 * rms_meas


# ----------------------------------------------------------------------------- torque control
# [Vertechy] (LQG joint-torque control) in the handler: firmware/isr.py TorqueControl.

CONTROL_FIELDS = (
    "tau_s_hat",
    "dtau_s_hat",
    "tau_lgd_hat",
    "tau_sD",
    "dtau_sD",
    "e_hat",
    "tau_m_request",
    "tau_m_cmd",
)


def _control_cfg(**control) -> FirmwareConfig:
    control.setdefault("law", Law.JTF1)
    return FirmwareConfig(control=ControlConfig(**control))


def test_default_config_runs_no_control_law() -> None:
    cfg = FirmwareConfig()
    assert cfg.control.law is Law.NONE and not cfg.control.active
    isr = InterruptHandler(cfg)
    assert isr.control is None
    for s in _samples(20):
        out = isr(s)
        assert all(getattr(out, name) == 0.0 for name in CONTROL_FIELDS)
        assert out.saturated is False


@pytest.mark.parametrize("law", [Law.JTF1, Law.JTF1_FF, Law.JTF2, Law.JTF3])
@pytest.mark.parametrize("delay, predict", [(1, True), (1, False), (0, False)])
def test_handler_commands_through_the_designs_gains(law: Law, delay: int, predict: bool) -> None:
    """The handler's command is LqgController's on -T_meas (seed sign), with the design
    computed from the configuration, and the DAC code is that torque over Nm per volt."""
    weights = LqgWeights(q1=800.0, V=3e4)
    cfg = _control_cfg(
        law=law,
        weights=weights,
        feedforward=Feedforward.EXACT,
        delay_samples=delay,
        predict=predict,
        torque_per_volt=200.0,  # +/-2000 Nm at the DAC: random torques never saturate
        torque_limit_Nm=2000.0,
        desired=DesiredTorqueConfig(amplitude_Nm=8.0, frequency_Hz=3.0, bias_Nm=1.0),
    )
    isr = InterruptHandler(cfg)
    assert isr.control is not None
    design = isr.control.design
    assert design.gains == design_lq(JointParams(), weights, feedforward=Feedforward.EXACT)
    assert design.weights == weights
    ref = LqgController(
        design_lqg(weights=weights, feedforward=Feedforward.EXACT),
        law.control_law,
        delay_samples=delay,
        predict=predict,
    )
    lsb_Nm = LSB * 200.0
    for k, s in enumerate(_samples(200, seed=3)):
        out = isr(s)
        t = k * 1e-3
        T_D = 1.0 + 8.0 * math.sin(2 * math.pi * 3.0 * t)
        dT_D = 8.0 * 2 * math.pi * 3.0 * math.cos(2 * math.pi * 3.0 * t)
        assert out.tau_sD == pytest.approx(T_D, abs=1e-12)
        assert out.dtau_sD == pytest.approx(dT_D, rel=1e-4)
        request = ref.step(-out.T_meas, -out.tau_sD, -out.dtau_sD)
        assert out.tau_m_request == pytest.approx(request, rel=1e-12, abs=1e-9)
        assert out.dac_counts == round(request / 200.0 / LSB)
        assert out.tau_m_cmd == pytest.approx(out.dac_counts * lsb_Nm)
        ref.set_applied(out.dac_counts * lsb_Nm)
        assert (out.tau_s_hat, out.dtau_s_hat) == (-ref.tau_s_hat, -ref.tau_s_dot_hat)
        assert out.tau_lgd_hat == ref.tau_lgd_hat
        assert out.e_hat == out.tau_s_hat - out.tau_sD
        assert not out.saturated


def test_gains_follow_the_configuration_not_constants() -> None:
    a = InterruptHandler(_control_cfg()).control
    b = InterruptHandler(_control_cfg(weights=LqgWeights(q1=2000.0))).control
    c = InterruptHandler(_control_cfg(joint=JointParams(Jl=1.4))).control
    assert a is not None and b is not None and c is not None
    assert a.design.gains.k1 == pytest.approx(-18.25, abs=0.01)  # [Vertechy] §VI: -18.3
    assert b.design.gains.k1 < a.design.gains.k1 < 0
    assert c.design.gains.k3 != a.design.gains.k3
    assert a.controller.law is ControlLaw.JTF1


def test_sign_mapping_product_convention() -> None:
    """Product sign: T positive when the motor drives the load.  Torque below the desired
    torque -> the motor pushes forward; the estimates come back in the product sign."""
    cfg = _control_cfg(
        law=Law.JTF3,
        desired=DesiredTorqueConfig(wave=Wave.NONE, bias_Nm=10.0),
        torque_per_volt=20.0,
        torque_limit_Nm=150.0,
    )
    isr = InterruptHandler(cfg)
    counts_3Nm = round(3.0 / 6.6 / LSB)  # a steady 3 Nm (< 10 Nm desired)
    for _ in range(1500):  # the observer settles (its poles, and the law's loop through it)
        out = isr(AdcSample(counts_3Nm, 0, 0, 0))
    assert out.tau_s_hat == pytest.approx(out.T_meas, abs=1e-6) and out.T_meas > 2.9
    assert out.tau_sD == 10.0 and out.e_hat == pytest.approx(out.T_meas - 10.0, abs=1e-3)
    assert out.tau_m_request > 0 and out.dac_counts > 0
    # the seed's own law in its own sign: tau_s = -3, tau_sD = -10, JTF3 (k3 = 0, k4 = 1)
    g = isr.control.design.gains_for(ControlLaw.JTF3)
    seed_eq4 = -(g.k1 * (-out.T_meas - -10.0) + g.k4 * -10.0)
    assert out.tau_m_request == pytest.approx(seed_eq4, rel=1e-3)
    # the disturbance estimate keeps the seed's sign: at rest Eq. 2 gives
    # (k/J) tau_s = (k/Jl) tau_lgd - (k/Jm) tau_m  ->  tau_lgd = Jl (tau_s/J + tau_m/Jm)
    p = JointParams()
    tau_lgd = p.Jl * (-out.T_meas / p.J + out.tau_m_cmd / p.Jm)
    assert out.tau_lgd_hat == pytest.approx(tau_lgd, abs=1e-6)


def test_command_saturates_at_the_torque_limit_and_reports_it() -> None:
    cfg = _control_cfg(
        desired=DesiredTorqueConfig(wave=Wave.NONE, bias_Nm=30.0),
        torque_per_volt=20.0,
        torque_limit_Nm=25.0,
    )
    isr = InterruptHandler(cfg)
    ref = LqgController(design_lqg(), ControlLaw.JTF1)
    for _ in range(50):
        out = isr(AdcSample(0, 0, 0, 0))
        request = ref.step(-out.T_meas, -30.0)
        assert out.tau_m_request == pytest.approx(request)
        assert out.saturated and abs(out.tau_m_request) > 25.0
        assert out.dac_counts == round(25.0 / 20.0 / LSB)  # 256 counts = 1.25 V
        assert out.tau_m_cmd == pytest.approx(256 * LSB * 20.0) and out.tau_m_cmd <= 25.0
        ref.set_applied(out.tau_m_cmd)  # the observer is told the clipped torque
    assert isr.control.saturations == 50
    isr.reset()
    assert isr.control.saturations == 0 and isr.control.controller.estimate == (0.0, 0.0, 0.0)


def test_command_saturates_at_the_dac_range() -> None:
    # 1 Nm/V: the +/-10 V DAC only reaches +/-10 Nm, below the 150 Nm torque limit
    cfg = _control_cfg(
        desired=DesiredTorqueConfig(wave=Wave.NONE, bias_Nm=-30.0),
        torque_per_volt=1.0,
        torque_limit_Nm=150.0,
    )
    isr = InterruptHandler(cfg)
    out = isr(AdcSample(0, 0, 0, 0))
    assert out.tau_m_request < -10.0
    assert out.dac_counts == -2048 and out.tau_m_cmd == -10.0 and out.saturated
    assert isr.control.controller._last_cmd == -10.0  # set_applied got the DAC's torque


def test_inverted_actuator_calibration_flips_the_dac_code_only() -> None:
    plain = InterruptHandler(_control_cfg(torque_per_volt=20.0, torque_limit_Nm=150.0))
    inverted = InterruptHandler(_control_cfg(torque_per_volt=-20.0, torque_limit_Nm=150.0))
    for s in _samples(30, seed=4):
        a, b = dataclasses.replace(plain(s)), inverted(s)
        assert b.dac_counts == -a.dac_counts
        assert b.tau_m_cmd == pytest.approx(a.tau_m_cmd)


def test_feedback_from_the_ripple_filtered_torque() -> None:
    cfg = dataclasses.replace(
        _control_cfg(feedback="T_filtered"), ripple=dataclasses.replace(RECOMMENDED.ripple)
    )
    isr = InterruptHandler(cfg)
    ref = LqgController(design_lqg(), ControlLaw.JTF1)
    for s in _samples(80, seed=5):
        out = isr(s)
        assert out.T_filtered != out.T_meas or out.ripple == 0.0
        request = ref.step(-out.T_filtered, -out.tau_sD, -out.dtau_sD)
        ref.set_applied(out.tau_m_cmd)
        assert out.tau_m_request == pytest.approx(request)


def test_startup_command_is_zero_torque_with_a_law() -> None:
    cfg = dataclasses.replace(_control_cfg(), reference=ReferenceConfig(wave=Wave.NONE, bias_V=2.0))
    assert InterruptHandler(cfg).startup_dac_counts == 0
    assert InterruptHandler(FirmwareConfig(reference=cfg.reference)).startup_dac_counts == 410


def test_ripple_filter_keeps_running_under_control() -> None:
    """With a law the ripple filter's output stays what it is without one."""
    plain = InterruptHandler(FirmwareConfig())
    controlled = InterruptHandler(_control_cfg())
    for s in _samples(100, seed=6):
        a, b = dataclasses.replace(plain(s)), controlled(s)
        assert (b.T_meas, b.T_filtered, b.ripple) == (a.T_meas, a.T_filtered, a.ripple)
