"""The nodes' object dictionaries (EDS) and the DBC describe the same PDOs.

For every PDO frame in control.dbc (message attribute ``CANopenObject`` = "PDO"), the
transmitting node's EDS has a TPDO and every receiving node's EDS an RPDO with that
COB-ID, and a mapping whose objects carry the DBC signals' names, widths, order and
signedness.  The transmission type follows the DBC's ``GenMsgSendType``: "Cyclic" is
synchronous (type 1) on both sides; "OnChange" is event-driven (CiA 301 type 254/255) on
both sides, with the TPDO's inhibit time (sub 3, 100 us units) equal to the DBC's
``GenMsgDelayTime`` (ms).  The CiA 301 service frames (SYNC, NMT, heartbeat, EMCY, SDO)
are in the DBC so that every frame on the bus decodes; they are not mapped, but their
COB-IDs must follow the pre-defined connection set and the nodes' EDS files.
"""

from __future__ import annotations

import canopen
import pytest

from hdhil.dbc import database, eds_path

NODE_IDS = {"CONTROLLER": 1, "DRIVE": 2}
SIGNED = {0x2: True, 0x3: True, 0x4: True, 0x5: False, 0x6: False, 0x7: False}


def _od(node: str) -> canopen.ObjectDictionary:
    return canopen.import_od(str(eds_path(node.lower())), NODE_IDS[node])


def _pdos(od: canopen.ObjectDictionary, comm_base: int) -> dict[int, tuple[int, list, int]]:
    """COB-ID -> (transmission type, [mapped variables], inhibit time) for PDOs at comm_base..

    The inhibit time (sub-index 3, 100 us units) is 0 when the record has no sub-index 3.
    """
    out = {}
    for n in range(512):
        comm = comm_base + n
        if comm not in od:
            continue
        cob_id = od[comm][1].default & 0x1FFFFFFF
        ttype = od[comm][2].default
        inhibit = od[comm][3].default if 3 in od[comm].subindices else 0
        mapping = od[comm + 0x200]
        entries = []
        for sub in range(1, mapping[0].default + 1):
            value = mapping[sub].default
            index, subindex, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
            var = (
                od[index]
                if subindex == 0 and not hasattr(od[index], "subindices")
                else od[index][subindex]
            )
            entries.append((var, bits))
        out[cob_id] = (ttype, entries, inhibit)
    return out


def _attribute(message, name: str):
    """A DBC message attribute, or the attribute's default when the message has none."""
    attributes = message.dbc.attributes if message.dbc else {}
    if name in attributes:
        return attributes[name].value
    return database("control").dbc.attribute_definitions[name].default_value


def _canopen_object(message) -> str:
    return _attribute(message, "CANopenObject")


#: CiA 301 communication objects besides PDOs; these frames are never mapped.
SERVICE_OBJECTS = {"SYNC", "NMT", "HEARTBEAT", "EMCY", "SDO"}
PDO_MESSAGES = [m for m in database("control").messages if _canopen_object(m) == "PDO"]
SERVICE_MESSAGES = [m for m in database("control").messages if _canopen_object(m) != "PDO"]
#: Transmission types per DBC send type (CiA 301 §7.5.2.35/36): cyclic = synchronous every
#: SYNC (1), on change = event-driven (254 manufacturer-specific, 255 device profile).
TRANSMISSION_TYPES = {"Cyclic": {1}, "OnChange": {254, 255}}


def test_every_control_frame_is_a_known_canopen_object():
    for message in database("control").messages:
        kind = _canopen_object(message)
        assert kind == "PDO" or kind in SERVICE_OBJECTS, f"{message.name}: {kind!r}"
        if kind == "PDO":
            assert _attribute(message, "GenMsgSendType") in TRANSMISSION_TYPES, message.name
        else:
            # Sporadic service frames stay out of the cyclic schedule (hdhil.can.busload),
            # except SYNC, which paces the cycle.
            assert bool(message.cycle_time) == (kind == "SYNC"), message.name


@pytest.mark.parametrize("message", PDO_MESSAGES, ids=lambda m: m.name)
def test_pdo_mapping_matches_dbc(message):
    signals = sorted(message.signals, key=lambda s: s.start)
    send_type = _attribute(message, "GenMsgSendType")
    allowed = TRANSMISSION_TYPES[send_type]
    roles = [(message.senders[0], 0x1800)] + [
        (r, 0x1400)
        for r in sorted({r for s in message.signals for r in s.receivers})
        if r in NODE_IDS
    ]
    for node, base in roles:
        pdos = _pdos(_od(node), base)
        kind = "TPDO" if base == 0x1800 else "RPDO"
        assert message.frame_id in pdos, f"{node} has no {kind} with COB-ID {message.frame_id:#x}"
        ttype, entries, inhibit = pdos[message.frame_id]
        assert ttype in allowed, (
            f"{node} {kind} {message.name}: transmission type {ttype}, the DBC says "
            f"{send_type} (types {sorted(allowed)})"
        )
        if kind == "TPDO" and send_type == "OnChange":
            delay_ms = _attribute(message, "GenMsgDelayTime")
            assert inhibit == 10 * delay_ms, (
                f"{node} TPDO {message.name}: inhibit time {inhibit} x 100 us, the DBC's "
                f"GenMsgDelayTime is {delay_ms} ms"
            )
        assert [v.name for v, _ in entries] == [s.name for s in signals]
        assert [bits for _, bits in entries] == [s.length for s in signals]
        assert [SIGNED[v.data_type] for v, _ in entries] == [s.is_signed for s in signals]
        assert all(v.pdo_mappable for v, _ in entries)


def test_sync_cob_id_agrees():
    sync = database("control").get_message_by_name("SYNC")
    controller, drive = _od("CONTROLLER"), _od("DRIVE")
    assert controller[0x1005].default & 0x7FF == sync.frame_id
    assert controller[0x1005].default & 0x40000000, "the controller must be the SYNC producer"
    assert drive[0x1005].default & 0x7FF == sync.frame_id
    assert not drive[0x1005].default & 0x40000000
    assert controller[0x1006].default == 1000  # communication cycle period, us


def test_node_ids_in_dbc_match_the_pdo_cob_ids():
    db = database("control")
    node_ids = {
        n.name: n.dbc.attributes["NodeId"].value
        for n in db.nodes
        if n.dbc and "NodeId" in n.dbc.attributes
    }
    assert node_ids["CONTROLLER"] == NODE_IDS["CONTROLLER"]
    assert node_ids["DRIVE"] == NODE_IDS["DRIVE"]
    # Pre-defined connection set: TPDO1 = 0x180 + node-ID of its producer.
    assert db.get_message_by_name("DRIVE_TPDO1").frame_id == 0x180 + node_ids["DRIVE"]
    assert db.get_message_by_name("CTRL_TPDO1").frame_id == 0x180 + node_ids["CONTROLLER"]
    assert db.get_message_by_name("DRIVE_RPDO1").frame_id == 0x200 + node_ids["DRIVE"]


def test_control_telemetry_pdo_is_tpdo2_of_the_controller_and_invalid_by_default():
    """CTRL_TPDO2 ([Vertechy] torque control): COB-ID 0x280 + node-ID (pre-defined TPDO2),
    mapped from object 0x2002 in the controller's EDS, not valid (COB-ID bit 31) in the
    default configuration, which runs no control law."""
    msg = database("control").get_message_by_name("CTRL_TPDO2")
    assert msg.frame_id == 0x280 + NODE_IDS["CONTROLLER"]
    assert msg.senders == ["CONTROLLER"]
    od = _od("CONTROLLER")
    comm = next(
        i for i in range(0x1800, 0x1A00) if i in od and od[i][1].default & 0x7FF == msg.frame_id
    )
    assert od[comm][1].default & 0x80000000, "TPDO for CTRL_TPDO2 must default to not valid"
    for idx in range(0x1800, 0x1A00):  # the other PDOs are valid
        if idx in od and idx != comm:
            assert not od[idx][1].default & 0x80000000
    mapped = [od[comm + 0x200][s].default >> 16 for s in range(1, 5)]
    assert mapped == [0x2002] * 4
    assert [od[0x2002][s].name for s in range(1, 5)] == [s.name for s in msg.signals]


def test_service_frames_follow_the_predefined_connection_set():
    """NMT 0x000, EMCY 0x080 + node-ID, SDO 0x580/0x600 + node-ID, heartbeat 0x700 +
    node-ID (CiA 301 §7.3.5 pre-defined connection set), sent by the right node."""
    db = database("control")
    base = {"NMT": 0x000, "EMCY": 0x080, "HEARTBEAT": 0x700}
    SDO_SERVER = {"CTRL": "CONTROLLER", "DRIVE": "DRIVE"}  # name suffix -> SDO server
    for message in SERVICE_MESSAGES:
        kind = _canopen_object(message)
        if kind == "SYNC":
            continue
        if kind == "NMT":
            assert message.frame_id == 0 and message.senders == ["CONTROLLER"]
            continue
        if kind == "SDO":
            server = SDO_SERVER[message.name.rsplit("_", 1)[1]]
            node_id = NODE_IDS[server]
            if message.name.startswith("SDO_TX"):
                assert message.frame_id == 0x580 + node_id and message.senders == [server]
            else:  # clients: the host tools, and the controller for the drive's server
                assert message.frame_id == 0x600 + node_id
                assert "HOST" in message.senders and server not in message.senders
            assert message.length == 8
            continue
        (sender,) = message.senders
        assert message.frame_id == base[kind] + NODE_IDS[sender], message.name
    names = {m.name for m in SERVICE_MESSAGES}
    assert {"NMT", "HEARTBEAT_CTRL", "HEARTBEAT_DRIVE", "EMCY_CTRL", "EMCY_DRIVE"} <= names
    assert {"SDO_TX_CTRL", "SDO_RX_CTRL", "SDO_TX_DRIVE", "SDO_RX_DRIVE"} <= names
    assert db.get_message_by_name("EMCY_DRIVE").length == 8


def test_drive_eds_communication_objects_agree_with_the_dbc():
    """The drive's EMCY COB-ID (0x1014), heartbeat producer (0x1017) and consumer of the
    controller (0x1016) as the DBC frames and the drive defaults describe them."""
    db = database("control")
    drive = _od("DRIVE")
    assert drive[0x1014].default == db.get_message_by_name("EMCY_DRIVE").frame_id
    assert drive[0x1017].default == 100
    consumer = drive[0x1016][1].default
    assert (consumer >> 16, consumer & 0xFFFF) == (NODE_IDS["CONTROLLER"], 250)
    statusword = db.get_message_by_name("DRIVE_TPDO2")
    assert statusword.frame_id == 0x280 + NODE_IDS["DRIVE"]  # pre-defined TPDO2
    assert not statusword.cycle_time  # event-driven: not in the cyclic schedule


def test_nodes_take_pdo_identifiers_from_their_object_dictionary():
    from hdhil.can.node import pdo_cob_id
    from hdhil.dbc import codec

    od = canopen.import_od(str(eds_path("drive")), 2)
    assert pdo_cob_id(od, 0x1800, codec("control", "DRIVE_TPDO1")) == 0x182
    assert pdo_cob_id(od, 0x1400, codec("control", "DRIVE_RPDO1")) == 0x202
    # the identifier follows the node-ID ($NODEID+0x180 in the EDS), the DBC's layout stays
    at5 = canopen.import_od(str(eds_path("drive")), 5)
    assert pdo_cob_id(at5, 0x1800, codec("control", "DRIVE_TPDO1")) == 0x185
    assert pdo_cob_id(at5, 0x1400, codec("control", "DRIVE_RPDO1")) == 0x205
    at5[0x1A00][4].default = 0x21010008  # a mapping edited out of step with the DBC's layout
    with pytest.raises(ValueError, match=r"DRIVE_TPDO1 in control\.dbc lays out 4 signal"):
        pdo_cob_id(at5, 0x1800, codec("control", "DRIVE_TPDO1"))


@pytest.mark.parametrize("node", sorted(NODE_IDS))
def test_every_valid_default_pdo_is_a_dbc_frame(node):
    """The other direction: a PDO mapped by default in an EDS is a frame of control.dbc
    with the same length (valid or not: the controller's CTRL_TPDO2 is valid only while a
    control law runs); the spare PDOs a master may configure at run time are not valid
    and not mapped by default."""
    od = _od(node)
    frames = {m.frame_id: m for m in PDO_MESSAGES}
    for comm in [*range(0x1400, 0x1600), *range(0x1800, 0x1A00)]:
        if comm not in od:
            continue
        cob = od[comm][1].default
        count = od[comm + 0x200][0].default
        if count == 0:
            assert cob & 0x80000000, f"{node} 0x{comm:04X}: valid without a mapping"
            continue
        message = frames.get(cob & 0x7FF)
        assert message is not None, f"{node} 0x{comm:04X}: COB-ID 0x{cob:03X} not in the DBC"
        bits = sum(od[comm + 0x200][s].default & 0xFF for s in range(1, count + 1))
        assert bits == 8 * message.length, f"{node} 0x{comm:04X}: {bits} bits"


def test_pdo_names_follow_the_eds_numbering():
    """A DBC message named NODE_TPDOn / NODE_RPDOn is the n-th TPDO / RPDO of its node's
    EDS (communication parameter 0x1800 / 0x1400 + n - 1): the COB-ID in that slot is the
    message's identifier, so the DBC's names and the EDS's numbering agree."""
    import re

    db = database("control")
    od = {"CTRL": _od("CONTROLLER"), "DRIVE": _od("DRIVE")}
    checked = 0
    for message in db.messages:
        m = re.fullmatch(r"(CTRL|DRIVE)_(T|R)PDO(\d)", message.name)
        if m is None:
            continue
        node, kind, n = m.group(1), m.group(2), int(m.group(3))
        base = 0x1800 if kind == "T" else 0x1400
        if kind == "R":  # an RPDO of the drive is a TPDO of the controller, and vice versa
            assert (base + n - 1) in od[node], f"{message.name}: no RPDO{n} in the EDS"
        comm = od[node][base + n - 1]
        assert comm[1].default & 0x7FF == message.frame_id, message.name
        checked += 1
    assert checked >= 5
