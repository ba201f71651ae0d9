"""CANopen services on simbus: NMT, heartbeat, EMCY, checked SDO server, SDO client, SYNC.

Every test runs in simulated time on ``simbus`` buses: no sleeps, no wall clock.  The SDO
server side is exercised with hand-crafted request frames (deterministic), the client
helpers with canopen's own ``SdoClient`` on a network that pumps the server on each send.
"""

from __future__ import annotations

import math
import struct

import can
import canopen
import pytest
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable
from canopen.objectdictionary import datatypes as dt
from conftest import BusHarness
from hypothesis import given, settings
from hypothesis import strategies as st

from hdhil.canopen.services import (
    ABORT_TEXT,
    BootTimeoutError,
    CanopenServices,
    EmcyCode,
    ErrorRegister,
    NmtCommand,
    NmtState,
    SdoError,
    SyncMonitor,
    SyncProducer,
    abort_text,
    default_error_register,
    emcy_text,
    load_od,
    sdo_read,
    sdo_write,
)
from hdhil.dbc import eds_path

# ----------------------------------------------------------------------------- fixtures


class Bench(BusHarness):
    """The shared bus harness; its host plays the other nodes, CANopen service nodes of
    the test on its channel."""

    def services(self, node_id: int, od, **kwargs) -> CanopenServices:
        return CanopenServices(self.bus(), node_id, od, **kwargs)


@pytest.fixture
def bench():
    with Bench("t-canopen") as b:
        yield b


def pump(services: CanopenServices, now: float | None = None) -> list[bool]:
    """Let a node handle everything waiting on its bus; returns what handle() said."""
    results = []
    while (msg := services.bus.recv(0)) is not None:
        results.append(services.handle(msg, now))
    return results


# ------------------------------------------------------------------- a test dictionary


def _var(name, index, sub=0, dtype=dt.UNSIGNED8, access="rw", default=0, **extra):
    var = ODVariable(name, index, sub)
    var.data_type = dtype
    var.access_type = access
    var.default = default
    var.pdo_mappable = extra.get("mappable", False)
    var.min = extra.get("lo")
    var.max = extra.get("hi")
    return var


def _array(name, index, n, dtype, access="rw", sub0_access="const", default=0, sub0=None):
    array = ODArray(name, index)
    array.add_member(_var("Highest sub-index", index, 0, dt.UNSIGNED8, sub0_access, sub0 or n))
    for sub in range(1, n + 1):
        array.add_member(_var(f"{name} {sub}", index, sub, dtype, access, default))
    return array


def services_od(node_id: int = 2) -> ObjectDictionary:
    """The objects the services need (the project EDS files lack some of them yet)."""
    od = ObjectDictionary()
    od.add_object(_var("Device type", 0x1000, 0, dt.UNSIGNED32, "ro", 0x00020192))
    od.add_object(_var("Error register", 0x1001, 0, dt.UNSIGNED8, "ro", 0))
    od.add_object(_array("Pre-defined error field", 0x1003, 4, dt.UNSIGNED32, "ro", "rw", sub0=0))
    od.add_object(_var("COB-ID SYNC", 0x1005, 0, dt.UNSIGNED32, "rw", 0x40000080))
    od.add_object(_var("Communication cycle period", 0x1006, 0, dt.UNSIGNED32, "rw", 1000))
    od.add_object(_array("Consumer heartbeat time", 0x1016, 2, dt.UNSIGNED32))
    od.add_object(_var("Producer heartbeat time", 0x1017, 0, dt.UNSIGNED16, "rw", 100))
    od.add_object(_var("Sync counter overflow", 0x1019, 0, dt.UNSIGNED8, "rw", 240, lo=0, hi=240))
    od.add_object(_array("Error behaviour", 0x1029, 1, dt.UNSIGNED8, default=1))
    mapping = ODRecord("TPDO1 mapping parameter", 0x1A00)
    mapping.add_member(_var("Number of mapped objects", 0x1A00, 0, dt.UNSIGNED8, "rw", 2))
    for sub, default in enumerate((0x60410010, 0x20100008, 0, 0), start=1):
        mapping.add_member(_var(f"Object {sub}", 0x1A00, sub, dt.UNSIGNED32, "rw", default))
    od.add_object(mapping)
    od.add_object(_var("cycle", 0x2010, 0, dt.UNSIGNED8, "rww", 0, mappable=True))
    od.add_object(_var("filter Q", 0x2300, 0, dt.REAL32, "rw", 1000.0, lo=0.0, hi=1e6))
    od.add_object(_var("gain", 0x2301, 0, dt.INTEGER16, "rw", 5, lo=-100, hi=100))
    od.add_object(_var("command", 0x2302, 0, dt.UNSIGNED32, "wo", 0))
    od.add_object(_var("big", 0x2303, 0, dt.UNSIGNED64, "rw", 0))
    od.add_object(_var("label", 0x2304, 0, dt.VISIBLE_STRING, "rw", "hdhil"))
    od.add_object(_var("controlword", 0x6040, 0, dt.UNSIGNED16, "rww", 0, mappable=True))
    od.add_object(_var("statusword", 0x6041, 0, dt.UNSIGNED16, "ro", 0, mappable=True))
    return od


# ------------------------------------------------------------------- SDO by hand


def sdo_download(bench: Bench, node: CanopenServices, index: int, sub: int, data: bytes):
    """Expedited download (1..4 bytes) by hand; returns the abort code or None."""
    n = len(data)
    command = 0x23 | ((4 - n) << 2)
    bench.send(
        0x600 + node.node_id, struct.pack("<BHB", command, index, sub) + data.ljust(4, b"\0")
    )
    pump(node)
    ((cob, response),) = bench.frames()
    assert cob == 0x580 + node.node_id
    if response[0] == 0x80:
        assert struct.unpack_from("<HB", response, 1) == (index, sub)
        return struct.unpack_from("<I", response, 4)[0]
    assert response[0] == 0x60
    return None


def sdo_upload(bench: Bench, node: CanopenServices, index: int, sub: int):
    """Expedited upload by hand; returns bytes, or ("abort", code)."""
    bench.send(0x600 + node.node_id, struct.pack("<BHB", 0x40, index, sub) + bytes(4))
    pump(node)
    ((cob, response),) = bench.frames()
    assert cob == 0x580 + node.node_id
    if response[0] == 0x80:
        return ("abort", struct.unpack_from("<I", response, 4)[0])
    assert response[0] & 0xE3 == 0x43, "expedited with size indicated"
    n = 4 - ((response[0] >> 2) & 3)
    return response[4 : 4 + n]


def booted(bench: Bench, node_id: int = 2, od=None, **kwargs) -> CanopenServices:
    node = bench.services(node_id, services_od(node_id) if od is None else od, **kwargs)
    node.boot(0.0)
    bench.frames()
    return node


# ============================================================================= NMT


def test_boot_sends_the_boot_up_message_and_enters_pre_operational(bench):
    node = bench.services(2, eds_path("drive"))
    changes = []
    node.on_state_change(lambda old, new: changes.append((old, new)))
    assert node.state is NmtState.INITIALISING
    node.boot(0.0)
    assert bench.frames() == [(0x702, b"\x00")]
    assert node.state is NmtState.PRE_OPERATIONAL
    assert changes == [(NmtState.INITIALISING, NmtState.PRE_OPERATIONAL)]
    with pytest.raises(RuntimeError, match="already booted"):
        node.boot(1.0)


def test_nmt_commands_before_boot_are_ignored(bench):
    node = bench.services(2, eds_path("drive"))
    bench.send(0x000, bytes((NmtCommand.START, 2)))
    assert pump(node) == [True]
    assert node.state is NmtState.INITIALISING
    assert bench.frames() == []


@pytest.mark.parametrize("target", [2, 0], ids=["addressed", "broadcast"])
def test_every_nmt_command(bench, target):
    node = booted(bench, od=eds_path("drive"))
    changes = []
    node.on_state_change(lambda old, new: changes.append(new))
    steps = [
        (NmtCommand.START, NmtState.OPERATIONAL),
        (NmtCommand.ENTER_PRE_OPERATIONAL, NmtState.PRE_OPERATIONAL),
        (NmtCommand.STOP, NmtState.STOPPED),
        (NmtCommand.START, NmtState.OPERATIONAL),
        (NmtCommand.STOP, NmtState.STOPPED),
        (NmtCommand.ENTER_PRE_OPERATIONAL, NmtState.PRE_OPERATIONAL),
        (NmtCommand.STOP, NmtState.STOPPED),
    ]
    for cs, state in steps:
        bench.send(0x000, bytes((cs, target)))
        assert pump(node) == [True]
        assert node.state is state
    assert changes == [state for _, state in steps]
    assert bench.frames() == []  # no heartbeat configured, no boot-up
    for cs in (NmtCommand.RESET_COMMUNICATION, NmtCommand.RESET_NODE):
        changes.clear()
        bench.send(0x000, bytes((cs, target)))
        pump(node)
        assert bench.frames() == [(0x702, b"\x00")]
        assert changes[-2:] == [NmtState.INITIALISING, NmtState.PRE_OPERATIONAL]
        assert node.state is NmtState.PRE_OPERATIONAL
    assert node.counters.nmt_commands == len(steps) + 2


def test_nmt_command_for_another_node_or_malformed_changes_nothing(bench):
    node = booted(bench, od=eds_path("drive"))
    bench.send(0x000, bytes((NmtCommand.START, 3)))
    bench.send(0x000, bytes((NmtCommand.START,)))  # DLC 1
    assert pump(node) == [True, True]
    assert node.state is NmtState.PRE_OPERATIONAL
    assert node.counters.malformed_frames == 1
    assert node.counters.nmt_commands == 0


def test_reset_node_restores_the_application_area_reset_comm_only_comm(bench):
    node = booted(bench)
    kinds = []
    node.on_reset(kinds.append)
    node.write(0x2301, 0, 42)
    node.write(0x1017, 0, 0)
    node.reset("communication")
    assert (node.read(0x2301), node.read(0x1017)) == (42, 100)
    node.write(0x1017, 0, 0)
    node.reset("node")
    assert (node.read(0x2301), node.read(0x1017)) == (5, 100)
    assert kinds == ["communication", "node"]


def test_stopped_allows_only_nmt_and_heartbeat(bench):
    node = booted(bench, heartbeat_producer_ms=10)
    node.enter_state(NmtState.STOPPED)
    assert not (node.pdo_allowed or node.sdo_allowed or node.sync_allowed or node.emcy_allowed)
    bench.send(0x602, struct.pack("<BHB4x", 0x40, 0x1000, 0))  # SDO upload request
    pump(node)
    assert not node.emcy.raise_error(EmcyCode.GENERIC)  # recorded, not sent
    assert node.emcy.error_register & ErrorRegister.GENERIC
    node.tick(0.010)
    assert bench.frames() == [(0x702, bytes((NmtState.STOPPED,)))]  # heartbeat only
    assert node.counters.ignored_in_state == 1
    node.enter_state(NmtState.OPERATIONAL)
    assert node.pdo_allowed and node.sdo_allowed


def test_service_permissions_follow_every_nmt_state_change(bench):
    node = booted(bench)
    expected_pdo = {NmtState.OPERATIONAL}
    expected_sdo = {NmtState.OPERATIONAL, NmtState.PRE_OPERATIONAL}
    seen = []
    for command in (0x01, 0x80, 0x02, 0x01, 0x82, 0x02, 0x80, 0x81, 0x01):
        bench.send(0x000, bytes((command, 2)))
        pump(node)
        state = node.state
        seen.append(state)
        allowed = (node.pdo_allowed, node.sdo_allowed, node.sync_allowed, node.emcy_allowed)
        sdo = state in expected_sdo
        assert allowed == (state in expected_pdo, sdo, sdo, sdo), state
    assert set(seen) == {NmtState.OPERATIONAL, NmtState.PRE_OPERATIONAL, NmtState.STOPPED}


def test_nmt_master_commands_and_boot_wait(bench):
    master = booted(bench, node_id=1, od=eds_path("controller"))
    master.nmt.expect_boot(2, now=0.0, timeout_s=0.5)
    assert not master.nmt.boot_seen(2) and master.nmt.check_boot(0.4) is False
    with pytest.raises(BootTimeoutError, match=r"node 2 \(COB-ID 0x702, data 00\) within 0.500 s"):
        master.nmt.check_boot(0.6)
    assert master.nmt.boot_timed_out(0.6) == (2,)
    drive = bench.services(2, eds_path("drive"))
    drive.boot(0.55)
    booted_seen = []
    master.on_boot(booted_seen.append)
    pump(master, now=0.55)
    assert master.nmt.boot_seen(2) and master.nmt.check_boot(0.6) is True
    assert booted_seen == [2]
    assert master.nmt.remote_states.get(2) is NmtState.PRE_OPERATIONAL
    bench.frames()

    master.nmt.command(NmtCommand.START, 2)
    assert bench.frames() == [(0x000, b"\x01\x02")]
    pump(drive)
    assert drive.state is NmtState.OPERATIONAL
    master.nmt.command(NmtCommand.RESET_NODE, 0)  # broadcast reset forgets the boot-ups
    assert not master.nmt.boot_seen(2)
    pump(drive)
    pump(master, now=0.7)
    assert master.nmt.boot_seen(2)
    assert master.state is NmtState.PRE_OPERATIONAL  # the master's own broadcast
    with pytest.raises(ValueError):
        master.nmt.command(0x55, 2)
    with pytest.raises(ValueError):
        master.nmt.command(NmtCommand.START, 128)


@pytest.mark.slow
def test_handle_ignores_non_service_frames_cheaply(bench):
    node = booted(bench, od=eds_path("drive"))
    for can_id, data, extra in [
        (0x080, b"\x01", {}),  # SYNC belongs to the node
        (0x182, bytes(8), {}),  # PDOs
        (0x202, bytes(5), {}),
        (0x582, bytes(8), {}),  # an SDO response, not a request to us
        (0x082, bytes(8), {}),  # our own EMCY COB-ID
        (0x702, b"\x05", {}),  # our own heartbeat COB-ID
        (0x602, bytes(8), {"is_remote_frame": False, "dlc": 8}),
    ]:
        msg = can.Message(arbitration_id=can_id, data=data, is_extended_id=False, **extra)
        expected = can_id == 0x602
        assert node.handle(msg) is expected, hex(can_id)
    ext = can.Message(arbitration_id=0x602, data=bytes(8), is_extended_id=True)
    assert node.handle(ext) is False
    rtr = can.Message(arbitration_id=0x701, is_remote_frame=True, is_extended_id=False)
    assert node.handle(rtr) is False


# ====================================================================== heartbeat


def run_ticks(bench: Bench, node: CanopenServices, until: float, dt_s: float = 0.001):
    """Tick every dt until ``until``; returns [(tick time, cob, data)] of frames sent."""
    sent = []
    k = round(node.now / dt_s)
    while (t := (k + 1) * dt_s) <= until + 1e-12:
        k += 1
        bench.clock.now = t
        node.tick(t)
        sent += [(round(t, 6), cob, data) for cob, data in bench.frames()]
    return sent


def test_heartbeat_producer_period_and_content(bench):
    node = booted(bench, heartbeat_producer_ms=100)
    sent = run_ticks(bench, node, 0.35)
    assert sent == [(0.1, 0x702, b"\x7f"), (0.2, 0x702, b"\x7f"), (0.3, 0x702, b"\x7f")]
    node.enter_state(NmtState.OPERATIONAL)
    sent = run_ticks(bench, node, 0.5)
    assert sent == [(0.4, 0x702, b"\x05"), (0.5, 0x702, b"\x05")]
    assert node.counters.heartbeats_sent == 5


def test_heartbeat_producer_from_the_od_and_sdo_write_of_0x1017(bench):
    node = booted(bench)  # OD default 100 ms
    assert node.heartbeat.period_s == pytest.approx(0.1)
    run_ticks(bench, node, 0.15)
    assert sdo_download(bench, node, 0x1017, 0, struct.pack("<H", 20)) is None
    sent = run_ticks(bench, node, 0.2)
    assert [t for t, _, _ in sent] == [0.17, 0.19]
    assert sdo_download(bench, node, 0x1017, 0, b"\0\0") is None
    assert run_ticks(bench, node, 1.0) == []


def test_heartbeat_late_tick_sends_once_and_keeps_the_grid(bench):
    node = booted(bench, heartbeat_producer_ms=100)
    node.tick(0.35)  # slots 0.1, 0.2, 0.3 overdue: one heartbeat, no burst
    assert len(bench.frames()) == 1
    node.tick(0.39)
    assert bench.frames() == []
    node.tick(0.4)
    assert len(bench.frames()) == 1


def test_heartbeat_is_deterministic(bench):
    runs = []
    for node_id in (5, 6):
        node = booted(bench, node_id=node_id, od=eds_path("drive"), heartbeat_producer_ms=7)
        bench.clock.now = 0.0
        runs.append([(t, data) for t, _, data in run_ticks(bench, node, 0.2, 0.0005)])
    assert runs[0] == runs[1]
    assert len(runs[0]) == 28  # floor(0.2 / 0.007)


def consumer_pair(bench: Bench, timeout_ms: int = 250, **kwargs):
    """A drive (node 2) monitoring the controller (node 1) at ``timeout_ms``."""
    drive = booted(bench, 2, heartbeat_consumers={1: timeout_ms}, **kwargs)
    lost, resumed = [], []
    drive.on_heartbeat_lost(lost.append)
    drive.on_heartbeat_resumed(resumed.append)
    return drive, lost, resumed


def heartbeat_from(bench: Bench, node: CanopenServices, node_id: int, t: float, state=0x05):
    bench.clock.now = t
    bench.send(0x700 + node_id, bytes((state,)))
    assert pump(node, now=t) == [True]


def test_consumer_does_not_monitor_before_the_first_heartbeat(bench):
    drive, lost, _ = consumer_pair(bench)
    assert drive.heartbeat_consumer.monitored[1].status == "waiting"
    heartbeat_from(bench, drive, 1, 0.0, state=0x00)  # a boot-up does not start it
    run_ticks(bench, drive, 5.0)
    assert lost == [] and drive.heartbeat_consumer.monitored[1].status == "waiting"


def test_consumer_detects_loss_once_between_timeout_and_one_tick_later(bench):
    drive, lost, resumed = consumer_pair(bench, timeout_ms=250)
    run_ticks(bench, drive, 0.1)
    heartbeat_from(bench, drive, 1, 0.1)
    assert drive.heartbeat_consumer.monitored[1].status == "active"
    detected_at = []
    drive.on_heartbeat_lost(lambda node: detected_at.append(drive.now))
    sent = run_ticks(bench, drive, 1.0)
    assert lost == [1]  # once, although the ticks go on
    assert 0.35 < detected_at[0] <= 0.35 + 0.001 + 1e-9
    monitor = drive.heartbeat_consumer.monitored[1]
    assert monitor.status == "lost" and monitor.losses == 1 and monitor.lost_at == detected_at[0]
    # EMCY 0x8130, manufacturer byte 0 = the lost node, communication bit in 0x1001.
    emcy = [(cob, data) for _, cob, data in sent if cob == 0x082]
    register = ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION
    assert emcy == [(0x082, struct.pack("<HB5s", 0x8130, register, b"\x01"))]
    assert drive.read(0x1001) == register

    heartbeat_from(bench, drive, 1, 1.2)
    assert resumed == [1] and monitor.status == "active" and monitor.resumed_at == 1.2
    assert bench.frames() == [(0x082, struct.pack("<HB5s", 0, 0, bytes(5)))]
    run_ticks(bench, drive, 1.4)
    assert lost == [1]
    run_ticks(bench, drive, 1.46)
    assert lost == [1, 1] and monitor.losses == 2


def test_heartbeats_in_time_never_trip_the_consumer(bench):
    drive, lost, _ = consumer_pair(bench, timeout_ms=250)
    for k in range(1, 40):
        run_ticks(bench, drive, k * 0.1)
        heartbeat_from(bench, drive, 1, k * 0.1)
    assert lost == []
    assert drive.nmt.remote_states.get(1) is NmtState.OPERATIONAL


def test_boot_up_of_a_monitored_node_restarts_monitoring(bench):
    drive, lost, _ = consumer_pair(bench, timeout_ms=250)
    heartbeat_from(bench, drive, 1, 0.0)
    heartbeat_from(bench, drive, 1, 0.1, state=0x00)  # node 1 rebooted
    assert drive.heartbeat_consumer.monitored[1].status == "waiting"
    run_ticks(bench, drive, 2.0)
    assert lost == []


@pytest.mark.parametrize(
    ("behaviour", "start", "after"),
    [
        (0, NmtState.OPERATIONAL, NmtState.PRE_OPERATIONAL),
        (1, NmtState.OPERATIONAL, NmtState.OPERATIONAL),
        (2, NmtState.PRE_OPERATIONAL, NmtState.STOPPED),
    ],
)
def test_error_behaviour_0x1029_on_heartbeat_loss(bench, behaviour, start, after):
    drive, lost, _ = consumer_pair(bench, timeout_ms=50)
    drive.write(0x1029, 1, behaviour)
    drive.enter_state(start)
    heartbeat_from(bench, drive, 1, 0.0)
    run_ticks(bench, drive, 0.1)
    assert lost == [1] and drive.state is after


def test_consumer_entries_written_by_sdo(bench):
    drive = booted(bench)
    assert drive.heartbeat_consumer.monitored == {}
    assert sdo_download(bench, drive, 0x1016, 1, struct.pack("<I", 0x00010064)) is None
    assert drive.heartbeat_consumer.monitored[1].timeout_s == pytest.approx(0.1)
    # The same node twice with non-zero times: general parameter incompatibility.
    assert sdo_download(bench, drive, 0x1016, 2, struct.pack("<I", 0x000100C8)) == 0x06040043
    assert drive.read(0x1016, 2) == 0
    assert sdo_download(bench, drive, 0x1016, 2, struct.pack("<I", 0x01030064)) == 0x06090030
    assert sdo_download(bench, drive, 0x1016, 1, bytes(4)) is None
    assert drive.heartbeat_consumer.monitored == {}


def test_consumer_without_0x1016_in_the_od_uses_the_argument(bench):
    drive = booted(bench, 2, od=eds_path("drive"), heartbeat_consumers={1: 30})
    lost = []
    drive.on_heartbeat_lost(lost.append)
    heartbeat_from(bench, drive, 1, 0.0)
    run_ticks(bench, drive, 0.05)
    assert lost == [1]
    with pytest.raises(ValueError):
        bench.services(2, eds_path("drive"), heartbeat_consumers={2: 100})  # itself


# ============================================================================ EMCY


NAMED_CODES = [code for code in EmcyCode if code != EmcyCode.NO_ERROR]


@pytest.mark.parametrize("code", NAMED_CODES, ids=lambda c: f"{c.name}_{c.value:04X}")
def test_emcy_frame_layout_for_each_named_code(bench, code):
    node = booted(bench)
    assert node.emcy.raise_error(code, manufacturer=b"\x11\x22")
    register = default_error_register(code) | ErrorRegister.GENERIC
    data = struct.pack("<H", code) + bytes((register,)) + b"\x11\x22\x00\x00\x00"
    assert bench.frames() == [(0x082, data)]
    assert node.read(0x1001) == register == node.emcy.error_register
    assert sdo_upload(bench, node, 0x1001, 0) == bytes((register,))
    assert node.emcy.history == (code | 0x2211 << 16,)
    assert emcy_text(code) != "unknown"


def test_error_register_classes():
    assert default_error_register(0x2310) == ErrorRegister.CURRENT
    assert default_error_register(0x3210) == ErrorRegister.VOLTAGE
    assert default_error_register(0x4210) == ErrorRegister.TEMPERATURE
    assert default_error_register(0x8130) == ErrorRegister.COMMUNICATION
    assert default_error_register(0x8250) == ErrorRegister.COMMUNICATION
    assert default_error_register(0x7300) == ErrorRegister.DEVICE_PROFILE
    assert default_error_register(0x8311) == ErrorRegister.DEVICE_PROFILE
    assert default_error_register(0xFF00) == ErrorRegister.MANUFACTURER
    assert default_error_register(0x6100) == ErrorRegister.GENERIC
    assert emcy_text(0x2351) == "current"


def test_emcy_once_per_error_clear_and_reset(bench):
    node = booted(bench)
    assert node.emcy.raise_error(EmcyCode.CONTINUOUS_OVER_CURRENT)
    assert not node.emcy.raise_error(EmcyCode.CONTINUOUS_OVER_CURRENT)  # still active: no flood
    assert node.emcy.raise_error(EmcyCode.SENSOR, register_bits=ErrorRegister.MANUFACTURER)
    frames = bench.frames()
    assert [struct.unpack_from("<HB", d) for _, d in frames] == [(0x2310, 0x03), (0x7300, 0x83)]
    assert node.emcy.active_errors == (0x2310, 0x7300)
    assert node.emcy.error_active(0x2310) and node.emcy.error_active(0x7300)
    assert not node.emcy.error_active(0x8250)
    assert node.emcy.clear(EmcyCode.CONTINUOUS_OVER_CURRENT)
    assert not node.emcy.error_active(0x2310) and node.emcy.error_active(0x7300)
    assert bench.frames() == [(0x082, struct.pack("<HB5x", 0, 0x81))]  # remaining register
    assert not node.emcy.clear(EmcyCode.CONTINUOUS_OVER_CURRENT)
    assert node.emcy.reset()
    assert bench.frames() == [(0x082, bytes(8))]
    assert node.emcy.error_register == 0 and node.read(0x1001) == 0
    with pytest.raises(ValueError):
        node.emcy.raise_error(0x1000, manufacturer=bytes(6))
    with pytest.raises(ValueError):
        node.emcy.raise_error(0x0000)


def test_error_history_0x1003(bench):
    node = booted(bench)
    for code in (0x1000, 0x2310, 0x6100, 0x7300, 0x8250):
        node.emcy.raise_error(code)
    bench.frames()
    assert node.emcy.history == (0x8250, 0x7300, 0x6100, 0x2310)  # newest first, 4 kept
    assert sdo_upload(bench, node, 0x1003, 0) == b"\x04"
    assert sdo_upload(bench, node, 0x1003, 1) == struct.pack("<I", 0x8250)
    assert sdo_upload(bench, node, 0x1003, 5) == ("abort", 0x06090011)
    assert sdo_download(bench, node, 0x1003, 0, b"\x02") == 0x06090030  # only 0 allowed
    assert sdo_download(bench, node, 0x1003, 1, bytes(4)) == 0x06010002
    assert node.emcy.history == (0x8250, 0x7300, 0x6100, 0x2310)
    assert sdo_download(bench, node, 0x1003, 0, b"\x00") is None
    assert node.emcy.history == ()


def test_errors_survive_a_communication_reset_but_not_a_node_reset(bench):
    node = booted(bench)
    node.emcy.raise_error(EmcyCode.SENSOR)
    register = node.emcy.error_register
    node.reset("communication")
    assert node.read(0x1001) == register and node.emcy.history == (0x7300,)
    assert node.emcy.active_errors == (0x7300,)
    node.reset("node")
    assert node.read(0x1001) == 0 and node.emcy.history == () and node.emcy.active_errors == ()


def test_emcy_cob_id_0x1014_invalid_bit_suppresses_the_frame(bench):
    od = services_od()
    od.add_object(_var("COB-ID EMCY", 0x1014, 0, dt.UNSIGNED32, "rw", 0x80000082))
    node = booted(bench, od=od)
    assert not node.emcy.raise_error(0x1000)
    assert bench.frames() == []
    node.write(0x1014, 0, 0x00000085)
    assert node.emcy.raise_error(0x2310)
    assert [cob for cob, _ in bench.frames()] == [0x085]


def test_emcy_consumer_decodes_other_nodes(bench):
    node = booted(bench)
    events = []
    node.on_emcy(lambda *args: events.append(args))
    bench.clock.now = 0.25
    bench.send(0x081, struct.pack("<HB5s", 0x8250, 0x11, b"\x07"))
    bench.send(0x081, b"\x30\x81")  # short EMCY: malformed
    assert pump(node, now=0.25) == [True, True]
    assert events == [(1, 0x8250, 0x11, b"\x07\x00\x00\x00\x00")]
    (event,) = node.emcy_log
    assert (event.node_id, event.code, event.time, event.text) == (1, 0x8250, 0.25, "RPDO timeout")
    assert node.counters.malformed_frames == 1


# =================================================================== SDO server


def test_sdo_expedited_read_and_write_on_the_project_eds(bench):
    drive = booted(bench, od=eds_path("drive"))
    assert sdo_upload(bench, drive, 0x1000, 0) == struct.pack("<I", 0x00020192)
    assert sdo_upload(bench, drive, 0x1018, 2) == struct.pack("<I", 2)
    assert sdo_download(bench, drive, 0x6040, 0, struct.pack("<H", 0x000F)) is None
    assert drive.read(0x6040) == 0x000F
    assert sdo_upload(bench, drive, 0x6040, 0) == b"\x0f\x00"
    assert sdo_download(bench, drive, 0x2200, 0, struct.pack("<h", -2048)) is None
    assert drive.read(0x2200) == -2048


def test_sdo_segmented_download_and_upload_by_hand(bench):
    node = booted(bench)
    value = 0x0123456789ABCDEF
    payload = struct.pack("<Q", value)
    bench.send(0x602, struct.pack("<BHBI", 0x21, 0x2303, 0, 8))  # initiate, size 8
    pump(node)
    assert bench.frames() == [(0x582, struct.pack("<BHB4x", 0x60, 0x2303, 0))]
    bench.send(0x602, b"\x00" + payload[:7])  # toggle 0, 7 bytes
    pump(node)
    assert bench.frames() == [(0x582, b"\x20" + bytes(7))]
    bench.send(0x602, bytes((0x10 | (6 << 1) | 1,)) + payload[7:] + bytes(6))  # last
    pump(node)
    assert bench.frames() == [(0x582, b"\x30" + bytes(7))]
    assert node.read(0x2303) == value

    bench.send(0x602, struct.pack("<BHB4x", 0x40, 0x2303, 0))
    pump(node)
    assert bench.frames() == [(0x582, struct.pack("<BHBI", 0x41, 0x2303, 0, 8))]
    bench.send(0x602, b"\x60" + bytes(7))
    pump(node)
    assert bench.frames() == [(0x582, b"\x00" + payload[:7])]
    bench.send(0x602, b"\x70" + bytes(7))
    pump(node)
    assert bench.frames() == [(0x582, bytes((0x10 | (6 << 1) | 1,)) + payload[7:] + bytes(6))]


def test_sdo_segments_outside_a_transfer_are_aborted_not_crashing(bench):
    node = booted(bench)
    bench.send(0x602, bytes(8))  # download segment, no transfer: canopen alone raises here
    bench.send(0x602, b"\x60" + bytes(7))  # upload segment, no transfer
    assert pump(node) == [True, True]
    codes = [struct.unpack_from("<BHBI", data) for _, data in bench.frames()]
    assert [(c[0], c[3]) for c in codes] == [(0x80, 0x05040001)] * 2
    assert node.counters.sdo_protocol_errors == 2
    # After a complete segmented download, a stray last segment must not write again.
    bench.send(0x602, struct.pack("<BHBI", 0x21, 0x2303, 0, 8))
    bench.send(0x602, b"\x00" + bytes(range(1, 8)))
    bench.send(0x602, b"\x1d\x08" + bytes(6))
    pump(node)
    assert [data[0] for _, data in bench.frames()] == [0x60, 0x20, 0x30]
    value = node.read(0x2303)
    assert value == int.from_bytes(bytes(range(1, 9)), "little")
    bench.send(0x602, b"\x01" + bytes(7))  # toggle 0, last, 7 zero bytes
    pump(node)
    ((_, data),) = bench.frames()
    assert struct.unpack_from("<BHBI", data)[::3] == (0x80, 0x05040001)
    assert node.read(0x2303) == value


UPLOAD_2303 = struct.pack("<BHB4x", 0x40, 0x2303, 0)  # 8 bytes: segmented
UPLOAD_SEGMENT, UPLOAD_SEGMENT_T1 = b"\x60" + bytes(7), b"\x70" + bytes(7)
DOWNLOAD_SEGMENT = b"\x00" + bytes(7)
OPEN_DOWNLOAD = struct.pack("<BHBI", 0x21, 0x2303, 0, 8)


@pytest.mark.parametrize(
    ("before", "stray"),
    [
        # an upload segment when no segmented upload is open (CiA 301 §7.2.4.3.4)
        ([UPLOAD_2303, UPLOAD_SEGMENT, UPLOAD_SEGMENT_T1], UPLOAD_SEGMENT),  # upload done
        ([struct.pack("<BHB4x", 0x40, 0x1000, 0)], UPLOAD_SEGMENT),  # after an expedited one
        ([OPEN_DOWNLOAD], UPLOAD_SEGMENT),  # during a segmented download
        ([OPEN_DOWNLOAD, b"\x00" + bytes(7), b"\x1d" + bytes(7)], UPLOAD_SEGMENT_T1),
        ([UPLOAD_2303, UPLOAD_SEGMENT_T1], UPLOAD_SEGMENT),  # after a toggle abort
        # a download segment when no segmented download is open
        ([UPLOAD_2303], DOWNLOAD_SEGMENT),  # during a segmented upload
        ([struct.pack("<BHBI", 0x2B, 0x2301, 0, 5)], DOWNLOAD_SEGMENT),  # after expedited
    ],
    ids=[
        "upload-finished",
        "upload-expedited",
        "download-open",
        "download-finished",
        "upload-aborted",
        "download-segment-in-upload",
        "download-expedited",
    ],
)
def test_sdo_segment_of_no_open_transfer_is_aborted_with_0x05040001(bench, before, stray):
    node = booted(bench)
    for request in before:
        bench.send(0x602, request)
    pump(node)
    bench.frames()
    bench.send(0x602, stray)
    pump(node)
    ((cob, data),) = bench.frames()
    assert cob == 0x582
    assert (data[0], struct.unpack_from("<I", data, 4)[0]) == (0x80, 0x05040001)
    assert node.counters.sdo_protocol_errors == 1
    # The abort ended any transfer: the next segment of either kind is aborted too, and a
    # new upload works from its start.
    bench.send(0x602, UPLOAD_SEGMENT)
    bench.send(0x602, DOWNLOAD_SEGMENT)
    pump(node)
    assert [struct.unpack_from("<I", d, 4)[0] for _, d in bench.frames()] == [0x05040001] * 2
    assert sdo_upload(bench, node, 0x1000, 0) == struct.pack("<I", 0x00020192)


@pytest.mark.parametrize(
    ("index", "sub", "data", "code"),
    [
        (0x2301, 0, struct.pack("<i", 7), 0x06070012),  # INTEGER16 written with 4 bytes
        (0x2301, 0, b"\x07", 0x06070013),  # ... with 1 byte
        (0x6041, 0, b"\x27\x00", 0x06010002),  # statusword is read-only
        (0x1000, 0, bytes(4), 0x06010002),
        (0x2301, 0, struct.pack("<h", 101), 0x06090031),  # HighLimit 100
        (0x2301, 0, struct.pack("<h", -101), 0x06090032),  # LowLimit -100
        (0x2300, 0, struct.pack("<f", 2e6), 0x06090031),  # REAL32 limits
        (0x2300, 0, struct.pack("<f", -1.0), 0x06090032),
        (0x2300, 0, struct.pack("<f", math.nan), 0x06090030),
        (0x1019, 0, b"\xf1", 0x06090031),
        (0x1019, 0, b"\x01", 0x06090030),  # reserved value
        (0x1019, 0, b"\x10", 0x08000022),  # only while 0x1006 == 0
        (0x3000, 0, b"\x01", 0x06020000),  # unknown object
        (0x1A00, 9, bytes(4), 0x06090011),  # unknown sub of a record
        (0x1016, 3, bytes(4), 0x06090011),  # undefined sub of an array
        (0x1A00, 1, struct.pack("<I", 0x10010008), 0x06040041),  # 0x1001 not mappable
        (0x1A00, 1, struct.pack("<I", 0x23010010), 0x06040041),  # PDOMapping=0 parameter
        (0x1A00, 1, struct.pack("<I", 0x30000010), 0x06020000),  # mapping a missing object
        (0x1A00, 1, struct.pack("<I", 0x20100010), 0x06040043),  # wrong bit length
        (0x1A00, 0, b"\x05", 0x06040042),  # more entries than the record has
    ],
)
def test_sdo_write_aborts_leave_the_parameter_unchanged(bench, index, sub, data, code):
    node = booted(bench)
    if index == 0x1A00 and 1 <= sub <= 8:  # CiA 301: entries change only while sub 0 is 0
        assert sdo_download(bench, node, 0x1A00, 0, b"\x00") is None
    before = node.node.get_data(index, sub) if code not in (0x06020000, 0x06090011) else None
    assert sdo_download(bench, node, index, sub, data) == code
    assert code in ABORT_TEXT
    if before is not None:
        assert node.node.get_data(index, sub) == before


def test_sdo_generic_length_code_option(bench):
    node = booted(bench, length_aborts="generic")
    assert sdo_download(bench, node, 0x2301, 0, struct.pack("<i", 7)) == 0x06070010
    assert sdo_download(bench, node, 0x2301, 0, b"\x07") == 0x06070010


def test_sdo_read_aborts(bench):
    node = booted(bench)
    assert sdo_upload(bench, node, 0x2302, 0) == ("abort", 0x06010001)  # write-only
    assert sdo_upload(bench, node, 0x3000, 0) == ("abort", 0x06020000)
    assert sdo_upload(bench, node, 0x1A00, 7) == ("abort", 0x06090011)
    assert sdo_download(bench, node, 0x2302, 0, struct.pack("<I", 9)) is None  # but writable


def test_pdo_mapping_accepts_valid_entries(bench):
    node = booted(bench, od=eds_path("drive"))
    # Project EDS: 0x2010 cycle is mappable (8 bit), 0x1001 error register is not.
    # CiA 301 procedure: PDO not valid (COB-ID bit 31), sub 0 to 0, entries, sub 0 to n.
    assert sdo_download(bench, node, 0x1800, 1, struct.pack("<I", 0x80000182)) is None
    assert sdo_download(bench, node, 0x1A00, 0, b"\x00") is None
    assert sdo_download(bench, node, 0x1A00, 1, struct.pack("<I", 0x20100008)) is None
    assert sdo_download(bench, node, 0x1A00, 1, struct.pack("<I", 0x10010008)) == 0x06040041
    assert node.read(0x1A00, 1) == 0x20100008
    assert sdo_download(bench, node, 0x1A00, 2, struct.pack("<I", 0x00050008)) is None  # dummy
    assert sdo_download(bench, node, 0x1A00, 0, b"\x02") is None
    # 0x1A00 sub 3/4 still map 16-bit objects: 8 + 8 + 16 + 16 = 48 bits fits.
    assert sdo_download(bench, node, 0x1A00, 0, b"\x04") is None


def test_float_limits_are_read_from_the_eds(tmp_path, bench):
    eds = (eds_path("controller").read_text()).replace(
        "[ManufacturerObjects]\nSupportedObjects=6",
        "[ManufacturerObjects]\nSupportedObjects=7\n7=0x2300",
    )
    eds += (
        "\n[2300]\nParameterName=filter Q\nObjectType=0x7\nDataType=0x0008\nAccessType=rw\n"
        "LowLimit=0.5\nHighLimit=2000.0\nDefaultValue=1000.0\nPDOMapping=0\n"
    )
    path = tmp_path / "controller-q.eds"
    path.write_text(eds)
    od = load_od(path, 1)
    assert (od[0x2300].min, od[0x2300].max) == (0.5, 2000.0)
    assert canopen.import_od(str(path), 1)[0x2300].min is None  # what canopen alone gives
    node = booted(bench, 1, od=path)
    assert sdo_download(bench, node, 0x2300, 0, struct.pack("<f", 0.25)) == 0x06090032
    assert sdo_download(bench, node, 0x2300, 0, struct.pack("<f", 1500.0)) is None
    assert node.read(0x2300) == 1500.0


def test_validators_and_change_callbacks(bench):
    node = booted(bench)
    applied = []
    node.add_validator(0x2300, 0, lambda q: 0x08000022 if q == 13.0 else None)
    node.on_write(0x2300, 0, applied.append)
    assert sdo_download(bench, node, 0x2300, 0, struct.pack("<f", 13.0)) == 0x08000022
    assert applied == [] and node.read(0x2300) == 1000.0
    assert sdo_download(bench, node, 0x2300, 0, struct.pack("<f", 250.0)) is None
    assert applied == [250.0] and node.read(0x2300) == 250.0

    def refuse(value):
        raise canopen.SdoAbortedError(0x08000021)

    node.on_write(0x2301, 0, refuse)
    assert sdo_download(bench, node, 0x2301, 0, struct.pack("<h", 9)) == 0x08000021
    assert node.read(0x2301) == 5  # restored (the EDS default)
    node.node.data_store[0x2301] = {0: struct.pack("<h", -7)}
    assert sdo_download(bench, node, 0x2301, 0, struct.pack("<h", 9)) == 0x08000021
    assert node.read(0x2301) == -7  # restored (the previously stored value)
    with pytest.raises(canopen.SdoAbortedError):
        node.write(0x2301, 0, 9)
    with pytest.raises(KeyError):
        node.on_write(0x3000, 0, print)


def test_local_writes_are_checked_but_may_write_read_only_objects(bench):
    node = booted(bench)
    node.write(0x6041, 0, 0x0237)  # the application updates its statusword
    assert sdo_upload(bench, node, 0x6041, 0) == b"\x37\x02"
    with pytest.raises(canopen.SdoAbortedError) as err:
        node.write(0x2301, 0, 500)
    assert err.value.code == 0x06090031


def test_sdo_requests_are_ignored_before_boot_and_malformed_ones_counted(bench):
    node = bench.services(2, services_od())
    bench.send(0x602, struct.pack("<BHB4x", 0x40, 0x1000, 0))
    pump(node)
    assert bench.frames() == []
    node.boot(0.0)
    bench.frames()
    bench.send(0x602, b"\x40\x00\x10")
    pump(node)
    assert bench.frames() == [] and node.counters.malformed_frames == 1


# =================================================================== SDO client


class PumpedNetwork(canopen.Network):
    """A client network without threads: each send lets the server answer at once."""

    def __init__(self, bus: can.BusABC, server: CanopenServices) -> None:
        super().__init__(bus)
        self.server = server

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        super().send_message(can_id, data, remote)
        pump(self.server)
        while (msg := self.bus.recv(0)) is not None:
            self.notify(msg.arbitration_id, msg.data, msg.timestamp)


@pytest.fixture
def client(bench):
    server = booted(bench)
    network = PumpedNetwork(bench.bus(), server)
    return network, server, services_od()


def test_client_expedited_and_segmented(client):
    network, server, od = client
    assert sdo_read(network, 2, 0x1000, od=od) == 0x00020192
    sdo_write(network, 2, 0x2301, 0, -42, od=od)
    assert server.read(0x2301) == -42
    sdo_write(network, 2, 0x2303, 0, 2**63 + 5)  # 8 bytes: segmented, OD already attached
    assert server.read(0x2303) == 2**63 + 5
    assert sdo_read(network, 2, 0x2303) == 2**63 + 5
    sdo_write(network, 2, 0x2304, 0, "harmonic drive joint 1")
    assert sdo_read(network, 2, 0x2304) == "harmonic drive joint 1"
    sdo_write(network, 2, 0x2301, 0, struct.pack("<h", 3), force_segment=True)
    assert sdo_read(network, 2, 0x2301, raw=True) == b"\x03\x00"


def test_client_reports_abort_codes_with_their_text(client):
    network, _, od = client
    with pytest.raises(SdoError) as err:
        sdo_write(network, 2, 0x2301, 0, 101, od=od)
    assert err.value.code == 0x06090031
    assert "0x06090031 (value of parameter written too high" in str(err.value)
    assert "0x2301:00 on node 2" in str(err.value)
    with pytest.raises(SdoError) as err:
        sdo_read(network, 2, 0x2302)
    assert err.value.code == 0x06010001
    with pytest.raises(TypeError):
        sdo_write(network, 2, 0x2999, 0, 5)


def test_client_timeout_is_abort_0x05040000(client):
    network, server, od = client
    server.enter_state(NmtState.STOPPED)  # the server stays silent
    with pytest.raises(SdoError) as err:
        sdo_read(network, 2, 0x1000, od=od, timeout=0.0)
    assert err.value.code == 0x05040000
    assert err.value.text == abort_text(0x05040000) == "SDO protocol timed out"
    assert abort_text(0x08000000) == "general error"


# ============================================================================ SYNC


def test_sync_producer_counter_wraps(bench):
    producer = SyncProducer(bench.bus(), overflow=3)
    assert [producer.send() for _ in range(7)] == [1, 2, 3, 1, 2, 3, 1]
    assert [data for _, data in bench.frames()] == [bytes((c,)) for c in (1, 2, 3, 1, 2, 3, 1)]
    producer.reset()
    assert producer.send() == 1
    plain = SyncProducer(bench.bus(), overflow=0)
    assert plain.send() is None
    frames = bench.frames()
    assert frames[-1] == (0x080, b"")
    for bad in (1, 241, -1):
        with pytest.raises(ValueError):
            SyncProducer(bench.bus(), overflow=bad)


def test_sync_producer_from_the_od_follows_nmt_and_0x1019(bench):
    node = booted(bench, 1, od=eds_path("controller"))
    producer = node.make_sync_producer()
    assert (producer.cob_id, producer.overflow) == (0x080, 240)
    assert node.sync_period_s == pytest.approx(1e-3)
    for _ in range(241):
        assert node.send_sync()
    assert producer.counter == 1  # 1..240, then 1
    bench.frames()
    node.enter_state(NmtState.STOPPED)
    assert not node.send_sync() and bench.frames() == []
    node.enter_state(NmtState.OPERATIONAL)  # leaving STOPPED restarts the counter
    node.send_sync()
    assert bench.frames() == [(0x080, b"\x01")]
    assert sdo_download(bench, node, 0x1019, 0, b"\x04") == 0x08000022  # 0x1006 = 1000 us
    assert sdo_download(bench, node, 0x1006, 0, bytes(4)) is None
    assert sdo_download(bench, node, 0x1019, 0, b"\x04") is None
    assert producer.overflow == 4
    assert [producer.send() for _ in range(5)] == [1, 2, 3, 4, 1]


def sync_times(n: int, period: float = 0.001) -> list[float]:
    return [k * period for k in range(1, n + 1)]


def test_sync_monitor_counts_missed_syncs_from_the_counter():
    monitor = SyncMonitor(overflow=4)
    counters = [1, 2, 4, 1, 3]  # 3 and 2 missing
    missed = [monitor.on_sync(c, t) for c, t in zip(counters, sync_times(5), strict=True)]
    assert missed == [0, 0, 1, 0, 1]
    assert monitor.missed_syncs == 2 and monitor.syncs == 5


def test_sync_monitor_uses_timing_without_a_counter_and_for_whole_wraps():
    plain = SyncMonitor(period_s=0.001)
    assert [plain.on_sync(None, t) for t in (0.001, 0.002, 0.005, 0.006)] == [0, 0, 2, 0]
    counted = SyncMonitor(period_s=0.001, overflow=4)
    counted.on_sync(1, 0.001)
    # 5 SYNCs lost: the counter alone sees 3 -> 3 ("none missing"), timing sees the wrap.
    assert counted.on_sync(3, 0.008) == 5 - 0
    assert counted.missed_syncs == 5


def test_sync_monitor_length_errors():
    monitor = SyncMonitor(period_s=0.001, overflow=240)
    monitor.on_sync(1, 0.001)
    monitor.on_sync_frame(can.Message(arbitration_id=0x80, data=b""), 0.002)
    monitor.on_sync_frame(can.Message(arbitration_id=0x80, data=b"\x03\x00"), 0.003)
    assert monitor.on_sync(241, 0.004) == 0
    assert monitor.length_errors == 3 and monitor.missed_syncs == 0


def test_sync_monitor_late_and_missing_commands():
    monitor = SyncMonitor(period_s=0.001, overflow=240, command_deadline_s=0.0008)
    monitor.on_sync(1, 0.001)
    assert monitor.on_command(0.0013)  # before any command: nothing is missing yet
    monitor.on_sync(2, 0.002)
    assert not monitor.on_command(0.00285)  # 0.85 ms after its SYNC: late
    monitor.on_sync(3, 0.003)
    monitor.on_sync(4, 0.004)  # cycle 3 had no command
    assert (monitor.late_commands, monitor.missing_commands) == (1, 1)
    assert monitor.next_sync_due == pytest.approx(0.005)
    default = SyncMonitor(period_s=0.001)
    default.on_sync(None, 0.0)
    assert default.on_command(0.001) and not default.on_command(0.0011)
    with pytest.raises(ValueError):
        SyncMonitor(overflow=1)


@settings(max_examples=100, deadline=None)
@given(
    st.integers(2, 240),
    st.lists(st.booleans(), min_size=1, max_size=600),
    st.booleans(),
)
def test_sync_monitor_finds_exactly_the_dropped_syncs(overflow, drops, with_period):
    producer_counter = 0
    monitor = SyncMonitor(period_s=0.001 if with_period else None, overflow=overflow)
    expected = 0
    pending = 0
    received = 0
    for k, dropped in enumerate([False, *drops], start=1):
        producer_counter = producer_counter % overflow + 1
        if dropped:
            pending += 1
            continue
        monitor.on_sync(producer_counter, k * 0.001)
        if received:
            expected += pending if with_period else pending % overflow
        pending = 0
        received += 1
    assert monitor.missed_syncs == expected


# ===================================================================== together


def test_controller_and_drive_boot_start_and_monitor_each_other(bench):
    """Both nodes on one simbus channel, driven tick by tick like the lockstep runner."""
    controller = bench.services(
        1, eds_path("controller"), heartbeat_producer_ms=100, heartbeat_consumers={2: 250}
    )
    drive = bench.services(
        2, eds_path("drive"), heartbeat_producer_ms=100, heartbeat_consumers={1: 250}
    )
    lost = []
    controller.on_heartbeat_lost(lambda n: lost.append(("controller saw", n)))
    drive.on_heartbeat_lost(lambda n: lost.append(("drive saw", n)))
    drive.boot(0.0)
    controller.boot(0.0)
    controller.nmt.expect_boot(2, 0.0, 1.0)
    controller.enter_state(NmtState.OPERATIONAL)
    started = False
    for k in range(1, 1001):
        now = k * 0.001
        bench.clock.now = now
        for node in (controller, drive):
            node.tick(now)
            pump(node)
        if not started and controller.nmt.check_boot(now):
            controller.nmt.command(NmtCommand.START, 0)
            started = True
    assert drive.state is NmtState.OPERATIONAL
    assert controller.nmt.remote_states.get(2) is NmtState.OPERATIONAL
    assert drive.nmt.remote_states.get(1) is NmtState.OPERATIONAL
    assert lost == []
    assert (
        drive.heartbeat_consumer.monitored[1].status
        == controller.heartbeat_consumer.monitored[2].status
        == "active"
    )
    # The drive goes silent: the controller notices within 250 ms + one tick.
    silent_from = 1.0
    for k in range(1001, 1400):
        now = k * 0.001
        bench.clock.now = now
        controller.tick(now)
        pump(controller)
        drive.bus.recv(0)
    assert lost == [("controller saw", 2)]
    last_heartbeat = controller.heartbeat_consumer.monitored[2].last_heartbeat
    # The drive's last heartbeat (sent at 1.0 s) is handled at the controller's next tick.
    assert last_heartbeat == pytest.approx(silent_from + 0.001)
    assert (
        0.25 < controller.heartbeat_consumer.monitored[2].lost_at - last_heartbeat <= 0.251 + 1e-9
    )


@settings(max_examples=60, deadline=None)
@given(
    events=st.lists(
        st.tuples(st.sampled_from(["tick", "hb", "boot", "configure"]), st.sampled_from([3, 4])),
        max_size=40,
    ),
    steps=st.lists(st.integers(1, 40), min_size=40, max_size=40),
)
def test_heartbeat_consumer_finds_the_same_losses_as_a_full_scan(events, steps):
    """``expired`` skips its scan until ``next_expiry``: it must report exactly the losses a
    scan at every call would, however heartbeats, boot-ups and reconfigurations interleave."""
    from hdhil.canopen.heartbeat import HeartbeatConsumer
    from hdhil.canopen.nmt import NmtMaster

    with can.Bus(interface="virtual", channel="hb-scan") as bus:
        consumer = HeartbeatConsumer(NmtMaster(bus))
        _run_heartbeat_events(consumer, events, steps)


def _run_heartbeat_events(consumer, events, steps):
    consumer.configure({3: 20, 4: 35})
    now = 0.0
    for (kind, node_id), step in zip(events, steps, strict=False):
        now += step * 1e-3
        if kind == "hb":
            consumer.on_frame(node_id, NmtState.OPERATIONAL, now, True)
        elif kind == "boot":
            consumer.on_frame(node_id, NmtState.INITIALISING, now, True)
        elif kind == "configure":
            consumer.configure({3: 20, 4: 35 if node_id == 3 else 50})
        due = sorted(
            m.node_id
            for m in consumer.monitored.values()
            if m.status == "active" and now > m.deadline + 1e-9
        )
        assert sorted(m.node_id for m in consumer.expired(now)) == due
