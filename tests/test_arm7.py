"""arm7 free motion: the ripple filter on every joint of a 7-joint arm moving under gravity.

The goal (issue #24): every joint's filtered RMS torque error at most 10 % of its raw
error, computed from the trace decoded by cantools with the DBCs `hdhil dbc export`
writes, and equal to what `hdhil run` prints. What makes it reachable is tested on its
own: the firmware's motor-speed loop (the filter's premise, a steady motor speed), the
arm's start at rest under its weight with its brakes on until operation, and the start
pose of the scenario. Expected values come from the loop's equations, from statics and
from the URDF's limits; the goal test decodes the trace with python-can and cantools
only, pairing frames as a logger would.
"""

from __future__ import annotations

import importlib.util
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.firmware.config import FirmwareConfig, SpeedLoopConfig
from hdhil.firmware.isr import AdcSample, InterruptHandler
from hdhil.firmware.stages import SpeedLoop
from hdhil.rig.scenario import load_scenario, scenario_data, scenario_from_dict

ARM = importlib.util.find_spec("mujoco") is not None
needs_arm = pytest.mark.skipif(not ARM, reason="the arm extra (hdhil[arm])")
TS = 1e-3


# ------------------------------------------------------------------ the speed loop


def test_speed_loop_holds_rest_then_ramps_to_its_set_point() -> None:
    """w_ref is 0 before start_s, a raised cosine over ramp_s (half the set point at
    half the ramp), the set point after; V = kp e + I with I += ki Ts e."""
    cfg = SpeedLoopConfig(setpoint_radps=100.0, start_s=0.01, ramp_s=0.02,
                          kp_V_per_radps=0.1, ki_V_per_rad=2.0)  # fmt: skip
    loop = SpeedLoop(cfg, TS, 10.0)
    # at rest before the start: a measured 1 rad/s gives -kp, and the integrator -ki Ts
    assert loop.step(0, 1.0) == pytest.approx(-0.1)
    assert loop.step(1, 1.0) == pytest.approx(-2.0 * TS - 0.1)
    loop.reset()
    outs = [loop.step(k, 0.0) for k in range(40)]
    # with the motor still, kp e + I traces the set point: e(k) = w_ref(k)
    integral = 0.0
    for k, out in enumerate(outs):
        if k < 10:
            ref = 0.0
        elif k < 30:
            ref = 50.0 * (1.0 - math.cos(math.pi * (k - 9) / 20))
        else:
            ref = 100.0
        assert out == pytest.approx(integral + 0.1 * ref), k
        integral += 2.0 * TS * ref


def test_speed_loop_integrator_stops_at_full_scale_and_skips_bad_samples() -> None:
    loop = SpeedLoop(SpeedLoopConfig(setpoint_radps=1e3, ki_V_per_rad=100.0), TS, 10.0)
    for k in range(200):
        out = loop.step(k, 0.0)
    assert out == pytest.approx(10.0)  # clipped: 200 samples x 100 V/rad x 1e-3 s x 1e3
    assert loop.step(200, math.nan) == pytest.approx(10.0)  # held, not NaN


def test_speed_loop_configuration_is_checked_and_off_by_default() -> None:
    assert not SpeedLoopConfig().active and not FirmwareConfig().speed.active
    assert SpeedLoopConfig(ki_V_per_rad=0.1).active
    with pytest.raises(ValueError, match="kp_V_per_radps"):
        SpeedLoopConfig(kp_V_per_radps=-1.0)
    with pytest.raises(ConfigError, match="ramp_s"):
        from_dict(FirmwareConfig, {"speed": {"ramp_s": -0.1}}, "firmware")


def test_the_handler_adds_the_loop_to_the_reference() -> None:
    """Without a control law the DAC gets reference + loop: at rest before the start,
    a measured speed is pushed back by kp; off, the handler writes the reference."""
    base = from_dict(FirmwareConfig, {"reference": {"bias_V": 1.0}}, "firmware")
    looped = from_dict(
        FirmwareConfig,
        {"reference": {"bias_V": 1.0}, "speed": {"start_s": 1.0, "kp_V_per_radps": 0.01}},
        "firmware",
    )
    tacho = 100  # ADC counts: 100 x 10 V / 2048 x 56.2565 rad/s per V
    velocity = tacho * 10.0 / 2048 * base.calibration.volt2radps
    for cfg, expected in ((base, 1.0), (looped, 1.0 - 0.01 * velocity)):
        isr = InterruptHandler(cfg)
        out = isr(AdcSample(0, tacho, 0, 0))
        assert out.reference_V == pytest.approx(expected, rel=1e-3)


# ------------------------------------------------------------------ the start pose


def _arm7_with(tmp_path: Path, table: str) -> Path:
    path = tmp_path / "arm.toml"
    path.write_text(
        '[scenario]\nbase = "free-motion"\nname = "a"\n[robot]\nurdf = "arm7"\n' + table
    )
    return path


@needs_arm
@pytest.mark.parametrize(
    ("table", "match"),
    [
        ("[joints.panda_joint4]\nstart_rad = 0.5\n", r"outside the URDF's limits -3\.0718"),
        ('[joints.panda_joint2]\nstart_rad = "up"\n', "expected a finite angle"),
    ],
)
def test_a_start_pose_outside_the_limits_is_a_one_line_error(
    tmp_path: Path, table: str, match: str
) -> None:
    with pytest.raises(ConfigError, match=match) as err:
        load_scenario(str(_arm7_with(tmp_path, table)))
    assert "\n" not in str(err.value)


def test_a_start_pose_needs_a_robot(tmp_path: Path) -> None:
    path = tmp_path / "rig.toml"
    path.write_text('[scenario]\nbase = "free-motion"\nname = "r"\n[joints.A]\nstart_rad = 0.3\n')
    with pytest.raises(ConfigError, match=r"joints\.A\.start_rad: a start pose is a \[robot\]"):
        load_scenario(str(path))


@needs_arm
def test_the_shipped_start_pose_and_motion_stay_inside_the_urdf_limits() -> None:
    """arm7's start angles round-trip through the scenario data, and each joint's travel
    over the run (its set point at the output for the duration, plus the 0.2 s ramp
    counted in full) stays inside the URDF's limits."""
    from hdhil.rig.layout import urdf_limits

    s = load_scenario("arm7")
    assert scenario_from_dict(scenario_data(s)) == s
    limits = urdf_limits(s.robot.path)
    for spec, (plant, fw) in zip(s.joints, s.joint_configs, strict=True):
        lo, hi = limits[spec.name]
        travel = fw.speed.setpoint_radps / plant.drivetrain.gear_ratio * s.duration_s
        end = spec.start_rad + travel
        assert lo < spec.start_rad < hi and lo < end < hi, spec.name
        assert fw.speed.active and fw.reference.wave.name == "NONE"


# ------------------------------------------------------------------ the arm's start


@needs_arm
@pytest.mark.slow
def test_an_arm_at_rest_under_its_weight_stays_put_and_brakes_hold_it(tmp_path: Path) -> None:
    """With each flexspline twisted by its link's gravity torque the links start in
    equilibrium (no link acceleration); braked, a step moves the clock and the currents
    but not the arm; released with no current the arm falls."""
    from hdhil.hostsim.plant.arm import ArmPlant
    from hdhil.hostsim.plant.multibody import LinkDynamics, shipped_robot

    s = load_scenario("arm7")
    link = LinkDynamics.from_urdf(shipped_robot("arm7"))
    q0 = [j.start_rad for j in s.joints]
    arm = ArmPlant(link, [p for p, _ in s.joint_configs], list(range(7)), q0)
    k = np.array([p.drivetrain.k_flex for p, _ in s.joint_configs])
    untwisted = [abs(arm.truth(j).link_acceleration_radps2) for j in range(7)]
    assert max(untwisted) > 1.0  # dropped onto untwisted flexsplines
    arm.rest_under_load()
    np.testing.assert_allclose(arm.state[:, 0], link.gravity(np.array(q0)) / k, rtol=1e-12)
    for j in range(7):
        assert abs(arm.truth(j).link_acceleration_radps2) < 1e-6
    arm.apply_brakes()
    before = arm.state
    arm.advance([1.0] * 7, TS)
    after = arm.state
    np.testing.assert_array_equal(after[:, [0, 1, 2, 4]], before[:, [0, 1, 2, 4]])
    assert after[:, 3] == pytest.approx([1.0 - math.exp(-TS / 4e-4)] * 7)  # the current lag
    assert arm.time == pytest.approx(TS)
    arm.release_brakes()
    for _ in range(20):
        arm.advance([0.0] * 7, TS)
    assert np.abs(arm.qd[[1, 3]]).min() > 0.01  # the shoulder and elbow sag without current


# ------------------------------------------------------------------ the goal


def _decode(trace: Path, dbcs: dict[str, Path], skip_s: float) -> dict[str, tuple[float, float]]:
    """Each joint's (raw, filtered) RMS torque error from the trace alone, as a logger
    computes it: the joint's CTRL_TPDO1 on its bus's channel paired with the latest
    TRUTH_TORQUE of the joint on the truth channel (each truth frame used once), the
    joint's telemetry in the first ``skip_s`` after its first frame left out (to half a
    1 ms period: the telemetry is decimated, every 10th cycle)."""
    import can
    import cantools

    side = json.loads(Path(f"{trace}.json").read_text())
    channels = side["channels"]
    dbs = {bus: cantools.database.load_file(path) for bus, path in dbcs.items()}
    truth_ids, tele_ids = {}, {}
    for j in side["rig"]["joints"]:
        db, name = dbs[j["bus"]], j["name"]
        truth_ids[db.get_message_by_name(f"{name}_TRUTH_TORQUE").frame_id] = name
        tele = db.get_message_by_name(f"{name}_CTRL_TPDO1").frame_id
        tele_ids[(channels[j["bus"]], tele)] = name
    bus_of = {j["name"]: j["bus"] for j in side["rig"]["joints"]}
    truth: dict[str, float | None] = dict.fromkeys(bus_of)
    first: dict[str, float | None] = dict.fromkeys(bus_of)
    sums = {name: [0, 0.0, 0.0] for name in bus_of}
    with can.BLFReader(str(trace)) as frames:
        for msg in frames:
            if msg.channel == channels["truth"] and msg.arbitration_id in truth_ids:
                name = truth_ids[msg.arbitration_id]
                decoded = dbs[bus_of[name]].decode_message(msg.arbitration_id, msg.data)
                truth[name] = decoded["T_true"]
                continue
            name = tele_ids.get((msg.channel, msg.arbitration_id))
            if name is None:
                continue
            start = first[name]
            if start is None:
                start = first[name] = msg.timestamp
            true = truth[name]
            if true is None or msg.timestamp - start < skip_s - 0.5e-3:
                continue
            truth[name] = None
            d = dbs[bus_of[name]].decode_message(msg.arbitration_id, msg.data)
            s = sums[name]
            s[0] += 1
            s[1] += (d["T_meas"] - true) ** 2
            s[2] += (d["T_filtered"] - true) ** 2
    return {n: (math.sqrt(s[1] / s[0]), math.sqrt(s[2] / s[0])) for n, s in sums.items()}


@needs_arm
@pytest.mark.slow
def test_arm7_filters_every_joint_to_a_tenth_of_its_raw_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`hdhil dbc export --scenario arm7`, `hdhil run --scenario arm7` with a BLF trace
    (its 2 s, scored from its evaluate_from_s 0.3 s), the trace decoded with python-can
    and cantools: every joint's filtered RMS error is at most 10 % of its raw one, and
    the figures are the ones `hdhil run` prints for the joint."""
    from hdhil.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["dbc", "export", "rig.dbc", "--scenario", "arm7"]) == 0
    capsys.readouterr()
    assert main(["run", "--scenario", "arm7", "--trace", "arm7.blf", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "per joint from 0.3 s" in printed
    buses = {"can0", "can1", "can2", "can3"}
    figures = _decode(tmp_path / "arm7.blf", {b: tmp_path / f"rig-{b}.dbc" for b in buses},
                      skip_s=0.3)  # fmt: skip
    assert len(figures) == 7
    for name, (raw, filtered) in figures.items():
        assert filtered <= 0.10 * raw, (name, raw, filtered)
        row = re.search(
            rf"^    {name} .* (\d+\.\d{{4}}) +(\d+\.\d{{4}}) +(\d+\.\d)%", printed, re.MULTILINE
        )
        assert row is not None, name
        assert row.groups() == (f"{raw:.4f}", f"{filtered:.4f}", f"{100 * filtered / raw:.1f}")
