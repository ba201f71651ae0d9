"""The third-party ``canopen`` master against ``hdhil emulate`` in another process, over
python-can's udp_multicast inside a private network namespace (loopback only): remap,
transmission type and a disabled PDO honoured, the CiA 301 refusals, SYNC loss detected
with EMCY 0x8100.  Skipped, with the reason, where a namespace cannot be created."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap

import pytest
from test_multiprocess import _hdhil

pytestmark = [pytest.mark.slow, pytest.mark.subprocess, pytest.mark.netns, pytest.mark.realtime]

GROUP = "239.74.163.4"

MASTER = textwrap.dedent(
    """
    import json, sys, time
    import can, canopen
    from canopen.sdo import SdoAbortedError
    from hdhil.dbc import eds_path

    group = sys.argv[1]
    net = canopen.Network()
    net.connect(interface="udp_multicast", channel=group)
    node = canopen.BaseNode402(2, str(eds_path("drive")))
    net.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 1.0
    listen = can.Bus(interface="udp_multicast", channel=group)
    out = {}
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:  # the emulator is up when its heartbeat comes
        m = listen.recv(0.5)
        if m is not None and m.arbitration_id == 0x702:
            break
    else:
        sys.exit("no heartbeat from the emulator (node 2)")

    def drain():
        frames = []
        while (m := listen.recv(0.05 if not frames else 0.01)) is not None:
            frames.append(m)
        return frames

    def abort(index, sub, value, size=4):
        try:
            node.sdo.download(index, sub, value.to_bytes(size, "little"))
        except SdoAbortedError as e:
            return e.code
        return None

    out["map_while_valid"] = abort(0x1A00, 1, 0x21000110)
    out["cob_change_while_valid"] = abort(0x1800, 1, 0x183)
    node.tpdo.read()
    tpdo = node.tpdo[1]
    tpdo.clear()
    tpdo.add_variable(0x2100, 1)
    tpdo.trans_type = 3
    tpdo.save()
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.1)
    drain()
    per_sync = []
    for k in range(1, 13):
        net.sync.transmit(k)
        time.sleep(0.01)
        per_sync.append([m.dlc for m in drain() if m.arbitration_id == 0x182])
    out["tpdo1_per_sync"] = per_sync
    node.nmt.state = "PRE-OPERATIONAL"
    tpdo.enabled = False
    tpdo.save()
    node.sdo.download(0x1006, 0, (20_000).to_bytes(4, "little"))
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.1)
    drain()
    net.sync.start(0.01)
    time.sleep(0.3)
    out["disabled_frames"] = sum(m.arbitration_id == 0x182 for m in drain())
    net.sync.stop()
    t0 = time.monotonic()
    emcy = node.emcy.wait(0x8100, timeout=2.0)
    out["sync_loss_emcy_s"] = None if emcy is None else time.monotonic() - t0
    print(json.dumps(out))
    net.disconnect()
    listen.shutdown()
    """
)


def test_canopen_master_configures_hdhil_emulate_over_udp_multicast(netns):
    bus = ["--interface", "udp_multicast", "--channel", GROUP]
    emulator = _hdhil(netns, "emulate", *bus, "--scenario", "free-motion")
    try:
        master = subprocess.run(
            ["ip", "netns", "exec", netns, sys.executable, "-c", MASTER, GROUP],
            capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip
        if master.returncode != 0:
            emulator.send_signal(signal.SIGTERM)
            raise AssertionError(master.stderr + emulator.communicate(timeout=60)[1])
        out = json.loads(master.stdout.strip().splitlines()[-1])
    finally:
        emulator.send_signal(signal.SIGTERM)
        emulator.communicate(timeout=60)
    assert out["map_while_valid"] == 0x06010000
    assert out["cob_change_while_valid"] == 0x06090030
    sent = [len(dlcs) for dlcs in out["tpdo1_per_sync"]]
    assert sum(sent) == 4 and max(sent) == 1, sent  # every 3rd of 12 SYNCs
    assert {d for dlcs in out["tpdo1_per_sync"] for d in dlcs} == {2}
    assert out["disabled_frames"] == 0
    assert out["sync_loss_emcy_s"] is not None and out["sync_loss_emcy_s"] < 0.5
