"""A rig of several joints as scenario data: named buses, joints and an optional URDF.

A scenario describes one joint on one bus with ``[plant]``, ``[firmware]`` and ``[bus]``.
A rig of several adds three tables (``docs/reference/scenario-keys.md``):

- ``[buses.NAME]``: each CAN bus, its bit rate, classical or FD (``fd``, and
  ``data_bitrate`` for bit-rate switching), and the node-ID of the controller node that
  produces its SYNC. Keys not given come from ``[bus]``.
- ``[joints.NAME]``: each joint, the bus it sits on and its drive's node-ID, plus
  ``plant`` and ``firmware`` sub-tables deep-merged over the scenario's own (gear ratio,
  stiffness, ripple, sensor, filter, law and gains per joint).
- ``[robot] urdf``: a URDF file (a path relative to the scenario file). Its revolute and
  continuous joints are the rig's joints, in the file's order; ``[joints.NAME]`` tables
  override them by URDF joint name, and a joint type hdhil cannot emulate is a one-line
  error. Fixed joints are not actuated (they join their links).

Node-IDs not given are the lowest free ones on the bus from 2 (the controller is 1, as in
the single-joint rig); a joint without ``bus`` sits on the only bus, and must name one
when there are several. Each joint's PDO COB-IDs follow from its node-ID (CiA 301's
predefined connection set). Everything here is validated when the scenario loads, so a
mistake is one :class:`~hdhil.core.dataconf.ConfigError` naming the key.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hdhil.core.dataconf import ConfigError, from_dict, merge

__all__ = [
    "BusSpec",
    "JointSpec",
    "RobotSpec",
    "UrdfJoint",
    "rigdb_layout",
    "urdf_joints",
]

#: The bus of a single-joint scenario (``[bus]``): the name its frames carry in traces.
DEFAULT_BUS = "control"
#: The joint of a single-joint scenario.
DEFAULT_JOINT = "joint"
#: URDF joint types hdhil gives an actuator.
ACTUATED_TYPES = ("revolute", "continuous")
#: URDF joint types that join two links rigidly.
PASSIVE_TYPES = ("fixed",)
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]*$")


@dataclass(frozen=True)
class BusSpec:
    """One CAN bus of the rig (``[buses.NAME]``)."""

    #: Nominal (arbitration-phase) bit rate, bit/s.
    bitrate: int = 1_000_000
    #: CAN FD frames (ISO 11898-1:2015) instead of classical ones.
    fd: bool = False
    #: FD data-phase bit rate with bit-rate switching, bit/s; 0: no switching.
    data_bitrate: int = 0
    #: The node-ID of the controller node on this bus (NMT master and SYNC producer).
    controller_node_id: int = 1
    #: The controller's telemetry of each joint every this many SYNC cycles (decimated
    #: telemetry; 1: every cycle), the joints' frames spread over the cycles between.
    telemetry_every: int = 1

    def __post_init__(self) -> None:
        if isinstance(self.bitrate, bool) or not 10_000 <= self.bitrate <= 1_000_000:
            raise ValueError(
                f"bitrate must be 10000..1000000 bit/s (ISO 11898-2), got {self.bitrate!r}"
            )
        if isinstance(self.telemetry_every, bool) or not 1 <= self.telemetry_every <= 1000:
            raise ValueError(
                f"telemetry_every must be 1..1000 cycles, got {self.telemetry_every!r}"
            )
        if not isinstance(self.fd, bool):
            raise ValueError(f"fd must be true or false, got {self.fd!r}")
        if self.data_bitrate:
            if not self.fd:
                raise ValueError("data_bitrate needs fd = true (bit-rate switching is CAN FD)")
            if isinstance(self.data_bitrate, bool) or not (
                self.bitrate <= self.data_bitrate <= 12_000_000
            ):
                raise ValueError(
                    f"data_bitrate must be bitrate..12000000 bit/s, got {self.data_bitrate!r}"
                )
        _check_node_id(self.controller_node_id, "controller_node_id")


@dataclass(frozen=True)
class JointSpec:
    """One joint of the rig: its bus, its drive's node-ID, and the scenario's ``[plant]``
    and ``[firmware]`` tables with the joint's own keys merged over them (plain data,
    validated into :class:`~hdhil.hostsim.plant.PlantConfig` and
    :class:`~hdhil.firmware.config.FirmwareConfig` by the scenario)."""

    name: str
    bus: str
    node_id: int
    #: The node-ID of the controller node that runs this joint's loop (the bus's own
    #: unless the joint names another: a controller node reports two joints' telemetry
    #: in its four pre-defined TPDOs, docs/rigdb.md).
    controller_node_id: int = 1
    #: The joint's angle at time 0 (rad), the arm at rest there: a ``[robot]`` rig's.
    start_rad: float = 0.0
    #: The joint's own ``plant`` and ``firmware`` keys (what ``[joints.NAME]`` gave).
    plant_overrides: dict[str, Any] = field(default_factory=dict, compare=False)
    firmware_overrides: dict[str, Any] = field(default_factory=dict, compare=False)

    def to_data(self) -> dict[str, Any]:
        """The ``[joints.NAME]`` table of this joint (without its name)."""
        data: dict[str, Any] = {
            "bus": self.bus,
            "node_id": self.node_id,
            "controller_node_id": self.controller_node_id,
        }
        if self.start_rad:
            data["start_rad"] = self.start_rad
        if self.plant_overrides:
            data["plant"] = self.plant_overrides
        if self.firmware_overrides:
            data["firmware"] = self.firmware_overrides
        return data


@dataclass(frozen=True)
class JointTable:
    """One joint of the rig (``[joints.NAME]``): its bus, its drive's node-ID, and its own
    plant and firmware keys (:func:`parse_joints` reads the table)."""

    #: The bus the joint sits on (a ``[buses.NAME]``); may be left out with one bus.
    bus: str = ""
    #: The drive's CANopen node-ID; 0: the lowest free one on its bus from 2.
    node_id: int = 0
    #: The node-ID of the controller node that runs the joint; 0: the bus's.
    controller_node_id: int = 0
    #: The joint's angle at time 0 (rad; a ``[robot]`` rig only, inside the URDF's
    #: limits): the arm starts at rest in this pose. 0 on every joint: the URDF's zero,
    #: or where the person who wears the arm holds it.
    start_rad: float = 0.0
    #: The joint's own ``[plant]`` keys, merged over the scenario's (same layout).
    plant: dict[str, Any] = field(default_factory=dict)
    #: The joint's own ``[firmware]`` keys, merged over the scenario's (same layout).
    firmware: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class UrdfJoint:
    """A joint of a URDF file: its name, type, and the links it connects."""

    name: str
    type: str
    parent: str
    child: str


@dataclass(frozen=True)
class RobotSpec:
    """``[robot]``: the URDF whose actuated joints are the rig's joints."""

    #: A shipped robot by name (``arm7``, ``rehabexos``) or a URDF file (a path relative
    #: to the scenario file that names it).
    urdf: str

    @property
    def path(self) -> Path:
        """The URDF file: a shipped robot's, or the path as resolved."""
        if is_robot_name(self.urdf):
            return shipped_robot(self.urdf)
        return Path(self.urdf)

    @property
    def joints(self) -> tuple[UrdfJoint, ...]:
        return urdf_joints(self.path)


def is_robot_name(urdf: str) -> bool:
    """Whether ``urdf`` names a shipped robot rather than a file."""
    return "/" not in urdf and "\\" not in urdf and not urdf.lower().endswith(".urdf")


def shipped_robots() -> list[str]:
    """Names of the shipped robots (``hdhil/hostsim/robots/*.urdf``), sorted."""
    from importlib import resources

    folder = resources.files("hdhil.hostsim") / "robots"
    return sorted(
        p.name.removesuffix(".urdf") for p in folder.iterdir() if p.name.endswith(".urdf")
    )


def shipped_robot(name: str) -> Path:
    """The URDF file of a shipped robot; an unknown name is a one-line error."""
    from importlib import resources

    if name not in shipped_robots():
        raise ConfigError(
            f"robot.urdf: no shipped robot {name!r} (shipped: {', '.join(shipped_robots())}; "
            "a file is named with its .urdf suffix)"
        )
    return Path(str(resources.files("hdhil.hostsim") / "robots" / f"{name}.urdf"))


def _check_node_id(value: Any, key: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 127:
        raise ValueError(f"{key} must be a CANopen node-ID 1..127, got {value!r}")


def urdf_joints(path: Path) -> tuple[UrdfJoint, ...]:
    """The joints of a URDF file, in file order; a type hdhil cannot emulate (prismatic,
    floating, planar) raises :class:`ConfigError` naming the joint."""
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise ConfigError(f"robot.urdf: no such file: {path}") from None
    except (OSError, ET.ParseError) as exc:
        raise ConfigError(f"robot.urdf: cannot read {path}: {exc}") from None
    if root.tag != "robot":
        raise ConfigError(f"robot.urdf: {path} is not a URDF file (root <{root.tag}>)")
    joints = []
    for element in root.findall("joint"):
        name = element.get("name", "")
        kind = element.get("type", "")
        if kind not in ACTUATED_TYPES + PASSIVE_TYPES:
            raise ConfigError(
                f"robot.urdf: joint {name!r} is {kind!r}; hdhil emulates revolute and "
                "continuous joints (and fixed ones as rigid)"
            )
        parent, child = element.find("parent"), element.find("child")
        joints.append(
            UrdfJoint(
                name,
                kind,
                parent.get("link", "") if parent is not None else "",
                child.get("link", "") if child is not None else "",
            )
        )
    return tuple(joints)


def _check_start(name: str, start: Any, robot: RobotSpec | None) -> None:
    """``joints.NAME.start_rad``: a finite angle, of a ``[robot]``'s joint, inside the
    URDF's limits (a revolute joint's ``<limit lower upper>``); else one-line error."""
    key = f"joints.{name}.start_rad"
    if isinstance(start, bool) or not isinstance(start, (int, float)) or not math.isfinite(start):
        raise ConfigError(f"{key}: expected a finite angle in rad, got {start!r}")
    if not start:
        return
    if robot is None:
        raise ConfigError(f"{key}: a start pose is a [robot] rig's (the arm's joint angles)")
    limits = urdf_limits(robot.path).get(name)
    if limits is not None and not limits[0] <= start <= limits[1]:
        raise ConfigError(
            f"{key}: {start:g} rad is outside the URDF's limits {limits[0]:g}..{limits[1]:g} rad"
        )


def urdf_limits(path: Path) -> dict[str, tuple[float, float]]:
    """The position limits (rad) of a URDF's revolute joints (``<limit lower upper>``),
    by joint name; a continuous joint has none."""
    out = {}
    for element in ET.parse(path).getroot().findall("joint"):
        limit = element.find("limit")
        if element.get("type") == "revolute" and limit is not None:
            lower, upper = limit.get("lower"), limit.get("upper")
            if lower is not None and upper is not None:
                out[element.get("name", "")] = (float(lower), float(upper))
    return out


def parse_buses(buses: Any, bus_defaults: dict[str, Any]) -> tuple[tuple[str, BusSpec], ...]:
    """``[buses.NAME]`` tables (None: the one bus of ``[bus]``) as (name, spec) pairs."""
    if buses is None:
        return ((DEFAULT_BUS, from_dict(BusSpec, _bus_keys(bus_defaults), "bus")),)
    if not isinstance(buses, dict) or not buses:
        raise ConfigError(f"buses: expected a table of named buses, got {buses!r}")
    out = []
    for name, table in buses.items():
        if not _NAME.match(name):
            raise ConfigError(f"buses.{name}: a bus name is letters, digits, _ . -")
        if not isinstance(table, dict):
            raise ConfigError(f"buses.{name}: expected a table, got {table!r}")
        out.append((name, from_dict(BusSpec, merge(_bus_keys(bus_defaults), table),
                                    f"buses.{name}")))  # fmt: skip
    return tuple(out)


def _bus_keys(bus: dict[str, Any]) -> dict[str, Any]:
    """What ``[bus]`` passes on to every named bus (its bit rate)."""
    return {k: v for k, v in bus.items() if k == "bitrate"}


def parse_joints(
    joints: Any,
    buses: tuple[tuple[str, BusSpec], ...],
    robot: RobotSpec | None,
) -> tuple[JointSpec, ...]:
    """``[joints.NAME]`` tables (with the URDF's actuated joints, if any) as specs in
    order: the URDF's order, else the tables' order. Empty: a single-joint scenario."""
    if joints is None:
        joints = {}
    if not isinstance(joints, dict):
        raise ConfigError(f"joints: expected a table of named joints, got {joints!r}")
    names = list(joints)
    if robot is not None:
        actuated = [j.name for j in robot.joints if j.type in ACTUATED_TYPES]
        if not actuated:
            raise ConfigError(f"robot.urdf: {robot.urdf} has no revolute or continuous joint")
        unknown = [n for n in names if n not in actuated]
        if unknown:
            raise ConfigError(
                f"joints.{unknown[0]}: the URDF has no actuated joint of that name "
                f"(it has: {', '.join(actuated)})"
            )
        names = actuated
    if not names:
        return ()
    bus_names = [name for name, _ in buses]
    specs = dict(buses)
    taken: dict[str, set[int]] = {b: {specs[b].controller_node_id} for b in bus_names}
    controllers: dict[str, set[int]] = {b: set() for b in bus_names}
    chosen: list[tuple[str, str, int | None, dict[str, Any]]] = []
    for name in names:
        if not _NAME.match(name):
            raise ConfigError(f"joints.{name}: a joint name is letters, digits, _ . -")
        table = joints.get(name, {})
        if not isinstance(table, dict):
            raise ConfigError(f"joints.{name}: expected a table, got {table!r}")
        known = {"bus", "node_id", "controller_node_id", "start_rad", "plant", "firmware"}
        unknown_keys = sorted(set(table) - known)
        if unknown_keys:
            raise ConfigError(
                f"unknown key joints.{name}.{unknown_keys[0]} (known: {', '.join(sorted(known))})"
            )
        bus = table.get("bus") or None
        if bus is None:
            if len(bus_names) > 1:
                raise ConfigError(
                    f"joints.{name}.bus: the rig has buses {', '.join(bus_names)}; "
                    "say which one this joint sits on"
                )
            bus = bus_names[0]
        if bus not in specs:
            raise ConfigError(f"joints.{name}.bus: no bus {bus!r} (buses: {', '.join(bus_names)})")
        node_id = table.get("node_id")
        if node_id == 0 and not isinstance(node_id, bool):  # 0: the lowest free one
            node_id = None
        if node_id is not None:
            try:
                _check_node_id(node_id, f"joints.{name}.node_id")
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
            if node_id in taken[bus]:
                raise ConfigError(
                    f"joints.{name}.node_id: node-ID {node_id} is already taken on bus {bus}"
                )
            taken[bus].add(node_id)
        controller = table.get("controller_node_id") or specs[bus].controller_node_id
        try:
            _check_node_id(controller, f"joints.{name}.controller_node_id")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        controllers[bus].add(controller)
        _check_start(name, table.get("start_rad", 0.0), robot)
        chosen.append((name, bus, node_id, table, controller))
    for bus, ids in controllers.items():  # a controller node is no drive
        clash = ids & {c[2] for c in chosen if c[1] == bus and c[2] is not None}
        if clash:
            raise ConfigError(
                f"bus {bus}: node-ID {min(clash)} is both a drive and a controller node"
            )
        taken[bus] |= ids
    out = []
    for name, bus, node_id, table, controller in chosen:
        if node_id is None:  # the lowest free node-ID on the bus
            free = next((n for n in range(2, 128) if n not in taken[bus]), None)
            if free is None:
                raise ConfigError(f"joints.{name}: bus {bus} has no free node-ID left")
            taken[bus].add(free)
            node_id = free
        for key in ("plant", "firmware"):
            if not isinstance(table.get(key, {}), dict):
                raise ConfigError(f"joints.{name}.{key}: expected a table")
        out.append(
            JointSpec(
                name,
                bus,
                node_id,
                controller,
                float(table.get("start_rad", 0.0)),
                dict(table.get("plant", {})),
                dict(table.get("firmware", {})),
            )
        )
    return tuple(out)


def rigdb_layout(
    joints: Sequence[JointSpec],
    buses: Sequence[tuple[str, BusSpec]],
    mapping: str = "raw",
    dcf: Path | None = None,
) -> tuple[list[Any], list[Any]]:
    """A rig's joints and buses as :mod:`hdhil.canopen.rigdb` takes them
    (:class:`~hdhil.canopen.rigdb.RigDrive`, :class:`~hdhil.canopen.rigdb.RigBus`), each
    drive with the shipped ``mapping`` or the drive's ``dcf``: the layout its databases,
    the planner and the rig run number the frames from."""
    from hdhil.canopen.rigdb import RigBus, RigDrive

    rig_buses = [
        RigBus(name, spec.controller_node_id, spec.bitrate, spec.fd, spec.data_bitrate)
        for name, spec in buses
    ]
    drives = [
        RigDrive(j.name, j.node_id, j.bus, mapping, dcf, j.controller_node_id) for j in joints
    ]
    return drives, rig_buses
