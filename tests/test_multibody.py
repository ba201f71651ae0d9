"""Multibody link dynamics from a URDF (hostsim.plant.multibody) against closed forms.

Every expected value is computed here with numpy from the textbook equations of a
pendulum and a two-link planar arm (M. W. Spong, S. Hutchinson, M. Vidyasagar, *Robot
Modeling and Control*, §7.4), not with the library under test.  The test robots hang
along -z at q = 0 and turn about the y axis: a link's centre of mass at distance ``c``
from its joint lies at ``(-c sin q, 0, -c cos q)``, so the gravity torque is
``m g c sin q``.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from hdhil.core.errors import UserError
from hdhil.hostsim.plant.multibody import (
    SHIPPED_ROBOTS,
    LinkDynamics,
    Wrench,
    shipped_robot,
)

needs_mujoco = pytest.mark.skipif(
    importlib.util.find_spec("mujoco") is None, reason="the arm extra (hdhil[arm])"
)

G = 9.81
# two links: mass, centre of mass from the joint, length, inertia about the centre of
# mass around the joint axis (y); the x and z inertias differ so a wrong axis shows
M1, C1, L1, I1 = 1.3, 0.21, 0.5, 0.031
M2, C2, L2, I2 = 0.8, 0.17, 0.4, 0.017


def _link(name: str, mass: float, com: float, iyy: float) -> str:
    return (
        f'<link name="{name}"><inertial><origin xyz="0 0 {-com}"/><mass value="{mass}"/>'
        f'<inertia ixx="{iyy * 1.2}" ixy="0" ixz="0" iyy="{iyy}" iyz="0" '
        f'izz="{iyy * 0.5}"/></inertial></link>'
    )


def _joint(name: str, parent: str, child: str, z: float = 0.0, kind: str = "revolute") -> str:
    limit = '<limit lower="-3" upper="3" effort="50" velocity="2"/>'
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
        f'<origin xyz="0 0 {z}"/><axis xyz="0 1 0"/>{limit if kind != "fixed" else ""}'
        "</joint>"
    )


def _urdf(tmp_path: Path, *parts: str, name: str = "robot.urdf") -> Path:
    path = tmp_path / name
    path.write_text(f'<?xml version="1.0"?><robot name="t">{"".join(parts)}</robot>')
    return path


def _pendulum(tmp_path: Path, kind: str = "revolute") -> Path:
    """Link a on joint j1, with a massless tip link welded at its end."""
    return _urdf(
        tmp_path,
        '<link name="base"/>',
        _link("a", M1, C1, I1),
        '<link name="tip"/>',
        _joint("j1", "base", "a", kind=kind),
        _joint("tip_mount", "a", "tip", z=-L1, kind="fixed"),
    )


def _two_link(tmp_path: Path, *, reversed_order: bool = False) -> Path:
    joints = [_joint("j1", "base", "a"), _joint("j2", "a", "b", z=-L1)]
    if reversed_order:
        joints.reverse()
    return _urdf(
        tmp_path,
        '<link name="base"/>',
        _link("a", M1, C1, I1),
        _link("b", M2, C2, I2),
        *joints,
    )


def _two_link_closed_form(q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Spong's M(q) and b(q, qd) = C(q, qd) qd + g(q), angles from the downward vertical."""
    c2 = math.cos(q[1])
    m11 = M1 * C1**2 + M2 * (L1**2 + C2**2 + 2 * L1 * C2 * c2) + I1 + I2
    m12 = M2 * (C2**2 + L1 * C2 * c2) + I2
    m22 = M2 * C2**2 + I2
    h = -M2 * L1 * C2 * math.sin(q[1])
    coriolis = np.array([h * (2 * qd[0] * qd[1] + qd[1] ** 2), -h * qd[0] ** 2])
    grav = G * np.array(
        [
            (M1 * C1 + M2 * L1) * math.sin(q[0]) + M2 * C2 * math.sin(q[0] + q[1]),
            M2 * C2 * math.sin(q[0] + q[1]),
        ]
    )
    return np.array([[m11, m12], [m12, m22]]), coriolis + grav


def _two_link_energy(q: np.ndarray, qd: np.ndarray) -> float:
    mass, _ = _two_link_closed_form(q, np.zeros(2))
    height = -(M1 * C1 + M2 * L1) * math.cos(q[0]) - M2 * C2 * math.cos(q[0] + q[1])
    return 0.5 * float(qd @ mass @ qd) + G * height


@needs_mujoco
@pytest.mark.parametrize("kind", ["revolute", "continuous"])
def test_pendulum_gravity_and_acceleration(tmp_path: Path, kind: str) -> None:
    dyn = LinkDynamics.from_urdf(_pendulum(tmp_path, kind), gravity=(0.0, 0.0, -G))
    inertia = I1 + M1 * C1**2
    for angle in (-2.0, -0.4, 0.0, 0.7, 1.9):
        q, tau = np.array([angle]), np.array([0.8])
        torque = M1 * G * C1 * math.sin(angle)
        assert dyn.gravity(q) == pytest.approx([torque], abs=1e-12)
        assert dyn.mass_matrix(q) == pytest.approx(np.array([[inertia]]), rel=1e-12)
        # the bias of a single joint has no velocity term
        assert dyn.bias(q, np.array([3.0])) == pytest.approx([torque], abs=1e-12)
        qdd = dyn.forward_dynamics(q, np.array([3.0]), tau)
        assert qdd == pytest.approx([(0.8 - torque) / inertia], rel=1e-12)


@needs_mujoco
def test_continuous_joint_has_no_position_limits(tmp_path: Path) -> None:
    dyn = LinkDynamics.from_urdf(_pendulum(tmp_path, "continuous"))
    (joint,) = dyn.joints
    assert (joint.kind, joint.lower, joint.upper) == ("continuous", -math.inf, math.inf)
    assert (joint.effort, joint.velocity) == (50.0, 2.0)
    revolute = LinkDynamics.from_urdf(_pendulum(tmp_path, "revolute")).joints[0]
    assert (revolute.lower, revolute.upper) == (-3.0, 3.0)


@needs_mujoco
def test_two_link_arm_mass_matrix_bias_and_gravity(tmp_path: Path) -> None:
    dyn = LinkDynamics.from_urdf(_two_link(tmp_path), gravity=(0.0, 0.0, -G))
    assert dyn.names == ("j1", "j2")
    rng = np.random.default_rng(3)
    for _ in range(5):
        q, qd = rng.uniform(-2.5, 2.5, 2), rng.uniform(-3.0, 3.0, 2)
        mass, bias = _two_link_closed_form(q, qd)
        _, grav = _two_link_closed_form(q, np.zeros(2))
        assert dyn.mass_matrix(q) == pytest.approx(mass, rel=1e-12)
        assert dyn.gravity(q) == pytest.approx(grav, abs=1e-12)
        assert dyn.bias(q, qd) == pytest.approx(bias, abs=1e-12)
        tau = rng.uniform(-5.0, 5.0, 2)
        expected = np.linalg.solve(mass, tau - bias)
        assert dyn.forward_dynamics(q, qd, tau) == pytest.approx(expected, rel=1e-9)


@needs_mujoco
def test_arrays_follow_the_urdf_joint_order(tmp_path: Path) -> None:
    """The file lists the elbow before the shoulder: every array is in the file's order."""
    dyn = LinkDynamics.from_urdf(_two_link(tmp_path, reversed_order=True), gravity=(0, 0, -G))
    assert dyn.names == ("j2", "j1")
    q, qd = np.array([0.9, -0.6]), np.array([1.5, -2.0])  # j2, j1
    flip = [1, 0]
    mass, bias = _two_link_closed_form(q[flip], qd[flip])
    assert dyn.mass_matrix(q) == pytest.approx(mass[np.ix_(flip, flip)], rel=1e-12)
    assert dyn.bias(q, qd) == pytest.approx(bias[flip], abs=1e-12)
    tau = np.array([0.5, 2.0])
    expected = np.linalg.solve(mass, tau[flip] - bias)[flip]
    assert dyn.forward_dynamics(q, qd, tau) == pytest.approx(expected, rel=1e-9)
    q2, qd2 = dyn.step(q, qd, tau, 1e-3)
    assert qd2 == pytest.approx(qd + 1e-3 * expected, rel=1e-9)
    assert q2 == pytest.approx(q + 1e-3 * qd2, rel=1e-12)


def _energy_error(dyn: LinkDynamics, dt: float) -> tuple[float, float]:
    """Released from rest, 1 s unforced: the largest energy error, the fastest joint."""
    q, qd, tau = np.array([1.2, -0.7]), np.zeros(2), np.zeros(2)
    energy0 = _two_link_energy(q, qd)
    error, fastest = 0.0, 0.0
    for _ in range(round(1.0 / dt)):
        q, qd = dyn.step(q, qd, tau, dt)
        error = max(error, abs(_two_link_energy(q, qd) - energy0))
        fastest = max(fastest, float(np.abs(qd).max()))
    return error, fastest


@needs_mujoco
def test_unforced_arm_keeps_its_energy(tmp_path: Path) -> None:
    """Semi-implicit Euler on a swinging double pendulum: at 1 kHz its energy (of the
    closed form) stays within 0.25 % of the span of its potential energy over 1 s (it
    is 0.14 %; explicit Euler's error is 0.45 %), and the error halves with the step
    (first order)."""
    dyn = LinkDynamics.from_urdf(_two_link(tmp_path), gravity=(0.0, 0.0, -G))
    span = 2 * G * (M1 * C1 + M2 * L1 + M2 * C2)  # stretched up less stretched down
    error, fastest = _energy_error(dyn, 1e-3)
    assert fastest > 5.0  # it did swing
    assert error < 2.5e-3 * span
    half, _ = _energy_error(dyn, 5e-4)
    assert 0.4 < half / error < 0.6


@needs_mujoco
def test_massless_link_between_two_joints(tmp_path: Path) -> None:
    """Two axes through one point, a URDF's virtual link between them (x then y):
    gravity and inertia of the closed form, the virtual link adding nothing."""
    path = _urdf(
        tmp_path,
        '<link name="base"/><link name="virtual"/>',
        _link("a", M1, C1, I1),
        '<joint name="jx" type="revolute"><parent link="base"/><child link="virtual"/>'
        '<axis xyz="1 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>',
        _joint("jy", "virtual", "a"),
    )
    dyn = LinkDynamics.from_urdf(path, gravity=(0.0, 0.0, -G))
    ixx, iyy, izz = 1.2 * I1, I1, 0.5 * I1
    for qx, qy in ((0.3, 0.5), (-1.0, 0.2), (0.7, -1.3)):
        q = np.array([qx, qy])
        # centre of mass at Rx(qx) Ry(qy) (0, 0, -c): height -c cos qx cos qy
        grav = M1 * G * C1 * np.array([math.sin(qx) * math.cos(qy), math.cos(qx) * math.sin(qy)])
        assert dyn.gravity(q) == pytest.approx(grav, abs=1e-12)
        # angular velocity in a's frame (qdx cos qy, qdy, qdx sin qy)
        mxx = (M1 * C1**2 + ixx) * math.cos(qy) ** 2 + izz * math.sin(qy) ** 2
        mass = np.diag([mxx, M1 * C1**2 + iyy])
        assert dyn.mass_matrix(q) == pytest.approx(mass, rel=1e-9, abs=1e-12)


@needs_mujoco
def test_fixed_child_mass_adds_to_its_parent(tmp_path: Path) -> None:
    """A payload welded by a fixed joint 0.45 m down link a, 0.25 m off its axis."""
    mp, dz, dx, ip = 0.6, 0.45, 0.25, 0.004
    path = _urdf(
        tmp_path,
        '<link name="base"/>',
        _link("a", M1, C1, I1),
        _link("payload", mp, 0.0, ip),
        _joint("j1", "base", "a"),
        f'<joint name="weld" type="fixed"><parent link="a"/><child link="payload"/>'
        f'<origin xyz="{dx} 0 {-dz}"/></joint>',
    )
    dyn = LinkDynamics.from_urdf(path, gravity=(0.0, 0.0, -G))
    assert dyn.names == ("j1",) and "payload" in dyn.links
    inertia = I1 + M1 * C1**2 + ip + mp * (dx**2 + dz**2)
    for angle in (-1.1, 0.0, 0.5):
        q = np.array([angle])
        # payload at (dx cos q - dz sin q, ., -dx sin q - dz cos q): height derivative
        torque = G * (
            M1 * C1 * math.sin(angle) + mp * (dz * math.sin(angle) - dx * math.cos(angle))
        )
        assert dyn.gravity(q) == pytest.approx([torque], abs=1e-12)
        assert dyn.mass_matrix(q) == pytest.approx(np.array([[inertia]]), rel=1e-12)


@needs_mujoco
def test_external_wrench_on_a_welded_link(tmp_path: Path) -> None:
    """A force at the tip (a link welded 0.5 m down the pendulum), a force at a point of
    link a, a pure torque: each gives the joint torque of the lever arm."""
    dyn = LinkDynamics.from_urdf(_pendulum(tmp_path), gravity=(0.0, 0.0, -G))
    inertia = I1 + M1 * C1**2
    angle = 0.6
    q, qd, tau = np.array([angle]), np.array([0.4]), np.array([0.3])
    fx, fz = 7.0, -4.0
    # tip at (-L sin q, 0, -L cos q): d/dq = (-L cos q, 0, L sin q)
    lever = -L1 * math.cos(angle) * fx + L1 * math.sin(angle) * fz
    tip = Wrench("tip", force=(fx, 0.0, fz))
    assert dyn.external_torques(q, tip) == pytest.approx([lever], rel=1e-12)
    same = Wrench("a", force=(fx, 0.0, fz), point=(0.0, 0.0, -L1))
    assert dyn.external_torques(q, same) == pytest.approx([lever], rel=1e-12)
    twist = Wrench("a", torque=(0.0, 2.5, 0.0))
    assert dyn.external_torques(q, twist) == pytest.approx([2.5], rel=1e-12)
    grav = M1 * G * C1 * math.sin(angle)
    qdd = dyn.forward_dynamics(q, qd, tau, [tip, twist])
    assert qdd == pytest.approx([(0.3 + lever + 2.5 - grav) / inertia], rel=1e-12)
    # no wrench, no extra torque: the same call without it is the plain pendulum
    assert dyn.forward_dynamics(q, qd, tau) == pytest.approx([(0.3 - grav) / inertia])


@needs_mujoco
def test_wrench_on_an_unknown_link_is_one_line(tmp_path: Path) -> None:
    dyn = LinkDynamics.from_urdf(_pendulum(tmp_path))
    with pytest.raises(UserError, match="no link 'hand'") as err:
        dyn.forward_dynamics(np.zeros(1), np.zeros(1), np.zeros(1), Wrench("hand"))
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("kind", ["prismatic", "floating", "planar"])
def test_joint_types_it_cannot_emulate_are_refused(tmp_path: Path, kind: str) -> None:
    path = _urdf(
        tmp_path,
        '<link name="base"/>',
        _link("a", M1, C1, I1),
        _link("b", M2, C2, I2),
        _joint("shoulder", "base", "a"),
        _joint("slide", "a", "b", z=-L1, kind=kind),
    )
    with pytest.raises(UserError) as err:
        LinkDynamics.from_urdf(path)
    message = str(err.value)
    assert "\n" not in message
    assert f"joint 'slide' is {kind}" in message
    assert str(path) in message


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("<robot", "not XML"),
        ('<sdf version="1.6"/>', "not a URDF"),
        ('<robot name="r"><link name="a"/></robot>', "no revolute or continuous joint"),
        (
            '<robot name="r"><link name="a"/><link name="b"/><joint name="j" type="revolute">'
            '<parent link="a"/><child link="b"/><axis xyz="0 0 1"/></joint></robot>',
            "joint 'j' is revolute without <limit>",
        ),
    ],
)
def test_bad_files_are_one_line(tmp_path: Path, text: str, expected: str) -> None:
    path = tmp_path / "bad.urdf"
    path.write_text(text)
    with pytest.raises(UserError, match=expected) as err:
        LinkDynamics.from_urdf(path)
    assert "\n" not in str(err.value)


def test_a_joint_moving_no_mass_is_refused(tmp_path: Path) -> None:
    path = _urdf(
        tmp_path,
        '<link name="base"/>',
        _link("a", M1, C1, I1),
        '<link name="empty"/><link name="empty_tip"/>',
        _joint("j1", "base", "a"),
        _joint("j2", "a", "empty", z=-L1),
        _joint("tip_mount", "empty", "empty_tip", kind="fixed"),
    )
    with pytest.raises(UserError, match="joint 'j2' moves no mass") as err:
        LinkDynamics.from_urdf(path)
    assert "\n" not in str(err.value)


@needs_mujoco
def test_an_inertia_no_body_can_have_is_refused(tmp_path: Path) -> None:
    link = (
        '<link name="odd"><inertial><mass value="1"/>'
        '<inertia ixx="0.1" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>'
    )
    path = _urdf(tmp_path, '<link name="base"/>', link, _joint("j1", "base", "odd"))
    with pytest.raises(UserError, match=r"A \+ B >= C \(link 'odd'\)") as err:
        LinkDynamics.from_urdf(path)
    assert "\n" not in str(err.value) and "balanceinertia" not in str(err.value)


def test_missing_file_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"cannot read .*missing\.urdf") as err:
        LinkDynamics.from_urdf(tmp_path / "missing.urdf")
    assert "\n" not in str(err.value)


def test_without_mujoco_the_error_names_the_extra(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "mujoco", None)  # import mujoco raises ImportError
    with pytest.raises(UserError, match=r"pip install 'hdhil\[arm\]'") as err:
        LinkDynamics.from_urdf(_pendulum(tmp_path))
    assert "\n" not in str(err.value)


@needs_mujoco
def test_shipped_arm7(tmp_path: Path) -> None:
    """The Panda (Gaz et al. 2019): joint 1 is vertical and never holds gravity; tilted
    0.5 rad forward on joint 2 with the arm stretched, joint 2 must push back, by less
    than the whole moving mass at full reach could need."""
    dyn = LinkDynamics.from_urdf(shipped_robot("arm7"))
    assert dyn.names == tuple(f"panda_joint{k}" for k in range(1, 8))
    assert "panda_link8" in dyn.links  # the flange, welded by panda_joint8
    assert dyn.lower[3] == -3.0718 and dyn.upper[5] == 3.7525
    q = np.array([0.0, 0.5, 0.0, -0.0698, 0.0, 0.0698, 0.0])
    grav = dyn.gravity(q)
    assert np.all(np.isfinite(grav))
    assert grav[0] == pytest.approx(0.0, abs=1e-12)
    moving = 0.646926 + 3.228604 + 3.587895 + 1.225946 + 1.666555 + 0.735522
    reach = 0.316 + 0.0825 + 0.384 + 0.088 + 0.107
    assert -moving * 9.81 * reach * math.sin(0.5) < grav[1] < -5.0
    mass = dyn.mass_matrix(q)
    assert mass == pytest.approx(mass.T, abs=1e-14)
    assert np.linalg.eigvalsh(mass).min() > 0.0
    # a 2 kg payload at the flange: joint 2 holds it too, joint 1 still nothing
    payload = Wrench("panda_link8", force=(0.0, 0.0, -2.0 * 9.81))
    held = -dyn.external_torques(q, payload)
    assert held[0] == pytest.approx(0.0, abs=1e-12)
    assert held[1] < 0.0


@needs_mujoco
def test_shipped_rehabexos() -> None:
    """Four joints after [Vertechy]; raised forward (J2), out to the side (J1) or at the
    elbow (J4), the joints that lift the arm hold it with positive torque; J2's and J4's
    torque in the sagittal plane follows from the masses in the file."""
    dyn = LinkDynamics.from_urdf(shipped_robot("rehabexos"))
    assert dyn.names == ("J1", "J2", "J3", "J4")
    assert "handle" in dyn.links
    assert np.all(dyn.effort == 150.0)
    assert dyn.gravity(np.zeros(4)) == pytest.approx(np.zeros(4), abs=1e-12)
    # the forearm group about the elbow: person's forearm and hand, shell, handle
    forearm = 1.65 * 0.174251 + 0.5 * 0.175 + 0.3 * 0.35
    forearm_mass = 1.65 + 0.5 + 0.3
    # about the shoulder: J3's AG2, upper arm, shell, J4's AG1 at the elbow, the forearm
    upper = 3.7 * 0.10 + 2.1 * 0.141918 + 1.0 * 0.16275 + (3.7 + forearm_mass) * 0.3255
    for j2, j4 in ((0.5, 0.0), (0.0, 0.5), (0.4, 0.9), (1.2, 1.0)):
        q = np.array([0.0, j2, 0.0, j4])
        grav = dyn.gravity(q)
        assert np.all(np.isfinite(grav))
        assert grav[3] == pytest.approx(9.81 * forearm * math.sin(j2 + j4), rel=1e-9)
        expected_j2 = 9.81 * (upper * math.sin(j2) + forearm * math.sin(j2 + j4))
        assert grav[1] == pytest.approx(expected_j2, rel=1e-9)
        assert grav[1] > 0.0 and grav[3] > 0.0
    assert dyn.gravity(np.array([0.5, 0.0, 0.0, 0.0]))[0] > 0.0
    # a person pushing the handle forward with the arm hanging: J2 and J4 see the lever
    push = dyn.external_torques(np.zeros(4), Wrench("handle", force=(10.0, 0.0, 0.0)))
    assert push == pytest.approx([0.0, 10.0 * (0.3255 + 0.35), 0.0, 10.0 * 0.35], abs=1e-12)


def test_shipped_robot_names() -> None:
    assert SHIPPED_ROBOTS == ("arm7", "rehabexos")
    for name in SHIPPED_ROBOTS:
        assert shipped_robot(name).is_file()
    with pytest.raises(UserError, match="no shipped robot 'arm8'"):
        shipped_robot("arm8")


@needs_mujoco
def test_free_torques_are_the_wrenches_less_the_bias(tmp_path: Path) -> None:
    """``free_torques`` is ``J^T w - b(q, qd)`` in one call (the arm's plant uses it)."""
    dyn = LinkDynamics.from_urdf(_pendulum(tmp_path))
    q, qd = np.array([0.7]), np.array([-1.3])
    push = Wrench("tip", force=(3.0, 0.0, 1.0))
    expected = dyn.external_torques(q, push) - dyn.bias(q, qd)
    assert dyn.free_torques(q, qd, push) == pytest.approx(expected, rel=1e-12)
    assert dyn.free_torques(q, qd) == pytest.approx(-M1 * G * C1 * math.sin(0.7), rel=1e-9)
