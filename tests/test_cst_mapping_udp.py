"""``hdhil firmware --mapping cst`` closes its loop against ``hdhil emulate`` in another
process over python-can's udp_multicast, inside a private network namespace (loopback
only), with ``hdhil log`` recording the bus: the command and sensor frames have the DLC
and layout of the CiA 402 CST mapping (decoded with canopen's PDO maps read from the
shipped DCF) and the joint moves.  Skipped, with the reason, where a namespace cannot
be created."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import can
import canopen
import pytest
from test_multiprocess import _hdhil

from hdhil.canopen.mapping import mapping_dcf
from hdhil.dbc import codec

pytestmark = [pytest.mark.slow, pytest.mark.subprocess, pytest.mark.netns, pytest.mark.realtime]

GROUP_CONTROL = "239.74.163.5"
GROUP_TRUTH = "239.74.163.6"


def run_over_udp(
    netns: str, tmp_path: Path, mapping: str, groups: tuple[str, str]
) -> tuple[dict, list[can.Message]]:
    """``hdhil firmware --mapping MAPPING`` (0.6 s, network lockstep) against ``hdhil
    emulate``, with ``hdhil log`` recording, each a process in ``netns`` on the
    udp_multicast ``groups`` (control, truth): the firmware's JSON summary and the
    logged frames.  Emulator and logger must stop cleanly by SIGTERM (exit 0)."""
    trace = tmp_path / f"{mapping}.blf"
    bus = ["--interface", "udp_multicast", "--channel", groups[0]]
    truth = ["--truth-interface", "udp_multicast", "--truth-channel", groups[1]]
    logger = _hdhil(netns, "log", str(trace), *bus, *truth)
    emulator = _hdhil(netns, "emulate", *bus, *truth, "--scenario", "free-motion")
    time.sleep(1.5)  # both up and listening before the firmware boots
    firmware = _hdhil(netns, "firmware", *bus, "--scenario", "free-motion", "--duration", "0.6",
                      "--mapping", mapping, "--lockstep")  # fmt: skip
    try:
        out, err = firmware.communicate(timeout=120)
        assert firmware.returncode == 0, err
        fw = json.loads(out.strip().splitlines()[-1])
    finally:
        for proc in (emulator, logger):
            proc.send_signal(signal.SIGTERM)
        outs = [proc.communicate(timeout=60) for proc in (emulator, logger)]
        firmware.kill()
    for proc, (_out, err) in zip((emulator, logger), outs, strict=True):
        assert proc.returncode == 0, err  # a clean stop by SIGTERM
    assert fw["mapping"] == mapping and fw["phase"] == "stopped", fw
    assert fw["operational_cycles"] == 600
    assert outs[0][0] and json.loads(outs[0][0].strip().splitlines()[-1])["commands"] >= 600
    with can.LogReader(str(trace)) as reader:
        return fw, [m for m in reader if not m.is_error_frame]


def test_firmware_in_the_cst_mapping_against_hdhil_emulate_over_udp(netns, tmp_path):
    fw, frames = run_over_udp(netns, tmp_path, "cst", (GROUP_CONTROL, GROUP_TRUTH))
    assert fw["rated_torque_Nm"] > 0

    network = canopen.Network()  # not connected: the logged frames are handed to it
    node = network.add_node(2, str(mapping_dcf("cst")))
    node.rpdo.read(from_od=True)
    node.tpdo.read(from_od=True)
    commands = [m for m in frames if m.arbitration_id == 0x202 and not m.is_extended_id]
    sensors = [m for m in frames if m.arbitration_id == 0x182 and not m.is_extended_id]
    assert {m.dlc for m in commands} == {sum(v.length for v in node.rpdo[1].map) // 8} == {4}
    assert {m.dlc for m in sensors} == {sum(v.length for v in node.tpdo[1].map) // 8} == {6}
    torques = []
    for m in commands:
        network.notify(0x202, m.data, m.timestamp)
        if node.rpdo[1]["controlword"].raw == 0x000F:
            torques.append(node.rpdo[1]["target_torque"].raw)
    assert len(torques) >= 600 and any(t != 0 for t in torques)
    positions = []
    for m in sensors:
        network.notify(0x182, m.data, m.timestamp)
        positions.append(node.tpdo[1]["position_actual_value"].raw)
    assert positions[-1] - positions[0] > 8000  # more than one motor turn
    motion = codec("truth", "TRUTH_MOTION")
    omega = [motion.decode(m.data)[2] for m in frames
             if m.is_extended_id and m.arbitration_id == motion.frame_id]  # fmt: skip
    assert omega and omega[-1] > 50.0  # the emulated motor ran up under 0x6071
