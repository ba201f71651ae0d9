"""Which process data two nodes exchange, from their object dictionaries.

A drive configured from a DCF (CiA 306) sends and receives the PDOs its mapping
parameters say; its controller must send what the drive receives and decode what it
sends.  This module derives the controller's side from the drive's, so nothing about a
mapping is typed twice:

- :func:`dcf_layouts`: the drive's valid PDOs as the DCF leaves them;
- :func:`peer_pdo_writes`: the writes that give the controller the matching PDOs (a
  transmit PDO of the drive is a receive PDO of the controller with the same COB-ID,
  each mapped object the controller's object of the same name and data type);
- :func:`layout_codec`: a compiled frame codec for a live layout, typed from the object
  dictionary;
- :func:`control_database`: ``control.dbc`` with the PDO messages a non-default mapping
  changes rebuilt from the drive's EDS, so tools decode a trace of that mapping;
- :func:`mapping_database`: ``control.dbc`` as a shipped mapping leaves it;
- :data:`MAPPINGS`: the shipped mappings by name (``raw``: the EDS defaults, no DCF;
  ``cst``: ``dbc/drive-cst.dcf``, CiA 402 cyclic synchronous torque; ``cst-sensor``:
  ``dbc/drive-cst-sensor.dcf``, the same with the joint-torque sensor 0x2102).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import canopen
from canopen.objectdictionary import ObjectDictionary, ODVariable, datatypes

from hdhil.canopen.od import variable
from hdhil.canopen.pdo import DUMMY_BITS, MAX_PDOS, PDO_NOT_VALID, PdoLayout, read_layout
from hdhil.dbc import MAPPINGS, FrameCodec, dcf_path, eds_path

__all__ = [
    "MAPPINGS",
    "control_database",
    "dcf_layouts",
    "layout_codec",
    "layout_message",
    "layouts_from_json",
    "layouts_to_json",
    "mapping_database",
    "mapping_dcf",
    "peer_pdo_writes",
    "raw_sensor_frames",
    "trace_decoder",
    "trace_node_ids",
]

Write = tuple[int, int, int]

_SIGNED = {datatypes.INTEGER8, datatypes.INTEGER16, datatypes.INTEGER32, datatypes.INTEGER64}
_FLOAT = {datatypes.REAL32, datatypes.REAL64}


def mapping_dcf(name: str) -> Path | None:
    """The DCF of the shipped mapping ``name`` (None for ``raw``); ``ValueError`` for an
    unknown name."""
    if name not in MAPPINGS:
        raise ValueError(f"unknown mapping {name!r} (known: {', '.join(MAPPINGS)})")
    file = MAPPINGS[name]
    return None if file is None else dcf_path(file)


def _reader(od: ObjectDictionary) -> Callable[[int, int], int]:
    def read(index: int, sub: int) -> int:
        var = variable(od, index, sub)
        if var is None:
            raise KeyError(f"0x{index:04X}:{sub:02X}")
        value = var.value if getattr(var, "value", None) is not None else var.default
        return int(value or 0)

    return read


def od_layouts(
    od: ObjectDictionary, read: Callable[[int, int], int] | None = None
) -> dict[tuple[str, int], PdoLayout]:
    """Every PDO of ``od`` (valid or not) as ``read`` gives its parameters (default: the
    DCF's ``ParameterValue`` where set, else the EDS default)."""
    read = read or _reader(od)
    out = {}
    for kind in ("rpdo", "tpdo"):
        for n in range(1, MAX_PDOS + 1):
            layout = read_layout(od, read, kind, n)
            if layout is not None:
                out[(kind, n)] = layout
    return out


def dcf_layouts(
    path: str | Path, node_id: int
) -> tuple[ObjectDictionary, dict[tuple[str, int], PdoLayout]]:
    """The node's object dictionary read from the DCF at ``path`` and its PDOs as the
    DCF leaves them.  ``ValueError`` for a file canopen cannot read."""
    try:
        od = canopen.import_od(str(path), node_id)
    except Exception as exc:
        raise ValueError(f"{path}: not a readable DCF/EDS ({exc})") from None
    return od, od_layouts(od)


def _by_name(od: ObjectDictionary) -> dict[str, ODVariable]:
    names: dict[str, ODVariable] = {}
    for index in od:
        obj = od[index]
        variables = (
            [obj]
            if isinstance(obj, ODVariable)
            else [v for s, v in obj.subindices.items() if s > 0]
        )
        for var in variables:
            names.setdefault(var.name, var)
    return names


def _translate(
    entries: Iterable[tuple[int, int, int]],
    peer_od: ObjectDictionary,
    own: dict[str, ODVariable],
    what: str,
) -> list[int]:
    out = []
    for index, sub, bits in entries:
        if index in DUMMY_BITS:
            out.append(index << 16 | sub << 8 | bits)
            continue
        peer = variable(peer_od, index, sub)
        name = peer.name if peer is not None else f"0x{index:04X}:{sub:02X}"
        mine = own.get(name) if peer is not None else None
        if mine is None:
            raise ValueError(
                f"{what} maps {name} (0x{index:04X}:{sub:02X}), which the controller's "
                "object dictionary does not have"
            )
        if mine.data_type != peer.data_type or len(mine) != bits:
            raise ValueError(
                f"{what} maps {name} as {bits} bits of type 0x{peer.data_type:04X}; the "
                f"controller's 0x{mine.index:04X}:{mine.subindex:02X} is {len(mine)} bits "
                f"of type 0x{mine.data_type:04X}"
            )
        out.append(mine.index << 16 | mine.subindex << 8 | bits)
    return out


def peer_pdo_writes(
    own_od: ObjectDictionary,
    own_read: Callable[[int, int], int],
    peer_od: ObjectDictionary,
    peer_layouts: Mapping[tuple[str, int], PdoLayout],
) -> list[Write]:
    """The writes (CiA 301 mapping procedure, in order) that make the controller's PDOs
    match the peer's: for each valid PDO of the peer, the controller's PDO of the other
    direction whose COB-ID (as ``own_read`` gives it now, valid or not) is the same gets
    the same objects, translated by name.  Empty when the two already match (the
    default mapping).  ``ValueError`` when the peer receives a PDO the controller has no
    transmit PDO for, or maps an object the controller does not have.
    """
    names = _by_name(own_od)
    own = od_layouts(own_od, own_read)
    by_cob = {(kind, layout.cob_id): layout for (kind, _), layout in own.items()}
    writes: list[Write] = []
    for (kind, number), peer in sorted(peer_layouts.items()):
        if not peer.valid:
            continue
        mine_kind = "tpdo" if kind == "rpdo" else "rpdo"
        mine = by_cob.get((mine_kind, peer.cob_id))
        what = f"the drive's {kind.upper()}{number} (COB-ID 0x{peer.cob_id:03X})"
        if mine is None:
            if kind == "rpdo":
                raise ValueError(
                    f"{what} has no matching transmit PDO in the controller "
                    f"(its TPDO COB-IDs: {', '.join(hex(c) for k, c in by_cob if k == 'tpdo')})"
                )
            continue  # a PDO the controller does not consume
        entries = _translate(peer.entries, peer_od, names, what)
        current = [i << 16 | s << 8 | b for i, s, b in mine.entries]
        if entries == current:
            continue
        comm, mapping = mine.comm_index, mine.comm_index + 0x200
        slots = len([s for s in own_od[mapping].subindices if s > 0])
        if len(entries) > slots:
            raise ValueError(
                f"{what} maps {len(entries)} objects; the controller's "
                f"{mine_kind.upper()}{mine.number} has room for {slots}"
            )
        cob = own_read(comm, 1)
        writes.append((comm, 1, cob | PDO_NOT_VALID))
        writes.append((mapping, 0, 0))
        writes.extend((mapping, sub, value) for sub, value in enumerate(entries, start=1))
        writes.append((mapping, 0, len(entries)))
        writes.append((comm, 1, cob))
    return writes


def layout_message(od: ObjectDictionary, layout: PdoLayout, name: str) -> Any:
    """A cantools message for ``layout``: one little-endian signal per mapped object,
    named, sized and signed from the object dictionary (dummy entries leave a gap)."""
    from cantools.database.can import Message, Signal
    from cantools.database.conversion import BaseConversion

    signals = []
    start = 0
    for index, sub, bits in layout.entries:
        if index not in DUMMY_BITS:
            var = variable(od, index, sub)
            if var is None:
                raise ValueError(f"{name}: 0x{index:04X}:{sub:02X} is not in the object dictionary")
            signals.append(
                Signal(
                    var.name,
                    start,
                    bits,
                    byte_order="little_endian",
                    is_signed=var.data_type in _SIGNED,
                    conversion=BaseConversion.factory(
                        scale=1, offset=0, is_float=var.data_type in _FLOAT
                    ),
                    comment=f"object 0x{index:04X}:{sub:02X}",
                )
            )
        start += bits
    return Message(layout.cob_id, name, layout.length, signals, strict=False)


def layout_codec(od: ObjectDictionary, layout: PdoLayout, name: str) -> FrameCodec:
    """The compiled codec of ``layout`` (signals named as the OD names the objects)."""
    return FrameCodec(layout_message(od, layout, name))


def layouts_to_json(layouts: Mapping[tuple[str, int], PdoLayout]) -> dict[str, Any]:
    """``{"tpdo1": {"cob_id": ..., "entries": [[index, sub, bits], ...]}, ...}`` of the
    valid PDOs (what a trace's sidecar records)."""
    return {
        f"{kind}{n}": {"cob_id": lay.cob_id, "entries": [list(e) for e in lay.entries]}
        for (kind, n), lay in sorted(layouts.items())
        if lay.valid
    }


def layouts_from_json(data: Mapping[str, Any]) -> dict[tuple[str, int], PdoLayout]:
    """The inverse of :func:`layouts_to_json` (``ValueError`` for malformed data)."""
    out = {}
    try:
        for key, value in data.items():
            kind, number = key[:4], int(key[4:])
            if kind not in ("rpdo", "tpdo"):
                raise ValueError(key)
            entries = tuple((int(i), int(s), int(b)) for i, s, b in value["entries"])
            out[(kind, number)] = PdoLayout(
                kind, number, int(value["cob_id"]), True, 1, 0.0, 0.0, entries
            )
    except (TypeError, KeyError, ValueError) as exc:
        raise ValueError(f"malformed PDO layouts in the trace's sidecar ({exc})") from None
    return out


def control_database(drive_layouts: Mapping[tuple[str, int], PdoLayout]) -> Any:
    """``control.dbc`` with each message whose identifier is a PDO of the drive whose
    mapping differs from the EDS default replaced by that PDO as the drive's EDS types
    it (same message name, e.g. ``DRIVE_TPDO1``)."""
    import copy

    from hdhil.dbc import database

    drive_od = canopen.import_od(str(eds_path("drive")), 2)
    defaults = od_layouts(drive_od)
    db = copy.deepcopy(database("control"))
    by_id = {m.frame_id: m for m in db.messages}
    for key, layout in drive_layouts.items():
        default = defaults.get(key)
        if default is not None and default.entries == layout.entries:
            continue
        old = by_id.get(layout.cob_id)
        name = old.name if old is not None else f"DRIVE_{key[0].upper()}{key[1]}"
        message = layout_message(drive_od, layout, name)
        if old is not None:
            message.senders.extend(old.senders)
            message.cycle_time = old.cycle_time
            db.messages.remove(old)
        db.messages.append(message)
    db.refresh()
    return db


def mapping_database(name: str) -> Any:
    """``control.dbc`` with the drive's PDOs as the shipped mapping ``name`` configures
    them (:func:`control_database` of its DCF; ``control.dbc`` itself for ``raw``).
    ``ValueError`` for an unknown name."""
    from hdhil.dbc import database, node_ids

    dcf = mapping_dcf(name)
    if dcf is None:
        return database("control")
    _, layouts = dcf_layouts(dcf, node_ids("control")["DRIVE"])
    return control_database(layouts)


def trace_decoder(trace: Path) -> Any:
    """The frame decoder (:class:`hdhil.can.traces.decode.FrameDecoder`) of ``trace``: the
    project DBCs, with the drive's PDOs as the trace's sidecar records them for a run in
    a mapping from a DCF (e.g. ``--mapping cst``: the sensor frame ``DRIVE_TPDO1``
    carries 0x6077 and 0x6064, decoded from the drive's EDS).  ``ValueError`` for a
    sidecar whose PDOs cannot be read."""
    from hdhil.can.traces.decode import FrameDecoder, default_decoder
    from hdhil.can.traces.sidecar import read_metadata
    from hdhil.dbc import database

    meta = read_metadata(trace) if Path(trace).is_file() else None
    if isinstance((meta or {}).get("rig"), dict):
        return rig_decoder(meta["rig"])  # type: ignore[index]
    drive_id, controller_id = trace_node_ids(meta)
    if (drive_id, controller_id) != (2, 1):
        return FrameDecoder(_layout_databases(meta or {}, drive_id, controller_id))
    pdos = (meta or {}).get("drive_pdos")
    if not pdos:
        return default_decoder()
    return FrameDecoder({"control": control_database(layouts_from_json(pdos)),
                         "truth": database("truth")})  # fmt: skip


def rig_sidecar_layout(
    rig: Mapping[str, Any],
) -> tuple[list[Any], dict[str, int], list[Any], list[int]]:
    """A rig's layout from its trace's sidecar ``rig`` entry: the buses
    (:class:`hdhil.canopen.rigdb.RigBus`), each bus's channel, the drives
    (:class:`~hdhil.canopen.rigdb.RigDrive`, the layout's order) and each joint's truth
    index.  ``ValueError`` for an entry that does not describe a layout."""
    from hdhil.canopen.rigdb import RigBus, RigDrive

    try:
        buses = [
            RigBus(str(b["name"]), int(b["controller_node_id"]), int(b["bitrate"]),
                   bool(b["fd"]), int(b["data_bitrate"]))
            for b in rig["buses"]
        ]  # fmt: skip
        channels = {str(b["name"]): int(b["channel"]) for b in rig["buses"]}
        drives = [
            RigDrive(str(j["name"]), int(j["node_id"]), str(j["bus"]),
                     controller_node_id=int(j["controller_node_id"]))
            for j in rig["joints"]
        ]  # fmt: skip
        indices = [int(j["joint_index"]) for j in rig["joints"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"the sidecar's rig layout cannot be read ({exc})") from None
    return buses, channels, drives, indices


def rig_decoder(rig: Mapping[str, Any]) -> Any:
    """The decoder of a rig's trace (:class:`hdhil.can.traces.decode.ChannelDecoder`) from
    its sidecar's ``rig`` entry (buses with their channels, joints): each bus's channel
    with the bus's database, the truth's channel 1 with every joint's truth
    (:func:`hdhil.canopen.rigdb.rig_databases`, :func:`~hdhil.canopen.rigdb.
    truth_database`).  ``ValueError`` for an entry that does not describe a layout."""
    from hdhil.can.traces.decode import ChannelDecoder
    from hdhil.canopen.rigdb import rig_databases, truth_database
    from hdhil.core.errors import UserError
    from hdhil.dbc import CHANNEL_NUMBER

    buses, channels, drives, _ = rig_sidecar_layout(rig)
    try:
        databases = rig_databases(drives, buses)
        truth = truth_database(drives, buses)
    except (KeyError, TypeError, ValueError, UserError) as exc:
        raise ValueError(f"the sidecar's rig layout cannot be read ({exc})") from None
    by_channel = {channels[name]: (name, db) for name, db in databases.items()}
    by_channel[CHANNEL_NUMBER["truth"]] = ("truth", truth)
    return ChannelDecoder(by_channel)


def trace_node_ids(meta: Mapping[str, Any] | None) -> tuple[int, int]:
    """The drive's and the controller's node-IDs a trace's sidecar records (its
    ``layout``, else its run request's); 2 and 1, the single-joint rig's, without."""
    meta = meta or {}
    layout = meta.get("layout")
    if not isinstance(layout, dict):
        request = meta.get("request")
        layout = request.get("layout") if isinstance(request, dict) else None
    if not isinstance(layout, dict):
        return 2, 1
    try:
        drives = layout.get("drives") or [{}]
        drive = int(drives[0].get("node_id", 2))
        controller = int(layout.get("controller_node_id", 1))
    except (AttributeError, TypeError, ValueError, IndexError, KeyError):
        return 2, 1
    ok = 1 <= drive <= 127 and 1 <= controller <= 127 and drive != controller
    return (drive, controller) if ok else (2, 1)


def _layout_databases(meta: Mapping[str, Any], drive_id: int, controller_id: int) -> Any:
    """The databases of a trace's layout (:func:`hdhil.canopen.rigdb.
    single_joint_databases`): the drive's shipped mapping by the sidecar's label, or its
    DCF where the sidecar names one that is still there (else the default mapping)."""
    from hdhil.canopen.rigdb import single_joint_databases

    label = str(meta.get("mapping") or "raw")
    dcf = None
    if label not in MAPPINGS:
        request = meta.get("request")
        named = (
            ((request or {}).get("mapping") or {}).get("dcf") if isinstance(request, dict) else None
        )
        dcf = str(named) if named and Path(str(named)).is_file() else None
        label = "raw"
    try:
        return single_joint_databases(drive_id, controller_id, label, dcf)
    except Exception as exc:  # UserError (a layout rigdb refuses) and the like
        raise ValueError(f"the trace's layout cannot be decoded: {exc}") from None


def raw_sensor_frames(trace: Path) -> str | None:
    """None if ``trace``'s sensor frames are the raw ADC/encoder frames (no
    sidecar mapping, or a DCF that keeps them); else the mapping's label from the
    sidecar (what a command that replays the raw channels names in its error)."""
    from hdhil.can.traces.sidecar import read_metadata

    meta = read_metadata(trace) if Path(trace).is_file() else None
    pdos = (meta or {}).get("drive_pdos")
    if not pdos:
        return None
    drive_od = canopen.import_od(str(eds_path("drive")), 2)
    default = od_layouts(drive_od).get(("tpdo", 1))
    recorded = layouts_from_json(pdos).get(("tpdo", 1))
    if default is not None and recorded is not None and recorded.entries == default.entries:
        return None
    return str((meta or {}).get("mapping") or "a DCF")
