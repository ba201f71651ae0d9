"""The flexible joint of [Vertechy] in the plant: parameters, prescribed link motion,
gravity, friction, saturation, sensor noise, and its truth frames on the bus."""

from __future__ import annotations

import math
from dataclasses import replace

import can
import numpy as np
import pytest
from runs import lockstep
from scipy.integrate import solve_ivp

from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.dbc import codec
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.stages import adc_read, calibrate
from hdhil.hostsim.bridge import BridgeConfig
from hdhil.hostsim.plant import (
    AmplifierConfig,
    DriveTrainConfig,
    GravityConfig,
    LinkMotionConfig,
    LoadTorqueConfig,
    Plant,
    PlantConfig,
    RippleConfig,
    SensorConfig,
)
from hdhil.rig.scenario import load_scenario

#: [Vertechy] §I-II, reduced to the output shaft; friction off unless a test adds it.
SEED003 = DriveTrainConfig(
    gear_ratio=100.0,
    J_motor=2.5,
    J_load=0.7,
    k_flex=6300.0,
    c_flex=11.8,
    b_motor=0.0,
    coulomb_motor=0.0,
    b_load=0.0,
    coulomb_load=0.0,
    friction_smoothing=0.02,
)
QUIET = SensorConfig(torque_noise_Nm=0.0, tacho_noise_radps=0.0, current_noise_A=0.0)
NO_RIPPLE = RippleConfig(amp2_Nm=0.0, amp4_Nm=0.0, misalignment_pp_Nm=0.0)
#: [Vertechy] §VI: theta_l = 20 sin(2 pi t) deg.
SEED_LINK = LinkMotionConfig(kind="sine", amplitude_deg=20.0, frequency_Hz=1.0)
#: 20 Nm per amplifier volt at the output (N 100 x Kt 0.1 x 2 A/V), limit 150 Nm.
AMP = AmplifierConfig(
    gain_A_per_V=2.0, current_lag_s=0.0, current_limit_A=15.0, torque_constant_Nm_per_A=0.1
)


#: The [Vertechy] sensor: a strain-gauged hub, ±120 Nm on ±10 V, no wave-generator modulation.
HUB = BridgeConfig.perfect(
    volt2Nm=12.0, wave_normal_strain=0.0, wave_shear_strain=0.0, rated_torque_Nm=120.0
)


def seed_plant(**changes: object) -> Plant:
    cfg = PlantConfig(
        amplifier=AMP, drivetrain=SEED003, ripple=NO_RIPPLE, bridge=HUB, sensors=QUIET, substeps=4
    )
    return Plant(replace(cfg, **changes))


# --------------------------------------------------------------------------- parameters


def test_seed_003_joint_parameters_give_17_hz_and_the_seed_damping() -> None:
    """[Vertechy] §II: sqrt(k/J)/2 pi ≈ 17 Hz, J = Jm Jl / (Jm + Jl); c = 11.8 Nms/rad."""
    d = SEED003
    assert d.reduced_inertia == pytest.approx(2.5 * 0.7 / 3.2)
    assert d.natural_frequency_Hz == pytest.approx(17.08, abs=0.01)
    assert d.natural_frequency_Hz == pytest.approx(17.0, abs=0.5)
    assert d.damping_ratio == pytest.approx(11.8 / (2 * math.sqrt(6300 * d.reduced_inertia)))
    assert d.damping_ratio == pytest.approx(0.1005, abs=1e-4)


def test_chirp_scenario_is_the_seed_joint() -> None:
    plant = load_scenario("chirp").plant
    d = plant.drivetrain
    assert (d.J_motor, d.J_load, d.k_flex, d.c_flex, d.gear_ratio) == (2.5, 0.7, 6300, 11.8, 100)
    assert plant.torque_per_volt == pytest.approx(20.0)
    assert plant.max_motor_torque_Nm == pytest.approx(150.0)
    assert plant.sensors.torque_measures == "spring"
    assert plant.sensors.torque_noise_Nm == pytest.approx(0.12)  # W, a standard deviation
    assert plant.bridge.volt2Nm * 10.0 == pytest.approx(120.0)  # ±120 Nm on the ±10 V ADC
    assert not plant.link.active and plant.gravity.mgl_Nm == 0.0


def test_spring_torque_step_response_is_seed_eq_2() -> None:
    """Free link, motor torque step: the spring torque follows [Vertechy] Eq. 2 exactly.

    Plant sign T = -tau_s: T'' + (c/J) T' + (k/J) T = (k/J_m) tau_m, from rest.
    """
    plant = seed_plant(sensors=replace(QUIET, torque_measures="spring"))
    d = SEED003
    volts = 1.5
    tau_m = volts * plant.cfg.torque_per_volt  # 30 Nm
    J = d.reduced_inertia
    wn, zeta = d.natural_frequency_radps, d.damping_ratio
    wd, sigma = wn * math.sqrt(1 - zeta**2), zeta * wn
    static = J / d.J_motor * tau_m
    for _ in range(300):
        plant.advance(volts, 1e-3)
        t = plant.time
        expected = static * (
            1 - math.exp(-sigma * t) * (math.cos(wd * t) + sigma / wd * math.sin(wd * t))
        )
        truth = plant.truth()
        assert truth.T_true_Nm == pytest.approx(expected, rel=1e-7, abs=1e-9)
        assert truth.T_true_Nm == truth.T_spring_Nm
        assert truth.T_transmitted_Nm == pytest.approx(
            truth.T_spring_Nm
            + d.c_flex * (truth.omega_motor_radps / d.gear_ratio - truth.omega_output_radps)
        )


# --------------------------------------------------------------------------- link motion


def motor_side_reference(cfg: PlantConfig, volts: float, t_end: float) -> np.ndarray:
    """[Vertechy] Eq. 1, first line, with theta_l(t) prescribed, written out independently.

    State [q_m, w_m] (output-referred), viscous friction only, ideal amplifier.
    """
    d, link = cfg.drivetrain, cfg.link
    tau_m = min(cfg.torque_per_volt * volts, cfg.max_motor_torque_Nm)

    def rhs(t: float, y: np.ndarray) -> list[float]:
        qm, wm = y
        ql, wl = link.angle(t), link.velocity(t)
        spring = d.k_flex * (ql - qm) + d.c_flex * (wl - wm)  # seed: k (θl − θm) + c (...)
        return [wm, (tau_m - d.b_motor * wm + spring) / d.J_motor]

    y0 = [link.angle(0.0), link.velocity(0.0)]  # rigid start
    sol = solve_ivp(rhs, (0.0, t_end), y0, method="DOP853", rtol=1e-12, atol=1e-14)
    return sol.y[:, -1]


def test_prescribed_link_follows_the_trajectory_exactly_and_motor_matches_eq_1() -> None:
    plant = seed_plant(link=SEED_LINK, drivetrain=replace(SEED003, b_motor=0.4))
    d = plant.cfg.drivetrain
    A, w = math.radians(20.0), 2 * math.pi
    truth = plant.truth()
    assert truth.theta_output_rad == 0.0
    assert truth.omega_output_radps == pytest.approx(A * w)
    assert truth.omega_motor_radps == pytest.approx(d.gear_ratio * A * w)  # rigid start
    volts = 0.4
    for k in range(1, 1501):
        plant.advance(volts, 1e-3)
        t = k * 1e-3
        truth = plant.truth()
        assert truth.theta_output_rad == pytest.approx(A * math.sin(w * t), abs=1e-12)
        assert truth.omega_output_radps == pytest.approx(A * w * math.cos(w * t), abs=1e-12)
        assert truth.link_acceleration_radps2 == pytest.approx(
            -A * w * w * math.sin(w * t), abs=1e-9
        )
        if k % 250 == 0:  # the motor side against an independent integration (exact ZOH)
            qm, wm = motor_side_reference(plant.cfg, volts, t)
            truth = plant.truth()
            assert truth.theta_motor_rad / d.gear_ratio == pytest.approx(qm, abs=1e-10)
            assert truth.omega_motor_radps / d.gear_ratio == pytest.approx(wm, rel=1e-8, abs=1e-10)


def test_external_torque_truth_is_link_inertia_times_acceleration_plus_joint_torque() -> None:
    """[Vertechy] Eq. 1 second line: tau_l + tau_g = J_l ddθl + k(θl − θm) + c(θ̇l − θ̇m)."""
    gravity = GravityConfig(mgl_Nm=8.0, offset_deg=30.0)
    plant = seed_plant(
        link=replace(SEED_LINK, offset_deg=10.0),
        gravity=gravity,
        drivetrain=replace(SEED003, b_load=0.3, coulomb_load=0.5, coulomb_motor=13.7),
    )
    d = plant.cfg.drivetrain
    seen = []
    for k in range(1, 2001):
        plant.advance(0.6 * math.sin(0.004 * k), 1e-3)
        t = plant.time
        ql = math.radians(10.0) + math.radians(20.0) * math.sin(2 * math.pi * t)
        wl = math.radians(20.0) * 2 * math.pi * math.cos(2 * math.pi * t)
        al = -math.radians(20.0) * (2 * math.pi) ** 2 * math.sin(2 * math.pi * t)
        truth = plant.truth()
        qm = truth.theta_motor_rad / d.gear_ratio
        wm = truth.omega_motor_radps / d.gear_ratio
        seed_joint = d.k_flex * (ql - qm) + d.c_flex * (wl - wm)  # seed's tau_s + damper
        assert truth.tau_ext_Nm == pytest.approx(d.J_load * al + seed_joint, abs=1e-7)
        tau_g = 8.0 * math.sin(ql + math.radians(30.0))
        assert truth.tau_g_Nm == pytest.approx(tau_g)
        friction = -0.3 * wl - 0.5 * math.tanh(wl / 0.02)
        assert truth.load_friction_Nm == pytest.approx(friction)
        assert truth.tau_l_Nm == pytest.approx(truth.tau_ext_Nm - tau_g - friction, abs=1e-9)
        seen.append(truth.tau_ext_Nm)
    assert max(seen) - min(seen) > 10.0  # it really varies (J_l a_l alone is ±9.6 Nm)


def test_motor_equation_holds_with_friction_under_prescribed_motion() -> None:
    """J_m ddθm = tau_m + tau_d − T_transmitted, by central differences of the motor speed."""
    plant = seed_plant(
        link=SEED_LINK, drivetrain=replace(SEED003, coulomb_motor=13.7, friction_smoothing=2.0)
    )
    d = plant.cfg.drivetrain
    h = 1e-5
    for _ in range(5):
        for _ in range(100):
            plant.advance(1.2, 1e-3)
        w0 = plant.truth().omega_motor_radps / d.gear_ratio
        plant.advance(1.2, h)
        tau_m, tau_d, joint = (
            plant.truth().tau_m_Nm,
            plant.truth().tau_d_Nm,
            plant.truth().T_transmitted_Nm,
        )
        plant.advance(1.2, h)
        acc = (plant.truth().omega_motor_radps / d.gear_ratio - w0) / (2 * h)
        assert tau_m == pytest.approx(24.0)
        assert d.J_motor * acc == pytest.approx(tau_m + tau_d - joint, rel=1e-3, abs=1e-3)


def test_hold_clamps_the_link_and_the_motor_rings_against_it() -> None:
    """Link clamped: the motor side alone, sqrt(k / J_m) = 50.2 rad/s (8.0 Hz)."""
    plant = seed_plant(link=LinkMotionConfig(kind="hold", offset_deg=45.0))
    ts, ys = [], []
    for _ in range(2000):
        plant.advance(1.0, 5e-4)
        truth = plant.truth()
        assert truth.theta_output_rad == pytest.approx(math.pi / 4, abs=1e-15)
        assert truth.omega_output_radps == 0.0
        ts.append(plant.time)
        # static: the spring carries the 20 Nm motor torque
        ys.append(plant.truth().T_true_Nm - 20.0)
    crossings = [ts[j] for j in range(len(ys) - 1) if ys[j] * ys[j + 1] < 0]
    damped_hz = (len(crossings) - 1) / 2 / (crossings[-1] - crossings[0])
    wn = math.sqrt(6300 / 2.5)
    zeta = 11.8 / (2 * math.sqrt(6300 * 2.5))
    assert damped_hz == pytest.approx(wn * math.sqrt(1 - zeta**2) / (2 * math.pi), rel=0.01)
    truth = plant.truth()
    assert truth.tau_ext_Nm == pytest.approx(-truth.T_transmitted_Nm)  # the clamp holds it


def test_prescribed_motion_has_no_sub_step_error_without_coulomb_friction() -> None:
    def final(substeps: int) -> tuple[float, float]:
        plant = seed_plant(link=SEED_LINK, substeps=substeps)
        for k in range(700):
            plant.advance(2.0 * math.sin(0.01 * k), 1e-3)
        return plant.truth().theta_motor_rad, plant.truth().T_true_Nm

    a, b = final(1), final(16)
    assert a == pytest.approx(b, rel=1e-9, abs=1e-9)


def test_link_motion_is_composable_with_the_ripple_model() -> None:
    """Ripple is measurement only: the same dynamics with and without it."""
    ripple = RippleConfig(amp2_Nm=0.6, amp4_Nm=0.25, misalignment_pp_Nm=2.0)
    a = seed_plant(link=SEED_LINK)
    b = seed_plant(link=SEED_LINK, ripple=ripple)
    parts = []
    for _ in range(500):
        a.advance(0.3, 1e-3)
        b.advance(0.3, 1e-3)
        ta, tb = a.truth(), b.truth()
        assert ta.T_true_Nm == tb.T_true_Nm and ta.theta_motor_rad == tb.theta_motor_rad
        assert ta.T_ripple_Nm == 0.0
        parts.append(tb.T_ripple_Nm)
    assert np.ptp(parts) > 1.0


# --------------------------------------------------------------------------- free link


def test_gravity_on_a_free_link_matches_an_independent_integration() -> None:
    """[Vertechy] Eq. 1 with tau_g = mgl sin(θl + offset), solved by solve_ivp."""
    gravity = GravityConfig(mgl_Nm=15.0, offset_deg=180.0)  # hanging: restoring
    plant = seed_plant(gravity=gravity, substeps=40)
    d = plant.cfg.drivetrain
    tau_m = 0.5 * plant.cfg.torque_per_volt

    def rhs(_t: float, y: np.ndarray) -> list[float]:
        qm, ql, wm, wl = y
        joint = d.k_flex * (qm - ql) + d.c_flex * (wm - wl)
        tau_g = 15.0 * math.sin(ql + math.pi)
        return [wm, wl, (tau_m - joint) / d.J_motor, (joint + tau_g) / d.J_load]

    sol = solve_ivp(rhs, (0.0, 2.0), [0.0] * 4, method="DOP853", rtol=1e-11, atol=1e-13)
    for _ in range(2000):
        plant.advance(0.5, 1e-3)
    _qm, ql, _wm, wl = sol.y[:, -1]
    assert abs(ql) > 0.5  # it swings far enough for sin() to matter
    truth = plant.truth()
    assert truth.theta_output_rad == pytest.approx(ql, rel=1e-4)
    assert truth.omega_output_radps == pytest.approx(wl, rel=1e-3, abs=1e-4)
    assert truth.tau_g_Nm == pytest.approx(-15.0 * math.sin(truth.theta_output_rad))
    assert truth.tau_ext_Nm == pytest.approx(truth.tau_g_Nm)


def test_free_link_external_torque_is_load_gravity_and_bearing_friction() -> None:
    plant = seed_plant(
        gravity=GravityConfig(mgl_Nm=5.0, offset_deg=90.0),
        drivetrain=replace(SEED003, b_load=0.2, coulomb_load=0.4),
        load=LoadTorqueConfig(kind="sine", amplitude_Nm=3.0, frequency_Hz=2.0),
    )
    d = plant.cfg.drivetrain
    h = 1e-6
    for _ in range(4):
        for _ in range(150):
            plant.advance(0.8, 1e-3)
        truth = plant.truth()
        expected = truth.tau_l_Nm + truth.tau_g_Nm + truth.load_friction_Nm
        assert truth.tau_ext_Nm == pytest.approx(expected)
        assert truth.tau_l_Nm == pytest.approx(plant.cfg.load.value(plant.time))  # free link
        w0, joint, tau_ext = (
            truth.omega_output_radps,
            truth.T_transmitted_Nm,
            truth.tau_ext_Nm,
        )
        acc = truth.link_acceleration_radps2
        plant.advance(0.8, h)
        assert acc == pytest.approx((plant.truth().omega_output_radps - w0) / h, rel=1e-3)
        assert d.J_load * acc == pytest.approx(joint + tau_ext)


def test_seed_003_motor_friction_tops_out_at_13_7_nm_and_opposes_motion() -> None:
    """The seed's tau_d read as -13.7 tanh(w / eps) (hostsim.plant.DriveTrainConfig)."""
    plant = seed_plant(drivetrain=replace(SEED003, coulomb_motor=13.7, friction_smoothing=0.02))
    tau_d = []
    for _ in range(1500):
        plant.advance(2.0, 1e-3)  # 40 Nm: breaks away and accelerates
        truth = plant.truth()
        w = truth.omega_motor_radps / 100.0
        assert truth.tau_d_Nm == pytest.approx(-13.7 * math.tanh(w / 0.02))
        tau_d.append(truth.tau_d_Nm)
    assert plant.truth().omega_motor_radps > 0
    assert min(tau_d) == pytest.approx(-13.7, abs=1e-6)
    assert all(-13.7 - 1e-12 <= x <= 0.0 for x in tau_d)


def test_motor_torque_saturates_at_the_amplifier_current_limit() -> None:
    plant = seed_plant()
    cfg = plant.cfg
    plant.advance(3.0, 1e-3)
    truth = plant.truth()
    assert truth.tau_m_cmd_Nm == pytest.approx(3.0 * cfg.torque_per_volt)
    assert truth.tau_m_Nm == pytest.approx(60.0)
    for volts, expected in ((9.0, 150.0), (-9.0, -150.0)):
        plant.advance(volts, 1e-3)
        truth = plant.truth()
        assert truth.tau_m_cmd_Nm == pytest.approx(expected)
        assert truth.tau_m_Nm == pytest.approx(expected)
    lagged = seed_plant(amplifier=replace(AMP, current_lag_s=4e-4))
    lagged.advance(3.0, 1e-4)
    lagged_truth = lagged.truth()
    assert 0 < lagged_truth.tau_m_Nm < lagged_truth.tau_m_cmd_Nm == 60.0


def test_torque_sensor_noise_is_the_seeds_w() -> None:
    """[Vertechy] §I: W = 0.12 Nm, a standard deviation (variance 0.0144 Nm²), through the
    sensor, ADC and firmware calibration."""
    scenario = load_scenario("chirp")
    fw = from_dict(FirmwareConfig, scenario.firmware, "firmware")
    plant = Plant(scenario.plant, seed=11)
    readings = []
    for _ in range(20000):
        plant.advance(0.0, 1e-3)
        counts = plant.sample()[0]
        readings.append(calibrate(adc_read(counts, 0, 0, fw.adc)[0], 0.0, 0.0, fw.calibration)[0])
    variance = float(np.var(readings))
    quantisation = (10.0 / 2048 * 12.0) ** 2 / 12  # 12-bit LSB of 0.059 Nm
    assert variance == pytest.approx(0.12**2 + quantisation, rel=0.04)


# --------------------------------------------------------------------------- configuration


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"link": {"kind": "ramp"}}, "link.kind"),
        ({"link": {"frequency_Hz": 0.0}}, "frequency_Hz"),
        ({"gravity": {"mgl_Nm": float("inf")}}, "mgl_Nm"),
        ({"sensors": {"torque_measures": "strain"}}, "torque_measures"),
        ({"link": {"kind": "sine"}, "load": {"kind": "constant"}}, "prescribed link motion"),
    ],
)
def test_bad_seed_003_configuration_is_a_one_line_error(data: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        from_dict(PlantConfig, data, "plant")
    assert "\n" not in str(info.value)


def test_hold_locked_refuses_a_prescribed_link() -> None:
    with pytest.raises(ValueError, match="prescribed"):
        seed_plant(link=SEED_LINK).hold_locked(0.0, 1.0)


# --------------------------------------------------------------------------- truth frames


def test_truth_joint_and_motor_torque_frames_are_published_and_decodable(tmp_path) -> None:
    """Over the bus: TRUTH_JOINT tau_ext = J_l a_l − T_transmitted for a prescribed link."""
    scenario = load_scenario(
        "chirp",
        {
            "scenario": {"duration_s": 0.5},
            "plant": {
                "sensors": {"torque_measures": "transmitted", "torque_noise_Nm": 0.0},
                "link": {"kind": "sine", "amplitude_deg": 20.0, "frequency_Hz": 1.0},
            },
        },
    )
    trace = tmp_path / "joint.blf"
    result = lockstep(scenario, trace=trace, evaluate=False)
    names = {name.split()[-1]: n for name, n in result.frames.items()}
    # Truth is published on every SYNC while the drive is operational: the 500 cycles of
    # operation plus the start-up walk and the stop.
    assert names["TRUTH_JOINT"] == names["TRUTH_TORQUE"] >= result.cycles == 500
    torque, joint = (codec("truth", n) for n in ("TRUTH_TORQUE", "TRUTH_JOINT"))
    rows: dict[str, list[tuple[float, ...]]] = {"torque": [], "joint": []}
    times: list[float] = []
    with can.LogReader(str(trace)) as reader:
        for msg in reader:
            for key, c in (("torque", torque), ("joint", joint)):
                if msg.is_extended_id and msg.arbitration_id == c.frame_id:
                    rows[key].append(c.decode(msg.data))
                    if key == "joint":
                        # the sample instant t(k): simulated time after the trace's start
                        times.append(msg.timestamp - result.start_time)
    assert len(rows["joint"]) == len(rows["torque"]) == names["TRUTH_JOINT"]
    A, w = math.radians(20.0), 2 * math.pi
    per_volt = scenario.plant.torque_per_volt
    resolution = 0.005  # TRUTH_JOINT scaling (truth.dbc)
    for t, (t_true, _), (tau_ext, tau_d, tau_m, tau_m_cmd) in zip(
        times, rows["torque"], rows["joint"], strict=True
    ):
        a_l = -A * w * w * math.sin(w * t)
        assert tau_ext == pytest.approx(0.7 * a_l - t_true, abs=resolution)
        assert tau_d == 0.0  # friction off in the chirp scenario
        step = per_volt * 10.0 / 2048  # commanded through the 12-bit DAC
        assert tau_m_cmd / step == pytest.approx(round(tau_m_cmd / step), abs=resolution / step)
        if t <= (result.startup_cycles + result.cycles) * 1e-3:  # not the torque-off step
            assert abs(tau_m - tau_m_cmd) < 0.5  # the 0.4 ms current lag
    assert max(abs(m[3]) for m in rows["joint"]) > 40.0  # the 50 Nm chirp
