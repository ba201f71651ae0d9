"""``hdhil firmware --mapping cst-sensor`` closes its loop against ``hdhil emulate`` in
another process over python-can's udp_multicast, inside a private network namespace
(loopback only), with ``hdhil log`` recording the bus: the sensor frames carry 0x6077,
0x6064 and the joint-torque sensor 0x2102 (decoded with canopen's PDO maps read from the
shipped DCF), the sensor value follows the emulator's true joint torque, and the joint
moves.  Skipped, with the reason, where a namespace cannot be created."""

from __future__ import annotations

import canopen
import numpy as np
import pytest
from test_cst_mapping_udp import run_over_udp

from hdhil.canopen.mapping import mapping_dcf
from hdhil.dbc import codec
from hdhil.firmware.config import FirmwareConfig

pytestmark = [pytest.mark.slow, pytest.mark.subprocess, pytest.mark.netns, pytest.mark.realtime]

GROUP_CONTROL = "239.74.163.7"
GROUP_TRUTH = "239.74.163.8"


def test_firmware_in_the_cst_sensor_mapping_against_hdhil_emulate_over_udp(netns, tmp_path):
    _fw, frames = run_over_udp(netns, tmp_path, "cst-sensor", (GROUP_CONTROL, GROUP_TRUTH))
    network = canopen.Network()  # not connected: the logged frames are handed to it
    node = network.add_node(2, str(mapping_dcf("cst-sensor")))
    node.tpdo.read(from_od=True)
    tpdo = node.tpdo[1]
    sensors = [m for m in frames if m.arbitration_id == 0x182 and not m.is_extended_id]
    assert {m.dlc for m in sensors} == {sum(v.length for v in tpdo.map) // 8} == {8}
    # each sensor frame's gauge value, calibrated, against the true joint torque the
    # emulator sent at the same SYNC (the frame just before it on the truth channel)
    torque = codec("truth", "TRUTH_TORQUE")
    cal = FirmwareConfig().calibration
    pairs, T_true, positions = [], None, []
    for m in frames:
        if m.is_extended_id and m.arbitration_id == torque.frame_id:
            T_true = torque.decode(m.data)[0]
        elif m.arbitration_id == 0x182 and not m.is_extended_id:
            network.notify(0x182, m.data, m.timestamp)
            positions.append(tpdo["position_actual_value"].raw)
            T = (tpdo["joint_torque_sensor"].raw * 1e-3 - cal.torque_offset_V) * cal.volt2Nm
            if T_true is not None:
                pairs.append((T, T_true))
    assert positions[-1] - positions[0] > 8000  # more than one motor turn
    measured, true = np.array(pairs[len(pairs) // 2 :]).T
    # the gauge reading is the joint torque plus its ripple (0.45 Nm RMS in free motion),
    # not the motor torque 0x6077 (3.8 Nm RMS off)
    assert np.sqrt(np.mean((measured - true) ** 2)) < 1.0
