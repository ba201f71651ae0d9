"""Physics and sensors of the drive emulator (hostsim.plant)."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.hostsim.bridge import BridgeConfig
from hdhil.hostsim.plant import (
    AmplifierConfig,
    DriveTrainConfig,
    LoadTorqueConfig,
    Plant,
    PlantConfig,
    RippleConfig,
    SensorConfig,
    steady_state_motor_velocity,
    steady_state_volts,
)
from hdhil.rig.scenario import load_scenario

LSB = 10.0 / 2048  # 12-bit, +/-10 V (the converter spec shared with the firmware)
QUIET = SensorConfig(torque_noise_Nm=0.0, tacho_noise_radps=0.0, current_noise_A=0.0)
NO_RIPPLE = RippleConfig(amp2_Nm=0.0, amp4_Nm=0.0, misalignment_pp_Nm=0.0)
TRUE_GAIN = BridgeConfig().volt2Nm  # the emulated sensor's true Nm/V (6.62, not the seed's 6.6)


def make(
    *,
    amplifier: dict | None = None,
    drivetrain: dict | None = None,
    ripple: dict | None = None,
    sensors: dict | None = None,
    bridge: BridgeConfig | None = None,
    load: dict | None = None,
    substeps: int = 4,
    seed: int = 0,
) -> Plant:
    """A plant from the defaults with field overrides."""
    cfg = PlantConfig(
        amplifier=replace(AmplifierConfig(), **(amplifier or {})),
        drivetrain=replace(DriveTrainConfig(), **(drivetrain or {})),
        ripple=replace(RippleConfig(), **(ripple or {})),
        bridge=bridge or BridgeConfig(),
        sensors=replace(QUIET, **(sensors or {})),
        load=LoadTorqueConfig(**(load or {})),
        substeps=substeps,
    )
    return Plant(cfg, seed=seed)


def run(plant: Plant, volts: float, seconds: float, dt: float = 1e-3) -> None:
    for _ in range(round(seconds / dt)):
        plant.advance(volts, dt)


# --------------------------------------------------------------------------- config


def test_plant_config_builds_from_nested_dict() -> None:
    cfg = from_dict(
        PlantConfig,
        {"drivetrain": {"b_motor": 2.5}, "adc": {"bits": 10}, "substeps": 8},
    )
    assert cfg.drivetrain.b_motor == 2.5
    assert cfg.drivetrain.J_load == DriveTrainConfig().J_load
    assert cfg.adc.bits == 10
    assert cfg.substeps == 8


@pytest.mark.parametrize(
    ("cls", "field", "value"),
    [
        (DriveTrainConfig, "J_motor", 0.0),
        (DriveTrainConfig, "k_flex", -1.0),
        (DriveTrainConfig, "b_load", -0.1),
        (DriveTrainConfig, "friction_smoothing", 0.0),
        (AmplifierConfig, "current_lag_s", -1e-4),
        (AmplifierConfig, "current_limit_A", float("nan")),
        (RippleConfig, "amp2_Nm", -0.5),
        (BridgeConfig, "volt2Nm", 0.0),
        (BridgeConfig, "hysteresis_span_Nm", 0.0),
        (BridgeConfig, "position_error_deg", (0.5,) * 7),
        (BridgeConfig, "sensitivity_error", (0.0,) * 7 + (-0.9,)),
        (LoadTorqueConfig, "frequency_Hz", 0.0),
        (LoadTorqueConfig, "duty", 1.5),
        (LoadTorqueConfig, "kind", "ramp"),
        (SensorConfig, "encoder_counts_per_rev", 0),
        (PlantConfig, "substeps", 0),
    ],
)
def test_config_rejects_out_of_range_naming_the_field(cls: type, field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        cls(**{field: value})


def test_from_dict_reports_bad_value_as_config_error() -> None:
    with pytest.raises(ConfigError, match="J_load"):
        from_dict(PlantConfig, {"drivetrain": {"J_load": -2.0}})


def test_advance_rejects_bad_arguments() -> None:
    plant = make()
    with pytest.raises(ValueError):
        plant.advance(1.0, 0.0)
    with pytest.raises(ValueError):
        plant.advance(float("nan"), 1e-3)


# --------------------------------------------------------------------------- mechanics


@pytest.mark.parametrize(
    ("volts", "drivetrain", "amplifier"),
    [
        (0.654296875, {}, {}),
        (-0.8, {}, {}),
        (1.5, {"b_motor": 0.6, "coulomb_motor": 0.3, "b_load": 0.2, "coulomb_load": 0.4}, {}),
        (0.9, {"gear_ratio": 50.0, "J_motor": 0.1}, {"gain_A_per_V": 2.0, "current_lag_s": 0.0}),
    ],
)
def test_steady_state_velocity_matches_torque_balance(
    volts: float, drivetrain: dict, amplifier: dict
) -> None:
    plant = make(drivetrain=drivetrain, amplifier=amplifier)
    d, a = plant.cfg.drivetrain, plant.cfg.amplifier
    tau_const = (d.J_motor + d.J_load) / (d.b_motor + d.b_load)
    run(plant, volts, 12 * tau_const)
    # at output: N Kt gain V = (b_m + b_l) w + (C_m + C_l) sign(w)
    drive = d.gear_ratio * a.torque_constant_Nm_per_A * a.gain_A_per_V * volts
    coulomb = math.copysign(d.coulomb_motor + d.coulomb_load, drive)
    w_out = (drive - coulomb) / (d.b_motor + d.b_load)
    truth = plant.truth()
    assert truth.omega_output_radps == pytest.approx(w_out, rel=1e-3)
    assert truth.omega_motor_radps == pytest.approx(d.gear_ratio * w_out, rel=1e-3)
    # in steady state the flexspline carries exactly the load friction
    assert truth.T_true_Nm == pytest.approx(
        d.b_load * w_out + math.copysign(d.coulomb_load, w_out), rel=1e-3
    )


def free_motion_velocity(times: list[float]) -> dict[float, float]:
    """Motor velocity of the free-motion scenario at the given times (ms grid)."""
    scn = load_scenario("free-motion")
    ref = scn.firmware.reference
    plant = Plant(scn.plant, seed=scn.seed)
    dac = scn.plant.dac
    step_V = dac.to_volts(dac.to_counts(ref.bias_V + ref.amplitude_V))
    bias_V = dac.to_volts(dac.to_counts(ref.bias_V))
    wanted = {round(t * 1000): t for t in times}
    out: dict[float, float] = {}
    for k in range(max(wanted) + 1):
        if k in wanted:
            out[wanted[k]] = plant.truth().omega_motor_radps
        t = k * 1e-3
        plant.advance(step_V if t >= ref.step_time_s - 1e-12 else bias_V, 1e-3)
    return out


def test_free_motion_step_reaches_156_rad_s_and_is_flat() -> None:
    """[Taghirad97] Fig. 8: velocity about 156 rad/s, almost flat from 0.8 s to 1.1 s."""
    window = [0.8 + 0.01 * j for j in range(31)]
    w = free_motion_velocity([0.05, 0.2, 1.0, *window])
    assert w[0.05] == 0.0
    assert 0.3 * 156 < w[0.2] < 0.95 * 156  # still accelerating
    assert w[1.0] == pytest.approx(156.0, abs=8.0)
    flat = [w[t] for t in window]
    assert (max(flat) - min(flat)) / w[1.0] < 0.02


def test_flexspline_oscillates_at_the_analytic_natural_frequency() -> None:
    """Friction, damping and ripple off: a load-torque step rings the flexspline mode.

    The period from the zero crossings of the twist torque must be
    2 pi / sqrt(k (1/J_m + 1/J_l)), and with no dissipation the discrete map must
    conserve energy: kinetic + elastic - work of the load torque.
    """
    plant = make(
        drivetrain={
            "b_motor": 0.0,
            "coulomb_motor": 0.0,
            "b_load": 0.0,
            "coulomb_load": 0.0,
            "c_flex": 0.0,
        },
        ripple={"amp2_Nm": 0.0, "amp4_Nm": 0.0},
    )
    d = plant.cfg.drivetrain
    tau = 0.5
    plant.set_load_torque(tau)
    mean = -tau * d.J_motor / (d.J_motor + d.J_load)  # quasi-static twist torque
    h = 2e-5
    ts, ys, energy = [], [], []
    for _ in range(5000):
        plant.advance(0.0, h)
        ts.append(plant.time)
        truth = plant.truth()
        ys.append(truth.T_true_Nm - mean)
        w_m = truth.omega_motor_radps / d.gear_ratio
        energy.append(
            0.5 * d.J_motor * w_m**2
            + 0.5 * d.J_load * truth.omega_output_radps**2
            + 0.5 * truth.T_true_Nm**2 / d.k_flex
            - tau * truth.theta_output_rad
        )
    crossings = [
        ts[j] - ys[j] * (ts[j + 1] - ts[j]) / (ys[j + 1] - ys[j])
        for j in range(len(ys) - 1)
        if ys[j] * ys[j + 1] < 0
    ]
    assert len(crossings) > 20
    period = 2 * (crossings[-1] - crossings[0]) / (len(crossings) - 1)
    omega_n = math.sqrt(d.k_flex * (1 / d.J_motor + 1 / d.J_load))
    assert 2 * math.pi / period == pytest.approx(omega_n, rel=0.02)
    assert max(energy) - min(energy) < 1e-9 * max(abs(e) for e in energy) + 1e-12


def test_seed_003_joint_rings_near_17_hz() -> None:
    """[Vertechy] §II: J_m 2.5, J_l 0.7 kg m², k 6.3 kNm/rad, c 11.8 -> "about 17 Hz"."""
    plant = make(
        drivetrain={
            "J_motor": 2.5,
            "J_load": 0.7,
            "k_flex": 6.3e3,
            "c_flex": 11.8,
            "coulomb_motor": 0.0,
            "coulomb_load": 0.0,
            "b_motor": 0.0,
            "b_load": 0.0,
        },
    )
    plant.set_load_torque(10.0)
    ys, ts = [], []
    for _ in range(4000):
        plant.advance(0.0, 1e-4)
        ts.append(plant.time)
        ys.append(plant.truth().T_true_Nm + 10.0 * 2.5 / 3.2)
    crossings = [ts[j] for j in range(len(ys) - 1) if ys[j] * ys[j + 1] < 0]
    damped_hz = (len(crossings) - 1) / 2 / (crossings[-1] - crossings[0])
    assert damped_hz == pytest.approx(17.0, abs=0.6)


def reference_rhs(cfg: PlantConfig, volts: float, tau_load: float):
    """[Vertechy] Eq. 1 + first-order amplifier, written out independently of the plant.

    State y = [q_m, q_l, dq_m, dq_l, i] (angles at the output), coulomb friction off.
    """
    d, a = cfg.drivetrain, cfg.amplifier
    i_cmd = max(-a.current_limit_A, min(a.current_limit_A, a.gain_A_per_V * volts))

    def rhs(_t: float, y: np.ndarray) -> list[float]:
        qm, ql, wm, wl, i = y
        if a.current_lag_s == 0.0:
            i = i_cmd
        tau_m = d.gear_ratio * a.torque_constant_Nm_per_A * i
        tau_d = -d.b_motor * wm
        spring = d.k_flex * (ql - qm) + d.c_flex * (wl - wm)
        dwm = (tau_m + tau_d + spring) / d.J_motor
        dwl = (tau_load - d.b_load * wl - spring) / d.J_load
        di = 0.0 if a.current_lag_s == 0.0 else (i_cmd - i) / a.current_lag_s
        return [wm, wl, dwm, dwl, di]

    return rhs, i_cmd


@pytest.mark.parametrize("lag", [4e-4, 0.0])
def test_exact_discretisation_matches_solve_ivp(lag: float) -> None:
    plant = make(
        drivetrain={"coulomb_motor": 0.0, "coulomb_load": 0.0},
        amplifier={"current_lag_s": lag},
        substeps=3,
    )
    cfg = plant.cfg
    d = cfg.drivetrain
    rng = np.random.default_rng(42)
    volts = rng.uniform(-1.5, 1.5, size=40)
    tau_load = 0.7
    plant.set_load_torque(tau_load)
    y = np.zeros(5)
    for v in volts:
        rhs, i_cmd = reference_rhs(cfg, float(v), tau_load)
        sol = solve_ivp(rhs, (0.0, 1e-3), y, method="DOP853", rtol=1e-12, atol=1e-14)
        y = sol.y[:, -1]
        if lag == 0.0:
            y[4] = i_cmd
        plant.advance(float(v), 1e-3)
        qm, ql, wm, wl, i = y
        t_true = d.k_flex * (qm - ql) + d.c_flex * (wm - wl)
        truth = plant.truth()
        assert truth.omega_motor_radps == pytest.approx(d.gear_ratio * wm, rel=1e-7, abs=1e-9)
        assert truth.omega_output_radps == pytest.approx(wl, rel=1e-7, abs=1e-9)
        assert truth.theta_output_rad == pytest.approx(ql, rel=1e-7, abs=1e-11)
        assert truth.T_true_Nm == pytest.approx(t_true, rel=1e-6, abs=1e-8)
        assert truth.current_A == pytest.approx(i, rel=1e-9, abs=1e-12)


def test_substeps_converge() -> None:
    """Coulomb friction is the only sub-step-dependent part: errors shrink with h."""

    def trajectory(substeps: int) -> np.ndarray:
        plant = make(substeps=substeps)
        out = []
        for k in range(1500):
            plant.advance(0.5 * math.sin(2 * math.pi * 2.0 * k * 1e-3), 1e-3)
            out.append(plant.truth().omega_output_radps)
        return np.array(out)

    ref = trajectory(64)
    errors = [float(np.max(np.abs(trajectory(n) - ref))) for n in (1, 4, 16)]
    scale = float(np.max(np.abs(ref)))
    assert scale > 0.1  # it moves, reverses, and crosses zero velocity
    assert errors[0] > errors[1] > errors[2]
    assert errors[1] < 0.01 * scale


def test_transmitted_torque_is_load_inertia_times_acceleration_plus_friction() -> None:
    """J_l ddq_l = T_true - load friction: what the [Taghirad97] firmware's T_mod assumes."""
    plant = make()
    d = plant.cfg.drivetrain
    run(plant, 0.654296875, 0.1)
    h = 1e-5
    for _ in range(3):
        run(plant, 0.654296875, 0.1)
        w0 = plant.truth().omega_output_radps
        plant.advance(0.654296875, h)
        truth = plant.truth()
        t_true, w1 = truth.T_true_Nm, truth.omega_output_radps
        plant.advance(0.654296875, h)
        alpha = (plant.truth().omega_output_radps - w0) / (2 * h)
        friction = d.b_load * w1 + d.coulomb_load * math.tanh(w1 / d.friction_smoothing)
        assert alpha > 0 and t_true > 0
        assert t_true == pytest.approx(d.J_load * alpha + friction, rel=2e-3)


def test_current_saturates_at_the_amplifier_limit() -> None:
    plant = make()
    run(plant, 50.0, 0.01)
    assert plant.truth().current_A == pytest.approx(plant.cfg.amplifier.current_limit_A, rel=1e-6)
    assert plant.truth().tau_m_Nm / plant.cfg.drivetrain.gear_ratio == pytest.approx(
        plant.cfg.amplifier.current_limit_A * plant.cfg.amplifier.torque_constant_Nm_per_A
    )
    run(plant, -50.0, 0.01)
    assert plant.truth().current_A == pytest.approx(-plant.cfg.amplifier.current_limit_A, rel=1e-6)


def test_time_accumulates_without_drift() -> None:
    plant = make()
    run(plant, 0.0, 10.0)
    assert plant.time == pytest.approx(10.0, abs=1e-12)


# --------------------------------------------------------------------------- sensors


def test_adc_counts_follow_the_calibrations_with_noise_off() -> None:
    plant = make(sensors={"torque_offset_V": 0.25})
    seen_torque = set()
    for k in range(600):
        plant.advance(0.0 if k < 50 else 0.654296875, 1e-3)
        torque, tacho, current, _ = plant.sample()
        # the sensor's TRUE gain (BridgeConfig.volt2Nm), not the seed's 6.6
        truth = plant.truth()
        expected = round(((truth.T_true_Nm + truth.T_ripple_Nm) / TRUE_GAIN + 0.25) / LSB)
        assert torque == expected
        assert tacho == round(truth.omega_motor_radps / 56.2565 / LSB)
        assert current == round(truth.current_A / 1.0 / LSB)
        seen_torque.add(torque)
    assert len(seen_torque) > 20  # the ripple really moves the torque channel


def test_adc_saturates_at_full_scale() -> None:
    plant = make(sensors={"volt2radps": 5.0, "torque_offset_V": 12.0})
    run(plant, 1.0, 1.0)  # > 100 rad/s at the motor: > 20 V out of the tacho
    torque, tacho, _, _ = plant.sample()
    assert (torque, tacho) == (2047, 2047)
    plant = make(sensors={"volt2radps": 5.0, "torque_offset_V": -12.0})
    run(plant, -1.0, 1.0)
    torque, tacho, _, _ = plant.sample()
    assert (torque, tacho) == (-2048, -2048)


@pytest.mark.parametrize("volts", [0.654296875, -0.4])
def test_encoder_wraps_and_counts_per_revolution(volts: float) -> None:
    plant = make()
    cpr = plant.cfg.sensors.encoder_counts_per_rev
    prev = plant.sample()[3]
    assert prev == 0
    total = 0
    raw = []
    for _ in range(1500):
        plant.advance(volts, 1e-3)
        enc = plant.sample()[3]
        assert 0 <= enc <= 65535
        step = (enc - prev) % 65536
        total += step if step < 32768 else step - 65536
        prev = enc
        raw.append(enc)
    revs = plant.truth().theta_motor_rad / (2 * math.pi)
    assert abs(revs) > 10
    assert total == math.floor(revs * cpr)
    assert total / revs == pytest.approx(cpr, abs=1 / abs(revs))
    # the 16-bit register really wrapped (several times), in the direction of motion
    wraps = sum(1 for a, b in itertools.pairwise(raw) if abs(b - a) > 32768)
    assert wraps == abs(total) // 65536 or wraps == abs(total) // 65536 + 1
    assert wraps >= 1


def test_encoder_wraps_below_zero_on_reverse_motion() -> None:
    plant = make()
    plant.advance(-0.3, 1e-3)
    plant.advance(-0.3, 1e-3)
    assert plant.truth().theta_motor_rad < 0
    assert plant.sample()[3] > 65000


def _peak(freqs: np.ndarray, spectrum: np.ndarray, lo: float, hi: float) -> tuple[float, float]:
    band = (freqs >= lo) & (freqs <= hi)
    j = int(np.argmax(np.where(band, spectrum, 0.0)))
    return float(freqs[j]), float(spectrum[j])


def test_torque_ripple_peaks_at_2x_4x_motor_and_1x_output_velocity() -> None:
    """[Taghirad97] Fig. 8 (312 and 624 rad/s at 156 rad/s) and §5 (output velocity).

    Measured through the noisy 12-bit torque channel at 1 kHz over a constant-speed
    window long enough to resolve the slow misalignment line.
    """
    plant = make(
        ripple={"misalignment_pp_Nm": 2.0, "misalignment_phase_rad": 0.7},
        sensors={"torque_noise_Nm": 0.02},
        seed=3,
    )
    run(plant, 0.654296875, 2.0)
    n = 1 << 15
    counts = np.empty(n)
    w_m = np.empty(n)
    for k in range(n):
        plant.advance(0.654296875, 1e-3)
        counts[k] = plant.sample()[0]
        w_m[k] = plant.truth().omega_motor_radps
    assert np.ptp(w_m) < 1e-3 * np.mean(w_m)  # constant speed
    torque = counts * LSB * TRUE_GAIN
    spectrum = np.abs(np.fft.rfft((torque - torque.mean()) * np.hanning(n)))
    freqs = 2 * np.pi * np.fft.rfftfreq(n, 1e-3)  # rad/s
    wm = float(np.mean(w_m))
    wo = wm / plant.cfg.drivetrain.gear_ratio
    bin_w = freqs[1]
    f2, a2 = _peak(freqs, spectrum, 0.5 * wm, 3 * wm)
    f4, a4 = _peak(freqs, spectrum, 3 * wm, 5 * wm)
    fo, ao = _peak(freqs, spectrum, 0.3 * wo, 1.7 * wo)
    assert f2 == pytest.approx(2 * wm, abs=1.5 * bin_w)
    assert f4 == pytest.approx(4 * wm, abs=1.5 * bin_w)
    assert fo == pytest.approx(wo, abs=1.5 * bin_w)
    # line heights in proportion to the amplitudes (0.6, 0.25, 1.0 Nm)
    assert a4 / a2 == pytest.approx(0.25 / 0.6, rel=0.15)
    assert ao / a2 == pytest.approx(1.0 / 0.6, rel=0.15)
    # and nothing comparable elsewhere (e.g. at 1x motor velocity)
    _, a1 = _peak(freqs, spectrum, 0.8 * wm, 1.2 * wm)
    assert a1 < 0.05 * a4


@pytest.mark.parametrize("perfect_bridge", [True, False])
def test_ripple_is_locked_to_motor_and_output_angles(perfect_bridge: bool) -> None:
    """Mesh ripple at 2x/4x motor angle, misalignment at the output angle; with a
    perfect bridge that is all of T_ripple, otherwise the gauge parts add to it."""
    plant = make(
        ripple={"misalignment_pp_Nm": 1.5, "misalignment_phase_rad": -0.3},
        bridge=BridgeConfig.perfect() if perfect_bridge else BridgeConfig(),
    )
    r = plant.cfg.ripple
    for _ in range(7):
        run(plant, 0.5, 0.0371)
        truth = plant.truth()  # angles wrapped as on the truth channel
        th, tho = truth.theta_motor_rad % (2 * math.pi), truth.theta_output_rad % (2 * math.pi)
        assert 0.0 <= th < 2 * math.pi and 0.0 <= tho < 2 * math.pi
        mesh = r.amp2_Nm * math.sin(2 * th + r.phase2_rad) + r.amp4_Nm * math.sin(
            4 * th + r.phase4_rad
        )
        mis = 0.75 * math.sin(tho + r.misalignment_phase_rad)
        parts = truth.ripple
        assert parts.mesh == pytest.approx(mesh, abs=1e-9)
        assert parts.misalignment == pytest.approx(mis, abs=1e-9)
        assert truth.T_ripple_Nm == pytest.approx(sum(parts), abs=1e-12)
        gauges = parts.modulation + parts.nonlinearity + parts.hysteresis
        if perfect_bridge:
            assert abs(gauges) < 1e-12  # exact cancellation up to rounding (Eq. 3)
            assert plant.truth().T_ripple_Nm == pytest.approx(mesh + mis, abs=1e-9)
        else:
            assert parts.modulation == pytest.approx(
                plant.bridge.modulation_Nm(plant.truth().beta_rad), abs=1e-12
            )
            assert 0.0 < abs(gauges) < 0.2


# --------------------------------------------------------------------------- noise


def _trace(seed: int, n: int = 3000) -> list[tuple[int, int, int, int]]:
    plant = make(
        sensors={"torque_noise_Nm": 0.5, "tacho_noise_radps": 1.0, "current_noise_A": 0.02},
        seed=seed,
    )
    out = []
    for k in range(n):
        plant.advance(0.0 if k < 50 else 0.654296875, 1e-3)
        out.append(plant.sample())
    return out


def test_same_seed_gives_identical_samples_and_different_seeds_differ() -> None:
    a, b, c = _trace(7), _trace(7), _trace(8)
    assert a == b
    for channel in range(3):
        assert sum(x[channel] != y[channel] for x, y in zip(a, c, strict=True)) > 100


def test_noise_has_the_configured_standard_deviation_in_physical_units() -> None:
    quiet = make(seed=5)
    noisy = make(sensors={"torque_noise_Nm": 1.0, "tacho_noise_radps": 2.0}, seed=5)
    diffs_t, diffs_v = [], []
    for _ in range(5000):
        quiet.advance(0.654296875, 1e-3)
        noisy.advance(0.654296875, 1e-3)
        q, n = quiet.sample(), noisy.sample()
        diffs_t.append((n[0] - q[0]) * LSB * TRUE_GAIN)
        diffs_v.append((n[1] - q[1]) * LSB * 56.2565)
    assert np.std(diffs_t) == pytest.approx(1.0, rel=0.05)
    assert np.std(diffs_v) == pytest.approx(2.0, rel=0.05)
    assert abs(np.mean(diffs_t)) < 0.05


# --------------------------------------------------------------------------- bridge in the plant


def test_bridge_modulation_is_locked_to_twice_the_relative_wave_generator_angle() -> None:
    """[Taghirad97] §2: the gauges' residual is at 2 beta, beta = theta_m + theta_out.

    Mesh ripple, gauge nonlinearity and hysteresis off: the torque reading minus
    T_true is then exactly a cos 2 beta + b sin 2 beta, with the bridge's amplitude; a
    fit at 2 theta_motor alone (what the seed cannot tell apart) leaves a residual.
    """
    bridge = BridgeConfig(nonlinearity=0.0, hysteresis_Nm=0.0)
    plant = make(ripple={"amp2_Nm": 0.0, "amp4_Nm": 0.0}, bridge=bridge)
    run(plant, 0.654296875, 1.0)
    betas, motor, extra = [], [], []
    for _ in range(3000):
        plant.advance(0.654296875, 1e-3)
        truth = plant.truth()
        betas.append(truth.beta_rad)
        motor.append(truth.theta_motor_rad)
        clean_V = (truth.T_true_Nm + truth.T_ripple_Nm) / plant.bridge.volt2Nm
        extra.append(clean_V * TRUE_GAIN - truth.T_true_Nm)
    betas_a, y = np.array(betas), np.array(extra)
    assert np.allclose(betas_a, np.array(motor) * 1.01 + 0.0, rtol=0, atol=1e-3 * betas_a.max())

    def fit(angle: np.ndarray) -> tuple[float, float]:
        basis = np.column_stack([np.cos(2 * angle), np.sin(2 * angle)])
        coef, *_ = np.linalg.lstsq(basis, y, rcond=None)
        return float(np.hypot(*coef)), float(np.max(np.abs(basis @ coef - y)))

    amp, worst = fit(betas_a)
    assert amp == pytest.approx(plant.bridge.modulation_amplitude_Nm, rel=1e-9)
    assert worst < 1e-9
    _, worst_motor = fit(np.array(motor))
    assert worst_motor > 0.5 * amp  # 2 theta_motor is not the sensor's angle


def test_hold_locked_is_the_calibration_rigs_static_state() -> None:
    plant = make()
    run(plant, 0.654296875, 0.3)
    d = plant.cfg.drivetrain
    theta_m = 123.4
    plant.hold_locked(theta_m, 25.0)
    truth = plant.truth()
    assert truth.T_true_Nm == pytest.approx(25.0, rel=1e-12)
    assert truth.theta_motor_rad == pytest.approx(theta_m, rel=1e-12)
    assert truth.theta_output_rad == pytest.approx(theta_m / d.gear_ratio - 25.0 / d.k_flex)
    assert truth.omega_motor_radps == truth.omega_output_radps == truth.current_A == 0.0
    assert truth.beta_rad == pytest.approx(theta_m + truth.theta_output_rad)
    t = plant.time
    torque, tacho, current, _ = plant.sample()
    assert plant.time == t and tacho == 0 and current == 0
    assert torque == round((25.0 + plant.truth().T_ripple_Nm) / TRUE_GAIN / LSB)
    with pytest.raises(ValueError):
        plant.hold_locked(float("nan"), 1.0)


def test_gauge_hysteresis_makes_the_reading_lag_the_load() -> None:
    """Loading then unloading to the same torque: the unloading reading is higher."""
    plant = make(bridge=BridgeConfig.perfect(hysteresis_Nm=0.05, hysteresis_span_Nm=0.5))
    plant.hold_locked(0.0, -10.0)
    plant.hold_locked(0.0, 5.0)  # rising
    rising = plant.truth().T_ripple_Nm
    plant.hold_locked(0.0, 10.0)
    plant.hold_locked(0.0, 5.0)  # falling
    truth = plant.truth()
    falling = truth.T_ripple_Nm
    mesh = truth.ripple.mesh
    assert rising - mesh == pytest.approx(-0.05, rel=1e-3)
    assert falling - mesh == pytest.approx(+0.05, rel=1e-3)


# --------------------------------------------------------------------------- load torque


@pytest.mark.parametrize(
    ("cfg", "expected"),
    [
        ({}, {0.0: 0.0, 1.0: 0.0}),
        ({"kind": "constant", "bias_Nm": -2.0, "start_s": 0.5}, {0.4: 0.0, 0.5: -2.0, 9.0: -2.0}),
        (
            {"kind": "square", "bias_Nm": 1.0, "amplitude_Nm": 3.0, "frequency_Hz": 2.0},
            {0.0: 4.0, 0.2: 4.0, 0.25: -2.0, 0.49: -2.0, 0.5: 4.0, 1.3: -2.0},
        ),
        (
            {"kind": "square", "amplitude_Nm": 1.0, "duty": 0.25, "start_s": 1.0},
            {0.9: 0.0, 1.0: 1.0, 1.2: 1.0, 1.3: -1.0},
        ),
        (
            {"kind": "sine", "bias_Nm": 0.5, "amplitude_Nm": 2.0, "frequency_Hz": 0.5},
            {0.0: 0.5, 0.5: 2.5, 1.5: -1.5},
        ),
        (
            {"kind": "steps", "step_times_s": (1.0, 2.0, 2.5), "step_values_Nm": (-1.0, 0.5, 0)},
            {0.0: 0.0, 0.999: 0.0, 1.0: -1.0, 2.1: 0.5, 2.5: 0.0, 10.0: 0.0},
        ),
    ],
)
def test_load_profiles(cfg: dict, expected: dict[float, float]) -> None:
    load = from_dict(LoadTorqueConfig, cfg)
    for t, value in expected.items():
        assert load.value(t) == pytest.approx(value, abs=1e-12), t


@pytest.mark.parametrize(
    ("cfg", "match"),
    [
        ({"kind": "steps"}, "same non-zero length"),
        ({"kind": "steps", "step_times_s": [1.0, 2.0], "step_values_Nm": [1.0]}, "same"),
        ({"kind": "steps", "step_times_s": [1.0, 1.0], "step_values_Nm": [1, 2]}, "increasing"),
        ({"kind": "sine", "step_times_s": [1.0], "step_values_Nm": [1.0]}, "kind 'steps'"),
        ({"kind": "ramp"}, "must be one of"),
        ({"kind": "sine", "frequency_Hz": -1.0}, "frequency_Hz"),
        ({"start_s": -0.1}, "start_s"),
        ({"step_values_Nm": ["x"]}, "expected a number"),
    ],
)
def test_load_config_errors_are_one_line(cfg: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        from_dict(PlantConfig, {"load": cfg})
    assert "\n" not in str(info.value)


def test_plant_evaluates_the_load_profile_from_its_own_clock() -> None:
    """A square load equals the same torque switched by hand at the same instants."""
    square = {"kind": "square", "bias_Nm": -0.5, "amplitude_Nm": 1.0, "frequency_Hz": 5.0}
    auto = make(load=square, substeps=4)
    manual = make(substeps=4)
    profile = auto.cfg.load
    for k in range(1500):
        assert auto.truth().tau_l_Nm == pytest.approx(profile.value(auto.time))
        manual.set_load_torque(profile.value(k * 1e-3))  # 0.1 s half periods: on the grid
        auto.advance(0.654296875, 1e-3)
        manual.advance(0.654296875, 1e-3)
        assert auto.truth().T_true_Nm == manual.truth().T_true_Nm
    assert auto.truth().omega_motor_radps == manual.truth().omega_motor_radps > 0


def test_load_profile_switches_inside_a_period_at_the_sub_step() -> None:
    """A step at 2.5 ms, advanced in 1 ms periods of 4 sub-steps: it acts from 2.5 ms."""
    steps = {"kind": "steps", "step_times_s": (0.0025,), "step_values_Nm": (2.0,)}
    coarse = make(load=steps, substeps=4)
    fine = make(substeps=1)
    for k in range(40):
        fine.set_load_torque(2.0 if k >= 10 else 0.0)
        fine.advance(0.0, 2.5e-4)
        if k % 4 == 3:
            coarse.advance(0.0, 1e-3)
            assert coarse.truth().T_true_Nm == pytest.approx(
                fine.truth().T_true_Nm, rel=1e-9, abs=1e-12
            )
    assert abs(coarse.truth().T_true_Nm) > 0.5


def test_set_load_torque_adds_to_the_profile() -> None:
    plant = make(load={"kind": "constant", "bias_Nm": 1.0})
    plant.set_load_torque(0.25)
    assert plant.truth().tau_l_Nm == 1.25


@pytest.mark.parametrize(("volts", "load"), [(0.654296875, 0.0), (0.5, -0.5), (-0.8, 0.3)])
def test_steady_state_relation_matches_the_simulation(volts: float, load: float) -> None:
    plant = make(load={"kind": "constant", "bias_Nm": load})
    run(plant, volts, 3.0)
    w = steady_state_motor_velocity(plant.cfg, volts, load)
    assert plant.truth().omega_motor_radps == pytest.approx(w, rel=2e-3)
    assert steady_state_volts(plant.cfg, w, load) == pytest.approx(volts, rel=1e-9)
    assert steady_state_motor_velocity(plant.cfg, 0.1) == 0.0  # below breakaway


# --------------------------------------------------------------------------- regression

#: Recorded with the plant before the [Vertechy] extensions (link motion, gravity, spring
#: sensing, joint truth): the harmonic-drive scenarios must not change.  Final T_true,
#: T_ripple, motor velocity, output angle and the sums of the four sensor readings after
#: 3 s of a step plus a slow sine at the amplifier, noise seed 7.
GOLDEN = {
    "free-motion": (
        0.017589705633993206,
        -0.006963281785952173,
        136.5882504849543,
        4.414813698492904,
        (8296, 1607477, 398776, 91041589),
    ),
    "torque-steps": (
        0.7570637476011716,
        0.651394054673026,
        100.12839405323058,
        3.678289279782762,
        (50377, 1339276, 398776, 90435109),
    ),
    "misalignment": (
        0.017589705633993206,
        -4.905198963232401,
        136.5882504849543,
        4.414813698492904,
        (95486, 1607477, 398776, 91041589),
    ),
}


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_harmonic_drive_scenarios_are_unchanged(name: str) -> None:
    plant = Plant(load_scenario(name).plant, 7)
    totals = [0, 0, 0, 0]
    for k in range(3000):
        plant.advance(0.654296875 * (k >= 50) + 0.2 * math.sin(0.01 * k), 1e-3)
        totals = [a + b for a, b in zip(totals, plant.sample(), strict=True)]
    t_true, t_ripple, omega, theta, sums = GOLDEN[name]
    truth = plant.truth()
    assert truth.T_true_Nm == pytest.approx(t_true, rel=1e-9, abs=1e-12)
    assert truth.T_ripple_Nm == pytest.approx(t_ripple, rel=1e-9, abs=1e-12)
    assert truth.omega_motor_radps == pytest.approx(omega, rel=1e-9)
    assert truth.theta_output_rad == pytest.approx(theta, rel=1e-9)
    assert tuple(totals) == sums
    # and the new truth of a free, gravity-free link without a load profile
    d = plant.cfg.drivetrain
    truth = plant.truth()
    assert truth.T_true_Nm == truth.T_transmitted_Nm
    assert truth.tau_ext_Nm == pytest.approx(truth.tau_l_Nm + truth.load_friction_Nm)
    assert truth.tau_d_Nm == pytest.approx(
        -d.b_motor * truth.omega_motor_radps / d.gear_ratio
        - d.coulomb_motor * math.tanh(truth.omega_motor_radps / d.gear_ratio / d.friction_smoothing)
    )
