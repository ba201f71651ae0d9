"""The CAN databases of a rig with several drives, generated from the object
dictionaries and node-IDs instead of typed.

A rig is a list of :class:`RigDrive` (joint name, node-ID, bus, the drive's mapping or
DCF, optionally its own controller node) and of :class:`RigBus` (name, the
controller's node-ID, bit rate, classical or CAN FD).  :func:`rig_databases` gives one
:class:`cantools.database.can.Database` per bus: every frame on that bus and the
ground-truth frames of its joints, with the signals, units, scaling, value tables,
comments and attributes of the single-joint databases (``control.dbc`` as the drive's
mapping leaves it, :func:`hdhil.canopen.mapping.mapping_database`, and ``truth.dbc``).
One database per bus, because every bus has its own SYNC (0x080), NMT (0x000) and
controller identifiers.

How identifiers are made (the single-joint layout, one drive at node-ID 2 with the
controller at node-ID 1 and an empty joint name, gives ``hdhil dbc export``'s database
exactly, :func:`hdhil.commands.dbc.merged_database`):

- per bus: SYNC 0x080 and NMT 0x000, sent by the bus's controller;
- per controller node ``c``: heartbeat 0x700+c, EMCY 0x080+c, SDO 0x580+c / 0x600+c;
- per drive at node-ID ``d``: heartbeat 0x700+d, EMCY 0x080+d, SDO 0x580+d / 0x600+d,
  and its PDOs as its EDS or DCF sets them (:func:`drive_pdo_layouts`): a COB-ID equal
  to the CiA 301 pre-defined connection set's value for the node-ID the file was
  written for (``[DeviceComissioning] NodeID``; 2, the shipped drive's, for a file
  without one) follows the node-ID (TPDO1 0x180+d, RPDO1 0x200+d, TPDO2 0x280+d, ...);
  any other COB-ID stays as the file sets it;
- the controller's telemetry of the ``r``-th joint it serves (0-based, in layout
  order): the identifiers the pre-defined connection set gives the controller's
  TPDO(2r+1) and TPDO(2r+2), so one controller node reports at most two joints;
- the ground truth of the ``j``-th joint of the rig (0-based, across all buses): the
  29-bit identifiers ``0x1F0000 | j << 4 | k`` (k = 1 torque, 2 motion, 3 joint), so
  joint 0 keeps ``truth.dbc``'s 0x1F0001..0x1F0003 and 4096 joints fit.

On a CAN FD bus each cyclic drive PDO of the joints (sensors, command) is one packed FD
frame, ``FD_DRIVE_TPDO1`` and ``FD_DRIVE_RPDO1``, at the first joint's identifier, and
the joints' telemetry is FD (:func:`rig_packing` gives the packing as well).

Names: a joint's messages and its drive node carry the joint name as a prefix
(``J1_DRIVE_TPDO1``, ``J1_CTRL_TPDO1``, ``J1_TRUTH_TORQUE``, node ``J1_DRIVE``; a ``.``
or ``-`` of the name written ``_``); an empty joint name keeps the single-joint names
and is allowed only in a rig of one drive. A bus with one controller node names it
``CONTROLLER`` and its service frames ``HEARTBEAT_CTRL`` etc.; with several, the node-ID
is appended (``CONTROLLER3``, ``HEARTBEAT_CTRL3``). A mistake in the layout (a node-ID
outside 1..127 or used twice on a bus, a joint name that is not a name or used twice, an
unknown mapping, two frames with one identifier) is a one-line
:class:`hdhil.core.errors.UserError`.
"""

from __future__ import annotations

import copy
import re
from collections import OrderedDict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cache
from pathlib import Path
from typing import Any

from hdhil.canopen.emcy import EMCY_BASE
from hdhil.canopen.mapping import control_database, mapping_database, mapping_dcf, od_layouts
from hdhil.canopen.nmt import HEARTBEAT_BASE, NMT_COB_ID
from hdhil.canopen.od import reference_od
from hdhil.canopen.pdo import PdoLayout
from hdhil.canopen.sdo import SDO_RX_BASE, SDO_TX_BASE
from hdhil.canopen.sync import SYNC_COB_ID
from hdhil.core.errors import UserError
from hdhil.dbc import (
    MAPPINGS,
    MAX_TRUTH_JOINTS,
    PDO_FUNCTION_CODES,
    TRUTH_BASE,
    database,
    eds_path,
    node_ids,
    predefined_cob_id,
)
from hdhil.dbc import truth_frame_id as _truth_frame_id

__all__ = [
    "MAX_TRUTH_JOINTS",
    "TRUTH_BASE",
    "PackedMember",
    "PackedPdo",
    "RigBus",
    "RigDrive",
    "drive_pdo_layouts",
    "predefined_cob_id",
    "rig_databases",
    "rig_packing",
    "single_joint_databases",
    "telemetry_phases",
    "truth_database",
    "truth_frame_id",
]


_SERVICE_BASES = (EMCY_BASE, HEARTBEAT_BASE, SDO_TX_BASE, SDO_RX_BASE)
_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: Joint and bus names (as a scenario's ``[joints.NAME]`` and ``[buses.NAME]``); in DBC
#: names a joint's ``.`` and ``-`` become ``_``.
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]*")
#: The arbitration phase's bit rate at most (ISO 11898-2), classical or FD.
_MAX_NOMINAL_BITRATE = 1_000_000
_MAX_DATA_BITRATE = 12_000_000
#: A controller's telemetry of a joint (``CTRL_TPDO1``, ``J1_CTRL_TPDO2``, ...).
_TELEMETRY = re.compile(r"(?:^|_)CTRL_TPDO\d+$")


@dataclass(frozen=True)
class RigBus:
    """One CAN bus of the rig: its name, the node-ID of its controller (the SYNC producer
    and NMT master; drives use it unless they name their own), its (arbitration-phase)
    bit rate, 1 Mbit/s at most, and whether it is a CAN FD bus (``data_bitrate``: the
    data phase's bit rate with bit-rate switching, 0 for none).  On an FD bus the
    database says so (``BusType`` "CAN FD"); on it the joints' cyclic drive PDOs are
    packed into FD frames and their telemetry is FD (:func:`_fd_packed`)."""

    name: str = "control"
    controller_node_id: int = 1
    bitrate: int = 1_000_000
    fd: bool = False
    data_bitrate: int = 0


@dataclass(frozen=True)
class RigDrive:
    """One drive of the rig: the joint it moves (e.g. ``J1``: letters, digits, ``_``,
    ``.`` and ``-``, not starting with a digit, the two last written ``_`` in DBC names;
    empty for the single-joint names), its CANopen node-ID, the bus it sits on, its PDO
    mapping (a shipped mapping name, :data:`hdhil.dbc.MAPPINGS`, or a DCF of the drive
    that overrides it) and the node-ID of the controller node that runs its loop (None:
    the bus's controller)."""

    joint: str
    node_id: int
    bus: str = "control"
    mapping: str = "raw"
    dcf: str | Path | None = None
    controller_node_id: int | None = None


@dataclass(frozen=True)
class _Node:
    """A controller node of one bus: its node-ID, DBC name, name tag of its service
    frames and the joints it serves (in layout order)."""

    node_id: int
    name: str
    tag: str
    primary: bool
    joints: list[_Joint] = field(default_factory=list)


@dataclass(frozen=True)
class _Joint:
    """A drive placed on the rig: its index among all the rig's drives, its name prefix,
    the DBC name of its node and the node-ID of its controller."""

    index: int
    drive: RigDrive
    prefix: str
    node_name: str
    controller_id: int


def truth_frame_id(joint_index: int, template_id: int) -> int:
    """The 29-bit identifier of a ground-truth frame (``template_id``, one of
    ``truth.dbc``'s 0x1F0001..0x1F0003) of the rig's ``joint_index``-th joint."""
    if not 0 <= joint_index < MAX_TRUTH_JOINTS:
        raise UserError(f"a rig has at most {MAX_TRUTH_JOINTS} joints with ground truth")
    return _truth_frame_id(joint_index, template_id)


def _int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check_node_id(value: object, what: str) -> int:
    if not _int(value) or not 1 <= value <= 127:  # type: ignore[operator]
        raise UserError(f"{what}: node-ID {value!r} is outside 1..127")
    return value  # type: ignore[return-value]


def _drive_file(drive: RigDrive) -> Path:
    if drive.dcf is not None:
        path = Path(drive.dcf)
        if not path.is_file():
            raise UserError(f"joint {drive.joint or '(single)'}: DCF {path} is not a file")
        return path
    if drive.mapping not in MAPPINGS:
        raise UserError(
            f"joint {drive.joint or '(single)'}: unknown mapping {drive.mapping!r} "
            f"(known: {', '.join(MAPPINGS)})"
        )
    dcf = mapping_dcf(drive.mapping)
    return dcf if dcf is not None else eds_path("drive")


def _stamp(path: Path) -> tuple[str, int, int]:
    """``path`` with its modification time and size: the key of what is read from it."""
    stat = path.stat()
    return str(path), stat.st_mtime_ns, stat.st_size


@cache
def _file_layouts(stamp: tuple[str, int, int]) -> tuple[int, dict[tuple[str, int], PdoLayout]]:
    """The node-ID the file ``stamp`` names was written for and its PDOs at that
    node-ID."""
    path = stamp[0]
    try:  # each parse kept on disk (hdhil.canopen.od): a node's start-up reads it too
        written_for = reference_od(path).node_id
        node = written_for if _int(written_for) and 1 <= written_for <= 127 else None
        node = node or node_ids("control")["DRIVE"]
        return node, od_layouts(reference_od(path, node))
    except Exception as exc:
        raise UserError(f"{path}: not a readable DCF/EDS ({exc})") from None


def _rebased(
    layouts: Mapping[tuple[str, int], PdoLayout], written_for: int, node_id: int
) -> dict[tuple[str, int], PdoLayout]:
    out = {}
    for key, layout in layouts.items():
        if key in PDO_FUNCTION_CODES and layout.cob_id == predefined_cob_id(*key, written_for):
            layout = replace(layout, cob_id=predefined_cob_id(*key, node_id))
        out[key] = layout
    return out


def drive_pdo_layouts(drive: RigDrive) -> dict[tuple[str, int], PdoLayout]:
    """The PDOs of ``drive`` at its node-ID, keyed ``("tpdo", 1)`` etc.: its DCF (or its
    shipped mapping's, or the EDS defaults), each COB-ID of the pre-defined connection
    set moved to the drive's node-ID (what the drive must be configured with and what
    its database messages use)."""
    _check_node_id(drive.node_id, f"joint {drive.joint or '(single)'}")
    written_for, layouts = _file_layouts(_stamp(_drive_file(drive)))
    return _rebased(layouts, written_for, drive.node_id)


def _at_template(
    layouts: Mapping[tuple[str, int], PdoLayout],
) -> dict[tuple[str, int], PdoLayout]:
    """``layouts`` with each PDO of the pre-defined connection set at its COB-ID for the
    shipped drive's node-ID, whatever the file sets: where its message is in the
    single-joint database (its name and signals; its identifier on the rig comes from
    :func:`drive_pdo_layouts`)."""
    node = node_ids("control")["DRIVE"]
    return {
        key: replace(lay, cob_id=predefined_cob_id(*key, node))
        if key in PDO_FUNCTION_CODES
        else lay
        for key, lay in layouts.items()
    }


def _template(drive: RigDrive) -> tuple[Any, dict[tuple[str, int], PdoLayout]]:
    """The single-joint control database of ``drive``'s mapping (its drive at node-ID
    2, as the shipped files) and the drive's PDOs in it."""
    stamp = _stamp(_drive_file(drive))
    at_template = _at_template(_file_layouts(stamp)[1])
    if drive.dcf is None:
        return _mapping_template(drive.mapping), at_template
    return _dcf_template(stamp), at_template


#: The single-joint control database of a shipped mapping (read only: every message
#: placed on a rig is a copy).
_mapping_template = cache(mapping_database)


@cache
def _dcf_template(stamp: tuple[str, int, int]) -> Any:
    return control_database(_at_template(_file_layouts(stamp)[1]))


# What a message of the single-joint control database is, by its identifier there:
# ("bus",), ("controller",), ("drive",), ("pdo", kind, number), ("telemetry", number),
# or ("unused",): a PDO of control.dbc the drive's mapping does not send (not valid).
Role = tuple[Any, ...]


def _roles(template: Any, layouts: Mapping[tuple[str, int], PdoLayout]) -> dict[int, Role]:
    ids = node_ids("control")
    drive_id, controller_id = ids["DRIVE"], ids["CONTROLLER"]
    pdos = {lay.cob_id: (key, lay.valid) for key, lay in layouts.items()}
    telemetry = {predefined_cob_id("tpdo", n, controller_id): n for n in range(1, 5)}
    roles: dict[int, Role] = {}
    for message in template.messages:
        fid = message.frame_id
        base, node = fid & ~0x7F, fid & 0x7F
        if fid in (NMT_COB_ID, SYNC_COB_ID):
            roles[fid] = ("bus",)
        elif fid in pdos:
            key, valid = pdos[fid]
            roles[fid] = ("pdo", *key) if valid else ("unused",)
        elif base in _SERVICE_BASES and node == drive_id:
            roles[fid] = ("drive",)
        elif base in _SERVICE_BASES and node == controller_id:
            roles[fid] = ("controller",)
        elif fid in telemetry:
            roles[fid] = ("telemetry", telemetry[fid])
        else:
            raise ValueError(f"{message.name} (0x{fid:03X}): no rule places it on a rig")
    return roles


def _rewrite(text: str | None, names: Mapping[str, str], ids: Mapping[int, int]) -> str | None:
    """``text`` with each ``node-ID n`` and message name of the single-joint database
    replaced by the rig's."""
    if not text:
        return text
    text = re.sub(r"\bnode-ID (\d+)\b", lambda m: f"node-ID {ids.get(int(m[1]), m[1])}", text)
    return _IDENTIFIER.sub(lambda m: names.get(m[0], m[0]), text)


def _nodes(names: Iterable[str], to: Mapping[str, Sequence[str]]) -> list[str]:
    out: list[str] = []
    for name in names:
        for new in to.get(name, (name,)):
            if new not in out:
                out.append(new)
    return out


def _message(
    template: Any,
    frame_id: int,
    name: str,
    to: Mapping[str, Sequence[str]],
    names: Mapping[str, str],
    ids: Mapping[int, int],
) -> Any:
    message = copy.deepcopy(template)
    message.frame_id = frame_id
    message.name = name
    message.senders[:] = _nodes(message.senders, to)
    message.comment = _rewrite(message.comment, names, ids)
    for signal in message.signals:
        signal.receivers[:] = _nodes(signal.receivers, to)
        signal.comment = _rewrite(signal.comment, names, ids)
    message.refresh()
    return message


def _node(template: Any, name: str, node_id: int | None, comment: str | None) -> Any:
    """A copy of ``template`` named ``name``, with ``comment`` and its NodeId attribute
    set (a new Node: cantools' ``Node.comment`` setter does not reach the comment the
    DBC writer reads)."""
    from cantools.database.can import Node
    from cantools.database.can.formats.dbc.dbc_attribute import DbcAttribute

    dbc = copy.deepcopy(template.dbc)
    if node_id is not None and dbc is not None and "NodeId" in dbc.attributes:
        dbc.attributes["NodeId"] = DbcAttribute(node_id, dbc.attributes["NodeId"].definition)
    return Node(name, comment, dbc_specifics=dbc)


def _check_layout(
    drives: Sequence[RigDrive], buses: Sequence[RigBus]
) -> tuple[dict[str, RigBus], list[_Joint]]:
    """The buses by name (those the drives name, with defaults, when ``buses`` is
    empty) and the joints; a one-line UserError for any mistake."""
    if not drives:
        raise UserError("the rig has no drives")
    by_bus: dict[str, RigBus] = {}
    for bus in buses:
        if not isinstance(bus.name, str) or not _NAME.fullmatch(bus.name):
            raise UserError(f"bus name {bus.name!r} is not a name (letters, digits, _ . -)")
        if bus.name in by_bus:
            raise UserError(f"bus {bus.name} is listed twice")
        _check_node_id(bus.controller_node_id, f"the controller of bus {bus.name}")
        if not _int(bus.bitrate) or not 0 < bus.bitrate <= _MAX_NOMINAL_BITRATE:
            raise UserError(f"bus {bus.name}: bit rate {bus.bitrate!r} is not 1..1000000 bit/s")
        if not isinstance(bus.fd, bool):
            raise UserError(f"bus {bus.name}: fd must be true or false, not {bus.fd!r}")
        if bus.data_bitrate != 0 and not (
            bus.fd and _int(bus.data_bitrate)
            and bus.bitrate <= bus.data_bitrate <= _MAX_DATA_BITRATE
        ):  # fmt: skip
            raise UserError(
                f"bus {bus.name}: data bit rate {bus.data_bitrate!r} needs fd and is "
                f"{bus.bitrate}..{_MAX_DATA_BITRATE} bit/s"
            )
        by_bus[bus.name] = bus
    joints: list[_Joint] = []
    for index, drive in enumerate(drives):
        what = f"joint {drive.joint or '(single)'}"
        if not isinstance(drive.joint, str):
            raise UserError(f"joint name {drive.joint!r} is not a string")
        if drive.joint == "" and len(drives) > 1:
            raise UserError("every joint of a rig of several drives needs a name")
        if drive.joint and not _NAME.fullmatch(drive.joint):
            raise UserError(
                f"joint name {drive.joint!r} is not a name (letters, digits, _ . -, not "
                "starting with a digit)"
            )
        prefix = f"{re.sub(r'[.-]', '_', drive.joint)}_" if drive.joint else ""
        for other in joints:
            if other.drive.joint == drive.joint:
                raise UserError(f"joint {drive.joint} is listed twice")
            if other.prefix == prefix:
                raise UserError(
                    f"joints {other.drive.joint} and {drive.joint} have the same DBC name "
                    f"{prefix[:-1]} (. and - are written _)"
                )
        _check_node_id(drive.node_id, what)
        if drive.bus not in by_bus:
            if buses:
                raise UserError(f"{what}: unknown bus {drive.bus!r} (known: {', '.join(by_bus)})")
            if not isinstance(drive.bus, str) or not _NAME.fullmatch(drive.bus):
                raise UserError(f"{what}: bus name {drive.bus!r} is not a name")
            by_bus[drive.bus] = RigBus(drive.bus)
        controller = by_bus[drive.bus].controller_node_id
        if drive.controller_node_id is not None:
            controller = _check_node_id(drive.controller_node_id, f"the controller of {what}")
        _drive_file(drive)
        joints.append(_Joint(index, drive, prefix, f"{prefix}DRIVE", controller))
    if len(joints) > MAX_TRUTH_JOINTS:
        raise UserError(f"a rig has at most {MAX_TRUTH_JOINTS} joints")
    for bus in by_bus.values():
        on_bus = [j for j in joints if j.drive.bus == bus.name]
        controllers = {bus.controller_node_id, *(j.controller_id for j in on_bus)}
        owner: dict[int, str] = {}
        for joint in on_bus:
            nid, name = joint.drive.node_id, joint.drive.joint or "(single)"
            if nid in owner:
                raise UserError(
                    f"bus {bus.name}: node-ID {nid} is used by joints {owner[nid]} and {name}"
                )
            if nid in controllers:
                raise UserError(
                    f"bus {bus.name}: node-ID {nid} is used by joint {name} and a controller"
                )
            owner[nid] = name
    return by_bus, joints


def _speed(bitrate: int) -> str:
    if bitrate % 1_000_000 == 0:
        return f"{bitrate // 1_000_000} Mbit/s"
    if bitrate % 1000 == 0:
        return f"{bitrate // 1000} kbit/s"
    return f"{bitrate} bit/s"


def _bus_comment(
    template: str | None, bus: RigBus, controllers: Sequence[_Node], joints: Sequence[_Joint]
) -> str | None:
    if not template:
        return template
    ids = ", ".join(str(c.node_id) for c in controllers)
    ctrl = f"controller node-ID{'s' if len(controllers) > 1 else ''} {ids}"
    if len(joints) == 1 and not joints[0].drive.joint:
        drives = f"drive node-ID {joints[0].drive.node_id}"
    else:
        listed = ", ".join(f"{j.drive.node_id} ({j.drive.joint})" for j in joints)
        drives = f"drive node-ID{'s' if len(joints) > 1 else ''} {listed}"
    legacy = "controller node-ID 1, drive node-ID 2, 1 Mbit/s"
    speed = _speed(bus.bitrate)
    if bus.fd:
        data = f", data phase {_speed(bus.data_bitrate)}" if bus.data_bitrate else ""
        speed = f"CAN FD at {speed}{data} (cyclic PDOs packed into FD frames)"
    text = template.replace(legacy, f"{ctrl}, {drives}, {speed}")
    if bus.name != "control":
        text = text.replace(
            "Control bus of the hdhil drive link", f"Control bus {bus.name} of the hdhil rig"
        )
    return text


def _specifics(control: Any, truth: Any, bus: RigBus) -> Any:
    """The database-level DBC specifics: ``control``'s attributes (the bus's bit rate and
    type set), both databases' attribute definitions and value tables (as the merged
    export)."""
    from cantools.database.can.formats.dbc.dbc_attribute import DbcAttribute
    from cantools.database.can.formats.dbc.dbc_specifics import DbcSpecifics

    definitions: OrderedDict[str, Any] = OrderedDict(control.dbc.attribute_definitions)
    for name, definition in truth.dbc.attribute_definitions.items():
        definitions.setdefault(name, definition)
    value_tables = OrderedDict(control.dbc.value_tables)
    value_tables.update(truth.dbc.value_tables)
    attributes = OrderedDict(control.dbc.attributes)
    if "Baudrate" in attributes:
        attributes["Baudrate"] = DbcAttribute(bus.bitrate, attributes["Baudrate"].definition)
    if bus.fd and "BusType" in attributes:
        attributes["BusType"] = DbcAttribute("CAN FD", attributes["BusType"].definition)
    return DbcSpecifics(
        attributes=attributes,
        attribute_definitions=definitions,
        environment_variables=control.dbc.environment_variables,
        value_tables=value_tables,
    )


def _truth_messages(joints: Iterable[_Joint]) -> list[Any]:
    truth = database("truth")
    out = []
    for joint in joints:
        names = {m.name: f"{joint.prefix}{m.name}" for m in truth.messages}
        for message in truth.messages:
            frame_id = truth_frame_id(joint.index, message.frame_id)
            out.append(_message(message, frame_id, names[message.name], {}, names, {}))
    return out


def _unique(messages: Sequence[Any], where: str) -> None:
    ids: dict[tuple[int, bool], str] = {}
    names: set[str] = set()
    for message in messages:
        key = (message.frame_id, message.is_extended_frame)
        if key in ids:
            raise UserError(
                f"{where}: {ids[key]} and {message.name} have the same identifier "
                f"0x{message.frame_id:03X} (a DCF that fixes a COB-ID used by two drives?)"
            )
        if message.name in names:
            raise UserError(f"{where}: two messages are named {message.name}")
        ids[key] = message.name
        names.add(message.name)


@dataclass(frozen=True)
class PackedMember:
    """One joint's frame inside a packed FD frame: the joint, the message it stands for
    (its name and identifier on a classical bus), its first byte and its length."""

    joint: str
    name: str
    frame_id: int
    offset: int
    length: int


@dataclass(frozen=True)
class PackedPdo:
    """A CAN FD frame that carries one cyclic PDO of several joints of an FD bus, one
    after another (:func:`_fd_packed`): its name and identifier in the bus's database,
    its length on the wire (an FD length) and its members in order."""

    name: str
    frame_id: int
    length: int
    members: tuple[PackedMember, ...]


#: The most bytes an FD frame carries.
_FD_MAX = 64


def _fd_length(n: int) -> int:
    from hdhil.can.bittiming import fd_length

    return int(fd_length(n))


def _fd_packed(
    messages: list[Any], origin: Mapping[int, tuple[_Joint, str, Role]]
) -> tuple[list[Any], list[PackedPdo]]:
    """An FD bus's messages: each cyclic drive PDO of the joints (``DRIVE_TPDO1``, the
    sensors, and ``DRIVE_RPDO1``, the command, with a cycle time) packed into CAN FD
    frames, the joints' payloads one after another in layout order, at most 64 bytes a
    frame and a joint's payload never split (as :func:`hdhil.can.schedule.fd_pack` plans
    them): ``FD_DRIVE_TPDO1`` (``FD_DRIVE_TPDO1_2``, ... when 64 bytes do not hold them
    all) at the identifier of its first joint's frame, each joint's signals under its
    name prefix (``J1_ADC_torque``).  The joints' cyclic telemetry becomes FD frames of
    its own.  The packed frames' layouts are generated from the joints' own messages,
    so cantools decodes every joint's signals by name."""
    from cantools.database.can import Message

    groups: dict[str, list[Any]] = {}
    for message in messages:
        joint, template, role = origin.get(id(message), (None, "", ("",)))
        if joint is None:
            continue
        if role[0] == "telemetry" and message.cycle_time:
            message.is_fd = True
        elif role[0] == "pdo" and message.cycle_time:
            groups.setdefault(template, []).append(message)
    packed_ids = {id(m) for group in groups.values() for m in group}
    out: list[Any] = []
    done: set[str] = set()
    packing: list[PackedPdo] = []
    for message in messages:
        if id(message) not in packed_ids:
            out.append(message)
            continue
        template = origin[id(message)][1]
        if template in done:
            continue
        done.add(template)
        chunks: list[list[Any]] = [[]]
        for member in groups[template]:
            if chunks[-1] and sum(m.length for m in chunks[-1]) + member.length > _FD_MAX:
                chunks.append([])
            chunks[-1].append(member)
        for k, chunk in enumerate(chunks):
            name = f"FD_{template}" + (f"_{k + 1}" if k else "")
            members, signals, offset = [], [], 0
            for member in chunk:
                joint = origin[id(member)][0]
                for signal in member.signals:
                    copied = copy.deepcopy(signal)
                    copied.name = f"{joint.prefix}{signal.name}"
                    copied.start += 8 * offset
                    signals.append(copied)
                members.append(PackedMember(joint.drive.joint, member.name, member.frame_id,
                                            offset, member.length))  # fmt: skip
                offset += member.length
            first = chunk[0]
            joints = ", ".join(m.joint for m in members)
            comment = (
                f"CAN FD frame with the {template} of joints {joints}, in this order "
                f"({first.length} bytes each): the cyclic PDO of the joints packed into one "
                "frame, sent with bit-rate switching."
            )
            senders = _nodes([s for m in chunk for s in m.senders], {})
            packed = Message(
                frame_id=first.frame_id,
                name=name,
                length=_fd_length(offset),
                signals=signals,
                comment=comment,
                senders=senders,
                cycle_time=first.cycle_time,
                send_type=first.send_type,
                dbc_specifics=copy.deepcopy(first.dbc),
                is_fd=True,
                strict=True,
            )
            out.append(packed)
            packing.append(PackedPdo(name, first.frame_id, packed.length, tuple(members)))
    return out, packing


def _bus_database(
    bus: RigBus, joints: Sequence[_Joint], packing: list[PackedPdo] | None = None
) -> Any:
    from cantools.database.can import Bus, Database

    ids = node_ids("control")
    drive_id, controller_id = ids["DRIVE"], ids["CONTROLLER"]
    truth = database("truth")

    order = [bus.controller_node_id, *(j.controller_id for j in joints)]
    several = len(set(order)) > 1
    controllers: dict[int, _Node] = {}
    for nid in order:
        if nid not in controllers:
            tag = str(nid) if several else ""
            controllers[nid] = _Node(nid, f"CONTROLLER{tag}", tag, nid == bus.controller_node_id)
    for joint in joints:
        controllers[joint.controller_id].joints.append(joint)
    primary = controllers[bus.controller_node_id]

    templates: dict[int, tuple[Any, dict[int, Role]]] = {}
    layouts: dict[int, dict[tuple[str, int], PdoLayout]] = {}
    for joint in joints:
        template, at_template = _template(joint.drive)
        templates[joint.index] = (template, _roles(template, at_template))
        layouts[joint.index] = drive_pdo_layouts(joint.drive)
    reference, roles = templates[joints[0].index]
    per_joint = {
        m.name
        for template, template_roles in templates.values()
        for m in template.messages
        if template_roles[m.frame_id][0] in ("drive", "pdo", "telemetry")
    }
    per_controller = {m.name for m in reference.messages if roles[m.frame_id] == ("controller",)}
    telemetry_count = sum(1 for r in roles.values() if r[0] == "telemetry")

    def joint_names(joint: _Joint) -> dict[str, str]:
        tag = controllers[joint.controller_id].tag
        names = {name: f"{joint.prefix}{name}" for name in per_joint}
        names.update({name: f"{name}{tag}" for name in per_controller})
        return names

    def joint_message(joint: _Joint, message: Any, role: Role) -> Any:
        controller = controllers[joint.controller_id]
        if role[0] == "pdo":
            frame_id = layouts[joint.index][(role[1], role[2])].cob_id
        elif role[0] == "drive":
            frame_id = (message.frame_id & ~0x7F) + joint.drive.node_id
        else:  # telemetry: the controller's TPDOs taken two per joint it serves
            number = role[1] + telemetry_count * controller.joints.index(joint)
            if number > 4:
                served = ", ".join(j.drive.joint for j in controller.joints)
                raise UserError(
                    f"bus {bus.name}: controller node-ID {controller.node_id} reports joints "
                    f"{served}, but its four pre-defined TPDOs carry the telemetry of two; "
                    f"give joint {joint.drive.joint} a controller node of its own"
                )
            frame_id = predefined_cob_id("tpdo", number, controller.node_id)
        to = {"CONTROLLER": [controller.name], "DRIVE": [joint.node_name]}
        renumber = {drive_id: joint.drive.node_id, controller_id: controller.node_id}
        names = joint_names(joint)
        return _message(message, frame_id, names[message.name], to, names, renumber)

    messages: list[Any] = []
    #: Each joint's message: its joint, its name in the single-joint database, its role.
    origin: dict[int, tuple[_Joint, str, Role]] = {}
    placed: set[tuple[int, str]] = set()
    for message in reference.messages:
        role = roles[message.frame_id]
        if role == ("bus",):
            others = [c.name for c in controllers.values() if not c.primary]
            to = {"CONTROLLER": [primary.name], "DRIVE": [j.node_name for j in joints] + others}
            messages.append(_message(message, message.frame_id, message.name, to, {},
                                     {controller_id: primary.node_id}))  # fmt: skip
        elif role == ("controller",):
            for c in controllers.values():
                to = {"CONTROLLER": [c.name], "DRIVE": [j.node_name for j in c.joints]}
                names = {name: f"{name}{c.tag}" for name in per_controller}
                frame_id = (message.frame_id & ~0x7F) + c.node_id
                messages.append(_message(message, frame_id, names[message.name], to, names,
                                         {controller_id: c.node_id}))  # fmt: skip
        elif role != ("unused",):
            for joint in joints:
                own, own_roles = templates[joint.index]
                mine = message
                if role[0] == "pdo":  # this joint's own PDO of the same kind and number
                    matches = [m for m in own.messages if own_roles[m.frame_id] == role]
                    if not matches:
                        continue
                    mine = matches[0]
                placed.add((joint.index, mine.name))
                messages.append(joint_message(joint, mine, role))
                origin[id(messages[-1])] = (joint, mine.name, role)
    for joint in joints:  # PDOs a joint's mapping has and the first joint's has not
        own, own_roles = templates[joint.index]
        for message in own.messages:
            role = own_roles[message.frame_id]
            if role[0] == "pdo" and (joint.index, message.name) not in placed:
                messages.append(joint_message(joint, message, role))
                origin[id(messages[-1])] = (joint, message.name, role)
    if bus.fd:
        messages, packed = _fd_packed(messages, origin)
        if packing is not None:
            packing.extend(packed)
    messages += _truth_messages(joints)
    _unique(messages, f"bus {bus.name}")

    nodes: list[Any] = []
    for node in reference.nodes:
        if node.name == "CONTROLLER":
            for c in controllers.values():
                comment = _rewrite(node.comment, {}, {controller_id: c.node_id})
                if comment and not c.primary:
                    comment = comment.replace("SYNC producer, ", "")
                if comment and any(j.drive.joint for j in c.joints):
                    comment += f" Runs the loop of {', '.join(j.drive.joint for j in c.joints)}."
                nodes.append(_node(node, c.name, c.node_id, comment))
        elif node.name == "DRIVE":
            for joint in joints:
                comment = _rewrite(node.comment, {}, {drive_id: joint.drive.node_id})
                if comment and joint.drive.joint:
                    comment += f" Joint {joint.drive.joint}."
                nodes.append(_node(node, joint.node_name, joint.drive.node_id, comment))
        else:
            nodes.append(copy.deepcopy(node))
    names = {n.name for n in nodes}
    nodes += [copy.deepcopy(n) for n in truth.nodes if n.name not in names]

    comment = _bus_comment(reference.buses[0].comment if reference.buses else None, bus,
                           list(controllers.values()), joints)  # fmt: skip
    return Database(
        messages=messages,
        nodes=nodes,
        buses=[Bus(bus.name, comment, baudrate=bus.bitrate, fd_baudrate=bus.data_bitrate or None)],
        version=reference.version,
        dbc_specifics=_specifics(reference, truth, bus),
        strict=True,
    )


def rig_databases(drives: Sequence[RigDrive], buses: Sequence[RigBus] = ()) -> dict[str, Any]:
    """One :class:`cantools.database.can.Database` per bus of the rig, by bus name (in
    the order of ``buses``, or of first use by ``drives`` when ``buses`` is empty: then
    every bus has the defaults of :class:`RigBus`): every frame on the bus and the
    ground truth of its joints, named and numbered as the module says.  A mistake in
    the layout is a one-line :class:`UserError`."""
    return rig_packing(drives, buses)[0]


def rig_packing(
    drives: Sequence[RigDrive], buses: Sequence[RigBus] = ()
) -> tuple[dict[str, Any], dict[str, tuple[PackedPdo, ...]]]:
    """:func:`rig_databases` and, per bus, its FD-packed PDOs (:class:`PackedPdo`; none
    on a classical bus): which joint frames each packed frame carries, where."""
    by_bus, joints = _check_layout(drives, buses)
    out = {}
    packed: dict[str, tuple[PackedPdo, ...]] = {}
    for name, bus in by_bus.items():
        on_bus = [j for j in joints if j.drive.bus == name]
        if on_bus:
            packing: list[PackedPdo] = []
            out[name] = _bus_database(bus, on_bus, packing)
            packed[name] = tuple(packing)
    return out, packed


def truth_database(drives: Sequence[RigDrive], buses: Sequence[RigBus] = ()) -> Any:
    """The ground truth of every joint of the rig as one database (``truth.dbc``'s
    messages per joint, numbered and named as :func:`rig_databases` does): for a trace
    that records the truth of all buses on one channel."""
    from cantools.database.can import Database

    _, joints = _check_layout(drives, buses)
    truth = database("truth")
    return Database(
        messages=_truth_messages(joints),
        nodes=copy.deepcopy(truth.nodes),
        buses=copy.deepcopy(truth.buses),
        version=truth.version,
        dbc_specifics=copy.deepcopy(truth.dbc),
        strict=True,
    )


@cache
def single_joint_databases(
    drive_node_id: int = 2,
    controller_node_id: int = 1,
    mapping: str = "raw",
    dcf: str | None = None,
) -> dict[str, Any]:
    """The databases of the single-joint rig with its drive at ``drive_node_id`` and the
    controller at ``controller_node_id`` (the drive's ``mapping``, or its ``dcf``), split
    as ``control.dbc`` and ``truth.dbc`` are: ``{"control": ..., "truth": ...}``, the
    first :func:`rig_databases`'s bus without its 29-bit truth frames.  Shared: for
    reading only.  A mistake in the layout is a one-line :class:`UserError`."""
    drives = [RigDrive("", drive_node_id, mapping=mapping, dcf=dcf)]
    buses = [RigBus(controller_node_id=controller_node_id)]
    control = rig_databases(drives, buses)["control"]
    control.messages[:] = [m for m in control.messages if not m.is_extended_frame]
    control.refresh()
    return {"control": control, "truth": truth_database(drives, buses)}


def is_telemetry(name: str) -> bool:
    """Whether the message ``name`` of a rig's database is a controller's telemetry of a
    joint (``CTRL_TPDOn``, with the joint's prefix on a rig)."""
    return _TELEMETRY.search(name) is not None


def telemetry_phases(db: Any, every: int) -> dict[int, int]:
    """Decimated telemetry (a bus's ``telemetry_every``): the cycle each telemetry frame
    of the bus database ``db`` goes in, by identifier.  The k-th joint with telemetry in
    the database (:func:`is_telemetry`, joints in the order of their first telemetry
    message) sends all its telemetry frames in the SYNC cycles c with c % ``every`` ==
    k % ``every``: the joints spread round robin over the cycles, each joint's frames in
    one cycle (its measured torque and its desired torque of one sample, as the
    tracking score pairs them).  The planner (:mod:`hdhil.analysis.rigplan`) and the
    controller nodes of a rig run (:mod:`hdhil.rig.rigrun`) both take them from here."""
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ValueError(f"telemetry_every must be an integer >= 1, got {every!r}")
    joints: dict[str, int] = {}
    out = {}
    for message in db.messages:
        match = _TELEMETRY.search(message.name) if message.cycle_time else None
        if match is None:
            continue
        joint = joints.setdefault(message.name[: match.start()], len(joints))
        out[message.frame_id] = joint % every
    return out
