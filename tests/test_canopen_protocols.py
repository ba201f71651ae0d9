"""The per-protocol modules of hdhil.canopen on their own: the non-blocking SDO client
against a server node, the NMT frame helpers, the EMCY layout (canopen's struct) and the
controller's CiA 402 walk decisions."""

from __future__ import annotations

import can
import canopen
import pytest

from hdhil.canopen.cia402 import CONTROLWORD, Command, DriveStateMachine, State
from hdhil.canopen.emcy import EMCY_STRUCT, decode_emcy
from hdhil.canopen.nmt import COMMAND_NAMES, NmtCommand, nmt_frame
from hdhil.canopen.sdo import SdoClient
from hdhil.canopen.services import CanopenServices
from hdhil.dbc import eds_path
from hdhil.firmware.walk import Cia402Walk


@pytest.fixture
def link(bus_harness):
    """A drive's CANopen services on the shared bus harness; its host is the client."""
    harness = bus_harness("t-protocols")
    server = CanopenServices(harness.bus(), 2, eds_path("drive"))
    server.boot(0.0)
    return server, harness.host


def _exchange(server: CanopenServices, client: SdoClient, client_bus: can.BusABC):
    """Serve the pending request, then feed the client every answer; the results."""
    while (msg := server.bus.recv(0)) is not None:
        server.handle(msg)
    results = []
    while (msg := client_bus.recv(0)) is not None:
        if msg.arbitration_id == client.response_id:
            result = client.on_response(msg)
            if result is not None:
                results.append(result)
    return results


def test_sdo_client_uploads_and_downloads_without_blocking(link):
    server, bus = link
    client = SdoClient(bus, 2)
    statusword = server.od["statusword"].index
    client.upload(statusword)
    assert client.pending == (statusword, 0, True)  # returned at once, answer pending
    (result,) = _exchange(server, client, bus)
    assert result.ok and int.from_bytes(result.data, "little") == server.read(statusword)
    assert len(result.data) == 2  # size from the expedited response's n bits
    assert client.pending is None

    option = server.od["quick_stop_option_code"].index
    client.download(option, 0, (5).to_bytes(2, "little", signed=True))
    (result,) = _exchange(server, client, bus)
    assert result.ok and server.read(option) == 5


def test_sdo_client_reports_the_servers_abort_code(link):
    server, bus = link
    client = SdoClient(bus, 2)
    client.upload(0x5FFF, 0)
    (result,) = _exchange(server, client, bus)
    assert result.abort == 0x06020000 and not result.ok
    client.download(server.od["statusword"].index, 0, b"\x00\x00")
    (result,) = _exchange(server, client, bus)
    assert result.abort == 0x06010002  # read-only
    assert client.aborts == 2


def test_sdo_client_ignores_answers_to_other_transfers(link):
    _, bus = link
    client = SdoClient(bus, 2)
    msg = can.Message(arbitration_id=client.response_id, is_extended_id=False,
                      data=bytes((0x4B, 0x41, 0x60, 0, 1, 0, 0, 0)))  # fmt: skip
    assert client.on_response(msg) is None  # nothing pending
    client.upload(0x6040)
    assert client.on_response(msg) is None  # answers 0x6041, not 0x6040
    assert client.pending == (0x6040, 0, True)


def test_nmt_frames_use_canopens_command_codes():
    from canopen.nmt import NMT_COMMANDS

    assert nmt_frame(NmtCommand.START, 2).data == bytes((NMT_COMMANDS["OPERATIONAL"], 2))
    assert {name: int(cs) for name, cs in COMMAND_NAMES.items()} == {
        "start": 0x01, "stop": 0x02, "pre-op": 0x80, "reset": 0x81, "reset-comm": 0x82,
    }  # fmt: skip
    with pytest.raises(ValueError):
        nmt_frame(0x42, 2)
    with pytest.raises(ValueError, match=r"0\.\.127"):
        nmt_frame(NmtCommand.START, 128)


def test_emcy_frames_decode_with_canopens_consumer_layout():
    payload = EMCY_STRUCT.pack(0x8130, 0x11, b"\x02\x00\x00\x00\x00")
    assert decode_emcy(payload) == (0x8130, 0x11, b"\x02\x00\x00\x00\x00")
    error = canopen.emcy.EmcyError(0x8130, 0x11, b"\x02", 0.0)
    assert error.code == decode_emcy(payload)[0]


def test_walk_follows_a_drive_state_machine_to_operation_enabled():
    """The walk's controlwords, fed to the CiA 402 state machine the drive runs, reach
    OPERATION ENABLED in three steps (transitions 2, 3, 4)."""
    sent: list[int] = []
    walk = Cia402Walk(2, sent.append)
    drive = DriveStateMachine()
    drive.complete_initialisation()
    steps = []
    for _ in range(5):
        walk.on_statusword(drive.statusword)
        step = walk.up()
        steps.append(step.action)
        if step.action == "operational":
            break
        drive.apply_controlword(walk.controlword)
    assert steps == ["walk", "walk", "walk", "operational"]
    assert sent == [CONTROLWORD[c] for c in (Command.SWITCH_ON, Command.ENABLE_OPERATION)]
    assert drive.state is State.OPERATION_ENABLED


def test_walk_resets_a_fault_once_then_gives_up():
    walk = Cia402Walk(2, lambda cw: None)
    drive = DriveStateMachine()
    drive.complete_initialisation()
    drive.fault(0x8250)
    drive.step(1.0)  # fault reaction completes
    walk.on_statusword(drive.statusword)
    assert walk.drive_state is State.FAULT
    assert walk.up().action == "walk" and walk.controlword == CONTROLWORD[Command.FAULT_RESET]
    walk.cw_sends += 1  # the reset went out, the drive stays in FAULT: refused
    step = walk.up()
    assert step.action == "safe" and "refused the fault reset" in step.reason
    assert walk.fault_resets == 1
    walk.on_statusword(drive.statusword)
    walk.set_controlword(CONTROLWORD[Command.SHUTDOWN])
    assert walk.up().action == "safe"  # a second fault: no second reset


# ------------------------------------------------------------------ SYNC counter


def _sync(counter: int) -> can.Message:
    return can.Message(arbitration_id=0x080, is_extended_id=False, data=bytes((counter,)))


def test_sync_monitor_tells_duplicates_reordering_loss_and_restarts_apart():
    from hdhil.canopen.sync import SyncMonitor

    m = SyncMonitor(overflow=240)
    assert [m.accept(_sync(c), 0.0) for c in (1, 2, 3)] == [0, 0, 0]
    assert m.accept(_sync(3), 0.0) is None and m.duplicates == 1
    assert m.accept(_sync(5), 0.0) == 1  # 4 lost
    assert m.accept(_sync(4), 0.0) is None and m.stale == 1  # 4 was only late
    assert m.accept(_sync(6), 0.0) == 0
    assert m.accept(_sync(1), 0.0) is None  # 5 behind: a late SYNC 1, not a restart
    assert m.accept(_sync(20), 0.0) == 13
    assert m.accept(_sync(1), 0.0) == 0 and m.restarts == 1  # producer restarted
    assert m.accept(_sync(2), 0.0) == 0
    assert m.accept(_sync(100), 0.0) == 97  # a long loss is still a loss
    m = SyncMonitor(overflow=240)
    for c in (239, 240, 1, 2):  # the counter wraps: no restart, no loss
        assert m.accept(_sync(c), 0.0) == 0
    assert m.restarts == 0 and m.missed_syncs == 0
    # SYNC 240 lost at the wrap: 1 after 239 is one SYNC missed, not a restart (the
    # drive's plant must advance two periods); likewise 239, 240 and 1 lost before 2.
    assert [m.accept(_sync(c), 0.0) for c in range(3, 240)] == [0] * 237
    assert m.accept(_sync(1), 0.0) == 1 and m.restarts == 0
    assert [m.accept(_sync(c), 0.0) for c in range(2, 239)] == [0] * 237
    assert m.accept(_sync(2), 0.0) == 3 and m.restarts == 0 and m.missed_syncs == 4
