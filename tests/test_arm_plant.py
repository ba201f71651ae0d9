"""An arm's plant (hostsim.plant.arm): N harmonic-drive actuators on the multibody links.

Expected values come from the single-joint :class:`Plant`, from closed forms (a pendulum,
Spong's two-link arm as in ``tests/test_multibody.py``), from energy and from the
Jacobian; none from the code under test.  AG1-like actuators: the parameters of the
[Vertechy] joint as the ``lqg-experiment`` scenario has them (``_ag1``).
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from hdhil.hostsim.plant import (
    AmplifierConfig,
    DriveTrainConfig,
    GravityConfig,
    LinkMotionConfig,
    LoadTorqueConfig,
    NonFiniteStateError,
    Plant,
    PlantConfig,
)
from hdhil.hostsim.plant_model import PlantModel

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("mujoco") is None, reason="the arm extra (hdhil[arm])"
)

if importlib.util.find_spec("mujoco") is not None:
    from hdhil.hostsim.plant.arm import ArmPlant
    from hdhil.hostsim.plant.multibody import LinkDynamics, Wrench, shipped_robot

G = 9.81
M1, C1, L1, I1 = 1.3, 0.21, 0.5, 0.031
M2, C2, I2 = 0.8, 0.17, 0.017
DT = 1e-3


def _link(name: str, mass: float, com: float, iyy: float) -> str:
    return (
        f'<link name="{name}"><inertial><origin xyz="0 0 {-com}"/><mass value="{mass}"/>'
        f'<inertia ixx="{iyy * 1.2}" ixy="0" ixz="0" iyy="{iyy}" iyz="0" '
        f'izz="{iyy * 0.5}"/></inertial></link>'
    )


def _joint(name: str, parent: str, child: str, z: float = 0.0) -> str:
    return (
        f'<joint name="{name}" type="revolute"><parent link="{parent}"/>'
        f'<child link="{child}"/><origin xyz="0 0 {z}"/><axis xyz="0 1 0"/>'
        '<limit lower="-3" upper="3" effort="50" velocity="2"/></joint>'
    )


def _urdf(tmp_path: Path, *parts: str) -> Path:
    path = tmp_path / "robot.urdf"
    path.write_text(f'<?xml version="1.0"?><robot name="t">{"".join(parts)}</robot>')
    return path


def _pendulum(tmp_path: Path) -> LinkDynamics:
    """One link hanging along -z at q = 0: gravity on it is ``-m g c sin q``."""
    return LinkDynamics.from_urdf(
        _urdf(tmp_path, '<link name="base"/>', _link("a", M1, C1, I1), _joint("j1", "base", "a"))
    )


def _two_link(tmp_path: Path) -> LinkDynamics:
    return LinkDynamics.from_urdf(
        _urdf(
            tmp_path,
            '<link name="base"/>',
            _link("a", M1, C1, I1),
            _link("b", M2, C2, I2),
            _joint("j1", "base", "a"),
            _joint("j2", "a", "b", z=-L1),
        )
    )


def _two_link_potential(q: np.ndarray) -> float:
    """Spong §7.4: the links' potential energy, angles from the downward vertical."""
    return -G * ((M1 * C1 + M2 * L1) * math.cos(q[0]) + M2 * C2 * math.cos(q[0] + q[1]))


def _frictionless(cfg: PlantConfig, c_flex: float = 0.0) -> PlantConfig:
    d = cfg.drivetrain
    drivetrain = replace(d, b_motor=0.0, coulomb_motor=0.0, b_load=0.0, coulomb_load=0.0)
    return replace(cfg, drivetrain=replace(drivetrain, c_flex=c_flex))


def _ag1() -> PlantConfig:
    """AG1 after [Vertechy] §I-II, as the lqg-experiment scenario has it: J_m 2.5 kg m²,
    k 6.3 kNm/rad, c 11.8 Nm s/rad, N = 100, motor friction 13.7 Nm saturating at 2 rad/s
    of the motor; a 20 Nm/V amplifier of 15 A and a 0.4 ms lag; no load-side friction."""
    return PlantConfig(
        amplifier=AmplifierConfig(
            gain_A_per_V=2.0, current_lag_s=4e-4, current_limit_A=15.0,
            torque_constant_Nm_per_A=0.1,
        ),
        drivetrain=DriveTrainConfig(
            gear_ratio=100.0, J_motor=2.5, b_motor=0.0, coulomb_motor=13.7,
            friction_smoothing=0.02, k_flex=6300.0, c_flex=11.8, b_load=0.0, coulomb_load=0.0,
        ),
    )  # fmt: skip


def _arm_energy(arm: ArmPlant, potential: float) -> float:
    """Motors, flexsplines and links: kinetic, elastic and potential energy (J)."""
    d, wm, wl = arm.state[:, 0], arm.state[:, 1], arm.state[:, 2]
    jm = np.array([c.drivetrain.J_motor for c in arm.cfgs])
    k = np.array([c.drivetrain.k_flex for c in arm.cfgs])
    mass = arm.link.mass_matrix(arm.q)
    return float(0.5 * jm @ wm**2 + 0.5 * k @ d**2 + 0.5 * wl @ mass @ wl + potential)


def _potential(link: LinkDynamics, q: np.ndarray, ref: np.ndarray) -> float:
    """``V(q) - V(ref)`` by Gauss-Legendre quadrature of ``gravity`` (= dV/dq) along the
    straight path: exact to round-off for the smooth trigonometric V of a rigid arm."""
    nodes, weights = np.polynomial.legendre.leggauss(12)
    step = q - ref
    return float(
        sum(
            0.5 * w * link.gravity(ref + 0.5 * (x + 1.0) * step) @ step
            for x, w in zip(nodes, weights, strict=True)
        )
    )


# ------------------------------------------------------------------ one joint = Plant


def _pendulum_runs(tmp_path: Path, substeps: int, reference: int) -> tuple[np.ndarray, ...]:
    """The pendulum as a one-joint arm and as a Plant with its inertia and gravity, both at
    ``substeps``, and the Plant at ``reference`` sub-steps, driven by the same 1.3 Hz sine
    for 2 s from 0.5 rad: (link angle, flexspline torque) of each per cycle, and the
    sample streams of the first two."""
    link = _pendulum(tmp_path)
    cfg = PlantConfig(substeps=substeps)
    single = replace(
        cfg,
        drivetrain=replace(cfg.drivetrain, J_load=I1 + M1 * C1**2),
        gravity=GravityConfig(mgl_Nm=M1 * G * C1, offset_deg=180.0),  # -mgl sin q
    )
    plant = Plant(single, seed=7)
    fine = Plant(replace(single, substeps=reference), seed=7)
    for p in (plant, fine):
        p.hold_locked(100.0 * 0.5, 0.0)  # at 0.5 rad, at rest, no twist
    arm = ArmPlant(link, [cfg], [7], q0=[0.5])
    runs: list[list[tuple[float, float]]] = [[], [], []]
    samples: list[list[tuple[int, ...]]] = [[], []]
    for n in range(2000):
        volts = 2.0 * math.sin(2.0 * math.pi * 1.3 * n * DT)
        plant.advance(volts, DT)
        fine.advance(volts, DT)
        arm.advance([volts], DT)
        truths = (plant.truth(), arm.truth(0), fine.truth())
        for run, t in zip(runs, truths, strict=True):
            run.append((t.theta_output_rad, t.T_true_Nm))
        assert truths[1].tau_g_Nm == pytest.approx(truths[0].tau_g_Nm, abs=1e-3)  # the sign
        # the torque on the link besides the joint's (gravity, bearings): 5e-3 Nm as the
        # flexspline torque (measured 1.6e-3 where it reaches 2.6 Nm)
        assert truths[1].tau_ext_Nm == pytest.approx(truths[0].tau_ext_Nm, abs=5e-3)
        samples[0].append(plant.sample())
        samples[1].append(arm.sample(0))
    return (*(np.array(r) for r in runs), *(np.array(s) for s in samples))


@pytest.mark.slow
def test_one_joint_arm_is_the_single_joint_plant(tmp_path: Path) -> None:
    """A one-joint arm whose link is a pendulum moves as the single-joint Plant with the
    pendulum's inertia and ``[plant.gravity]``, to within the Plant's own integration
    error.  Both hold the Coulomb frictions over each sub-step (a first-order error); the
    arm takes gravity at the sub-step's predicted midpoint where the Plant takes it at
    the start, and the trapezoidal rule where the Plant has its exact map (second
    order).  Over 2 s at 4 sub-steps the two differ by less than the Plant differs from
    itself at 32 sub-steps (measured: 8.7e-5 against 1.2e-4 rad, 1.8e-3 against 1.7e-2
    Nm of a torque swinging over +-10 Nm); bounds 2e-4 rad and 5e-3 Nm.  The sensors
    read the same torque, tacho and current counts with the same noise stream (a
    rounding boundary may split one by one count: in under a quarter of the samples),
    and encoder counts apart by at most the angle bound (2e-4 rad x 100 x 8000 / 2 pi:
    26 counts)."""
    plant, arm, fine, plant_samples, arm_samples = _pendulum_runs(tmp_path, 4, 32)
    apart = np.abs(arm - plant).max(axis=0)
    plant_error = np.abs(plant - fine).max(axis=0)
    assert np.all(apart < plant_error)
    assert apart[0] < 2e-4 and apart[1] < 5e-3
    diffs = np.abs(plant_samples - arm_samples)
    assert diffs[:, :3].max() <= 1
    assert (diffs[:, :3] == 0).all(axis=1).mean() > 0.75
    encoder = np.minimum(diffs[:, 3], 65536 - diffs[:, 3])  # the wrapping count
    assert encoder.max() <= 26


# ------------------------------------------------------------------ statics


def _held_arm(tmp_path: Path, sign: float) -> tuple[ArmPlant, np.ndarray, np.ndarray]:
    link = _two_link(tmp_path)
    q0 = np.array([0.4, -0.7])
    cfg = _frictionless(PlantConfig(), c_flex=5.0)  # nothing but the motors can hold it
    arm = ArmPlant(link, [cfg, cfg], [1, 2], q0=q0)
    hold = link.gravity(q0)  # what the joints must supply
    volts = sign * hold / cfg.torque_per_volt
    arm.set_state(q0, twist=sign * hold / cfg.drivetrain.k_flex, current=volts)
    return arm, q0, volts


def test_two_joint_arm_holds_against_gravity(tmp_path: Path) -> None:
    """Motors supplying the gravity torques hold a frictionless two-joint arm where it is
    (static equilibrium): over 0.5 s nothing moves beyond round-off; the truth says
    gravity is balanced by the flexsplines ([Vertechy]'s sign: tau_g = -gravity).  Load
    torques at the outputs equal to the gravity torques hold it too, motors off."""
    arm, q0, volts = _held_arm(tmp_path, 1.0)
    for _ in range(500):
        arm.advance(volts, DT)
    assert np.abs(arm.q - q0).max() < 1e-12
    assert np.abs(arm.qd).max() < 1e-10
    for k in range(2):
        truth = arm.truth(k)
        assert truth.T_true_Nm == pytest.approx(-truth.tau_g_Nm, rel=1e-9)
        assert abs(truth.link_acceleration_radps2) < 1e-6
        assert truth.tau_ext_Nm == pytest.approx(truth.tau_g_Nm, rel=1e-9)
    # load torques at the outputs (one held, one a profile) hold it as well, motors off
    link = arm.link
    hold = link.gravity(q0)
    cfg = _frictionless(PlantConfig(), c_flex=5.0)
    profile = replace(cfg, load=LoadTorqueConfig(kind="constant", bias_Nm=float(hold[1])))
    loaded = ArmPlant(link, [cfg, profile], [1, 2], q0=q0)
    loaded.set_load_torque(0, float(hold[0]))
    for _ in range(200):
        loaded.advance([0.0, 0.0], DT)
    assert np.abs(loaded.q - q0).max() < 1e-12
    assert [loaded.truth(k).tau_l_Nm for k in range(2)] == pytest.approx(hold, rel=1e-12)
    # the same arm with its motors pushing the wrong way falls
    arm, q0, volts = _held_arm(tmp_path, -1.0)
    for _ in range(100):
        arm.advance(volts, DT)
    assert np.abs(arm.q - q0).max() > 0.02


def _worn(stroke: LinkMotionConfig) -> PlantConfig:
    """A frictionless joint with a lightly damped flexspline, its motor unpowered, and a
    person's ``stroke`` on its link."""
    return replace(_frictionless(PlantConfig(), c_flex=5.0), link=stroke)


def test_person_holds_the_arm_through_their_impedance(tmp_path: Path) -> None:
    """A person holding a two-link arm at a posture (kind hold) with a joint stiffness
    and damping, motors off: the arm settles where the person's spring balances the
    rest, found here from the statics alone (brentq on the link's gravity).  Carrying
    the weight, a 2 Nm load on joint 0 deflects it by 2 Nm / K and joint 1 not at all;
    not carrying it, the arm sags to where K (q_p - q) equals gravity.  The truth's
    tau_l is the person's torque, here the load's negative plus, carrying, gravity's."""
    from scipy.optimize import brentq

    link = _two_link(tmp_path)
    k, d = 40.0, 8.0
    posture = LinkMotionConfig(
        kind="hold", offset_deg=20.0, stiffness_Nm_per_rad=k, damping_Nms_per_rad=d,
        holds_weight=True,
    )  # fmt: skip
    qp = math.radians(20.0)
    arm = ArmPlant(link, [_worn(posture), _worn(posture)], [1, 2])
    assert arm.q == pytest.approx([qp, qp], abs=1e-15)  # starts where the person holds it
    arm.set_load_torque(0, 2.0)
    for _ in range(4000):
        arm.advance([0.0, 0.0], DT)
    assert arm.q == pytest.approx([qp + 2.0 / k, qp], abs=1e-6)
    assert np.abs(arm.qd).max() < 1e-6
    held = link.gravity(arm.q)
    assert [arm.truth(j).tau_l_Nm for j in range(2)] == pytest.approx(
        [2.0 + (k * (qp - arm.q[0]) + held[0]), k * (qp - arm.q[1]) + held[1]], abs=1e-6
    )
    assert arm.truth(0).tau_l_Nm - 2.0 == pytest.approx(-2.0 + held[0], abs=1e-5)
    # not carrying the weight: each joint sags until the spring holds the links
    light = replace(posture, holds_weight=False)
    arm = ArmPlant(link, [_worn(light), _worn(light)], [1, 2])
    for _ in range(6000):
        arm.advance([0.0, 0.0], DT)
    assert np.abs(arm.qd).max() < 1e-6
    q1 = arm.q[1]
    q0 = brentq(lambda x: k * (qp - x) - link.gravity(np.array([x, q1]))[0], -1.0, 1.0)
    assert arm.q[0] == pytest.approx(q0, abs=1e-6)
    assert k * (qp - q1) == pytest.approx(link.gravity(arm.q)[1], abs=1e-4)
    assert abs(arm.q[0] - qp) > 0.05  # it did sag


def test_person_moves_the_arm_along_their_stroke(tmp_path: Path) -> None:
    """A stiff person moving both joints along the person-like stroke (the
    lqg-experiment's kind) carries the arm with it: it starts on the stroke, moving with
    it, and follows it within the lag of the impedance; the person's torque in the
    truth is K (q_p - q) + D (qd_p - qd) + the weight."""
    link = _two_link(tmp_path)
    k, d = 400.0, 20.0
    strokes = [
        LinkMotionConfig(kind="person", amplitude_deg=30.0, motion_seed=s, horizon_s=4.0,
                         stiffness_Nm_per_rad=k, damping_Nms_per_rad=d, holds_weight=True)
        for s in (1, 2)
    ]  # fmt: skip
    arm = ArmPlant(link, [_worn(s) for s in strokes], [1, 2])
    assert arm.q == pytest.approx([s.angle(0.0) for s in strokes], abs=1e-15)
    assert arm.qd == pytest.approx([s.velocity(0.0) for s in strokes], abs=1e-15)
    worst = 0.0
    for _ in range(2000):
        arm.advance([0.0, 0.0], DT)
        t = arm.time
        qp = np.array([s.angle(t) for s in strokes])
        worst = max(worst, float(np.abs(arm.q - qp).max()))
    assert 0.0 < worst < 0.02  # 30 deg strokes followed within about a degree
    qdp = np.array([s.velocity(arm.time) for s in strokes])
    expected = k * (qp - arm.q) + d * (qdp - arm.qd) + link.gravity(arm.q)
    assert [arm.truth(j).tau_l_Nm for j in range(2)] == pytest.approx(expected, abs=1e-9)


def test_person_refusals(tmp_path: Path) -> None:
    link = _two_link(tmp_path)
    imposed = _worn(LinkMotionConfig(kind="sine", amplitude_deg=10.0))
    with pytest.raises(ValueError, match="a person moves it through an impedance"):
        ArmPlant(link, [imposed, imposed], [1, 2])
    bearing = _worn(
        LinkMotionConfig(kind="hold", stiffness_Nm_per_rad=10.0, bearing_coulomb_Nm=1.0)
    )
    with pytest.raises(ValueError, match=r"coulomb_load, not plant\.link\.bearing_coulomb_Nm"):
        ArmPlant(link, [bearing, bearing], [1, 2])
    with pytest.raises(ValueError, match="for a joint of an arm"):
        Plant(_worn(LinkMotionConfig(kind="hold", stiffness_Nm_per_rad=10.0)), 1)
    with pytest.raises(ValueError, match="kind hold, sine or person"):
        LinkMotionConfig(holds_weight=True)
    with pytest.raises(ValueError, match="stiffness_Nm_per_rad"):
        LinkMotionConfig(kind="hold", stiffness_Nm_per_rad=-1.0)


# ------------------------------------------------------------------ energy


@pytest.mark.slow
def test_unforced_frictionless_arm_keeps_its_energy(tmp_path: Path) -> None:
    """Motors off, no friction, no damping: a swinging two-joint arm on its undamped
    flexsplines has constant energy; the step keeps it within 1e-4 of the potential
    energy's span over 2 s (measured 1.2e-5; with gravity taken at the start of each
    sub-step instead of its predicted midpoint the energy drifts, 6e-4 after 2 s and
    growing linearly)."""
    link = _two_link(tmp_path)
    cfg = replace(_frictionless(PlantConfig()), amplifier=AmplifierConfig(current_lag_s=0.0))
    q0 = np.array([1.2, -0.6])
    arm = ArmPlant(link, [cfg, cfg], [1, 2], q0=q0)
    span = G * 2.0 * (M1 * C1 + M2 * L1 + M2 * C2)
    e0 = _arm_energy(arm, _two_link_potential(q0))
    errors, speed = [], 0.0
    for _ in range(2000):
        arm.advance([0.0, 0.0], DT)
        errors.append(abs(_arm_energy(arm, _two_link_potential(arm.q)) - e0) / span)
        speed = max(speed, float(np.abs(arm.qd).max()))
    assert speed > 2.0  # it swings
    assert max(errors) < 1e-4


# ------------------------------------------------------------------ the shipped arms


@pytest.mark.slow
@pytest.mark.parametrize("robot", ["arm7", "rehabexos"])
@pytest.mark.parametrize("substeps", [1, 4])
def test_coupling_is_stable_at_1_ms(robot: str, substeps: int) -> None:
    """AG1 actuators (``_ag1``) on every joint of a shipped arm, released at 1 ms steps
    from a pose where gravity pulls every joint, the motors off: the arm is passive (the
    flexspline damper and the motor friction only take energy out), so the energy of
    motors, springs and links must never rise above its start, and the flexspline
    vibrations must die out (the twist settles to what gravity loads it with).  At this
    pose the Panda wrist's link has 4.7e-3 kg m² (the smallest eigenvalue of ``M``), so
    with one sub-step an explicit step is past its bounds (the joint mode at 1.2e3 rad/s
    is within ``omega h < 2``, but the damper's rate ``c / lambda_min`` is 2.5e3 /s,
    ``c h`` = 2.5 > 2): an explicit coupling fails this case, the trapezoidal one not."""
    link = LinkDynamics.from_urdf(shipped_robot(robot))
    cfg = replace(_ag1(), substeps=substeps)
    n = link.size
    q0 = (
        np.array([0.3, -0.5, 0.4, -1.8, 0.5, 1.6, 0.3])[:n]
        if n == 7
        else np.array([0.6, 0.8, 0.3, 1.0])
    )
    arm = ArmPlant(link, [cfg] * n, list(range(n)), q0=q0)
    arm.prepare(DT)
    e0 = _arm_energy(arm, 0.0)
    top = e0
    for step in range(1000):
        arm.advance(np.zeros(n), DT)
        if step % 10 == 9:
            energy = _arm_energy(arm, _potential(link, arm.q, q0))
            top = max(top, energy)
    span = float(np.abs(link.gravity(q0)).sum())  # J per rad of motion, a scale
    assert top - e0 < 1e-3 * span
    assert np.all(np.isfinite(arm.state))
    twist_rate = np.abs(arm.state[:, 1] - arm.state[:, 2])  # d' = w_m - w_l
    assert twist_rate.max() < 1e-2


def test_force_at_the_handle_moves_the_joints_as_the_jacobian_says() -> None:
    """A person pushing the RehabExos handle (no gravity, motors off, at rest): the
    joints start to move as ``(M + J_m)^-1 J^T w`` says, with its signs (over 0.1 s
    ``a t^2 / 2`` with each link ahead of its motor by the twist ``J_m a / k`` that
    accelerates the motor), and the force does positive work; the truth reports
    ``J^T w`` as each joint's ``tau_l``."""
    link = LinkDynamics.from_urdf(shipped_robot("rehabexos"), gravity=(0.0, 0.0, 0.0))
    cfg = _frictionless(_ag1(), c_flex=11.8)
    q0 = np.array([0.5, 0.7, 0.3, 1.1])
    arm = ArmPlant(link, [cfg] * 4, [0, 1, 2, 3], q0=q0)
    push = Wrench("handle", force=(12.0, -5.0, 8.0))
    arm.set_wrenches(push)
    jtw = link.external_torques(q0, push)
    for k in range(4):
        assert arm.truth(k).tau_l_Nm == pytest.approx(jtw[k], rel=1e-12)
    inertia = link.mass_matrix(q0) + np.diag([cfg.drivetrain.J_motor] * 4)
    accel = np.linalg.solve(inertia, jtw)  # the rigid joints' acceleration
    expected = accel * (0.5 * 0.1**2 + cfg.drivetrain.J_motor / cfg.drivetrain.k_flex)
    for _ in range(100):
        arm.advance(np.zeros(4), DT)
    moved = arm.q - q0
    assert np.sign(moved).tolist() == np.sign(expected).tolist()
    assert moved == pytest.approx(expected, rel=0.1)  # M(q) moves, the joint mode rings
    assert float(jtw @ arm.qd) > 0.0  # w^T J qd: the handle moves along the force


# ------------------------------------------------------------------ N drives, one arm


def test_each_joint_is_a_drive_plant(tmp_path: Path) -> None:
    """ArmJoint is a PlantModel; the rig advances the arm once, then every drive's
    advance finds it there with its own input, and reads its own joint; with an input
    source the first drive's advance moves the arm for all of them."""
    link = _two_link(tmp_path)
    cfg = PlantConfig()
    arm = ArmPlant(link, [cfg, cfg], [3, 4], q0=[0.2, 0.1])
    twin = ArmPlant(link, [cfg, cfg], [3, 4], q0=[0.2, 0.1])
    views = [arm.joint(0), arm.joint(1)]
    assert all(isinstance(v, PlantModel) for v in views)
    inputs = [0.5, -0.3]
    arm.advance(inputs, DT)  # the rig, before SYNC
    for view, volts in zip(views, inputs, strict=True):
        view.advance(volts, DT)  # each drive at its SYNC
    twin.input_source = lambda: inputs
    twin.joint(0).advance(0.5, DT)  # the first drive moves the arm...
    twin.joint(1).advance(-0.3, DT)  # ...the second finds it moved
    assert twin.time == arm.time == views[1].time == pytest.approx(DT)
    for k in range(2):
        assert views[k].sample() == twin.sample(k)
        assert views[k].truth() == twin.truth(k)
    with pytest.raises(ValueError, match="held"):
        arm.advance(inputs, DT)
        views[0].advance(0.4, DT)
    with pytest.raises(ValueError, match="the arm is at"):
        views[1].advance(-0.3, 2 * DT)


def test_refusals_and_non_finite_state(tmp_path: Path) -> None:
    link = _two_link(tmp_path)
    cfg = PlantConfig()
    with pytest.raises(ValueError, match="2 actuated joints"):
        ArmPlant(link, [cfg], [0])
    with pytest.raises(ValueError, match="gravity comes from the URDF"):
        ArmPlant(link, [cfg, replace(cfg, gravity=GravityConfig(mgl_Nm=1.0))], [0, 1])
    with pytest.raises(ValueError, match=r"share plant\.substeps"):
        ArmPlant(link, [cfg, replace(cfg, substeps=2)], [0, 1])
    arm = ArmPlant(link, [cfg, cfg], [0, 1])
    arm.set_load_torque(0, 1e308)
    arm.set_load_torque(1, 1e308)
    state = arm.state
    with pytest.raises(NonFiniteStateError):
        for _ in range(10):
            arm.advance([0.0, 0.0], DT)
    assert np.all(np.isfinite(arm.state)) and arm.state.shape == state.shape


@pytest.mark.slow
def test_two_drive_nodes_share_one_arm(tmp_path: Path, bus_harness) -> None:
    """Two CiA 402 drives (node-IDs 2 and 3) on one bus, each around one joint of the
    arm: at every SYNC the first drive's advance moves the whole arm once with both
    drives' held inputs (``input_source``), and each drive reads its own joint: its
    samples are those of a twin arm stepped by hand with the same inputs."""
    from hdhil.dbc import codec
    from hdhil.hostsim.drive import DriveConfig, DriveNode

    link = _two_link(tmp_path)
    cfg = PlantConfig()
    arm = ArmPlant(link, [cfg, cfg], [5, 6], q0=[0.3, -0.2])
    twin = ArmPlant(link, [cfg, cfg], [5, 6], q0=[0.3, -0.2])
    harness = bus_harness("t-arm")
    drives = [
        harness.add(DriveNode(harness.bus(), arm.joint(k), DriveConfig(node_id=2 + k)))
        for k in range(2)
    ]
    inputs: list[list[float]] = []

    def held() -> list[float]:
        inputs.append([d.io.step_V for d in drives])
        return inputs[-1]

    arm.input_source = held
    for d in drives:
        d.boot(0.0)
    harness.send(0x000, bytes((1, 0)))  # NMT start, all nodes
    harness.pump()
    command = codec("control", "DRIVE_RPDO1")
    for cycle in range(60):
        harness.tick()
        harness.send_sync()
        harness.pump()
        cw = (0x06, 0x07, 0x0F)[min(cycle, 2)]
        for node_id in (2, 3):  # each drive's RPDO1 at its node-ID (0x200 + node-ID)
            harness.send(0x200 + node_id, command.encode(600, cw, cycle & 0xFF))
        harness.pump()
        harness.k += 1
        if cycle:  # the first SYNC marks t(0)
            twin.advance(inputs[-1], DT)
        assert [d.io.sample for d in drives] == [twin.sample(0), twin.sample(1)]
    assert len(inputs) == 59 and arm.time == pytest.approx(59 * DT)
    assert inputs[-1] == [2.9296875, 2.9296875]  # both enabled, each by its own command
    assert arm.truth(0) == twin.truth(0)


def test_held_friction_bound_is_checked(tmp_path: Path) -> None:
    """A Coulomb friction too sharp for the sub-step (``h C / (eps J) > 2``) is named by
    ``prepare`` before a run, on the motor (``J_m``) and on the link (the smallest
    eigenvalue of ``M``); more sub-steps lift it."""
    link = _two_link(tmp_path)
    cfg = PlantConfig()
    sharp = replace(cfg, drivetrain=replace(cfg.drivetrain, coulomb_load=5.0))
    arm = ArmPlant(link, [cfg, sharp], [0, 1])
    lam = float(np.linalg.eigvalsh(link.mass_matrix(np.zeros(2)))[0])
    h = DT / cfg.substeps
    assert h * 5.0 / (0.01 * lam) > 2.0  # past the bound on the link
    with pytest.raises(ValueError, match=r"joint j2: coulomb_load 5 Nm"):
        arm.prepare(DT)
    fine = replace(sharp, substeps=64)
    ArmPlant(link, [replace(cfg, substeps=64), fine], [0, 1]).prepare(DT)
    motor = replace(cfg, drivetrain=replace(cfg.drivetrain, coulomb_motor=500.0))
    assert "coulomb_motor" in ArmPlant(link, [motor, cfg], [0, 1]).step_problems(DT)[0]
