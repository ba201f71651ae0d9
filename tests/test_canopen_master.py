"""The third-party ``canopen`` package as the master of the emulated drive, in process on a
python-can virtual bus (the drive served in real time, as ``hdhil emulate`` runs it):
PDOs configured at run time (remap, transmission type, disabled PDO) with the CiA 301
refusals, the RPDO event timer, SYNC supervision, the statusword's event timer and
``BaseNode402.reset_from_fault()``, and the SDO details (single-value sub-indices,
block transfers)."""

from __future__ import annotations

import time

import can
import canopen
import pytest
from canopen.sdo import SdoAbortedError

from hdhil.canopen.cia402 import State, state_from_statusword
from hdhil.dbc import eds_path
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant, PlantConfig

pytestmark = [pytest.mark.realtime]

TPDO1, TPDO2 = 0x182, 0x282


class Master:
    """canopen's Network with a BaseNode402 for node 2, and a listener bus that counts
    the drive's frames."""

    def __init__(self, channel: str) -> None:
        self.network = canopen.Network()
        self.network.connect(interface="virtual", channel=channel)
        self.node = canopen.BaseNode402(2, str(eds_path("drive")))
        self.network.add_node(self.node)
        self.node.sdo.RESPONSE_TIMEOUT = 1.0
        self.listener = can.Bus(interface="virtual", channel=channel)
        self.counter = 0

    def drain(self) -> list[can.Message]:
        out = []
        while (msg := self.listener.recv(0.05 if not out else 0.01)) is not None:
            out.append(msg)
        return out

    def syncs(self, n: int, gap_s: float = 0.004) -> list[list[can.Message]]:
        """Send n SYNCs (with counter); the drive's frames after each."""
        per_sync = []
        for _ in range(n):
            self.counter = self.counter % 240 + 1
            self.network.sync.transmit(self.counter)
            time.sleep(gap_s)
            per_sync.append(self.drain())
        return per_sync

    def close(self) -> None:
        self.network.sync.stop()
        self.network.disconnect()
        self.listener.shutdown()


@pytest.fixture
def master(serve_drive):
    cfg = DriveConfig(controller_heartbeat_timeout_ms=0, command_hold_cycles=0)
    drive, args = serve_drive(lambda bus: DriveNode(bus, Plant(PlantConfig()), cfg))
    m = Master(args[args.index("--channel") + 1])
    m.drive = drive
    deadline = time.monotonic() + 2
    while drive.nmt_state.name != "PRE_OPERATIONAL" and time.monotonic() < deadline:
        time.sleep(0.01)
    yield m
    m.close()


def _ids(frames: list[can.Message], cob: int) -> list[can.Message]:
    return [f for f in frames if f.arbitration_id == cob]


@pytest.mark.slow
def test_remap_transmission_type_and_disable_are_honoured(master):
    node = master.node
    node.tpdo.read()
    tpdo = node.tpdo[1]
    tpdo.clear()
    tpdo.add_variable(0x2100, 1)  # ADC torque only: 16 bits
    tpdo.trans_type = 2  # every 2nd SYNC
    tpdo.save()
    node.nmt.state = "OPERATIONAL"
    master.drain()
    frames = master.syncs(10)
    sent = [len(_ids(f, TPDO1)) for f in frames]
    assert sum(sent) == 5 and max(sent) == 1, sent  # one frame per two SYNCs
    assert {f.dlc for fs in frames for f in _ids(fs, TPDO1)} == {2}
    counts = [
        int.from_bytes(f.data, "little", signed=True) for fs in frames for f in _ids(fs, TPDO1)
    ]
    assert all(-2048 <= c <= 2047 for c in counts)

    node.nmt.state = "PRE-OPERATIONAL"
    tpdo.enabled = False  # COB-ID bit 31
    tpdo.save()
    node.nmt.state = "OPERATIONAL"
    master.drain()
    assert sum(len(_ids(f, TPDO1)) for f in master.syncs(6)) == 0

    # NMT reset communication restores the default mapping (the DBC's DRIVE_TPDO1).
    node.nmt.state = "RESET COMMUNICATION"
    time.sleep(0.1)
    node.nmt.state = "OPERATIONAL"
    master.drain()
    frames = master.syncs(4)
    assert [len(_ids(f, TPDO1)) for f in frames] == [1, 1, 1, 1]
    assert {f.dlc for fs in frames for f in _ids(fs, TPDO1)} == {8}


def test_cia301_refusals_of_the_mapping_procedure(master):
    sdo = master.node.sdo

    def abort(index: int, sub: int, value: int, size: int = 4) -> int:
        with pytest.raises(SdoAbortedError) as err:
            sdo.download(index, sub, value.to_bytes(size, "little"))
        return err.value.code

    # Mapping while the PDO is valid, and entries while sub-index 0 is non-zero.
    assert abort(0x1A00, 1, 0x21000110) == 0x06010000
    assert abort(0x1A00, 0, 0, 1) == 0x06010000
    # COB-ID change while valid.
    assert abort(0x1800, 1, 0x00000183) == 0x06090030
    # Reserved transmission type.
    assert abort(0x1800, 2, 245, 1) == 0x06090030
    # Following the procedure: invalid, sub 0 = 0, entries ...
    sdo.download(0x1800, 1, (0x80000182).to_bytes(4, "little"))
    sdo.download(0x1A00, 0, b"\x00")
    assert abort(0x1A00, 1, 0x10010008) == 0x06040041  # error register: not mappable
    assert abort(0x1A00, 1, 0x21000120) == 0x06040043  # wrong length
    assert abort(0x1A00, 1, 0x30000010) == 0x06020000  # no such object
    for sub in range(1, 6):
        sdo.download(0x1A00, sub, (0x21000110).to_bytes(4, "little"))
    assert abort(0x1A00, 0, 5, 1) == 0x06040042  # 80 bits > 64
    # An empty PDO cannot be made valid.
    assert abort(0x1800, 1, 0x00000182) == 0x06090030
    # The SDO details: a sub-index of a single-value object, block transfers.
    assert abort(0x1000, 1, 0) == 0x06090011
    with pytest.raises(SdoAbortedError) as err:
        sdo.upload(0x1017, 1)
    assert err.value.code == 0x06090011
    with (
        pytest.raises(SdoAbortedError) as err,
        sdo.open(0x1018, 1, "rb", block_transfer=True) as f,
    ):
        f.read()
    assert err.value.code == 0x05040001


def _enable(master: Master) -> None:
    sdo = master.node.sdo
    for cw in (0x06, 0x07, 0x0F):
        sdo.download(0x6040, 0, cw.to_bytes(2, "little"))
    assert master.drive.drive_state is State.OPERATION_ENABLED


@pytest.mark.slow
def test_sync_loss_raises_emcy_0x8100_and_the_abort_connection_reaction(master):
    node = master.node
    period = 0.04  # 0x1006 = 40 ms, SYNC every 5 ms: a loaded machine never gaps 60 ms
    node.sdo.download(0x1006, 0, round(period * 1e6).to_bytes(4, "little"))
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)
    _enable(master)
    master.network.sync.start(0.005)
    time.sleep(0.3)
    assert not [e for e in node.emcy.log if e.code == 0x8100]
    master.network.sync.stop()
    stopped = time.monotonic()
    emcy = node.emcy.wait(0x8100, timeout=1.0)
    assert emcy is not None
    # Detected within two periods after the timeout (1.5 periods after the last SYNC).
    assert time.monotonic() - stopped < 1.5 * period + 2 * period
    time.sleep(0.05)
    # 0x6007 = 2 (default): disable voltage.
    assert master.drive.drive_state is State.SWITCH_ON_DISABLED
    assert master.drive.diagnostics.sync_timeouts == 1


def test_rpdo_event_timer_deadline_raises_emcy_0x8250(master):
    node = master.node
    node.sdo.download(0x1400, 5, (100).to_bytes(2, "little"))  # 100 ms, RPDOs every 10 ms
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)
    _enable(master)
    node.rpdo.read()
    rpdo = node.rpdo[1]
    rpdo["controlword"].raw = 0x0F
    for _ in range(5):
        rpdo.transmit()
        time.sleep(0.01)
    assert not [e for e in node.emcy.log if e.code == 0x8250]
    emcy = node.emcy.wait(0x8250, timeout=1.0)
    assert emcy is not None and emcy.data[0] == 1  # RPDO number 1
    assert master.drive.diagnostics.rpdo_timeouts == 1


@pytest.mark.slow
def test_statusword_event_timer_repeats_the_statusword(master):
    node = master.node
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.35)
    words = _ids(master.drain(), TPDO2)
    # Sent once on entering OPERATIONAL, then every 100 ms (0x1801:5) unchanged.
    assert 3 <= len(words) <= 5, len(words)
    assert len({bytes(w.data) for w in words}) == 1


@pytest.mark.slow
def test_reset_from_fault_works_with_basenode402(master):
    node = master.node
    node.tpdo.read()
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)
    _enable(master)
    # A fault: the RPDO event timer with no RPDO at all after one command.
    node.sdo.download(0x1400, 5, (20).to_bytes(2, "little"))
    node.rpdo.read()
    node.rpdo[1]["controlword"].raw = 0x0F
    node.rpdo[1].transmit()
    node.sdo.download(0x6007, 0, (1).to_bytes(2, "little", signed=True))  # fault reaction
    node.rpdo[1].transmit()
    deadline = time.monotonic() + 1
    while master.drive.drive_state is not State.FAULT and time.monotonic() < deadline:
        time.sleep(0.01)
    assert master.drive.drive_state is State.FAULT
    node.sdo.download(0x1400, 5, (0).to_bytes(2, "little"))
    node.reset_from_fault()
    assert state_from_statusword(master.drive.statusword) is not State.FAULT


@pytest.mark.slow
def test_identity_strings_and_store_restore(master):
    node = master.node
    # Visible strings longer than 4 bytes: segmented upload.
    assert node.sdo[0x1008].raw == "hdhil drive"
    assert node.sdo[0x100A].raw == "0.1.0"
    assert node.sdo[0x1018][2].raw == int(
        canopen.import_od(str(eds_path("drive"))).device_information.product_number
    )
    # 0x1010:1 = "save": the present values become what NMT reset node restores.
    node.sdo[0x605A].raw = 5
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[0x1010][1].raw = 0x12345678  # not the signature
    assert err.value.code == 0x08000020
    node.sdo[0x1010][1].raw = int.from_bytes(b"save", "little")
    assert node.sdo[0x1010][1].raw == 1  # reads back the capability: saves on command
    node.sdo[0x605A].raw = 6
    node.nmt.state = "RESET"
    time.sleep(0.1)
    assert node.sdo[0x605A].raw == 5
    # 0x1011:1 = "load": the EDS defaults come back at the next reset.
    node.sdo[0x1011][1].raw = int.from_bytes(b"load", "little")
    node.nmt.state = "RESET"
    time.sleep(0.1)
    assert node.sdo[0x605A].raw == canopen.import_od(str(eds_path("drive")))[0x605A].default


@pytest.mark.slow
def test_a_cst_torque_loop_entirely_through_the_standard_objects(master):
    """canopen's master maps 0x6071 target torque (with the controlword) into RPDO1 and
    0x6077 torque actual with 0x6064 position actual into TPDO1, enables the drive in
    cyclic synchronous torque and closes a loop through them alone."""
    node = master.node
    assert node.sdo["modes_of_operation_display"].raw == 10  # CST
    node.rpdo.read()
    node.tpdo.read()
    rpdo, tpdo = node.rpdo[1], node.tpdo[1]
    rpdo.clear()
    rpdo.add_variable("target_torque")
    rpdo.add_variable("controlword")
    rpdo.save()
    tpdo.clear()
    tpdo.add_variable("torque_actual_value")
    tpdo.add_variable("position_actual_value")
    tpdo.save()
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)

    def cycle(cw: int, torque: int) -> None:
        rpdo["controlword"].raw = cw
        rpdo["target_torque"].raw = torque
        rpdo.transmit()
        master.counter = master.counter % 240 + 1
        master.network.sync.transmit(master.counter)
        time.sleep(0.003)

    for cw in (0x06, 0x07, 0x0F, 0x0F):
        cycle(cw, 0)
    assert master.drive.drive_state is State.OPERATION_ENABLED
    start = None
    actual = []
    for _ in range(100):  # a P loop on torque actual, commanded through 0x6071 only
        error = 150 - (tpdo["torque_actual_value"].raw if actual else 0)
        cycle(0x0F, max(-300, min(300, 150 + error // 2)))
        actual.append(tpdo["torque_actual_value"].raw)
        if start is None:
            start = tpdo["position_actual_value"].raw
    assert abs(sum(actual[-20:]) / 20 - 150) <= 10, actual[-20:]  # per mille of rated
    assert tpdo["position_actual_value"].raw != start  # the joint moved
    assert {len(bytes(tpdo.data))} == {6}
