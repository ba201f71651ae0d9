"""The CAN databases of a rig of several drives (:mod:`hdhil.canopen.rigdb`), generated
from the object dictionaries and node-IDs: one drive at node-ID 2 gives the merged
database of ``hdhil dbc export`` exactly; several drives on several buses get the CiA
301 pre-defined connection set's identifiers, distinct truth identifiers and unique
names; cantools and python-can decode every joint's frames by name, also after a round
trip through a .dbc file; a bad layout is a one-line UserError."""

from __future__ import annotations

import math

import can
import cantools
import pytest

from hdhil.canopen.rigdb import (
    RigBus,
    RigDrive,
    drive_pdo_layouts,
    rig_databases,
    truth_database,
)
from hdhil.commands.dbc import merged_database
from hdhil.core.errors import UserError
from hdhil.dbc import MAPPINGS, FrameCodec, dcf_path

# The RehabExos layout of issue #24: J1, J2 on one bus, J3 (another mapping) and J4 on
# a second one at half the bit rate.
FOUR = [
    RigDrive("J1", 2, "can0"),
    RigDrive("J2", 3, "can0"),
    RigDrive("J3", 4, "can1", mapping="cst-sensor"),
    RigDrive("J4", 5, "can1"),
]
BUSES = [RigBus("can0"), RigBus("can1", controller_node_id=1, bitrate=500_000)]


@pytest.fixture(scope="module")
def four():
    return rig_databases(FOUR, BUSES)


def _signals(message):
    return [
        (s.name, s.start, s.length, s.byte_order, s.is_signed, s.is_float, s.scale,
         s.offset, s.minimum, s.maximum, s.unit, s.choices, s.comment, s.receivers)
        for s in message.signals
    ]  # fmt: skip


def _attributes(obj):
    return {k: a.value for k, a in obj.dbc.attributes.items()} if obj.dbc else {}


@pytest.mark.parametrize("mapping", list(MAPPINGS))
def test_one_drive_at_node_2_is_the_exported_merged_database(mapping):
    """The single-joint layout (no joint name, drive node-ID 2, controller node-ID 1)
    is the database ``hdhil dbc export`` writes, message for message, and as DBC text,
    in every shipped mapping: a single-joint trace decodes with either."""
    ours = rig_databases([RigDrive("", 2, mapping=mapping)])
    assert list(ours) == ["control"]
    db = ours["control"]
    exported = merged_database(mapping)
    assert [m.name for m in db.messages] == [m.name for m in exported.messages]
    for mine, theirs in zip(db.messages, exported.messages, strict=True):
        assert (mine.frame_id, mine.is_extended_frame, mine.length) == (
            theirs.frame_id, theirs.is_extended_frame, theirs.length)  # fmt: skip
        assert mine.senders == theirs.senders
        assert (mine.comment, mine.cycle_time, mine.send_type) == (
            theirs.comment, theirs.cycle_time, theirs.send_type)  # fmt: skip
        assert _attributes(mine) == _attributes(theirs)
        assert _signals(mine) == _signals(theirs)
    assert [(n.name, n.comment, _attributes(n)) for n in db.nodes] == [
        (n.name, n.comment, _attributes(n)) for n in exported.nodes
    ]
    assert db.as_dbc_string() == exported.as_dbc_string()


def _expected_ids(node_id: int, controller: int, rank: int) -> dict[str, int]:
    """The CiA 301 pre-defined connection set, written out for one joint."""
    return {
        "DRIVE_TPDO1": 0x180 + node_id,
        "DRIVE_RPDO1": 0x200 + node_id,
        "DRIVE_TPDO2": 0x280 + node_id,
        "EMCY_DRIVE": 0x080 + node_id,
        "HEARTBEAT_DRIVE": 0x700 + node_id,
        "SDO_TX_DRIVE": 0x580 + node_id,
        "SDO_RX_DRIVE": 0x600 + node_id,
        # the controller's telemetry: its TPDO1/2 for its first joint, TPDO3/4 for the next
        "CTRL_TPDO1": (0x180, 0x380)[rank] + controller,
        "CTRL_TPDO2": (0x280, 0x480)[rank] + controller,
    }


def test_four_drives_on_two_buses_follow_the_predefined_connection_set(four):
    assert list(four) == ["can0", "can1"]
    for bus, joints in (("can0", [("J1", 2), ("J2", 3)]), ("can1", [("J3", 4), ("J4", 5)])):
        db = four[bus]
        ids = {m.name: m.frame_id for m in db.messages}
        # per bus: SYNC, NMT and the controller's own service frames
        assert {k: ids[k] for k in ("SYNC", "NMT", "HEARTBEAT_CTRL", "EMCY_CTRL",
                                    "SDO_TX_CTRL", "SDO_RX_CTRL")} == {
            "SYNC": 0x080, "NMT": 0x000, "HEARTBEAT_CTRL": 0x701, "EMCY_CTRL": 0x081,
            "SDO_TX_CTRL": 0x581, "SDO_RX_CTRL": 0x601}  # fmt: skip
        for rank, (joint, node_id) in enumerate(joints):
            for name, frame_id in _expected_ids(node_id, 1, rank).items():
                assert ids[f"{joint}_{name}"] == frame_id, (bus, joint, name)
            node = db.get_node_by_name(f"{joint}_DRIVE")
            assert node.dbc.attributes["NodeId"].value == node_id
            assert db.get_message_by_name(f"{joint}_DRIVE_TPDO1").senders == [f"{joint}_DRIVE"]
            assert db.get_message_by_name(f"{joint}_DRIVE_RPDO1").senders == ["CONTROLLER"]
            receivers = db.get_message_by_name(f"{joint}_DRIVE_TPDO2").signals[0].receivers
            assert receivers == ["CONTROLLER", "HOST"]
        # no two frames of a bus share an identifier, no two messages a name
        keys = [(m.frame_id, m.is_extended_frame) for m in db.messages]
        assert len(set(keys)) == len(keys)
        assert len({m.name for m in db.messages}) == len(db.messages)
        assert len({n.name for n in db.nodes}) == len(db.nodes)
        # every joint's message is its joint's: the single-joint set once per joint
        # (the four CAN service frames of the controller and SYNC/NMT once per bus)
        one = merged_database("raw")
        per_joint = {m.name for m in one.messages} - {
            "SYNC", "NMT", "HEARTBEAT_CTRL", "EMCY_CTRL", "SDO_TX_CTRL", "SDO_RX_CTRL"}  # fmt: skip
        for joint, _ in joints:
            assert {f"{joint}_{n}" for n in per_joint} <= set(ids)
    assert four["can0"].buses[0].baudrate == 1_000_000
    assert four["can1"].buses[0].baudrate == 500_000
    assert 'BA_ "Baudrate" 500000;' in four["can1"].as_dbc_string()
    assert "drive node-IDs 4 (J3), 5 (J4), 500 kbit/s" in four["can1"].buses[0].comment


def test_truth_frames_are_distinct_across_the_rig_and_joint_0_keeps_truth_dbcs(four):
    ids = {m.name: m.frame_id for db in four.values() for m in db.messages if m.is_extended_frame}
    for index, joint in enumerate(("J1", "J2", "J3", "J4")):
        assert ids[f"{joint}_TRUTH_TORQUE"] == 0x1F0001 + 16 * index
        assert ids[f"{joint}_TRUTH_MOTION"] == 0x1F0002 + 16 * index
        assert ids[f"{joint}_TRUTH_JOINT"] == 0x1F0003 + 16 * index
    everything = truth_database(FOUR, BUSES)
    assert {m.name: m.frame_id for m in everything.messages} == ids
    assert all(m.frame_id < 1 << 29 for m in everything.messages)


def test_a_mapping_from_a_dcf_moves_to_the_drives_node_id(four):
    """J3 runs the cst-sensor DCF: its PDOs carry the DCF's objects, at node-ID 4."""
    layouts = drive_pdo_layouts(FOUR[2])
    assert layouts[("tpdo", 1)].cob_id == 0x184 and layouts[("rpdo", 1)].cob_id == 0x204
    tpdo1 = four["can1"].get_message_by_name("J3_DRIVE_TPDO1")
    assert tpdo1.frame_id == 0x184
    single = merged_database("cst-sensor").get_message_by_name("DRIVE_TPDO1")
    assert _signals(tpdo1) == _signals(single)
    raw = four["can1"].get_message_by_name("J4_DRIVE_TPDO1")
    assert "ADC_torque" in [s.name for s in raw.signals]


def test_a_cob_id_the_dcf_fixes_stays_and_two_drives_with_it_collide(tmp_path):
    text = dcf_path("drive-cst.dcf").read_text(encoding="utf-8")
    section = text.index("[1800sub1]")
    old = "DefaultValue=$NODEID+0x180"
    value = text.index(old, section)
    fixed = tmp_path / "fixed.dcf"
    fixed.write_text(
        text[:value] + "DefaultValue=0x00000190" + text[value + len(old) :], encoding="utf-8"
    )
    one = rig_databases([RigDrive("J1", 3, dcf=fixed)])["control"]
    assert one.get_message_by_name("J1_DRIVE_TPDO1").frame_id == 0x190
    assert one.get_message_by_name("J1_DRIVE_RPDO1").frame_id == 0x203
    with pytest.raises(UserError) as err:
        rig_databases([RigDrive("J1", 3, dcf=fixed), RigDrive("J2", 4, dcf=fixed)])
    assert "J1_DRIVE_TPDO1 and J2_DRIVE_TPDO1 have the same identifier 0x190" in str(err.value)


def test_joints_with_controllers_of_their_own():
    db = rig_databases(
        [
            RigDrive("A", 2, controller_node_id=10),
            RigDrive("B", 3, controller_node_id=11),
            RigDrive("C", 4),
        ]
    )["control"]
    ids = {m.name: m.frame_id for m in db.messages}
    assert ids["A_CTRL_TPDO1"] == 0x18A and ids["B_CTRL_TPDO2"] == 0x28B
    assert ids["C_CTRL_TPDO1"] == 0x181
    assert ids["HEARTBEAT_CTRL10"] == 0x70A and ids["SDO_RX_CTRL11"] == 0x60B
    assert ids["HEARTBEAT_CTRL1"] == 0x701
    assert db.get_message_by_name("SYNC").senders == ["CONTROLLER1"]
    assert db.get_message_by_name("A_DRIVE_RPDO1").senders == ["CONTROLLER10"]
    assert db.get_node_by_name("CONTROLLER10").dbc.attributes["NodeId"].value == 10


def _frame(db, name: str, values: dict[str, float]) -> can.Message:
    message = db.get_message_by_name(name)
    return can.Message(
        arbitration_id=message.frame_id,
        is_extended_id=message.is_extended_frame,
        data=message.encode(values),
    )


def _decode(db, frame: can.Message) -> tuple[str, dict]:
    message = db.get_message_by_frame_id(frame.arbitration_id)
    return message.name, message.decode(frame.data, decode_choices=False)


J3_TRUTH = {"T_true": 12.5, "T_ripple": -0.25}
J3_TELEMETRY = {"T_meas": 3.2, "T_filtered": 3.1, "velocity": -4.5, "current": 0.75}


def test_a_frame_of_joint_3_encodes_and_decodes_by_name(four):
    db = four["can1"]
    frame = _frame(db, "J3_CTRL_TPDO1", J3_TELEMETRY)
    assert frame.arbitration_id == 0x181
    name, values = _decode(db, frame)
    assert name == "J3_CTRL_TPDO1"
    assert values == pytest.approx(J3_TELEMETRY, abs=0.002)
    # J3's sensor frame in its DCF's mapping, and its truth, decode by name too; the
    # project's compiled codec agrees with cantools on the generated message
    sensor = db.get_message_by_name("J3_DRIVE_TPDO1")
    sample = {s.name: 7 for s in sensor.signals}
    name, values = _decode(db, _frame(db, "J3_DRIVE_TPDO1", sample))
    assert name == "J3_DRIVE_TPDO1" and values == sample
    assert FrameCodec(sensor).decode(sensor.encode(sample)) == tuple(sample.values())
    name, values = _decode(db, _frame(db, "J3_TRUTH_TORQUE", J3_TRUTH))
    assert name == "J3_TRUTH_TORQUE" and values == pytest.approx(J3_TRUTH)
    # the other joint on the bus does not decode J3's frames
    assert db.get_message_by_name("J4_CTRL_TPDO1").frame_id != frame.arbitration_id


def test_a_dbc_file_written_by_cantools_decodes_every_joint_after_loading(tmp_path, four):
    """Third-party round trip: cantools writes each bus's database to a .dbc file, loads
    it back as any tool would, and decodes the joints' frames by name."""
    for bus, db in four.items():
        path = tmp_path / f"{bus}.dbc"
        cantools.database.dump_file(db, str(path))
        loaded = cantools.database.load_file(str(path))
        assert [(m.name, m.frame_id, m.is_extended_frame) for m in loaded.messages] == [
            (m.name, m.frame_id, m.is_extended_frame) for m in db.messages
        ]
        for original in db.messages:
            assert _signals(loaded.get_message_by_name(original.name)) == _signals(original)
    loaded = cantools.database.load_file(str(tmp_path / "can1.dbc"))
    frame = _frame(four["can1"], "J3_CTRL_TPDO1", J3_TELEMETRY)
    name, values = _decode(loaded, frame)
    assert name == "J3_CTRL_TPDO1" and values == pytest.approx(J3_TELEMETRY, abs=0.002)
    name, values = _decode(loaded, _frame(four["can1"], "J3_TRUTH_TORQUE", J3_TRUTH))
    assert name == "J3_TRUTH_TORQUE" and values == pytest.approx(J3_TRUTH)
    status = _frame(four["can1"], "J4_DRIVE_TPDO2", {"statusword": 0x237})
    message = loaded.get_message_by_frame_id(status.arbitration_id)
    assert message.name == "J4_DRIVE_TPDO2"
    assert str(message.decode(status.data)["statusword"]) == "operation enabled"


@pytest.mark.parametrize(
    ("drives", "expected"),
    [
        ([RigDrive("J1", 2), RigDrive("J2", 2)],
         "bus control: node-ID 2 is used by joints J1 and J2"),
        ([RigDrive("J1", 0)], "joint J1: node-ID 0 is outside 1..127"),
        ([RigDrive("J1", 128)], "joint J1: node-ID 128 is outside 1..127"),
        ([RigDrive("J1", True)], "joint J1: node-ID True is outside 1..127"),
        ([RigDrive("J1", 1)], "bus control: node-ID 1 is used by joint J1 and a controller"),
        ([RigDrive("J1", 2, controller_node_id=200)], "the controller of joint J1: node-ID 200"),
        ([RigDrive("", 2), RigDrive("J2", 3)],
         "every joint of a rig of several drives needs a name"),
        ([RigDrive("J1", 2), RigDrive("J1", 3, "b")], "joint J1 is listed twice"),
        ([RigDrive("1x", 2)], "joint name '1x' is not a name"),
        ([RigDrive("a-b", 2), RigDrive("a_b", 3)],
         "joints a-b and a_b have the same DBC name a_b"),
        ([RigDrive("J1", 2, mapping="csp")], "joint J1: unknown mapping 'csp'"),
        ([RigDrive("J1", 2), RigDrive("J2", 3), RigDrive("J3", 4)],
         "give joint J3 a controller node of its own"),
        ([], "the rig has no drives"),
    ],
)  # fmt: skip
def test_a_bad_layout_is_one_line(drives, expected):
    with pytest.raises(UserError) as err:
        rig_databases(drives)
    message = str(err.value)
    assert expected in message and "\n" not in message


def test_the_same_node_id_on_two_buses_is_fine_and_bus_settings_are_checked():
    dbs = rig_databases([RigDrive("J1", 2, "a"), RigDrive("J2", 2, "b")])
    assert dbs["a"].get_message_by_name("J1_DRIVE_TPDO1").frame_id == 0x182
    assert dbs["b"].get_message_by_name("J2_DRIVE_TPDO1").frame_id == 0x182
    assert dbs["b"].get_message_by_name("J2_TRUTH_TORQUE").frame_id == 0x1F0011
    for buses, expected in (
        ([RigBus("a", controller_node_id=0)], "the controller of bus a: node-ID 0"),
        ([RigBus("a", bitrate=2_000_000)], "bus a: bit rate 2000000"),
        ([RigBus("a"), RigBus("a")], "bus a is listed twice"),
        ([RigBus("a", data_bitrate=2_000_000)], "bus a: data bit rate 2000000 needs fd"),
        ([RigBus("a", fd=True, data_bitrate=500_000)], "bus a: data bit rate 500000"),
        ([RigBus("x")], "joint J1: unknown bus 'a' (known: x)"),
    ):
        with pytest.raises(UserError, match=expected.replace("(", r"\(").replace(")", r"\)")):
            rig_databases([RigDrive("J1", 2, "a")], buses)


def test_scaled_signals_keep_their_scaling(four):
    """Units, scaling and value tables are the single-joint database's on every joint."""
    one = merged_database("raw")
    for joint, bus in (("J1", "can0"), ("J4", "can1")):
        for name in ("CTRL_TPDO2", "DRIVE_RPDO1", "TRUTH_MOTION"):
            mine = four[bus].get_message_by_name(f"{joint}_{name}")
            assert _signals(mine) == _signals_renamed(one.get_message_by_name(name), joint)
    velocity = four["can0"].get_message_by_name("J2_CTRL_TPDO1").get_signal_by_name("velocity")
    assert (velocity.scale, velocity.unit) == (0.01, "rad/s")
    assert math.isclose(velocity.maximum, 327.67)


def _signals_renamed(message, joint):
    to = {"DRIVE": f"{joint}_DRIVE"}
    return [
        (*s[:12], s[12].replace("DRIVE_RPDO1", f"{joint}_DRIVE_RPDO1")
         .replace("CTRL_TPDO1", f"{joint}_CTRL_TPDO1") if s[12] else s[12],
         [to.get(r, r) for r in s[13]])
        for s in _signals(message)
    ]  # fmt: skip


def _edited_dcf(tmp_path, name: str, edits: dict[tuple[str, str], str]):
    """drive-cst.dcf with the first ``old`` after each ``[section]`` replaced by ``new``."""
    text = dcf_path("drive-cst.dcf").read_text(encoding="utf-8")
    for (section, old), new in edits.items():
        at = text.index(old, text.index(section))
        text = text[:at] + new + text[at + len(old) :]
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_a_dcf_written_for_another_node_id_moves_with_the_drive(tmp_path):
    """A DCF written for node-ID 5 (its PDOs at 0x185, 0x205, 0x285) placed at node-ID 3
    gives the pre-defined set's 0x183, 0x203, 0x283."""
    dcf = _edited_dcf(
        tmp_path,
        "node5.dcf",
        {
            ("[DeviceComissioning]", "NodeID=2"): "NodeID=5",
            ("[1400sub1]", "$NODEID+0x200"): "0x00000205",
            ("[1800sub1]", "$NODEID+0x180"): "0x00000185",
            ("[1801sub1]", "$NODEID+0x280"): "0x00000285",
        },
    )
    layouts = drive_pdo_layouts(RigDrive("J1", 3, dcf=dcf))
    assert [layouts[k].cob_id for k in (("tpdo", 1), ("rpdo", 1), ("tpdo", 2))] == [
        0x183, 0x203, 0x283]  # fmt: skip
    db = rig_databases([RigDrive("J1", 3, dcf=dcf)])["control"]
    ids = {m.name: m.frame_id for m in db.messages}
    assert (ids["J1_DRIVE_TPDO1"], ids["J1_DRIVE_RPDO1"], ids["J1_DRIVE_TPDO2"]) == (
        0x183, 0x203, 0x283)  # fmt: skip


def test_a_pdo_the_dcf_turns_off_is_not_on_the_rig(tmp_path):
    off = {("[1801sub1]", "$NODEID+0x280"): "$NODEID+0x80000280"}
    dcf = _edited_dcf(tmp_path, "quiet.dcf", off)
    names = {m.name for m in rig_databases([RigDrive("J1", 2, dcf=dcf)])["control"].messages}
    assert "J1_DRIVE_TPDO1" in names and "J1_DRIVE_TPDO2" not in names


def test_names_from_a_urdf_and_a_can_fd_bus(tmp_path):
    """Joint names as a URDF writes them (``.`` and ``-``) give DBC identifiers; an FD
    bus is marked as one (BusType "CAN FD", the data phase's bit rate) and its frames
    still decode after a round trip through a .dbc file."""
    drives = [RigDrive("shoulder.flex", 2, "fd0"), RigDrive("elbow-1", 3, "fd0")]
    db = rig_databases(drives, [RigBus("fd0", fd=True, data_bitrate=5_000_000)])["fd0"]
    packed = db.get_message_by_name("FD_DRIVE_TPDO1")  # the sensors packed (FD bus)
    assert "shoulder_flex_ADC_torque" in [s.name for s in packed.signals]
    assert db.get_node_by_name("elbow_1_DRIVE").dbc.attributes["NodeId"].value == 3
    assert db.buses[0].fd_baudrate == 5_000_000
    assert "CAN FD at 1 Mbit/s, data phase 5 Mbit/s" in db.buses[0].comment
    path = tmp_path / "fd0.dbc"
    cantools.database.dump_file(db, str(path))
    assert 'BA_ "BusType" "CAN FD";' in path.read_text(encoding="cp1252")
    loaded = cantools.database.load_file(str(path))
    frame = _frame(db, "elbow_1_CTRL_TPDO1", J3_TELEMETRY)
    name, values = _decode(loaded, frame)
    assert name == "elbow_1_CTRL_TPDO1" and values == pytest.approx(J3_TELEMETRY, abs=0.002)


def test_the_drives_truth_publisher_sends_the_rigs_truth_identifiers() -> None:
    """The emulated drive of the rig's j-th joint publishes its truth at the identifiers
    the rig's database names for that joint, decoded by name with cantools."""
    import can

    from hdhil.canopen.rigdb import RigDrive, truth_database
    from hdhil.hostsim.drive.truth_channel import TruthPublisher
    from hdhil.hostsim.plant import Plant, PlantConfig

    drives = [RigDrive(f"J{i + 1}", 2 + i) for i in range(3)]
    db = truth_database(drives)
    truth = Plant(PlantConfig(), seed=1).truth()
    sent: list[can.Message] = []

    class Bus:
        def send_frames(self, msgs):
            sent.extend(can.Message(arbitration_id=m.arbitration_id, data=bytes(m.data),
                                    is_extended_id=True) for m in msgs)  # fmt: skip

    TruthPublisher(Bus(), joint_index=2).publish(truth)  # type: ignore[arg-type]
    names = [db.get_message_by_frame_id(m.arbitration_id).name for m in sent]
    assert names == ["J3_TRUTH_TORQUE", "J3_TRUTH_MOTION", "J3_TRUTH_JOINT"]
    torque = db.decode_message(sent[0].arbitration_id, sent[0].data)
    assert torque["T_true"] == pytest.approx(truth.T_true_Nm, abs=1e-3)
    assert TruthPublisher(None).ids == (0x1F0001, 0x1F0002, 0x1F0003)  # joint 0: truth.dbc's


def test_an_fd_bus_packs_each_cyclic_drive_pdo_of_its_joints_into_one_fd_frame(tmp_path):
    """On a CAN FD bus the joints' sensor PDOs share FD_DRIVE_TPDO1 and their commands
    FD_DRIVE_RPDO1 (at the first joint's identifiers, the joints one after another, each
    joint's signals under its name), generated from the joints' own layouts: a payload
    encoded by a joint's own message decodes by name from the packed frame, also after a
    round trip through a .dbc file. The telemetry is FD; 64 bytes hold eight joints'
    sensors, a ninth starts a second frame."""
    from hdhil.canopen.rigdb import rig_packing

    names = [f"J{k}" for k in range(1, 10)]
    drives = [RigDrive(n, k + 2, "fd0", controller_node_id=1 + 20 * (k // 2))
              for k, n in enumerate(names)]  # fmt: skip
    buses = [RigBus("fd0", fd=True, data_bitrate=5_000_000)]
    dbs, packing = rig_packing(drives, buses)
    db = dbs["fd0"]
    classical = rig_databases(drives, [RigBus("fd0")])["fd0"]
    listed = [m.name for m in db.messages]
    assert not [n for n in listed if n.startswith("J") and "DRIVE_" in n and "PDO1" in n]
    tpdo = db.get_message_by_name("FD_DRIVE_TPDO1")
    assert tpdo.is_fd and tpdo.frame_id == 0x182 and tpdo.length == 64
    second = db.get_message_by_name("FD_DRIVE_TPDO1_2")
    assert second.frame_id == 0x182 + 8 and second.length == 8
    rpdo = db.get_message_by_name("FD_DRIVE_RPDO1")
    assert rpdo.is_fd and rpdo.frame_id == 0x202 and rpdo.length == 48  # 45 bytes padded
    assert db.get_message_by_name("J5_CTRL_TPDO1").is_fd
    layout = {p.name: p for p in packing["fd0"]}["FD_DRIVE_TPDO1"]
    assert [m.joint for m in layout.members] == names[:8]
    assert [m.offset for m in layout.members] == [8 * k for k in range(8)]
    # joint 4's own sensor frame, placed at its offset, decodes by its name
    own = classical.get_message_by_name("J4_DRIVE_TPDO1")
    values = {"ADC_torque": 1234, "ADC_tacho": -56, "ADC_current": 78, "ENC_count": 4321}
    payload = bytearray(64)
    payload[24:32] = own.encode(values)
    path = tmp_path / "fd0.dbc"
    cantools.database.dump_file(db, str(path))
    loaded = cantools.database.load_file(str(path))
    decoded = loaded.decode_message(0x182, bytes(payload))
    assert {k: decoded[f"J4_{k}"] for k in values} == pytest.approx(values)
    assert loaded.get_message_by_name("FD_DRIVE_TPDO1").is_fd
