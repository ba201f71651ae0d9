"""[Vertechy] §VI experiment (Fig. 8): the person-moved link, the experiment's motor
friction, JTF1 with the Eq. 5 friction compensation, its scoring from the trace alone,
the §V filter-based JTF2/JTF3, and ``hdhil plot --figure fig8``."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math

import can
import numpy as np
import pytest

from hdhil.cli import main
from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.firmware.config import (
    SEED_FRICTION_MODEL,
    ControlConfig,
    FirmwareConfig,
    FrictionModelConfig,
    Law,
)
from hdhil.firmware.isr import SENSOR_TORQUE_SIGN, IsrOutput, TorqueControl
from hdhil.firmware.lqg import LqgController
from hdhil.hostsim.plant import LinkMotionConfig, Plant, PlantConfig
from hdhil.rig.scenario import load_scenario

MAX_OUTPUT_SPEED = 1000.0 * 2 * math.pi / 60.0 / 100.0  # [Vertechy] §I: 1000 rpm, 100:1


# ------------------------------------------------------------------ person-like motion
def _sampled(link: LinkMotionConfig, seconds: float = 20.0) -> tuple[np.ndarray, ...]:
    t = np.arange(0.0, seconds, 0.002)
    return (
        np.array([link.angle(x) for x in t]),
        np.array([link.velocity(x) for x in t]),
        np.array([link.acceleration(x) for x in t]),
        t,
    )


@pytest.mark.parametrize("seed", [0, 1, 7])
def test_person_motion_spans_60_degrees_below_the_motor_speed_limit(seed) -> None:
    link = LinkMotionConfig(kind="person", amplitude_deg=60.0, motion_seed=seed, horizon_s=20.0)
    th, om, acc, t = _sampled(link)
    peak = np.degrees(np.max(np.abs(th)))
    assert peak <= 60.0 + 1e-3
    assert np.max(np.abs(om)) <= MAX_OUTPUT_SPEED * (1 + 1e-9)
    # either the angle or the speed bound is reached (the scale is set by one of them)
    assert peak > 59.9 or np.max(np.abs(om)) > 0.999 * MAX_OUTPUT_SPEED
    # irregular: no single period; smooth: derivatives agree with finite differences
    assert len(link.components()) == 5
    assert len({round(w, 9) for _a, w, _p in link.components()}) == 5
    np.testing.assert_allclose(np.gradient(th, t)[5:-5], om[5:-5], atol=1e-4)
    np.testing.assert_allclose(np.gradient(om, t)[5:-5], acc[5:-5], atol=1e-4)


def test_person_motion_is_reproducible_by_seed() -> None:
    a = LinkMotionConfig(kind="person", amplitude_deg=60.0, motion_seed=3)
    b = from_dict(LinkMotionConfig, {"kind": "person", "amplitude_deg": 60.0, "motion_seed": 3})
    c = LinkMotionConfig(kind="person", amplitude_deg=60.0, motion_seed=4)
    assert a.components() == b.components()
    assert a.components() != c.components()
    with pytest.raises(ConfigError, match="motion_seed"):
        from_dict(LinkMotionConfig, {"kind": "person", "motion_seed": -1})


def _experiment_plant(**drivetrain) -> PlantConfig:
    sc = load_scenario("lqg-experiment")
    cfg = sc.plant
    return dataclasses.replace(cfg, drivetrain=dataclasses.replace(cfg.drivetrain, **drivetrain))


@pytest.mark.slow
def test_person_link_is_integrated_exactly_and_its_torque_is_truth() -> None:
    """Without Coulomb friction the exosystem makes the step exact for any sub-step count;
    the handle torque is J_l theta_l'' - T_transmitted ([Vertechy] Eq. 1, second line)."""
    cfg = _experiment_plant(coulomb_motor=0.0)
    coarse = Plant(dataclasses.replace(cfg, substeps=1))
    fine = Plant(dataclasses.replace(cfg, substeps=32))
    for k in range(3000):
        v = 0.3 * math.sin(0.002 * k)
        coarse.advance(v, 1e-3)
        fine.advance(v, 1e-3)
    c, f = coarse.truth(), fine.truth()
    assert c.T_spring_Nm == pytest.approx(f.T_spring_Nm, rel=1e-9, abs=1e-9)
    assert c.omega_motor_radps == pytest.approx(f.omega_motor_radps, rel=1e-9, abs=1e-9)
    link = cfg.link
    assert f.theta_output_rad == pytest.approx(link.angle(3.0))
    assert f.tau_ext_Nm == pytest.approx(
        cfg.drivetrain.J_load * link.acceleration(3.0) - f.T_transmitted_Nm
    )


def test_experiment_motor_friction_is_the_seed_model_exactly() -> None:
    """The plant's tau_d is the firmware's Eq. 5 model (13.7 Nm, 2 rad/s at the motor
    shaft), opposing the motion: the unmodelled friction is on the link side."""
    sc = load_scenario("lqg-experiment")
    fw = from_dict(FirmwareConfig, sc.firmware, "firmware")
    assert fw.control.friction == SEED_FRICTION_MODEL
    plant = Plant(sc.plant)
    for w_motor in (-50.0, -2.0, -0.3, 0.0, 0.5, 2.0, 80.0):
        plant._wm = w_motor / sc.plant.drivetrain.gear_ratio
        assert plant.truth().tau_d_Nm == pytest.approx(
            fw.control.friction.torque(w_motor), abs=1e-9
        )
    assert fw.control.friction.torque(100.0) == pytest.approx(-13.7, rel=1e-9)
    assert fw.control.friction.torque(-100.0) > 13.69
    assert sc.plant.link.bearing_coulomb_Nm > 0.0


def test_link_bearing_friction_separates_the_handle_torque_from_tau_ext() -> None:
    """The output-shaft bearings' friction between the sensor and the handle: the
    person supplies it, so the joint moves as without it, tau_ext (what the observer
    estimates, TRUTH_JOINT.tau_ext) keeps it and the handle torque tau_l does not."""
    sc = load_scenario("lqg-experiment")
    link = sc.plant.link
    without = dataclasses.replace(sc.plant, link=dataclasses.replace(link, bearing_coulomb_Nm=0.0))
    a, b = Plant(sc.plant, seed=3), Plant(without, seed=3)
    for k in range(1500):
        v = 0.4 * math.sin(0.003 * k)
        a.advance(v, 1e-3)
        b.advance(v, 1e-3)
        if k % 50:
            continue
        ta, tb = a.truth(), b.truth()
        assert a.sample() == b.sample()
        assert ta[:10] == tb[:10]  # every truth-channel field, tau_ext included
        bearing = -link.bearing_coulomb_Nm * math.tanh(ta.omega_output_radps / 0.01)
        assert ta.load_friction_Nm == pytest.approx(bearing, abs=1e-12)
        assert ta.tau_l_Nm == pytest.approx(tb.tau_l_Nm - bearing, abs=1e-9)
        assert ta.tau_l_Nm == pytest.approx(
            link.handle_torque(ta.tau_ext_Nm, ta.omega_output_radps), abs=1e-9
        )
    assert link.handle_torque(1.0, 0.5) == pytest.approx(1.0 + link.bearing_coulomb_Nm)
    assert LinkMotionConfig().handle_torque(1.0, 0.5) == 1.0
    with pytest.raises(ConfigError, match="coulomb_load"):
        from_dict(LinkMotionConfig, {"bearing_coulomb_Nm": 3.0})  # a free link
    with pytest.raises(ConfigError, match="bearing_smoothing_radps"):
        from_dict(LinkMotionConfig, {"kind": "hold", "bearing_smoothing_radps": 0.0})


def test_the_tracking_score_compares_the_estimate_with_the_handle_torque() -> None:
    """With a bearing friction the external-torque estimate is scored against the
    handle torque: TRUTH_JOINT.tau_ext less the friction at TRUTH_MOTION.omega_output;
    the disturbance estimate still against tau_ext (what the observer estimates)."""
    from hdhil.dbc import codec
    from hdhil.rig.score import TrackingScorer

    truth = codec("truth", "TRUTH_TORQUE")
    motion = codec("truth", "TRUTH_MOTION")
    joint = codec("truth", "TRUTH_JOINT")
    tele2 = codec("control", "CTRL_TPDO2")
    link = LinkMotionConfig(kind="hold", bearing_coulomb_Nm=3.0)
    scorers = [TrackingScorer(0.28, 0.0, True, 1e-3, h) for h in (None, LinkMotionConfig(), link)]

    def frame(c, t, *values):
        return can.Message(timestamp=t, arbitration_id=c.frame_id,
                           is_extended_id=c.is_extended_id, data=c.encode(*values))  # fmt: skip

    # (link velocity, tau_ext, tau_lgd_hat): the estimate follows tau_ext
    samples = [(0.5, 2.0, 2.0), (-0.5, -1.0, -1.0), (0.0, 0.0, 0.0)]
    for k, (w, tau_ext, est) in enumerate(samples):
        t = k * 1e-3
        for sc in scorers:
            sc.on_message_received(frame(truth, t, 0.0, 0.0))
            sc.on_message_received(frame(motion, t, 0.0, 0.0, 100.0 * w, w))
            sc.on_message_received(frame(joint, t, tau_ext, 0.0, 0.0, 0.0))
            sc.on_message_received(frame(tele2, t, 0.0, est, 0.0, 0.0))
    plain, default, handle = (sc.result() for sc in scorers)
    assert plain == default
    assert plain.max_external_error == pytest.approx(0.0, abs=1e-9)
    assert handle.max_external_error == pytest.approx(3.0, abs=1e-6)  # 3 tanh(50)
    assert handle.rms_external_error == pytest.approx(math.sqrt(2 * 9.0 / 3), abs=1e-6)
    assert handle.rms_disturbance_error == plain.rms_disturbance_error == 0.0


# ------------------------------------------------------------------ firmware Eq. 5
def test_eq5_fade_in_reading_is_the_printed_formula_with_one_bracket_moved() -> None:
    """[Vertechy] Eq. 5 read as -13.7 sgn(w) (1 + tanh(|w|/2 - 4)) / 2, w the motor-shaft
    speed: a compensation that fades in around 8 rad/s; selectable beside the tanh one."""
    fade = FrictionModelConfig(coulomb_Nm=13.7, velocity_scale_radps=2.0, model="fade-in")
    for w in (-300.0, -20.0, -8.0, -3.0, -0.5, 1e-3, 0.7, 4.0, 8.0, 9.5, 30.0, 100.0):
        expected = -13.7 * math.copysign(1.0, w) * (1.0 + math.tanh(abs(w) / 2.0 - 4.0)) / 2.0
        assert fade.torque(w) == pytest.approx(expected, rel=1e-12, abs=1e-15)
    assert fade.torque(0.0) == 0.0
    assert fade.torque(8.0) == pytest.approx(-13.7 / 2.0)
    assert abs(fade.torque(2.0)) < 0.05 < 0.3 * abs(SEED_FRICTION_MODEL.torque(2.0))
    # the key of a scenario file, and its check
    ctl = from_dict(ControlConfig, {"law": "jtf1", "friction": {"coulomb_Nm": 13.7,
                                                                 "model": "fade-in"}})  # fmt: skip
    assert ctl.friction == fade
    assert from_dict(ControlConfig, {"friction": {"coulomb_Nm": 13.7}}).friction.model == "tanh"
    with pytest.raises(ConfigError, match="model"):
        from_dict(ControlConfig, {"friction": {"coulomb_Nm": 13.7, "model": "sgn"}})
    # the interrupt stage applies it on the tacho velocity
    stage = TorqueControl(FirmwareConfig(control=ControlConfig(law=Law.JTF1, friction=fade)))
    out = IsrOutput()
    stage(0, 0.0, out, 8.0)
    assert out.tau_d_hat == pytest.approx(-13.7 / 2.0)


def test_interrupt_stage_applies_eq5_with_the_tacho_velocity() -> None:
    """TorqueControl passes tau_d_hat = model(velocity) to the LQG controller (Eq. 5):
    the same commands as a controller driven by hand with that model."""
    control = ControlConfig(law=Law.JTF1, friction=SEED_FRICTION_MODEL, torque_limit_Nm=1e3,
                            torque_per_volt=200.0)  # fmt: skip
    fw = FirmwareConfig(control=control)
    stage = TorqueControl(fw)
    ref = LqgController(stage.design, Law.JTF1.control_law)
    out = IsrOutput()
    s = SENSOR_TORQUE_SIGN
    rng = np.random.default_rng(0)
    for k in range(200):
        T = 5.0 * math.sin(0.01 * k) + 0.1 * rng.standard_normal()
        vel = 30.0 * math.sin(0.02 * k)
        stage(k, T, out, vel)
        d = SEED_FRICTION_MODEL.torque(vel)
        T_D = stage.desired.value(k)
        dT_D = (stage.desired.value(k + 1) - stage.desired.value(k - 1)) * 500.0
        expected = ref.step(s * T, s * T_D, s * dT_D, d)
        ref.set_applied(out.tau_m_cmd)
        assert out.tau_d_hat == d
        assert out.tau_m_request == pytest.approx(expected, rel=1e-12, abs=1e-12)
    assert FrictionModelConfig().active is False


def test_filter_estimates_are_for_jtf2_and_jtf3_only() -> None:
    with pytest.raises(ValueError, match="jtf2 and jtf3"):
        ControlConfig(law=Law.JTF1, estimates="filters")
    with pytest.raises(ConfigError, match="estimates"):
        from_dict(ControlConfig, {"law": "jtf3", "estimates": "kalman"})
    stage = TorqueControl(FirmwareConfig(control=ControlConfig(law=Law.JTF3, estimates="filters")))
    out = IsrOutput()
    stage(0, 2.0, out)
    # first sample: the low-pass starts at the input, the law is -[k1 (ts - tsD) + k2 dts + k4 tsD]
    g = stage.controller.gains
    s = SENSOR_TORQUE_SIGN
    dts = stage.derivative.a_1
    expected = -(g.k1 * (s * 2.0 - s * stage.desired.value(0)) + g.k2 * dts
                 + 1.0 * s * stage.desired.value(0))  # fmt: skip
    assert out.tau_m_request == pytest.approx(expected)
    assert out.tau_s_hat == pytest.approx(2.0)


# ------------------------------------------------------------------ the experiment over CAN
@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    out = tmp_path_factory.mktemp("exp") / "exp.blf"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["run", "--scenario", "lqg-experiment", "--duration", "8",
                     "--compare-laws", "--trace", str(out), "--json"])  # fmt: skip
    assert code == 0
    rows = {row["law"]: row for row in json.loads(buf.getvalue())["laws"]}
    return rows, out


@pytest.mark.slow
def test_experiment_with_friction_compensation_meets_the_seed(experiment) -> None:
    rows, _ = experiment
    eq5 = rows["JTF1 with friction comp. (Eq. 5)"]
    eq4 = rows["JTF1 without friction comp. (Eq. 4)"]
    assert eq5["samples"] >= 6900
    # seed: e within ±0.5 Nm, on the measured torque too; τm near ±40 Nm
    assert eq5["rms_error"] < 0.3
    assert eq5["share_within_goal"] > 0.97
    assert eq5["share_within_goal_measured"] > 0.95
    assert eq5["max_abs_error_measured"] > eq5["max_abs_error"]  # the sensor's noise
    assert eq5["max_abs_tau_m"] <= 40.0
    # the external-torque estimate follows the handle torque with Eq. 5 up to the
    # unmodelled bearing friction (seed: "roughly ±3 Nm"); without Eq. 5 it is tau_lgd,
    # off by Jl/Jm tau_d (3.8 Nm) against the motion, and the bearing friction's 3 Nm
    # partly cancels that
    assert 2.0 < eq5["max_external_error"] < 5.0
    assert eq4["rms_disturbance_error"] > eq5["rms_disturbance_error"]
    assert eq4["max_abs_error"] > 2.0 * eq5["max_abs_error"]
    # seed §V: the filter-fed JTF3 is worse than the observer-fed one on the noisy sensor
    assert rows["JTF3, filters (§V)"]["rms_error"] > 3.0 * rows["JTF3"]["rms_error"]


@pytest.mark.slow
def test_the_experiment_meets_the_three_statements_of_fig8() -> None:
    """The whole run as the scenario sets it (20 s, from 1 s): [Vertechy] §VI "τm ...
    remains within ±40 Nm", e within ±0.5 Nm on the measured torque (>= 95 % of the
    samples: the sensor's noise alone leaves it now and then) and τ̂l off the handle's
    τl^m by "roughly ±3 Nm"."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["run", "--scenario", "lqg-experiment", "--json"]) == 0
    row = json.loads(buf.getvalue())["tracking"]
    assert row["samples"] == 19000
    assert row["max_abs_tau_m"] <= 40.0
    assert row["share_within_goal_measured"] >= 0.95
    assert 2.0 <= row["max_external_error"] <= 4.5
    assert row["rms_external_error"] >= 1.5  # an error of that order throughout, not a spike


@pytest.mark.slow
def test_the_trace_alone_scores_the_experiment(experiment, capsys) -> None:
    rows, out = experiment
    trace = out.with_name(f"{out.stem}-jtf1{out.suffix}")
    assert main(["evaluate", str(trace), "--scenario", "lqg-experiment", "--skip", "1",
                 "--json"]) == 0  # fmt: skip
    tracking = json.loads(capsys.readouterr().out)["tracking"]
    run_row = rows["JTF1 with friction comp. (Eq. 5)"]
    for key in ("samples", "max_abs_error", "rms_error", "max_external_error", "max_abs_tau_m"):
        assert tracking[key] == pytest.approx(run_row[key], rel=1e-12), key


@pytest.mark.slow
def test_tracking_from_python_is_what_evaluate_reports(experiment, capsys) -> None:
    """The library alone (no argparse) scores the trace as ``hdhil evaluate`` does."""
    from hdhil.rig.trace_score import tracking_from_trace

    _rows, out = experiment
    trace = out.with_name(f"{out.stem}-jtf1{out.suffix}")
    sc = load_scenario("lqg-experiment")
    fw = from_dict(FirmwareConfig, sc.firmware, "firmware")
    tracking = tracking_from_trace(trace, fw, 1.0, sc.plant.link)
    assert main(["evaluate", str(trace), "--scenario", "lqg-experiment", "--skip", "1",
                 "--json"]) == 0  # fmt: skip
    assert json.loads(json.dumps(tracking)) == json.loads(capsys.readouterr().out)["tracking"]


@pytest.mark.slow
def test_plot_draws_fig8(experiment, tmp_path, capsys) -> None:
    _rows, out = experiment
    trace = out.with_name(f"{out.stem}-jtf1{out.suffix}")
    png = tmp_path / "fig8.png"
    assert main(["plot", str(trace), "--figure", "fig8", "--scenario", "lqg-experiment",
                 "--out", str(png)]) == 0  # fmt: skip
    assert png.stat().st_size > 20_000
    from hdhil.analysis.paper_figures import fig8_data

    data, damage = fig8_data(trace)
    assert damage == ""
    assert np.max(np.abs(data.theta_l_deg)) <= 60.5
    # τl^m: the handle torque, tau_ext less the bearing friction at the link's velocity
    link = load_scenario("lqg-experiment").plant.link
    handle, _ = fig8_data(trace, link)
    np.testing.assert_allclose(
        handle.tau_l_meas - data.tau_l_meas,
        link.bearing_coulomb_Nm * np.tanh(data.omega_l / link.bearing_smoothing_radps),
        atol=1e-9,
    )
    # seed sign: the desired torque is +20 sin(0.4 pi t)
    k = np.searchsorted(data.t, 1.25)
    assert data.tau_sD[k] == pytest.approx(20.0 * math.sin(0.4 * math.pi * data.t[k]), abs=0.05)


def test_plot_fig8_without_control_telemetry_is_a_one_line_error(tmp_path, capsys) -> None:
    trace = tmp_path / "free.blf"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["run", "--scenario", "free-motion", "--duration", "0.2", "--trace",
                     str(trace)]) == 0  # fmt: skip
    capsys.readouterr()
    assert main(["plot", str(trace), "--figure", "fig8", "--out", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hdhil: error:") and "CTRL_TPDO2" in err[0]
    from hdhil.rig.trace_score import tracking_from_trace

    assert tracking_from_trace(trace, FirmwareConfig(), 0.0) is None  # no torque control


def test_lowpass_of_the_section_v_estimates() -> None:
    """The first-order low-pass (firmware.stages.LowPass): starts at its first input,
    unity gain at DC, -3 dB at the cut-off (Tustin: at the pre-warped frequency)."""
    from hdhil.firmware.stages import LowPass

    Ts, fc = 1e-3, 50.0
    lp = LowPass(fc, Ts)
    assert lp.step(3.0) == 3.0
    for _ in range(2000):
        y = lp.step(3.0)
    assert y == pytest.approx(3.0, rel=1e-12)
    # amplitude at the analog cut-off mapped through the bilinear transform
    f_digital = math.atan(math.pi * fc * Ts) / (math.pi * Ts)
    lp.reset()
    n = 20_000
    out = [lp.step(math.sin(2 * math.pi * f_digital * k * Ts)) for k in range(n)]
    amp = max(abs(v) for v in out[n // 2 :])
    assert amp == pytest.approx(1 / math.sqrt(2), rel=2e-3)
    with pytest.raises(ValueError, match="cut-off"):
        LowPass(500.0, Ts)


def test_the_tracking_score_pairs_the_measured_torque_of_the_same_cycle_only() -> None:
    """Decimated telemetry: a cycle with CTRL_TPDO1 but no CTRL_TPDO2, then a cycle with
    CTRL_TPDO2 only. The measured torque of the first cycle is not scored against the
    second cycle's desired torque (each truth frame starts a cycle); e on the truth and
    on the estimate still score from the CTRL_TPDO2 present."""
    from hdhil.dbc import codec
    from hdhil.rig.score import TrackingScorer

    tele1, tele2 = codec("control", "CTRL_TPDO1"), codec("control", "CTRL_TPDO2")
    truth, joint = codec("truth", "TRUTH_TORQUE"), codec("truth", "TRUTH_JOINT")
    scorer = TrackingScorer(0.28, friction_compensated=True)

    def frame(c, t, *values):
        return can.Message(timestamp=t, arbitration_id=c.frame_id,
                           is_extended_id=c.is_extended_id, data=c.encode(*values))  # fmt: skip

    for k in range(2):
        scorer.on_message_received(frame(truth, k * 1e-3, 1.0, 0.0))
        scorer.on_message_received(frame(joint, k * 1e-3, 0.0, 0.0, 0.0, 0.0))
        if k == 0:
            scorer.on_message_received(frame(tele1, 0.0, 5.0, 5.0, 0.0, 0.0))
        else:
            scorer.on_message_received(frame(tele2, 1e-3, 0.0, 0.0, 1.0, 0.0))
    r = scorer.result()
    assert r.samples == 1 and r.max_abs_error == pytest.approx(0.0, abs=1e-3)
    assert math.isnan(r.rms_error_measured)


def test_the_tracking_score_has_e_on_the_true_measured_and_estimated_torque() -> None:
    """Each telemetry sample scores e = torque − T_desired three times: on the truth of
    its instant, on the measured torque of its CTRL_TPDO1 (once: a sample whose measured
    frame is missing is not scored against the previous one) and on the estimate."""
    from hdhil.dbc import codec
    from hdhil.rig.score import TrackingScorer

    tele1 = codec("control", "CTRL_TPDO1")
    tele2 = codec("control", "CTRL_TPDO2")
    truth = codec("truth", "TRUTH_TORQUE")
    joint = codec("truth", "TRUTH_JOINT")
    scorer = TrackingScorer(0.28, friction_compensated=True)

    def frame(c, t, *values):
        return can.Message(timestamp=t, arbitration_id=c.frame_id,
                           is_extended_id=c.is_extended_id, data=c.encode(*values))  # fmt: skip

    # (T_true, T_meas or None, e_hat, T_desired) per sample
    samples = [(1.0, 1.2, 0.1, 1.0), (2.0, 1.0, -0.7, 2.0), (3.0, None, 0.2, 3.5),
               (0.0, 0.3, 0.0, 0.0)]  # fmt: skip
    for k, (T, meas, e_hat, T_D) in enumerate(samples):
        t = k * 1e-3
        scorer.on_message_received(frame(truth, t, T, 0.0))
        scorer.on_message_received(frame(joint, t, 0.0, 0.0, 0.0, 0.0))
        if meas is not None:
            scorer.on_message_received(frame(tele1, t, meas, meas, 0.0, 0.0))
        scorer.on_message_received(frame(tele2, t, 0.0, 0.0, T_D, e_hat))
    r = scorer.result()
    assert r.samples == 4
    assert r.max_abs_error == pytest.approx(0.5, abs=1e-3)  # sample 3: 3.0 − 3.5
    assert r.share_within_goal == 1.0
    # measured: 0.2, −1.0, (none), 0.3
    assert r.max_abs_error_measured == pytest.approx(1.0, abs=1e-2)
    assert r.share_within_goal_measured == pytest.approx(2 / 3)
    assert r.rms_error_measured == pytest.approx(math.sqrt((0.04 + 1.0 + 0.09) / 3), abs=1e-2)
    # estimated: the telemetry's e_hat
    assert r.max_abs_error_estimated == pytest.approx(0.7, abs=1e-3)
    assert r.share_within_goal_estimated == pytest.approx(3 / 4)
