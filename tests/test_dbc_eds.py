"""The nodes' object dictionaries (EDS) and the DBC describe the same PDOs.

For every PDO frame in control.dbc, the transmitting node's EDS has a TPDO and every
receiving node's EDS an RPDO with that COB-ID, transmission type 1 (synchronous), and a
mapping whose objects carry the DBC signals' names, widths, order and signedness.
"""

from __future__ import annotations

import canopen
import pytest

from hdhil.dbc import database, eds_path

NODE_IDS = {"CONTROLLER": 1, "DRIVE": 2}
SIGNED = {0x2: True, 0x3: True, 0x4: True, 0x5: False, 0x6: False, 0x7: False}


def _od(node: str) -> canopen.ObjectDictionary:
    return canopen.import_od(str(eds_path(node.lower())), NODE_IDS[node])


def _pdos(od: canopen.ObjectDictionary, comm_base: int) -> dict[int, tuple[int, list]]:
    """COB-ID -> (transmission type, [mapped variables]) for PDOs at comm_base.."""
    out = {}
    for n in range(512):
        comm = comm_base + n
        if comm not in od:
            continue
        cob_id = od[comm][1].default & 0x1FFFFFFF
        ttype = od[comm][2].default
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
        out[cob_id] = (ttype, entries)
    return out


PDO_MESSAGES = [m for m in database("control").messages if m.name != "SYNC"]


@pytest.mark.parametrize("message", PDO_MESSAGES, ids=lambda m: m.name)
def test_pdo_mapping_matches_dbc(message):
    signals = sorted(message.signals, key=lambda s: s.start)
    roles = [(message.senders[0], 0x1800)] + [
        (r, 0x1400)
        for r in sorted({r for s in message.signals for r in s.receivers})
        if r in NODE_IDS
    ]
    for node, base in roles:
        pdos = _pdos(_od(node), base)
        kind = "TPDO" if base == 0x1800 else "RPDO"
        assert message.frame_id in pdos, f"{node} has no {kind} with COB-ID {message.frame_id:#x}"
        ttype, entries = pdos[message.frame_id]
        assert ttype == 1, f"{node} {kind} {message.name} is not synchronous (type 1)"
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
    """CTRL_TPDO2 (seed 003 torque control): COB-ID 0x280 + node-ID (pre-defined TPDO2),
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
