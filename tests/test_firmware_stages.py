"""Tests of the pure firmware stages (firmware/stages/) and their configuration
(firmware/config/), ported from [Taghirad97], listing A.1 ``c_int10``."""

from __future__ import annotations

import dataclasses
import math

import pytest

from hdhil.core.converter import Converter
from hdhil.core.dataconf import ConfigError, from_dict, to_dict
from hdhil.firmware.config import (
    LISTING_A1_RIPPLE,
    LISTING_A2_RIPPLE,
    RECOMMENDED_RIPPLE,
    RECOMMENDED_SECTION5_RIPPLE,
    SECTION5_RIPPLE,
    Calibration,
    FirmwareConfig,
    Oscillator,
    ReferenceConfig,
    RippleFilterConfig,
    Wave,
    paper_config,
    recommended_config,
)
from hdhil.firmware.interrupt import AdcSample
from hdhil.firmware.stages import (
    AdcSource,
    Differentiator,
    EncoderUnwrap,
    ReferenceGenerator,
    VelocityIntegrator,
    adc_read,
    calibrate,
    dac_write,
    expected_torque,
    filtered_torque,
    torque_error,
)

LSB = 10.0 / 2048  # 12-bit, +/-10 V


# --------------------------------------------------------------------- differentiator
def test_differentiator_coefficients_equal_the_listing_at_1ms() -> None:
    # [Taghirad97], listing A.1, Diff_filter: nd = {181.818181818182, -181.818181818182},
    # dd = {1.00000000000000, -0.81818181818182}.
    d = Differentiator(tau_s=0.005, sample_period_s=1e-3)
    expected_nd = (181.818181818182, -181.818181818182)
    expected_dd = (1.0, -0.81818181818182)
    for got, want in zip(d.nd + d.dd, expected_nd + expected_dd, strict=True):
        assert got == pytest.approx(want, rel=1e-9)


def test_differentiator_coefficients_follow_tustin_for_other_periods() -> None:
    # Tustin of s/(tau s + 1): nd0 = 2/(2 tau + T), dd1 = (T - 2 tau)/(T + 2 tau).
    # tau = 4 ms, T = 1 ms: nd0 = 2/0.009 = 222.2..., dd1 = -0.007/0.009 = -0.7777...
    d = Differentiator(tau_s=0.004, sample_period_s=1e-3)
    assert d.nd[0] == pytest.approx(2 / 0.009, rel=1e-12)
    assert d.nd[1] == pytest.approx(-2 / 0.009, rel=1e-12)
    assert d.dd[1] == pytest.approx(-7 / 9, rel=1e-12)


def test_differentiator_step_response() -> None:
    # Unit step from the zero state: a(0) = nd0, then a(k) = -dd1 * a(k-1) (v constant);
    # its area sum(a) * T is the size of the step, 1 rad/s.
    d = Differentiator(0.005, 1e-3)
    out = [d.step(1.0) for _ in range(400)]
    assert out[0] == pytest.approx(181.818181818182, rel=1e-12)
    for k in range(1, 10):
        assert out[k] == pytest.approx(181.818181818182 * (9 / 11) ** k, rel=1e-9)
    assert sum(out) * 1e-3 == pytest.approx(1.0, rel=1e-9)


def test_differentiator_ramp_converges_to_slope() -> None:
    a0 = 37.5  # rad/s^2
    T = 1e-3
    d = Differentiator(0.005, T)
    out = [d.step(a0 * k * T) for k in range(300)]
    assert out[-1] == pytest.approx(a0, rel=1e-9)
    assert abs(out[20] - a0) > 1e-3 * a0  # and it did take a while (time constant 5 ms)


def test_differentiator_reset_and_state() -> None:
    d = Differentiator()
    first = d.step(2.0)
    d.step(3.0)
    d.reset()
    assert d.step(2.0) == first


def test_differentiator_coefficients_can_be_set() -> None:
    d = Differentiator()
    d.nd = (2.0, -1.0)
    d.dd = (1.0, -0.5)
    assert (d.nd, d.dd) == ((2.0, -1.0), (1.0, -0.5))
    assert d.step(1.0) == 2.0  # 2 * 1 - 1 * 0 + 0.5 * 0
    assert d.step(1.0) == 2.0 - 1.0 + 0.5 * 2.0
    with pytest.raises(ValueError, match="normalised"):
        d.dd = (2.0, -0.5)


def test_differentiator_skips_a_non_finite_velocity() -> None:
    d, clean = Differentiator(), Differentiator()
    d.step(1.0)
    clean.step(1.0)
    assert math.isnan(d.step(float("nan")))
    assert math.isnan(d.step(float("inf")))
    assert d.step(2.0) == clean.step(2.0)  # the state was left alone


def test_differentiator_rejects_bad_parameters() -> None:
    with pytest.raises(ValueError, match="tau_s"):
        Differentiator(tau_s=0.0)
    with pytest.raises(ValueError, match="sample_period_s"):
        Differentiator(sample_period_s=float("nan"))


# --------------------------------------------------------------------- converters
def test_adc_read_counts_to_volts() -> None:
    adc = Converter()
    torque_V, tacho_V, current_V = adc_read(1024, -2048, 1, adc)
    assert torque_V == pytest.approx(5.0)
    assert tacho_V == pytest.approx(-10.0)
    assert current_V == pytest.approx(LSB)
    # out-of-range codes are clipped to the converter's range
    assert adc_read(5000, -5000, 2047, adc) == pytest.approx((2047 * LSB, -10.0, 2047 * LSB))


def test_dac_write_quantizes_and_saturates() -> None:
    dac = Converter()
    assert dac_write(10.5, dac) == 2047
    assert dac_write(-12.0, dac) == -2048
    assert dac_write(LSB, dac) == 1
    assert dac_write(-LSB, dac) == -1
    assert dac_write(0.4 * LSB, dac) == 0
    assert dac_write(0.6 * LSB, dac) == 1
    assert dac_write(2.5, dac) == 512
    assert dac_write(float("nan"), dac) == 0


def test_dac_adc_round_trip_within_half_lsb() -> None:
    conv = Converter()
    for v in (-9.99, -3.3, -0.001, 0.0, 0.7, 4.2, 9.99):
        back = adc_read(dac_write(v, conv), 0, 0, conv)[0]
        assert abs(back - v) <= LSB / 2 + 1e-12


# --------------------------------------------------------------------- calibration
def test_calibrate_with_seed_gains_from_counts() -> None:
    cal = Calibration()
    torque_V, tacho_V, current_V = adc_read(1024, 512, -256, Converter())
    T_meas, vel, current = calibrate(torque_V, tacho_V, current_V, cal)
    assert T_meas == pytest.approx(5.0 * 6.6)  # 1024 counts = 5 V; Table 1: 6.60 Nm/V
    assert vel == pytest.approx(2.5 * 56.2565)  # 512 counts = 2.5 V; listing volt2radps
    assert current == pytest.approx(-1.25)  # volt2amp = 1 keeps the listing's volts


def test_calibrate_subtracts_torque_offset_before_scaling() -> None:
    cal = Calibration(volt2Nm=6.6, torque_offset_V=0.1, volt2amp=2.0)
    T_meas, vel, current = calibrate(1.1, -1.0, 0.5, cal)
    assert T_meas == pytest.approx(6.6)
    assert vel == pytest.approx(-56.2565)
    assert current == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("adc", "cal"),
    [
        (Converter(), Calibration()),
        (Converter(bits=16, full_scale_V=5.0),
         Calibration(volt2Nm=-3.3, volt2radps=12.5, volt2amp=2.5, torque_offset_V=0.37)),
    ],
)  # fmt: skip
def test_adc_source_is_adc_read_then_calibrate_bit_for_bit(
    adc: Converter, cal: Calibration
) -> None:
    source = AdcSource(adc, cal)
    lo, hi = adc.code_min, adc.code_max
    codes = [*range(lo - 3, lo + 40), *range(-700, 700, 7), *range(hi - 40, hi + 4), 10**6]
    for i, code in enumerate(codes):
        tacho, current = codes[-1 - i], codes[(7 * i) % len(codes)]
        volts = adc_read(code, tacho, current, adc)
        want = (*calibrate(*volts, cal), i, volts[0], volts[1])
        got = source(AdcSample(code, tacho, current, i))
        assert [x.hex() if isinstance(x, float) else x for x in got] == [
            x.hex() if isinstance(x, float) else x for x in want
        ]


# --------------------------------------------------------------------- torque algebra
def test_expected_torque_error_and_filtered_torque() -> None:
    # T_mod = J_load * acc / Gain = 1.725e-2 * 1000 / 100 = 0.1725 Nm
    assert expected_torque(1000.0, 1.725e-2, 100.0) == pytest.approx(0.1725)
    assert torque_error(2.0, 0.1725) == pytest.approx(1.8275)
    assert filtered_torque(2.0, 0.5) == pytest.approx(1.5)
    assert filtered_torque(2.0, -0.5) == pytest.approx(2.5)


# --------------------------------------------------------------------- reference
def _ref(**kw: float | Wave) -> ReferenceGenerator:
    return ReferenceGenerator(ReferenceConfig(**kw), 1e-3)  # type: ignore[arg-type]


def test_reference_none_is_bias_only() -> None:
    g = _ref(wave=Wave.NONE, bias_V=1.5, amplitude_V=3.0)
    assert [g.value(k) for k in (0, 1, 250, 12345)] == [1.5] * 4


def test_reference_sine() -> None:
    g = _ref(wave=Wave.SINE, bias_V=0.5, amplitude_V=2.0, frequency_Hz=2.0)
    # f = 2 Hz: a quarter period is 125 samples
    assert g.value(0) == pytest.approx(0.5)
    assert g.value(125) == pytest.approx(2.5)
    assert g.value(250) == pytest.approx(0.5, abs=1e-12)
    assert g.value(375) == pytest.approx(-1.5)
    assert g.value(50) == pytest.approx(0.5 + 2.0 * math.sin(2 * math.pi * 2.0 * 0.05))


def test_reference_square_with_duty() -> None:
    g = _ref(wave=Wave.SQUARE, bias_V=1.0, amplitude_V=2.0, frequency_Hz=1.0, duty=0.25)
    assert g.value(0) == pytest.approx(3.0)
    assert g.value(249) == pytest.approx(3.0)
    assert g.value(251) == pytest.approx(-1.0)
    assert g.value(999) == pytest.approx(-1.0)
    assert g.value(1000) == pytest.approx(3.0)  # next period
    assert g.value(1100) == pytest.approx(3.0)


def test_reference_triangle() -> None:
    g = _ref(wave=Wave.TRIANGLE, bias_V=0.0, amplitude_V=4.0, frequency_Hz=1.0)
    # tri(p): 0 at p=0, +1 at 1/4, 0 at 1/2, -1 at 3/4; p = k/1000
    expected = {0: 0.0, 100: 1.6, 250: 4.0, 400: 1.6, 500: 0.0, 750: -4.0, 900: -1.6, 1250: 4.0}
    for k, v in expected.items():
        assert g.value(k) == pytest.approx(v, abs=1e-9), k


def test_reference_sawtooth() -> None:
    g = _ref(wave=Wave.SAWTOOTH, bias_V=1.0, amplitude_V=1.0, frequency_Hz=4.0)
    # f = 4 Hz: period 250 samples; 2p - 1 from -1 to 1
    assert g.value(0) == pytest.approx(0.0)
    assert g.value(125) == pytest.approx(1.0)
    assert g.value(200) == pytest.approx(1.6)
    assert g.value(250) == pytest.approx(0.0)


def test_reference_step() -> None:
    g = _ref(wave=Wave.STEP, bias_V=-1.0, amplitude_V=3.0, step_time_s=0.1)
    assert g.value(0) == -1.0
    assert g.value(99) == -1.0
    assert g.value(100) == pytest.approx(2.0)
    assert g.value(5000) == pytest.approx(2.0)
    g0 = _ref(wave=Wave.STEP, amplitude_V=3.0, step_time_s=0.0)
    assert g0.value(0) == pytest.approx(3.0)


# --------------------------------------------------------------------- config
@pytest.mark.parametrize(
    ("build", "field_name"),
    [
        (lambda: ReferenceConfig(frequency_Hz=0.0), "frequency_Hz"),
        (lambda: ReferenceConfig(duty=1.5), "duty"),
        (lambda: ReferenceConfig(step_time_s=-1.0), "step_time_s"),
        (lambda: ReferenceConfig(bias_V=float("inf")), "bias_V"),
        (lambda: Calibration(volt2Nm=0.0), "volt2Nm"),
        (lambda: Calibration(volt2radps=float("nan")), "volt2radps"),
        (lambda: Oscillator(source="load"), "source"),  # type: ignore[arg-type]
        (lambda: Oscillator(multiple=-2.0), "multiple"),
        (lambda: Oscillator(q=-1.0), "q"),
        (lambda: Oscillator(q=float("inf")), "q"),
        (lambda: RippleFilterConfig(oscillators=()), "oscillators"),
        (lambda: RippleFilterConfig(r=0.0), "r"),
        (lambda: RippleFilterConfig(p0=-1.0), "p0"),
        (lambda: RippleFilterConfig(mode="kalman"), "mode"),  # type: ignore[arg-type]
        (lambda: RippleFilterConfig(phase_source="gps"), "phase_source"),  # type: ignore[arg-type]
        (lambda: RippleFilterConfig(residual_q=-1.0), "residual_q"),
        (lambda: RippleFilterConfig(standstill_radps=float("nan")), "standstill_radps"),
        (lambda: Calibration(encoder_counts_per_rev=0), "encoder_counts_per_rev"),
        (lambda: Calibration(encoder_counts_per_rev=8000.5), "encoder_counts_per_rev"),
        (lambda: FirmwareConfig(sample_period_s=0.0), "sample_period_s"),
        (lambda: FirmwareConfig(sample_period_s=2.0), "sample_period_s"),
        (lambda: FirmwareConfig(num_samples=-1), "num_samples"),
        (lambda: FirmwareConfig(J_load=0.0), "J_load"),
        (lambda: FirmwareConfig(gear_ratio=-100.0), "gear_ratio"),
        (lambda: FirmwareConfig(diff_tau_s=0.0), "diff_tau_s"),
    ],
)
def test_config_rejects_out_of_range_values(build, field_name: str) -> None:
    with pytest.raises(ValueError, match=field_name):
        build()


def test_config_defaults_carry_the_seed_values() -> None:
    cfg = FirmwareConfig()
    gen = ReferenceGenerator(cfg.reference, cfg.sample_period_s)
    assert gen.value(123) == 0.0  # wavetype = 0: bias only, Nbias = 0
    d = Differentiator(cfg.diff_tau_s, cfg.sample_period_s)
    assert d.nd[0] == pytest.approx(181.818181818182, rel=1e-9)
    assert expected_torque(100.0, cfg.J_load, cfg.gear_ratio) == pytest.approx(1.725e-2)
    assert cfg.calibration.encoder_counts_per_rev == 8000  # the emulator's default
    # the default filter is the recommended one, on the paper's harmonics
    assert cfg.ripple == RECOMMENDED_RIPPLE
    assert cfg.ripple.mode == "recommended" and cfg.ripple.phase_source == "encoder"
    assert [(o.source, o.multiple, o.q) for o in cfg.ripple.oscillators] == [
        ("motor", 2.0, 3e-6),
        ("motor", 4.0, 3e-6),
    ]
    assert cfg.ripple.r == 5e-4 and cfg.ripple.p0 == 1.0
    assert cfg.ripple.residual_q == 1e-3 and cfg.ripple.standstill_radps == 2.0
    assert cfg.ripple.order == 4 and cfg.ripple.n_states == 5
    # the paper filter with the same harmonics is exactly listing A.1
    paper = paper_config(cfg)
    assert paper.ripple == LISTING_A1_RIPPLE
    assert [(o.source, o.multiple, o.q) for o in paper.ripple.oscillators] == [
        ("motor", 2.0, 1e3),
        ("motor", 4.0, 1e3),
    ]
    assert paper.ripple.r == 1.0 and paper.ripple.p0 == 1.0 and paper.ripple.n_states == 4
    assert dataclasses.replace(paper, ripple=cfg.ripple) == cfg  # nothing else changed


def test_mode_defaults_fill_unset_tuning() -> None:
    paper = RippleFilterConfig(
        oscillators=(Oscillator("motor", 2.0), Oscillator("output", 1.0)), mode="paper"
    )
    assert paper == LISTING_A2_RIPPLE  # q: 1e3 motor, 5e-2 output; R = 1
    rec = RippleFilterConfig(oscillators=(Oscillator("motor", 2.0), Oscillator("motor", 4.0, 7e-6)))
    assert [o.q for o in rec.oscillators] == [3e-6, 7e-6]  # an explicit q is kept
    assert RippleFilterConfig(r=2.0).r == 2.0
    # q 1e-4 for an output harmonic; p0 25 Nm^2 with one ([Taghirad97] §5: up to 5 Nm)
    assert [o.q for o in RECOMMENDED_SECTION5_RIPPLE.oscillators] == [3e-6, 3e-6, 1e-4]
    assert RECOMMENDED_SECTION5_RIPPLE.p0 == 25.0 and RECOMMENDED_RIPPLE.p0 == 1.0
    assert SECTION5_RIPPLE.p0 == 1.0  # listing: P = I
    assert RippleFilterConfig(oscillators=(Oscillator("output", 1.0),), p0=4.0).p0 == 4.0


def test_paper_and_recommended_config_switch_modes_keeping_the_harmonics() -> None:
    s5 = FirmwareConfig(ripple=RECOMMENDED_SECTION5_RIPPLE)
    assert paper_config(s5).ripple == SECTION5_RIPPLE
    assert recommended_config(paper_config(s5)) == s5
    tuned = FirmwareConfig(ripple=dataclasses.replace(LISTING_A1_RIPPLE, r=3.0))
    assert paper_config(tuned) is tuned  # already paper: kept as it is
    assert recommended_config(FirmwareConfig()) == FirmwareConfig()


def test_from_dict_builds_nested_config() -> None:
    cfg = from_dict(
        FirmwareConfig,
        {
            "sample_period_s": 0.002,
            "num_samples": 5000,
            "reference": {"wave": "step", "amplitude_V": 1.0, "step_time_s": 0.25},
            "calibration": {"torque_offset_V": 0.02, "encoder_counts_per_rev": 4096},
            "ripple": {
                "mode": "paper",
                "oscillators": [
                    {"source": "motor", "multiple": 2},
                    {"source": "output", "multiple": 1.0, "q": 5e-2},
                ],
                "r": 2.0,
            },
            "dac": {"bits": 16},
        },
    )
    assert cfg.reference.wave is Wave.STEP
    assert cfg.ripple.mode == "paper"
    assert cfg.ripple.oscillators == LISTING_A2_RIPPLE.oscillators
    assert isinstance(cfg.ripple.oscillators, tuple)
    assert cfg.dac.code_max == 32767
    assert cfg.adc.code_max == 2047
    assert cfg.calibration.volt2Nm == 6.6
    assert cfg.calibration.encoder_counts_per_rev == 4096
    # the plain-data form goes back to the same config
    assert from_dict(FirmwareConfig, to_dict(cfg)) == cfg
    assert from_dict(FirmwareConfig, to_dict(FirmwareConfig())) == FirmwareConfig()


def test_from_dict_recommended_mode_keys() -> None:
    cfg = from_dict(
        FirmwareConfig,
        {
            "ripple": {
                "mode": "recommended",
                "phase_source": "tacho",
                "residual_q": 5e-3,
                "standstill_radps": 1.0,
                "oscillators": [{"source": "motor", "multiple": 2}, {"multiple": 4, "q": 1e-6}],
            }
        },
    )
    assert cfg.ripple.phase_source == "tacho"
    assert (cfg.ripple.residual_q, cfg.ripple.standstill_radps) == (5e-3, 1.0)
    assert [o.q for o in cfg.ripple.oscillators] == [3e-6, 1e-6]


def test_from_dict_accepts_wave_by_number() -> None:
    cfg = from_dict(ReferenceConfig, {"wave": 2})
    assert cfg.wave is Wave.SQUARE


def test_from_dict_unknown_key_and_bad_values() -> None:
    with pytest.raises(ConfigError, match=r"reference\.amplitude"):
        from_dict(FirmwareConfig, {"reference": {"amplitude": 1.0}})
    with pytest.raises(ConfigError, match="duty"):
        from_dict(FirmwareConfig, {"reference": {"duty": 2.0}})
    with pytest.raises(ConfigError, match="wave"):
        from_dict(FirmwareConfig, {"reference": {"wave": "cosine"}})
    with pytest.raises(ConfigError, match="source"):
        from_dict(FirmwareConfig, {"ripple": {"oscillators": [{"source": "load"}]}})
    with pytest.raises(ConfigError, match=r"ripple\.mode"):
        from_dict(FirmwareConfig, {"ripple": {"mode": "papr"}})
    with pytest.raises(ConfigError, match=r"ripple\.phase_source"):
        from_dict(FirmwareConfig, {"ripple": {"phase_source": "hall"}})


# --------------------------------------------------------------------- encoder unwrap
def test_encoder_unwrap_follows_counts_and_starts_at_the_first_count() -> None:
    u = EncoderUnwrap()
    assert u.step(1234) == 1234
    assert u.step(1300) == 1300
    assert u.step(1200) == 1200  # backwards
    assert u.step(1200 + 65536) == 1200  # only the low 16 bits count


@pytest.mark.parametrize("step_counts", [1, 199, 8000, 32767, -1, -199, -8000, -32767])
def test_encoder_unwrap_across_wraps_in_both_directions(step_counts: int) -> None:
    u = EncoderUnwrap()
    start = 64536 if step_counts > 0 else 1000  # 1000 counts before the wrap
    true = start
    for _ in range(2000):  # wraps 65535 -> 0 (forwards) or 0 -> 65535 (backwards)
        assert u.step(true % 65536) == true
        true += step_counts
    assert true // 65536 != start // 65536  # it did cross the wrap


def test_encoder_unwrap_crossing_the_wrap_exactly() -> None:
    u = EncoderUnwrap()
    assert [u.step(c) for c in (65534, 65535, 0, 1, 0, 65535, 65534)] == [
        65534,
        65535,
        65536,
        65537,
        65536,
        65535,
        65534,
    ]
    u.reset()
    assert u.step(5) == 5


def test_encoder_unwrap_aliases_beyond_half_the_counter() -> None:
    # the documented limit: 32768 counts or more per sample cannot be told from backwards
    u = EncoderUnwrap()
    u.step(0)
    assert u.step(32768) == -32768


# --------------------------------------------------------------------- tacho integrator
def test_velocity_integrator_is_trapezoidal_and_skips_non_finite() -> None:
    vi = VelocityIntegrator(1e-3)
    assert vi.step(10.0) == 0.0
    assert vi.step(20.0) == pytest.approx(0.015)
    assert vi.step(float("nan")) == pytest.approx(0.015)
    assert vi.step(20.0) == pytest.approx(0.035)
    # a ramp is integrated exactly: angle = a t^2 / 2
    vi.reset()
    for k in range(1001):
        angle = vi.step(50.0 * k * 1e-3)
    assert angle == pytest.approx(25.0, rel=1e-12)
    with pytest.raises(ValueError, match="sample_period_s"):
        VelocityIntegrator(0.0)


@pytest.mark.slow
def test_tustin_differentiator_coefficients_are_scipys_bit_for_bit():
    """The differentiator's Tustin design without scipy.signal gives the very floats
    ``scipy.signal.bilinear`` gives (the golden runs depend on them), over a spread of
    time constants and sample periods, the listing's 5 ms / 1 ms included."""
    import random

    from scipy.signal import bilinear

    from hdhil.firmware.stages import tustin_differentiator

    rng = random.Random(7)
    cases = [(0.005, 1e-3), (0.002, 1e-3), (0.01, 5e-4)]
    cases += [(10 ** rng.uniform(-4, -1), 10 ** rng.uniform(-5, -2)) for _ in range(2000)]
    for tau, Ts in cases:
        b, a = bilinear([1.0, 0.0], [tau, 1.0], fs=1.0 / Ts)
        expected = ((float(b[0] / a[0]), float(b[1] / a[0])), (1.0, float(a[1] / a[0])))
        assert tustin_differentiator(tau, Ts) == expected, (tau, Ts)
