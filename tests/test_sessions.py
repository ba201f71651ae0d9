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


def _firmware(channel: str, duration_s: float = 0.05, lockstep: bool = True) -> int:
    pacing = ["--lockstep"] if lockstep else []  # real time: heartbeats while it runs
    return main(["firmware", "--interface", "virtual", "--channel", channel, *pacing,
                 "--duration", str(duration_s)])  # fmt: skip


def _stop(drive: StandaloneDrive, stop: threading.Event, served: threading.Thread) -> dict:
    stop.set()
    served.join(5)
    summary = drive.summary()
    drive.bus.shutdown()
    return summary


def test_two_sessions_in_a_row_both_succeed_and_the_drive_counts_them(capsys):
    channel, drive, stop, served = _served_drive("two")
    try:
        assert _firmware(channel, 0.3, lockstep=False) == 0
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
            assert _firmware(channel, 0.3, lockstep=False) == 0
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
