"""Sessions that follow each other (:mod:`hdhil.rig.session`): ``hdhil firmware`` twice
against one served drive, both clean, the drive counting two sessions; a drive left in
FAULT by a controller that vanished is reset by the next firmware, which says so."""

from __future__ import annotations

import json
import threading
import time

import can
import pytest

import hdhil.rig.standalone as standalone
from hdhil.cli import main
from hdhil.core.faultbase import FaultLog
from hdhil.rig.faults import FaultConfig, FaultInjector
from hdhil.rig.request import resolve
from hdhil.rig.standalone import StandaloneDrive

pytestmark = [pytest.mark.slow, pytest.mark.realtime]


def _served_drive(name: str) -> tuple[str, StandaloneDrive, threading.Event, threading.Thread]:
    channel = f"hdhil-sessions-{name}-{time.monotonic_ns()}"
    bus = can.Bus(interface="virtual", channel=channel)
    injector = FaultInjector(FaultConfig(), FaultLog(None, keep=False), stream="test")
    drive = StandaloneDrive(resolve("free-motion", duration_s=0.05), bus, None, injector)
    stop = threading.Event()
    served = threading.Thread(target=drive.serve, args=(stop.is_set,), daemon=True)
    served.start()
    return channel, drive, stop, served


#: A session long enough for the controller's heartbeats (every 100 ms of wall time) to
#: follow its boot-up, so the drive monitors them (CiA 301: from the first heartbeat):
#: 3000 lockstep cycles take 0.3 s even at 10 kHz (1 s was once done within 100 ms).
MONITORED_S = 3.0


def _firmware(channel: str, duration_s: float = 0.05) -> int:
    """One firmware session in network lockstep. Not real time: the drive here is a
    thread at normal priority, which a loaded machine can hold off the CPU for more than
    the controller's sensor hold (10 SYNCs, 10 ms at 1 kHz); real-time pacing against a
    separate emulator is test_multiprocess's. The heartbeats run on wall-clock timers in
    both (while a cycle waits, too)."""
    return main(["firmware", "--interface", "virtual", "--channel", channel, "--lockstep",
                 "--duration", str(duration_s)])  # fmt: skip


def _monitored(drive: StandaloneDrive) -> bool:
    """Whether the drive received a heartbeat of the controller after its boot-up."""
    return drive.node.services.counters.heartbeats_received >= 2


def _stop(drive: StandaloneDrive, stop: threading.Event, served: threading.Thread) -> dict:
    stop.set()
    served.join(5)
    summary = drive.summary()
    drive.bus.shutdown()
    return summary


def test_two_sessions_in_a_row_both_succeed_and_the_drive_counts_them(capsys):
    channel, drive, stop, served = _served_drive("two")
    try:
        assert _firmware(channel, MONITORED_S) == 0
        assert _monitored(drive)
        time.sleep(0.4)  # longer than the drive's 250 ms heartbeat consumer time
        assert _firmware(channel, 0.3) == 0
    finally:
        summary = _stop(drive, stop, served)
    out = [json.loads(line) for line in capsys.readouterr().out.strip().splitlines()]
    assert [s["ended_clean"] for s in out] == [True, True]
    assert all("recovery" not in s for s in out)
    assert summary["sessions"] == 2 and "verdict" not in summary
    assert [s["end"] for s in summary["session_log"]] == ["clean", "clean"]
    assert all(s["nmt_starts"] >= 1 and s["syncs"] > 0 for s in summary["session_log"])
    assert summary["drive_state"] != "FAULT"


def test_a_drive_left_in_fault_is_reset_by_the_next_firmware(capsys, monkeypatch):
    channel, drive, stop, served = _served_drive("fault")
    try:
        with monkeypatch.context() as m:  # a controller that vanishes without its clean end
            m.setattr(standalone, "end_session", lambda *args: False)
            assert _firmware(channel, MONITORED_S) == 0
        assert _monitored(drive)
        time.sleep(0.6)  # the drive loses the heartbeat: FAULT
        assert drive.node.drive_state.name == "FAULT", drive.node.diagnostics
        capsys.readouterr()
        assert _firmware(channel) == 0
    finally:
        summary = _stop(drive, stop, served)
    captured = capsys.readouterr()
    lines = [ln for ln in captured.err.splitlines() if ln.startswith("hdhil: firmware:")]
    assert len(lines) == 1 and "was in FAULT" in lines[0], captured.err
    printed = json.loads(captured.out.strip().splitlines()[-1])
    assert printed["ended_clean"] and "verdict" not in printed
    assert summary["session_log"][0]["end"] == "heartbeat lost"
    assert summary["session_log"][-1]["end"] == "clean"


class _SlowConsumerRequests:
    """A python-can bus on which the drive sees the SDO requests about 0x1016 (its
    heartbeat consumer) ``delay_s`` late: a drive busy elsewhere when the firmware ends
    its session (everything else as the wrapped bus)."""

    def __init__(self, bus: can.BusABC, delay_s: float) -> None:
        self._bus = bus
        self.delay_s = delay_s
        self.delayed = 0
        self._held: list[tuple[float, can.Message]] = []

    def __getattr__(self, name: str):
        return getattr(self._bus, name)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        if self._held and self._held[0][0] <= time.monotonic():
            return self._held.pop(0)[1]
        msg = self._bus.recv(timeout)
        if msg is not None and msg.arbitration_id == 0x602 and bytes(msg.data[1:3]) == b"\x16\x10":
            self.delayed += 1
            self._held.append((time.monotonic() + self.delay_s, msg))
            return None
        return msg


def test_the_heartbeat_goes_on_while_a_slow_drive_answers_the_session_end(capsys):
    """The session end's transfers wait for the drive's answers with the controller's
    heartbeat going on: a drive that takes each of them up 150 ms late (the read and
    the clearing of the entry: 300 ms, more than its 250 ms consumer time, were the
    heartbeat stopped) stays healthy and records a clean end."""
    channel = f"hdhil-sessions-slow-{time.monotonic_ns()}"
    slow = _SlowConsumerRequests(can.Bus(interface="virtual", channel=channel), 0.15)
    injector = FaultInjector(FaultConfig(), FaultLog(None, keep=False), stream="test")
    drive = StandaloneDrive(resolve("free-motion", duration_s=0.05), slow, None, injector)
    stop = threading.Event()
    served = threading.Thread(target=drive.serve, args=(stop.is_set,), daemon=True)
    served.start()
    try:
        assert _firmware(channel, MONITORED_S) == 0
        assert _monitored(drive)
        time.sleep(0.4)  # longer than the drive's consumer time: a loss would show
    finally:
        summary = _stop(drive, stop, served)
    assert slow.delayed >= 2  # the read and the clearing of the entry were both late
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["ended_clean"]
    assert [s["end"] for s in summary["session_log"]] == ["clean"]
    assert summary["drive_state"] != "FAULT" and "verdict" not in summary
