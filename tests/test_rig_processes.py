"""A rig of several joints served by bus (``hdhil emulate --bus``, ``hdhil firmware
--bus``; :mod:`hdhil.rig.rigprocess`): the command line's refusals, the arm's clock, and
the drives and a bus's controller nodes in one process on python-can's ``virtual`` bus
(the processes over udp_multicast: test_rig_processes_udp.py)."""

from __future__ import annotations

import threading
import time

import can
import pytest

from hdhil.cli import main


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["emulate", "--scenario", "rehabexos"], "give --bus NAME (or --node JOINT)"),
        (["firmware", "--scenario", "rehabexos"], "on bus(es) can0, can1: give --bus NAME"),
        (["emulate", "--scenario", "rehabexos", "--bus", "can9"], "has no bus 'can9'"),
        (["emulate", "--scenario", "rehabexos", "--node", "J9"], "has no joint 'J9'"),
        (
            ["emulate", "--scenario", "rehabexos", "--bus", "can0", "--node", "J3"],
            "joint J3 is on bus can1",
        ),
        (["emulate", "--scenario", "free-motion", "--bus", "can0"], "take a scenario of several"),
        (
            ["emulate", "--scenario", "rehabexos", "--bus", "can0=239.1.1.1", "--bus", "can1"],
            "give each its channel",
        ),
        (["emulate", "--scenario", "rehabexos", "--bus", "can0", "--bus", "can0"], "given twice"),
        (["emulate", "--scenario", "rehabexos", "--bus", "=x"], "use NAME or NAME=CHANNEL"),
        (
            ["emulate", "--scenario", "rehabexos", "--bus", "can0", "--node-id", "5"],
            "runs without --node-id",
        ),
        (["firmware", "--scenario", "free-motion", "--floor-s", "1"], "take a rig's controller"),
    ],
)
def test_a_bus_of_a_rig_is_named_or_refused_in_one_line(args, message, capsys):
    assert main([*args, "--interface", "virtual"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("hdhil: error: ") and message in err, err


def _request(duration_s: float):
    from hdhil.rig.request import resolve

    return resolve("rehabexos", duration_s=duration_s)


def test_the_arm_moves_with_its_clock_joint_alone():
    """The first drive served is the arm's clock: its SYNC advances every joint with the
    held inputs; another joint's SYNC only samples the arm (buses not in step)."""
    pytest.importorskip("mujoco")
    from hdhil.hostsim.plant.arm import ArmPlant
    from hdhil.hostsim.plant.multibody import LinkDynamics
    from hdhil.rig.rigprocess import CoupledJoint

    s = _request(0.01).scenario
    arm = ArmPlant(LinkDynamics.from_urdf(s.robot.path), [p for p, _ in s.joint_configs],
                   [1, 2, 3, 4])  # fmt: skip
    arm.input_source = lambda: [0.0, 0.0, 0.0, 0.0]
    clock, other = CoupledJoint(arm, 0, clock=True), CoupledJoint(arm, 2, clock=False)
    other.advance(0.0, 1e-3)
    assert arm.time == 0.0 and other.time == 0.0
    clock.advance(0.0, 1e-3)
    clock.advance(0.0, 2e-3)  # a missed SYNC: two periods
    assert arm.time == pytest.approx(3e-3) and other.time == arm.time


@pytest.mark.slow
@pytest.mark.realtime
def test_a_bus_controller_runs_the_drives_of_one_emulator_on_a_virtual_bus():
    """:class:`RigDrives` serves all four joints of rehabexos (one arm) in a thread; the
    controller nodes of can0 run 0.1 s in network lockstep against them: both joints
    run every cycle, the arm advances with can0's SYNC, and the drives of can1 (no
    controller) answer nothing and stay disabled."""
    pytest.importorskip("mujoco")
    from hdhil.rig.rigprocess import RigController, RigDrives, served_joints

    request = _request(0.1)
    prefix = f"hdhil-rigproc-{time.monotonic_ns()}"
    opened: list[can.BusABC] = []

    def open_bus(name: str) -> can.BusABC:
        bus = can.Bus(interface="virtual", channel=f"{prefix}-{name}")
        opened.append(bus)
        return bus

    stop = threading.Event()
    try:
        drives = RigDrives(request, served_joints(request, ["can0", "can1"]), open_bus)
        assert drives.passive == []
        server = threading.Thread(target=drives.serve, args=(stop.is_set,), daemon=True)
        server.start()
        ctrl = RigController(request, "can0", open_bus, boot_timeout_s=10.0)
        assert ctrl.boot(lambda: False) is None
        assert ctrl.run(lambda: False, realtime=False) >= 100
        summary = ctrl.summary(stopped=False)
    finally:
        stop.set()
        time.sleep(0.05)
        for bus in opened:
            bus.shutdown()
    assert "verdict" not in summary, summary
    assert sorted(summary["joints"]) == ["J1", "J2"]
    assert min(r["samples"] for r in summary["joints"].values()) == 100
    assert all(r["ended_clean"] for r in summary["joints"].values())
    assert all(r["tracking"]["telemetry_frames"] > 0 for r in summary["joints"].values())
    rows = drives.summary()["joints"]
    assert rows["J1"]["syncs"] == rows["J2"]["syncs"] > 100
    assert drives.arm is not None and drives.arm.time == pytest.approx(
        (rows["J1"]["syncs"] - 1) * request.sample_period_s
    )
    assert rows["J3"]["syncs"] == 0 and rows["J3"]["drive_state"] == "SWITCH_ON_DISABLED"
