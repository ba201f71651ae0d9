"""Rigid-body link dynamics of a robot from its URDF: :class:`LinkDynamics`.

The link side of an arm whose every joint carries the emulated harmonic-drive actuator:
the links' configuration-dependent inertia, their coupling, gravity and external forces
on links (a person at a handle, a payload), for all joints at once, on numpy arrays::

    M(q) qdd + b(q, qd) = tau + J(q)^T w

``M`` is :meth:`LinkDynamics.mass_matrix`, ``b`` (Coriolis, centrifugal and gravity
torques) :meth:`LinkDynamics.bias`, its gravity part :meth:`LinkDynamics.gravity`,
``tau`` the joint torques the actuators apply to the links and ``w`` the external
wrenches (:class:`Wrench`); :meth:`LinkDynamics.forward_dynamics` solves for ``qdd`` and
:meth:`LinkDynamics.step` advances the links one fixed step by semi-implicit Euler.

The URDF is read as URDF defines it: the actuated joints are its ``revolute`` and
``continuous`` joints, in the order the file lists them (a continuous joint is a
revolute joint without position limits); a ``fixed`` joint welds its child link to its
parent, whose mass and inertia the child's add to; a joint hdhil cannot give an actuator
(``prismatic``, ``floating``, ``planar``) is refused in one line (:class:`UserError`).
Visuals, collisions and ``<dynamics>`` tags are ignored: friction and damping belong to
the actuator model. Position limits are reported (:class:`JointInfo`), not enforced.

The computations are MuJoCo's (the ``mujoco-core`` package, the ``arm`` extra:
``pip install 'hdhil[arm]'``), chosen by measurement against Pinocchio
(``docs/multibody.md``); it is imported when a robot is loaded, not with this module.
Pure: no CAN, no clock.
"""

from __future__ import annotations

import copy
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from hdhil.core.errors import UserError

__all__ = [
    "ACTUATED_TYPES",
    "SHIPPED_ROBOTS",
    "JointInfo",
    "LinkDynamics",
    "LinkDynamicsConfig",
    "Wrench",
    "shipped_robot",
]

#: The URDF joint types that get an actuator; ``fixed`` joints are merged, any other
#: type is refused.
ACTUATED_TYPES = ("revolute", "continuous")

#: The robot descriptions shipped with hdhil (``hostsim/robots/NAME.urdf``).
SHIPPED_ROBOTS = ("arm7", "rehabexos")

_INSTALL_HINT = "pip install 'hdhil[arm]'"


def shipped_robot(name: str) -> Path:
    """The path of a shipped URDF (:data:`SHIPPED_ROBOTS`)."""
    if name not in SHIPPED_ROBOTS:
        raise UserError(f"no shipped robot {name!r}; shipped: {', '.join(SHIPPED_ROBOTS)}")
    return Path(str(resources.files("hdhil.hostsim").joinpath("robots", f"{name}.urdf")))


@dataclass(frozen=True)
class JointInfo:
    """One actuated joint as the URDF describes it (SI units: rad, rad/s, Nm).

    A continuous joint has ``lower = -inf``, ``upper = +inf``; ``effort`` and
    ``velocity`` are ``inf`` where the URDF gives none.
    """

    name: str
    kind: str
    parent: str
    child: str
    lower: float
    upper: float
    effort: float
    velocity: float


@dataclass(frozen=True)
class Wrench:
    """An external wrench on a link: a person at a handle, a payload.

    ``force`` (N) and ``torque`` (Nm) are in the world frame; the force acts at
    ``point``, given in the link's own frame (m; the link's origin by default).
    ``link`` may be any link of the URDF, one welded by fixed joints included.
    """

    link: str
    force: Sequence[float] = (0.0, 0.0, 0.0)
    torque: Sequence[float] = (0.0, 0.0, 0.0)
    point: Sequence[float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class LinkDynamicsConfig:
    """What :class:`LinkDynamics` is built from.

    ``urdf``: the robot description; ``gravity``: the acceleration of gravity in the
    URDF's root frame, m/s^2 (z up by URDF convention: ``(0, 0, -9.81)``).
    """

    urdf: Path
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)

    def __post_init__(self) -> None:
        if len(self.gravity) != 3 or not all(math.isfinite(g) for g in self.gravity):
            raise UserError(f"gravity must be three finite numbers, got {self.gravity!r}")


@dataclass
class _Robot:
    """The URDF read for hdhil: actuated joints in file order, the tree for MuJoCo."""

    joints: list[JointInfo]
    links: list[str]
    tree: ET.Element = field(repr=False)


def _float(text: str | None, default: float, where: str) -> float:
    if text is None:
        return default
    try:
        return float(text)
    except ValueError:
        raise UserError(f"{where}: {text!r} is not a number") from None


def _read_urdf(path: Path) -> _Robot:
    """Parse ``path``; refuse what hdhil cannot emulate, in one line."""
    try:
        root = ET.parse(path).getroot()
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc.strerror or exc}") from None
    except ET.ParseError as exc:
        raise UserError(f"{path}: not XML ({exc})") from None
    if root.tag != "robot":
        raise UserError(f"{path}: not a URDF (the root element is <{root.tag}>, not <robot>)")
    links = [link.get("name", "") for link in root.findall("link")]
    joints: list[JointInfo] = []
    for joint in root.findall("joint"):
        name = joint.get("name", "")
        kind = joint.get("type", "")
        if kind == "fixed":
            continue
        if kind not in ACTUATED_TYPES:
            raise UserError(
                f"{path}: joint {name!r} is {kind or 'of no type'}; hdhil emulates revolute "
                "and continuous joints (fixed joints are merged)"
            )
        parent = joint.find("parent")
        child = joint.find("child")
        limit = joint.find("limit")
        where = f"{path}: joint {name!r}"
        if kind == "revolute" and limit is None:
            raise UserError(f"{where} is revolute without <limit> (URDF requires one)")
        get = limit.get if limit is not None else {}.get
        lower, upper = -math.inf, math.inf
        if kind == "revolute":
            lower = _float(get("lower"), 0.0, where)
            upper = _float(get("upper"), 0.0, where)
        joints.append(
            JointInfo(
                name=name,
                kind=kind,
                parent="" if parent is None else parent.get("link", ""),
                child="" if child is None else child.get("link", ""),
                lower=lower,
                upper=upper,
                effort=_float(get("effort"), math.inf, where),
                velocity=_float(get("velocity"), math.inf, where),
            )
        )
    if not joints:
        raise UserError(f"{path}: no revolute or continuous joint to emulate")
    _check_moved_mass(path, root, joints)
    return _Robot(joints=joints, links=links, tree=root)


def _check_moved_mass(path: Path, root: ET.Element, joints: list[JointInfo]) -> None:
    """Refuse a joint with no mass behind it: its acceleration would be undefined."""
    mass: dict[str, float] = {}
    for link in root.findall("link"):
        value = link.find("inertial/mass")
        where = f"{path}: link {link.get('name', '')!r}"
        mass[link.get("name", "")] = 0.0 if value is None else _float(value.get("value"), 0, where)
    children: dict[str, list[str]] = {}
    for joint in root.findall("joint"):
        parent, child = joint.find("parent"), joint.find("child")
        if parent is not None and child is not None:
            children.setdefault(parent.get("link", ""), []).append(child.get("link", ""))
    for joint in joints:
        todo, seen, moved = [joint.child], set(), 0.0
        while todo:
            link = todo.pop()
            if link not in seen:
                seen.add(link)
                moved += mass.get(link, 0.0)
                todo.extend(children.get(link, ()))
        if moved <= 0.0:
            raise UserError(
                f"{path}: joint {joint.name!r} moves no mass (link {joint.child!r} and what "
                "it carries have none)"
            )


def _mujoco_xml(root: ET.Element) -> str:
    """The URDF as MuJoCo should compile it: dynamics only, every link kept by name."""
    tree = copy.deepcopy(root)
    for element in tree.findall("mujoco"):
        tree.remove(element)
    moving = {
        child.get("link", "")
        for joint in tree.findall("joint")
        if joint.get("type") != "fixed" and (child := joint.find("child")) is not None
    }
    for link in tree.findall("link"):
        for element in link.findall("visual") + link.findall("collision"):
            link.remove(element)
        mass = link.find("inertial/mass")
        massless = mass is None or _float(mass.get("value"), 0.0, "mass") <= 0.0
        if link.get("name") in moving and massless:
            # a massless link between two joints (a URDF's way to build a joint of two
            # axes): MuJoCo needs mass on every body a joint moves; 1e-9 kg, 1e-12 kg m^2
            # (a joint that moves no mass at all was refused before)
            for old in link.findall("inertial"):
                link.remove(old)
            inertial = ET.SubElement(link, "inertial")
            ET.SubElement(inertial, "mass", value="1e-9")
            moments = {"ixx": "1e-12", "iyy": "1e-12", "izz": "1e-12"}
            ET.SubElement(inertial, "inertia", ixy="0", ixz="0", iyz="0", **moments)
    # fusestatic="false": links welded by fixed joints stay bodies (their names are
    # frames for external wrenches); their masses still move with their parents.
    extension = ET.Element("mujoco")
    ET.SubElement(extension, "compiler", fusestatic="false")
    tree.insert(0, extension)
    return ET.tostring(tree, encoding="unicode")


def _why(exc: ValueError) -> str:
    """MuJoCo's compiler error in one line, naming the link it is about."""
    text = str(exc)
    first = next((line.strip() for line in text.splitlines() if line.strip()), "invalid")
    first = re.sub(r"; use '\w+' to fix$", "", first.removeprefix("Error: "))
    element = re.search(r"Element name '([^']*)'", text)
    return f"{first} (link {element.group(1)!r})" if element else first


def _import_mujoco() -> Any:
    try:
        import mujoco
    except ImportError:
        raise UserError(f"multibody link dynamics need MuJoCo: {_INSTALL_HINT}") from None
    return mujoco


class LinkDynamics:
    """The rigid-body dynamics of a robot's links, all actuated joints at once.

    Arrays are in the order of :attr:`joints` (the URDF's order); ``q`` in rad, ``qd``
    in rad/s, torques in Nm. Each method computes from its arguments alone (no state
    kept between calls), so calls may come in any order.
    """

    def __init__(self, config: LinkDynamicsConfig) -> None:
        robot = _read_urdf(config.urdf)
        mujoco = _import_mujoco()
        self.config = config
        try:
            model = mujoco.MjModel.from_xml_string(_mujoco_xml(robot.tree))
        except ValueError as exc:
            raise UserError(f"{config.urdf}: MuJoCo cannot load it: {_why(exc)}") from None
        # rigid links only: no joint-limit or contact constraints, no URDF damping or
        # friction (the actuator model carries them), no armature
        model.opt.disableflags |= (
            mujoco.mjtDisableBit.mjDSBL_LIMIT
            | mujoco.mjtDisableBit.mjDSBL_CONTACT
            | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
        )
        model.opt.gravity[:] = config.gravity
        model.dof_damping[:] = 0.0
        model.dof_frictionloss[:] = 0.0
        model.dof_armature[:] = 0.0
        model.jnt_stiffness[:] = 0.0
        self._mj = mujoco
        self._model = model
        self._data = mujoco.MjData(model)
        self.joints: tuple[JointInfo, ...] = tuple(robot.joints)
        self.names: tuple[str, ...] = tuple(j.name for j in robot.joints)
        self.links: tuple[str, ...] = tuple(robot.links)
        self.size = n = len(self.joints)
        if model.nv != n or model.nq != n:
            raise UserError(
                f"{config.urdf}: {n} actuated joints but MuJoCo made {model.nv} degrees of "
                "freedom (a joint hdhil does not model: mimic or a second root?)"
            )
        qadr = [int(model.joint(name).qposadr[0]) for name in self.names]
        vadr = [int(model.joint(name).dofadr[0]) for name in self.names]
        if qadr != vadr:
            raise UserError(f"{config.urdf}: joint coordinates MuJoCo cannot map one to one")
        #: URDF order -> MuJoCo order; None when they agree (a chain listed root first)
        self._order: np.ndarray | None = None
        if qadr != list(range(n)):
            self._order = np.array(qadr, dtype=np.intp)
        self._body = {model.body(i).name: i for i in range(model.nbody)}
        self.lower = np.array([j.lower for j in self.joints])
        self.upper = np.array([j.upper for j in self.joints])
        self.effort = np.array([j.effort for j in self.joints])
        self._M = np.zeros((n, n))
        self._out = np.zeros(n)
        self._qfrc = np.zeros(n)

    @classmethod
    def from_urdf(
        cls, path: str | Path, *, gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    ) -> LinkDynamics:
        """Load the URDF at ``path`` (:class:`LinkDynamicsConfig`)."""
        return cls(LinkDynamicsConfig(urdf=Path(path), gravity=tuple(gravity)))

    # ----- the state in MuJoCo's order

    def _set(self, q: np.ndarray, qd: np.ndarray | None) -> None:
        d = self._data
        if self._order is None:
            d.qpos[:] = q
            d.qvel[:] = 0.0 if qd is None else qd
        else:
            d.qpos[self._order] = q
            d.qvel[self._order] = 0.0 if qd is None else qd

    def _urdf_order(self, x: np.ndarray) -> np.ndarray:
        return x.copy() if self._order is None else x[self._order]

    # ----- the terms of the equation of motion

    def mass_matrix(self, q: np.ndarray) -> np.ndarray:
        """The joint-space inertia matrix ``M(q)``, (n, n), symmetric, kg m^2."""
        mj, m, d = self._mj, self._model, self._data
        self._set(q, None)
        mj.mj_kinematics(m, d)
        mj.mj_comPos(m, d)
        mj.mj_crb(m, d)
        mj.mj_fullM(m, d, self._M)
        if self._order is None:
            return self._M.copy()
        return self._M[np.ix_(self._order, self._order)]

    def _rne(self, q: np.ndarray, qd: np.ndarray | None) -> np.ndarray:
        mj, m, d = self._mj, self._model, self._data
        self._set(q, qd)
        mj.mj_kinematics(m, d)
        mj.mj_comPos(m, d)
        mj.mj_comVel(m, d)
        mj.mj_rne(m, d, 0, self._out)
        return self._urdf_order(self._out)

    def bias(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Coriolis, centrifugal and gravity torques ``b(q, qd)``, Nm (RNEA, qdd = 0)."""
        return self._rne(q, qd)

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """The gravity part of :meth:`bias`: the torques that hold the links still, Nm."""
        return self._rne(q, None)

    def _wrench_forces(self, external: Wrench | Sequence[Wrench]) -> np.ndarray:
        """``J^T w`` summed over the wrenches, in MuJoCo's order (kinematics current)."""
        mj, m, d = self._mj, self._model, self._data
        qfrc = self._qfrc
        qfrc[:] = 0.0
        for w in (external,) if isinstance(external, Wrench) else external:
            body = self._body.get(w.link)
            if body is None:
                raise UserError(
                    f"no link {w.link!r} for an external wrench; links: {', '.join(self.links)}"
                )
            point = d.xpos[body]
            if any(w.point):
                point = point + d.xmat[body].reshape(3, 3) @ np.asarray(w.point, float)
            force = np.asarray(w.force, float)
            torque = np.asarray(w.torque, float)
            mj.mj_applyFT(m, d, force, torque, point, body, qfrc)
        return qfrc

    def external_torques(self, q: np.ndarray, external: Wrench | Sequence[Wrench]) -> np.ndarray:
        """The joint torques ``J(q)^T w`` of external wrenches, Nm."""
        mj, m, d = self._mj, self._model, self._data
        self._set(q, None)
        mj.mj_kinematics(m, d)
        mj.mj_comPos(m, d)
        return self._urdf_order(self._wrench_forces(external))

    def free_torques(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        external: Wrench | Sequence[Wrench] | None = None,
    ) -> np.ndarray:
        """``J(q)^T w - b(q, qd)``: the joint torques on the links from everything but the
        actuators (gravity, Coriolis and centrifugal torques, external wrenches), Nm, in
        one kinematics pass: ``M qdd = tau + free_torques(q, qd, w)``."""
        out = -self._rne(q, qd)
        if external is not None:
            out += self._urdf_order(self._wrench_forces(external))
        return out

    def forward_dynamics(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        tau: np.ndarray,
        external: Wrench | Sequence[Wrench] | None = None,
    ) -> np.ndarray:
        """The link accelerations ``qdd = M^-1 (tau + J^T w - b)``, rad/s^2."""
        mj, m, d = self._mj, self._model, self._data
        self._set(q, qd)
        mj.mj_fwdPosition(m, d)  # kinematics, composite inertia, M factorised
        mj.mj_fwdVelocity(m, d)  # qfrc_bias
        if self._order is None:
            d.qfrc_applied[:] = tau
        else:
            d.qfrc_applied[self._order] = tau
        if external is not None:
            d.qfrc_applied += self._wrench_forces(external)
        mj.mj_fwdAcceleration(m, d)
        return self._urdf_order(d.qacc_smooth)

    def step(
        self,
        q: np.ndarray,
        qd: np.ndarray,
        tau: np.ndarray,
        dt: float,
        external: Wrench | Sequence[Wrench] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One fixed step of ``dt`` seconds by semi-implicit (symplectic) Euler.

        ``qd' = qd + dt * qdd(q, qd, tau)``, then ``q' = q + dt * qd'``: first order,
        but its energy error stays bounded on an unforced arm instead of growing as
        explicit Euler's does. ``tau`` and ``external`` are held over the step.
        Returns ``(q', qd')`` as new arrays.
        """
        qd_next = qd + dt * self.forward_dynamics(q, qd, tau, external)
        return q + dt * qd_next, qd_next
