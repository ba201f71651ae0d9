"""The strain-gauge torque sensor (hostsim.bridge; [Taghirad97] §2, Eqs. 1-4)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.hostsim.bridge import (
    GAUGE_COUNT,
    BridgeConfig,
    GaugeHysteresis,
    StrainGaugeBridge,
    bridge_output_V,
)
from hdhil.hostsim.plant import RippleConfig

BETAS = np.linspace(0.0, 2 * math.pi, 256, endpoint=False)


def only(index: int, value: float) -> tuple[float, ...]:
    out = [0.0] * GAUGE_COUNT
    out[index] = value
    return tuple(out)


def harmonics(bridge: StrainGaugeBridge, torque: float = 0.0) -> np.ndarray:
    """|FFT| of the amplifier output over one turn of beta, in volts per harmonic of beta."""
    v = np.array([bridge.amplified_V(torque, b) for b in BETAS])
    return np.abs(np.fft.rfft(v)) / len(BETAS) * 2


# --------------------------------------------------------------------------- Eqs. 1-4


def test_eq4_for_hand_computed_strains() -> None:
    """E_out = K/4 (e1 + e3 - e2 - e4) E_sup ([Taghirad97] Eq. 4), four gauges."""
    strains = [100e-6, -50e-6, 80e-6, -30e-6]
    # 2.0 / 4 * (100 + 80 + 50 + 30) e-6 * 10 V = 1.3 mV
    assert bridge_output_V(strains, 2.0, 10.0) == pytest.approx(1.3e-3, rel=1e-12)
    # pure torsion, Eq. 1 without the wave terms: E_out = K eps_t E_sup
    eps_t = 1e-4
    assert bridge_output_V([eps_t, -eps_t, eps_t, -eps_t], 2.1, 5.0) == pytest.approx(
        2.1 * eps_t * 5.0, rel=1e-12
    )
    # eight gauges, two in series per arm: the same strains twice give the same output
    assert bridge_output_V(strains * 2, 2.0, 10.0) == pytest.approx(1.3e-3, rel=1e-12)
    # a gauge factor per gauge weighs each strain
    assert bridge_output_V([1e-4, 0, 0, 0], [3.0, 1, 1, 1], 4.0) == pytest.approx(3e-4)
    with pytest.raises(ValueError, match="4 or 8"):
        bridge_output_V([1e-6] * 6, 2.0, 10.0)


def test_rosette_differences_follow_eqs_2_and_3() -> None:
    """e1 - e2 = 2 e_t + Psi_0 sin 2b (Eq. 2); e3 - e4 = 2 e_t + Psi_0 sin(2b - pi) (Eq. 3)."""
    bridge = StrainGaugeBridge(BridgeConfig.perfect())
    psi0 = 2 * bridge.cfg.wave_shear_strain
    for beta in (0.0, 0.3, 1.9, 4.0):
        e = bridge.strains(12.0, beta)
        eps_t = bridge.strain_per_Nm * 12.0
        assert e[0] - e[1] == pytest.approx(2 * eps_t + psi0 * math.sin(2 * beta), abs=1e-15)
        assert e[2] - e[3] == pytest.approx(
            2 * eps_t + psi0 * math.sin(2 * beta - math.pi), abs=1e-15
        )
        # the elliptical strain itself is large: cancellation, not absence
        assert np.max(np.abs(e - bridge.signs * eps_t)) > 0.5 * bridge.cfg.wave_normal_strain


def test_perfect_bridge_has_no_modulation_and_the_nominal_gain() -> None:
    """Zero positioning errors: the 2 beta terms cancel exactly (Eq. 3) and 6.6 Nm/V of
    Table 1 is K eps_t E_sup x 1000 with K = 2 and E_sup = 10 V (Eq. 4, §2)."""
    bridge = StrainGaugeBridge(BridgeConfig.perfect(volt2Nm=6.6))
    assert bridge.strain_per_Nm == pytest.approx(1 / (6.6 * 1000 * 2.0 * 10.0), rel=1e-12)
    for torque in (-40.0, 0.0, 6.6, 17.0):
        for beta in BETAS[::17]:
            assert bridge.amplified_V(torque, beta) == pytest.approx(torque / 6.6, abs=1e-12)
    assert bridge.modulation_amplitude_Nm < 1e-12
    assert bridge.volt2Nm == pytest.approx(6.6, rel=1e-12)
    assert np.max(harmonics(bridge)) < 1e-12


def test_default_bridge_true_gain_and_residual() -> None:
    """Default: true gain 6.62 Nm/V; residual 2 beta modulation 0.05-0.1 Nm, well below
    the 0.6 Nm meshing ripple."""
    bridge = StrainGaugeBridge(BridgeConfig())
    assert bridge.volt2Nm == pytest.approx(6.62, rel=1e-12)
    # the small-signal slope of the eight-gauge computation is the analytic gain
    for beta in (0.2, 2.5):
        slope = (bridge.amplified_V(1.0, beta) - bridge.amplified_V(-1.0, beta)) / 2.0
        assert 1 / slope == pytest.approx(bridge.volt2Nm, rel=1e-9)
    assert 0.05 < bridge.modulation_amplitude_Nm < 0.1
    assert bridge.modulation_amplitude_Nm < 0.2 * RippleConfig().amp2_Nm


def test_closed_form_equals_the_gauge_by_gauge_bridge() -> None:
    bridge = StrainGaugeBridge(BridgeConfig())
    rng = np.random.default_rng(1)
    for torque, beta in zip(rng.uniform(-40, 40, 50), rng.uniform(-50, 50, 50), strict=True):
        closed = torque / bridge.volt2Nm + bridge.modulation_V(beta)
        assert bridge.amplified_V(torque, beta) == pytest.approx(closed, rel=1e-12, abs=1e-14)
        assert bridge.modulation_Nm(beta) == pytest.approx(
            bridge.modulation_V(beta) * 6.62, rel=1e-12
        )


@pytest.mark.parametrize(
    "errors",
    [
        {"position_error_deg": (0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0)},  # rosette B
        {"position_error_deg": only(0, 0.5)},  # one gauge
        {"sensitivity_error": only(3, 0.01)},  # one gauge's sensitivity (radial/angular)
    ],
)
def test_positioning_errors_modulate_at_exactly_twice_the_wave_generator_angle(
    errors: dict,
) -> None:
    """Only the 2nd harmonic of beta appears; it scales linearly with the error."""
    full = StrainGaugeBridge(BridgeConfig.perfect(**errors))
    spectrum = harmonics(full, torque=5.0)
    assert spectrum[2] > 1e-4  # volts at the amplifier: > 0.66 mNm
    others = np.delete(spectrum, [0, 2])
    assert np.max(others) < 1e-9 * spectrum[2]
    assert spectrum[0] / 2 == pytest.approx(5.0 / full.volt2Nm, rel=1e-9)  # the DC is torque
    assert spectrum[2] * full.volt2Nm == pytest.approx(full.modulation_amplitude_Nm, rel=1e-9)
    halved = {k: tuple(v / 2 for v in vals) for k, vals in errors.items()}
    half = StrainGaugeBridge(BridgeConfig.perfect(**halved))
    assert full.modulation_amplitude_Nm / half.modulation_amplitude_Nm == pytest.approx(
        2.0, rel=2e-3
    )


def test_circumferential_error_of_a_rosette_pair_gives_the_analytic_amplitude() -> None:
    """Rosette B turned by e: residual = 2 Psi_s sin(2e) x 2 gauges / (8 eps_t per Nm)."""
    e_deg = 0.5
    bridge = StrainGaugeBridge(
        BridgeConfig.perfect(position_error_deg=(0.0, 0.0, e_deg, e_deg, 0.0, 0.0, 0.0, 0.0))
    )
    psi_s = bridge.cfg.wave_shear_strain
    # sum over R3, R4 of psi_s [sin(2b - pi - 2e) - sin(2b - pi)], amplitude 2 sin(e) each
    expected = 2 * 2 * psi_s * math.sin(math.radians(e_deg)) / (8 * bridge.strain_per_Nm)
    assert bridge.modulation_amplitude_Nm == pytest.approx(expected, rel=1e-9)


def test_config_from_toml_lists_and_validation() -> None:
    cfg = from_dict(BridgeConfig, {"position_error_deg": [0, 0, 1, 1, 0, 0, 0, 0]})
    assert cfg.position_error_deg == (0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0)
    for bad, match in (
        ({"position_error_deg": [0.0] * 3}, "8 values"),
        ({"sensitivity_error": [0.0] * 7 + [0.7]}, r"sensitivity_error\[7\]"),
        ({"position_error_deg": [0.0] * 7 + [float("nan")]}, r"position_error_deg\[7\]"),
        ({"gauge_factor": -2.0}, "gauge_factor"),
        ({"wave_shear_strain": -1e-6}, "wave_shear_strain"),
    ):
        with pytest.raises(ConfigError, match=match):
            from_dict(BridgeConfig, bad)


def test_gain_scales_with_the_configured_true_gain() -> None:
    a = StrainGaugeBridge(BridgeConfig())
    b = StrainGaugeBridge(replace(BridgeConfig(), volt2Nm=6.0))
    assert a.amplified_V(10.0, 0.0) - a.modulation_V(0.0) == pytest.approx(10.0 / 6.62)
    assert b.amplified_V(10.0, 0.0) - b.modulation_V(0.0) == pytest.approx(10.0 / 6.0)
    assert b.strain_per_Nm == pytest.approx(a.strain_per_Nm * 6.62 / 6.0)


def test_nonlinearity_is_the_configured_fraction_at_rated_torque() -> None:
    bridge = StrainGaugeBridge(BridgeConfig(nonlinearity=2e-3, rated_torque_Nm=40.0))
    assert bridge.nonlinearity_Nm(40.0) == pytest.approx(0.08)
    assert bridge.nonlinearity_Nm(-20.0) == pytest.approx(-0.01)


# --------------------------------------------------------------------------- hysteresis


def test_hysteresis_is_rate_independent_on_a_monotonic_path() -> None:
    one, many = GaugeHysteresis(0.05, 0.5), GaugeHysteresis(0.05, 0.5)
    one.update(-3.0)
    many.update(-3.0)
    one.update(1.2)
    for t in np.linspace(-3.0, 1.2, 97)[1:]:
        many.update(float(t))
    assert one.value_Nm == pytest.approx(many.value_Nm, rel=1e-12)


def test_hysteresis_loop_height_and_direction() -> None:
    h = GaugeHysteresis(0.05, 0.5)
    for t in (10.0, -10.0, 0.0):  # rising to 0 from far below
        h.update(t)
    assert h.value_Nm == pytest.approx(-0.05, rel=1e-6)  # reading low while loading up
    h.update(10.0)
    h.update(0.0)
    assert h.value_Nm == pytest.approx(+0.05, rel=1e-6)  # high while unloading
    h.update(0.1)  # a small reversal moves it only part of the way
    assert -0.05 < h.value_Nm < 0.05
    with pytest.raises(ValueError):
        GaugeHysteresis(0.05, 0.0)
