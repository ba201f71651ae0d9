"""One controller node serving two joints on one bus: one SYNC and one NMT master for the
bus, one interrupt handler per joint, each on its own drive's frames and configuration,
the telemetry numbered as the rig's generated database says (hdhil.canopen.rigdb)."""

from __future__ import annotations

import dataclasses

import pytest
from conftest import BusHarness

from hdhil.canopen.cia402 import State
from hdhil.canopen.rigdb import RigDrive, rig_databases
from hdhil.core.dataconf import ConfigError
from hdhil.firmware.config import FirmwareConfig, paper_config, recommended_config
from hdhil.firmware.controller import ControllerNode, DriveLink, JointSetup
from hdhil.firmware.interrupt import AdcSample
from hdhil.firmware.isr import InterruptHandler
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant, PlantConfig
from hdhil.rig.factories import DriveSlot, NodeSite, RigLayout, layout_joints, scenario_controller
from hdhil.rig.scenario import load_scenario, scenario_from_dict

Ts = 1e-3
#: The rig of the tests: joints J1 (drive 2) and J2 (drive 3) on one bus, controller 1.
RIG = [RigDrive("J1", 2), RigDrive("J2", 3)]
PAPER = paper_config(FirmwareConfig())
RECOMMENDED = recommended_config(FirmwareConfig())


class Recording:
    """An interrupt handler that keeps every sample it is given, then runs the firmware's."""

    def __init__(self, isr: InterruptHandler) -> None:
        self.isr = isr
        self.samples: list[tuple[int, ...]] = []

    def __call__(self, sample):
        self.samples.append(tuple(sample))
        return self.isr(sample)

    def __getattr__(self, name: str):
        return getattr(self.isr, name)


def drive(harness: BusHarness, node_id: int, seed: int = 0) -> DriveNode:
    """An emulated drive at ``node_id``: its PDO identifiers follow its node-ID (CiA 301's
    pre-defined connection set, as rigdb numbers them)."""
    node = DriveNode(harness.bus(), Plant(PlantConfig(), seed),
                     DriveConfig(sample_period_s=Ts, node_id=node_id))  # fmt: skip
    return harness.add(node)


def two_joints(harness: BusHarness, **kwargs) -> ControllerNode:
    ctrl = ControllerNode(harness.bus(), joints=[JointSetup(PAPER, 2, "J1"),
                                                 JointSetup(RECOMMENDED, 3, "J2")],
                          **kwargs)  # fmt: skip
    for joint in ctrl.joints:
        joint.isr = Recording(joint.isr)  # type: ignore[assignment]
    return harness.add(ctrl, sync=True)


def run(harness: BusHarness, nodes, cycles: int) -> None:
    for node in nodes:
        node.boot(0.0)
    for _ in range(cycles):
        harness.cycle()


def test_two_joints_reach_operation_each_interrupt_on_its_own_frames_and_config():
    with BusHarness("t-joints", period_s=Ts) as harness:
        ctrl = two_joints(harness)
        # Different noise seeds, so the two drives' sensor frames differ.
        d2 = drive(harness, 2, seed=1)
        d3 = drive(harness, 3, seed=2)
        run(harness, [ctrl, d2, d3], 100)
    j1, j2 = ctrl.joints
    assert ctrl.phase == "operational" and ctrl.boot_error is None
    assert [j.phase for j in ctrl.joints] == ["operational", "operational"]
    assert d2.machine.state is State.OPERATION_ENABLED
    assert d3.machine.state is State.OPERATION_ENABLED
    assert j1.diagnostics.syncs_sent == j2.diagnostics.syncs_sent == 100
    assert sum(cob == 0x080 for _, cob, _ in harness.log) == 100  # one SYNC per cycle
    # each drive sends at its own node-ID's identifiers, and the node knows every frame
    # of both drives at theirs
    sent = {cob for _, cob, _ in harness.log}
    assert {0x182, 0x282, 0x183, 0x283, 0x202, 0x203} <= sent
    assert ctrl.unknown_frames == {}

    db = rig_databases(RIG)["control"]
    log = harness.log
    for joint, name in ((j1, "J1"), (j2, "J2")):
        # The interrupt ran on exactly its drive's sensor frames in operation (after the
        # listing's settling pause), and on nothing else.
        sensor = db.get_message_by_name(f"{name}_DRIVE_TPDO1")
        frames = [data for _, cob, data in log if cob == sensor.frame_id]
        decoded = [tuple(sensor.decode(d, scaling=False).values()) for d in frames]
        samples = joint.isr.samples  # type: ignore[attr-defined]
        assert len(samples) == joint.isr.samplecount > 60
        assert samples == decoded[len(decoded) - len(samples) :]
        # Its telemetry, numbered as rigdb numbers the joint's, is what its own
        # configuration makes of those samples (and not what the other's would).
        telemetry = db.get_message_by_name(f"{name}_CTRL_TPDO1")
        sent = [data for _, cob, data in log if cob == telemetry.frame_id]
        assert len(sent) == len(samples)
        assert sent == replay(joint.config, samples)
    assert j1.config.ripple.mode == "paper" and j2.config.ripple.mode == "recommended"
    assert replay(RECOMMENDED, j1.isr.samples) != replay(PAPER, j1.isr.samples)  # type: ignore[attr-defined]


def replay(config: FirmwareConfig, samples: list[tuple[int, ...]]) -> list[bytes]:
    """The telemetry frames a fresh interrupt handler with ``config`` sends for ``samples``."""
    from hdhil.firmware.controller.codecs import default_codecs

    codec = default_codecs().telemetry
    isr = InterruptHandler(config)
    out = []
    for sample in samples:
        o = isr(AdcSample(*sample))
        out.append(codec.encode(o.T_meas, o.T_filtered, o.velocity, o.current))
    return out


def test_the_node_knows_every_frame_of_each_of_its_drives_at_its_node_id():
    """A tool's SDO request to drive 3 is a known frame to the node of drives 2 and 3
    (not counted as unknown), one to a drive it does not serve is counted."""
    with BusHarness("t-joints-known", period_s=Ts) as harness:
        ctrl = two_joints(harness)
        for cob in (0x603, 0x602, 0x604):
            harness.send(cob, bytes((0x40, 0x41, 0x60, 0, 0, 0, 0, 0)))
        harness.pump()
    assert ctrl.unknown_frames == {0x604: 1}


def test_a_drive_that_never_boots_leaves_the_other_joint_running_and_is_reported():
    with BusHarness("t-joints-boot", period_s=Ts) as harness:
        ctrl = two_joints(harness, boot_timeout_s=0.05)
        d2 = drive(harness, 2)  # no drive at node-ID 3
        run(harness, [ctrl, d2], 200)
    j1, j2 = ctrl.joints
    assert j2.phase == "safe"
    assert j2.boot_error is not None and "node 3" in j2.boot_error
    assert "boot-up" in (j2.diagnostics.safe_reason or "")
    assert j1.phase == "operational" and j1.isr.samplecount > 60
    assert d2.machine.state is State.OPERATION_ENABLED
    assert ctrl.phase == "operational" and ctrl.boot_error is None
    assert ctrl.services.state.name == "OPERATIONAL"  # the node still commands drive 2
    # no NMT command to drive 3 (it was never started, so never stopped either)
    assert not [d for _, cob, d in harness.log if cob == 0x000 and d[1] == 3]


def test_joints_at_other_node_ids_follow_the_predefined_connection_set():
    """Drives 4 and 5: joint 0's PDOs in the node's object dictionary move to drive 4's
    identifiers, joint 1's are its link's; both reach operation on those frames."""
    with BusHarness("t-joints-ids", period_s=Ts) as harness:
        ctrl = harness.add(ControllerNode(harness.bus(), joints=[JointSetup(PAPER, 4, "J1"),
                                                                 JointSetup(PAPER, 5, "J2")]),
                           sync=True)  # fmt: skip
        d4, d5 = drive(harness, 4), drive(harness, 5)
        run(harness, [ctrl, d4, d5], 60)
    od = [ctrl.services.read(index, 1) & 0x7FF for index in (0x1400, 0x1401, 0x1802, 0x1800)]
    assert od == [0x184, 0x284, 0x204, 0x181]
    assert [j.phase for j in ctrl.joints] == ["operational", "operational"]
    assert d4.machine.state is d5.machine.state is State.OPERATION_ENABLED
    db = rig_databases([RigDrive("J1", 4), RigDrive("J2", 5)])["control"]
    ids = {cob for _, cob, _ in harness.log}
    for name in ("J1_CTRL_TPDO1", "J2_CTRL_TPDO1", "J1_DRIVE_RPDO1", "J2_DRIVE_RPDO1"):
        assert db.get_message_by_name(name).frame_id in ids, name


def test_a_control_law_on_one_joint_sends_that_joints_control_telemetry_only():
    law = load_scenario("lqg-experiment").firmware
    assert law.control.active and not PAPER.control.active
    with BusHarness("t-joints-law", period_s=Ts) as harness:
        ctrl = harness.add(ControllerNode(harness.bus(), joints=[JointSetup(PAPER, 2, "J1"),
                                                                 JointSetup(law, 3, "J2")]),
                           sync=True)  # fmt: skip
        run(harness, [ctrl, drive(harness, 2), drive(harness, 3)], 40)
    db = rig_databases(RIG)["control"]
    sent = {cob for _, cob, _ in harness.log}
    assert db.get_message_by_name("J2_CTRL_TPDO2").frame_id in sent  # 0x481
    assert db.get_message_by_name("J1_CTRL_TPDO2").frame_id not in sent  # 0x281: no law
    j1, j2 = ctrl.joints
    assert j2.diagnostics.control_frames_sent == j2.isr.samplecount > 0
    assert j1.diagnostics.control_frames_sent == 0 and j1.phase == j2.phase == "operational"


def test_a_third_joint_runs_on_a_second_node_that_follows_the_buses_sync():
    """rehabexos-fd's layout on a small scale: J1 and J2 on the bus's controller node 1,
    J3 (drive 4) on controller node 6, which follows node 1's SYNC instead of producing
    one; every frame at the identifier rigdb gives it."""
    rig = [*RIG, RigDrive("J3", 4, controller_node_id=6)]
    with BusHarness("t-joints-second", period_s=Ts) as harness:
        ctrl = two_joints(harness)
        second = harness.add(ControllerNode(harness.bus(), node_id=6, sync_producer=False,
                                            joints=[JointSetup(RECOMMENDED, 4, "J3")]))  # fmt: skip
        config = DriveConfig(sample_period_s=Ts, node_id=4, controller_node_id=6)
        d4 = harness.add(DriveNode(harness.bus(), Plant(PlantConfig(), 3), config))
        run(harness, [ctrl, second, drive(harness, 2), drive(harness, 3), d4], 60)
    assert [j.phase for j in (*ctrl.joints, *second.joints)] == ["operational"] * 3
    assert d4.machine.state is State.OPERATION_ENABLED
    assert sum(cob == 0x080 for _, cob, _ in harness.log) == 60  # node 1's SYNC only
    assert second.joints[0].diagnostics.syncs_sent == 60
    db = rig_databases(rig)["control"]
    ids = {cob for _, cob, _ in harness.log}
    for name in ("J3_CTRL_TPDO1", "J3_DRIVE_RPDO1", "HEARTBEAT_CTRL6", "J1_CTRL_TPDO1"):
        assert db.get_message_by_name(name).frame_id in ids, name
    assert ids <= {m.frame_id for m in db.messages}  # nothing rigdb does not name


def test_a_drive_that_falls_silent_in_operation_stops_its_joint_only():
    with BusHarness("t-joints-silent", period_s=Ts) as harness:
        ctrl = two_joints(harness)
        d2, d3 = drive(harness, 2), drive(harness, 3)
        run(harness, [ctrl, d2, d3], 60)
        assert [j.phase for j in ctrl.joints] == ["operational", "operational"]
        harness.nodes.remove(d3)  # drive 3 sends nothing more
        before = ctrl.joints[0].isr.samplecount
        for _ in range(30):
            harness.cycle()
    j1, j2 = ctrl.joints
    assert (
        j2.phase == "safe" and "no sensor frame from drive (node 3)" in j2.diagnostics.safe_reason
    )
    # EMCY 0x8250 "RPDO timeout" naming drive 3, and NMT pre-operational for drive 3 only
    assert any(cob == 0x081 and d[:2] == b"\x50\x82" and d[3] == 3 for _, cob, d in harness.log)
    assert [d for _, cob, d in harness.log if cob == 0x000][-1] == bytes((0x80, 3))
    assert j1.phase == "operational" and j1.isr.samplecount == before + 30
    assert d2.machine.state is State.OPERATION_ENABLED
    assert ctrl.phase == "operational" and ctrl.services.state.name == "OPERATIONAL"


def test_each_joints_sensor_emcy_names_its_drive_and_clears_apart():
    """Two joints with a stuck torque channel each: one EMCY 0x7300 per joint (the drive's
    node-ID in manufacturer byte 4), and clearing one leaves the other's error active."""

    class Stuck:
        events, tacho_events, tacho_stuck = 1, 0, False

        def __init__(self, stuck: bool, revision: int) -> None:
            self.torque_stuck, self.revision = stuck, revision

    with BusHarness("t-joints-emcy", period_s=Ts) as harness:
        ctrl = two_joints(harness)
        ctrl.boot(0.0)
        j1, j2 = ctrl.joints
        j1.supervision.report_stuck(Stuck(True, 1))
        j2.supervision.report_stuck(Stuck(True, 1))
        j1.supervision.report_stuck(Stuck(False, 2))
        emcys = [d for cob, d in harness.pump() if cob == 0x081]
    assert emcys[0][:2] == emcys[1][:2] == b"\x00\x73"
    assert emcys[0][3:] == bytes((1, 0, 0, 0, 2)) and emcys[1][3:] == bytes((1, 0, 0, 0, 3))
    assert emcys[2][:2] == b"\x00\x00" and emcys[2][2] != 0  # J2's error still active
    assert list(ctrl.services.emcy.active) == [(0x7300, bytes((1, 0, 0, 0, 3)))]


def test_a_stop_walks_every_drive_back_then_the_node_goes_pre_operational():
    with BusHarness("t-joints-stop", period_s=Ts) as harness:
        ctrl = two_joints(harness)
        d2, d3 = drive(harness, 2), drive(harness, 3)
        run(harness, [ctrl, d2, d3], 30)
        ctrl.request_stop("test")
        assert ctrl.phase == "stopping"
        for _ in range(10):
            if harness.cycle(stop=lambda: ctrl.phase == "stopped") is None:
                break
    assert [j.phase for j in ctrl.joints] == ["stopped", "stopped"]
    nmt = [d for _, cob, d in harness.log if cob == 0x000]
    assert nmt[-2:] in ([b"\x80\x02", b"\x80\x03"], [b"\x80\x03", b"\x80\x02"])
    assert ctrl.services.state.name == "PRE_OPERATIONAL"
    assert d2.machine.state is d3.machine.state is State.SWITCH_ON_DISABLED


def test_every_drive_missing_is_the_nodes_boot_error():
    with BusHarness("t-joints-none", period_s=Ts) as harness:
        ctrl = two_joints(harness, boot_timeout_s=0.02)
        run(harness, [ctrl], 40)
    assert ctrl.phase == "safe"
    assert ctrl.boot_error is not None
    assert "J1: drive (node 2)" in ctrl.boot_error and "J2: drive (node 3)" in ctrl.boot_error


def single(harness: BusHarness, config: FirmwareConfig, joints: bool) -> ControllerNode:
    bus = harness.bus()
    ctrl = (ControllerNode(bus, joints=[JointSetup(config)]) if joints
            else ControllerNode(bus, config))  # fmt: skip
    return harness.add(ctrl, sync=True)


def test_one_joint_behaves_as_the_single_joint_controller():
    """The node of one joint given as ``joints``, and joint 0 of a node of two, send
    byte-identical frames to those of the single-joint controller."""
    logs = []
    for kind in ("single", "one", "two"):
        with BusHarness("t-joints-same", period_s=Ts) as harness:
            if kind == "two":
                ctrl = two_joints(harness)
                run(harness, [ctrl, drive(harness, 2), drive(harness, 3)], 120)
            else:
                ctrl = single(harness, PAPER, joints=kind == "one")
                run(harness, [ctrl, drive(harness, 2)], 120)
        logs.append(harness.log)
    assert logs[0] == logs[1]
    joint0 = {0x080, 0x181, 0x281, 0x182, 0x282, 0x202, 0x582, 0x602}
    assert [f for f in logs[2] if f[1] in joint0] == [f for f in logs[0] if f[1] in joint0]
    assert sum(f[1] == 0x181 for f in logs[0]) > 10  # the interrupt ran


def test_a_further_joint_has_the_predefined_link_of_its_rank():
    ctrl_id = 1
    assert DriveLink.predefined(2, ctrl_id, 0) == DriveLink()
    link = DriveLink.predefined(3, ctrl_id, 1)
    db = rig_databases(RIG)["control"]
    names = {m.frame_id: m.name for m in db.messages}
    assert [names[c] for c in link.cob_ids] == [
        "J2_DRIVE_TPDO1", "J2_DRIVE_TPDO2", "J2_DRIVE_RPDO1", "J2_CTRL_TPDO1", "J2_CTRL_TPDO2"
    ]  # fmt: skip


def test_joint_0s_own_link_gives_the_nodes_pdos_their_cob_ids():
    link = DriveLink(2, 0x1A2, 0x2A2, 0x222, 0x1A1, 0x2A1)
    with BusHarness("t-joints-link0", period_s=Ts) as harness:
        ctrl = ControllerNode(harness.bus(), joints=[JointSetup(PAPER, 2, "J1", link=link)])
    read = ctrl.services.read
    assert [read(i, 1) & 0x7FF for i in (0x1400, 0x1401, 0x1802, 0x1800, 0x1801)] == [
        0x1A2, 0x2A2, 0x222, 0x1A1, 0x2A1
    ]  # fmt: skip
    assert read(0x1801, 1) >> 31 == 1  # CTRL_TPDO2 still not valid without a law
    assert ctrl.joints[0].link == link and ctrl.io.command_msg.arbitration_id == 0x222


@pytest.mark.parametrize(
    ("joints", "message"),
    [
        ([JointSetup(PAPER, 2), JointSetup(PAPER, 3), JointSetup(PAPER, 4)], "at most 2 joints"),
        ([JointSetup(PAPER, 2), JointSetup(PAPER, 2)], "distinct node-IDs"),
        ([JointSetup(PAPER, 1)], "controller's"),
        (
            [JointSetup(PAPER, 2), JointSetup(dataclasses.replace(PAPER, sample_period_s=2e-3), 3)],
            "one sample period",
        ),
        ([], "at least one joint"),
    ],
)
def test_a_layout_one_node_cannot_serve_is_refused(joints, message):
    with (
        BusHarness("t-joints-bad", period_s=Ts) as harness,
        pytest.raises(ValueError, match=message),
    ):
        ControllerNode(harness.bus(), joints=joints)


def test_joints_or_one_joints_arguments_not_both():
    with (
        BusHarness("t-joints-both", period_s=Ts) as harness,
        pytest.raises(ValueError, match="not both"),
    ):
        ControllerNode(harness.bus(), PAPER, joints=[JointSetup(PAPER)])


RIG_SCENARIO = {
    "scenario": {"name": "two-joints", "duration_s": 1.0},
    "joints": {
        "J1": {"firmware": {"ripple": {"mode": "paper"}}},
        "J2": {"firmware": {"ripple": {"mode": "recommended"}}},
    },
}


def test_the_scenario_controller_serves_the_layouts_drives_with_their_joints_configs():
    scenario = scenario_from_dict(RIG_SCENARIO)
    layout = RigLayout(drives=(DriveSlot(2), DriveSlot(3)))
    with BusHarness("t-joints-factory", period_s=Ts) as harness:
        site = NodeSite(harness.bus(), 1, 1, Ts, 0, drive_node_ids=(2, 3),
                        joint_configs=layout_joints(scenario, layout))  # fmt: skip
        ctrl = scenario_controller(site, scenario.firmware)
    assert [(j.name, j.drive_node_id, j.config.ripple.mode) for j in ctrl.joints] == [
        ("J1", 2, "paper"),
        ("J2", 3, "recommended"),
    ]
    assert [j.link for j in ctrl.joints] == [DriveLink.predefined(2, 1, 0),
                                             DriveLink.predefined(3, 1, 1)]  # fmt: skip
    with pytest.raises(ConfigError, match="node-ID 4 must be one joint"):
        layout_joints(scenario, RigLayout(drives=(DriveSlot(2), DriveSlot(4))))


def test_the_scenario_controller_of_one_drive_is_the_single_joint_controller():
    scenario = scenario_from_dict({"scenario": {"name": "one", "duration_s": 1.0}})
    layout = RigLayout()
    with BusHarness("t-joints-factory1", period_s=Ts) as harness:
        site = NodeSite(harness.bus(), 1, 1, Ts, 0, drive_node_ids=(2,),
                        joint_configs=layout_joints(scenario, layout))  # fmt: skip
        ctrl = scenario_controller(site, scenario.firmware)
    assert len(ctrl.joints) == 1 and ctrl.config is scenario.firmware
    assert ctrl.joints[0].link == DriveLink()


def test_decimated_telemetry_settings_are_checked() -> None:
    """A joint's telemetry every N >= 1 cycles, each frame's phase a cycle 0..N-1."""
    from hdhil.firmware.config import FirmwareConfig
    from hdhil.firmware.controller import JointSetup

    assert JointSetup(FirmwareConfig(), telemetry_every=10, telemetry_phases=(9, 0))
    for every, phases in ((0, (0, 0)), (4, (4, 0)), (4, (0, -1)), (True, (0, 0))):
        with pytest.raises(ValueError, match="telemetry"):
            JointSetup(FirmwareConfig(), telemetry_every=every, telemetry_phases=phases)
