"""A rig of several joints, one process per bus, over python-can's udp_multicast inside a
private network namespace (loopback only, one multicast group per bus): a stock canopen
master finds and walks the drives that ``hdhil emulate --scenario rehabexos --bus can0``
serves, and ``hdhil firmware --bus`` of each bus runs the rig in real time against one
``hdhil emulate`` that owns the arm. Skipped, with the reason, where a namespace cannot
be created."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import time

import pytest
from test_multiprocess import _hdhil

pytestmark = [pytest.mark.slow, pytest.mark.subprocess, pytest.mark.netns, pytest.mark.realtime]

GROUPS = {"can0": "239.74.163.8", "can1": "239.74.163.9"}

MASTER = textwrap.dedent(
    """
    import json, sys, time
    import canopen
    from hdhil.canopen.cia402 import state_from_statusword
    from hdhil.dbc import eds_path

    group, expected = sys.argv[1], [int(n) for n in sys.argv[2].split(",")]
    net = canopen.Network()
    net.connect(interface="udp_multicast", channel=group)
    out = {"found": [], "nodes": {}}
    deadline = time.monotonic() + 60  # the emulator is up when the scanner finds it
    while time.monotonic() < deadline:
        net.scanner.reset()
        net.scanner.search()
        time.sleep(0.3)
        if all(n in net.scanner.nodes for n in expected):
            break
    out["found"] = sorted(net.scanner.nodes)
    nodes = []
    for node_id in out["found"]:
        node = canopen.BaseNode402(node_id, str(eds_path("drive")))
        net.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = 1.0
        node.tpdo.read()
        node.rpdo.read()
        out["nodes"][node_id] = {
            "device_type": node.sdo[0x1000].raw,
            "tpdo_cob_ids": [node.tpdo[n].cob_id for n in (1, 2)],
            "rpdo1_cob_id": node.rpdo[1].cob_id,
        }
        node.sdo[0x1006].raw = 10_000  # this master's SYNC period, 10 ms
        node.setup_402_state_machine(read_pdos=False)
        node.TIMEOUT_SWITCH_STATE_FINAL = 20.0  # a loaded machine: the walk's frames
        node.TIMEOUT_SWITCH_STATE_SINGLE = 10.0  # and threads can be late
        nodes.append(node)
    net.sync.start(0.01)
    for node in nodes:
        node.rpdo[1].start(0.005)  # a command in every SYNC cycle
        node.nmt.state = "OPERATIONAL"
    for node in nodes:
        node.state = "OPERATION ENABLED"
    for node in nodes:
        status = node.sdo["statusword"].raw
        out["nodes"][node.id]["state"] = state_from_statusword(status).name
    for node in nodes:
        node.state = "SWITCH ON DISABLED"
        node.nmt.state = "PRE-OPERATIONAL"
        node.rpdo[1].stop()
    net.sync.stop()
    print(json.dumps(out))
    net.disconnect()
    """
)


def _stop(proc: subprocess.Popen) -> tuple[str, str]:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    return proc.communicate(timeout=60)


def test_a_stock_canopen_master_finds_and_walks_every_drive_of_a_bus(netns):
    """python canopen's scanner finds both drives of rehabexos's bus can0 (J1 at node-ID
    2, J2 at 3), reads their objects and PDO COB-IDs and walks each to OPERATION ENABLED;
    the emulator's SYNC-driven arm advances with the master's SYNC."""
    emulator = _hdhil(netns, "emulate", "--scenario", "rehabexos", "--bus", "can0",
                      "--interface", "udp_multicast", "--channel", GROUPS["can0"])  # fmt: skip
    try:
        master = subprocess.run(
            ["ip", "netns", "exec", netns, sys.executable, "-c", MASTER, GROUPS["can0"], "2,3"],
            capture_output=True, text=True, timeout=180, check=False,
        )  # fmt: skip
    finally:
        out, err = _stop(emulator)
    assert master.returncode == 0, master.stderr + err
    found = json.loads(master.stdout.strip().splitlines()[-1])
    assert found["found"] == [2, 3]
    for node_id in (2, 3):
        row = found["nodes"][str(node_id)]
        assert row["device_type"] & 0xFFFF == 402  # CiA 402 drive
        assert row["tpdo_cob_ids"] == [0x180 + node_id, 0x280 + node_id]
        assert row["rpdo1_cob_id"] == 0x200 + node_id
        assert row["state"] == "OPERATION_ENABLED"
    summary = json.loads(out.strip().splitlines()[-1])
    assert sorted(summary["joints"]) == ["J1", "J2"]
    assert summary["arm"]["passive"] == ["J3", "J4"]  # can1's joints: not served here
    assert summary["arm"]["plant_time_s"] > 0  # moved by the master's SYNC
    assert "couples joints J3, J4" in err


def test_rehabexos_one_firmware_per_bus_against_one_emulator_in_real_time(netns):
    """One ``hdhil emulate`` owns the arm and serves both buses' drives (each bus on its
    multicast group), one ``hdhil firmware --bus`` per bus in real time for 2 s: every
    joint reaches operation and the firmware reports each joint's samples and torque
    error, the SYNC jitter and the machine floor of the same run (printed)."""
    buses = [f"--bus={name}={group}" for name, group in GROUPS.items()]
    emulator = _hdhil(netns, "emulate", "--scenario", "rehabexos", *buses,
                      "--interface", "udp_multicast", priority=True)  # fmt: skip
    firmwares = {}
    try:
        for name, group in GROUPS.items():
            firmwares[name] = _hdhil(
                netns, "firmware", "--scenario", "rehabexos", f"--bus={name}={group}",
                "--interface", "udp_multicast", "--duration", "2", "--boot-timeout", "60",
                "--spin-us", "150", "--floor-s", "0.5",
            )  # fmt: skip
            time.sleep(0.5)  # the second firmware's loop takes the other CPU
        results = {name: p.communicate(timeout=240) for name, p in firmwares.items()}
    finally:
        for p in firmwares.values():
            if p.poll() is None:
                _stop(p)
        out, _ = _stop(emulator)
    drives = json.loads(out.strip().splitlines()[-1])
    assert sorted(drives["joints"]) == ["J1", "J2", "J3", "J4"]
    assert drives["arm"]["passive"] == [] and drives["arm"]["clock"] == "J1"
    for name, (fw_out, fw_err) in results.items():
        assert firmwares[name].returncode in (0, 1), fw_err  # 1: a verdict (a stall)
        summary = json.loads(fw_out.strip().splitlines()[-1])
        rt = summary["realtime"]
        print(f"\n{name}: {summary['operational_cycles']} cycles in operation, "
              f"{rt['deadline_misses']} deadline misses, SYNC jitter p99.9 "
              f"{rt['jitter_us']['p99.9']} us, machine floor p99.9 "
              f"{rt['floor']['jitter_us']['p99.9']} us; {fw_err.strip()}")  # fmt: skip
        assert summary["bus"] == name
        joints = summary["joints"]
        assert sorted(joints) == (["J1", "J2"] if name == "can0" else ["J3", "J4"])
        for joint, row in joints.items():
            print(f"  {joint}: {row['samples']} samples, {row['phase']}, "
                  f"{row['drive_state']}, tracking {row['tracking']}"
                  + (f", {row['safe_reason']}" if "safe_reason" in row else ""))  # fmt: skip
            assert row["samples"] > 0, (joint, row)  # reached operation
            assert row["tracking"]["telemetry_frames"] > 0
        assert rt["cycles"] > 0 and rt["floor"]["cycles"] > 0


ISOLATION = textwrap.dedent(
    """
    import sys
    import can
    from hdhil.can.multicast import own_group_only

    a, b = (can.Bus(interface="udp_multicast", channel=g) for g in sys.argv[1:3])
    other = can.Bus(interface="udp_multicast", channel=sys.argv[2])
    print(own_group_only(a), own_group_only(b))
    other.send(can.Message(arbitration_id=0x182, data=b"x", is_extended_id=False))
    print(b.recv(2.0) is not None, a.recv(0.5) is not None)
    for bus in (a, b, other):
        bus.shutdown()
    """
)


def test_a_rig_bus_handle_receives_its_own_multicast_group_only(netns):
    """Two buses' groups in one namespace share python-can's port: a handle limited by
    ``own_group_only`` receives a frame of its own group and none of the other's."""
    run = subprocess.run(
        ["ip", "netns", "exec", netns, sys.executable, "-c", ISOLATION, *GROUPS.values()],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["True", "True", "True", "False"]
