"""The trace writer process: same file as python-can's writer, nothing lost, clear errors."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import can
import pytest
from conftest import FrameRecorder

from hdhil.can.simbus import SimClock
from hdhil.can.traces.tap import BusTap, FrameCounter
from hdhil.can.traces.writer import BATCH_FRAMES, WriterProcess, open_writer
from hdhil.core.errors import UserError


def _frames(n: int) -> list[can.Message]:
    return [
        can.Message(
            timestamp=i * 1e-4,
            arbitration_id=0x1F0001 if i % 3 == 0 else 0x182,
            is_extended_id=i % 3 == 0,
            data=bytes((i + k) & 0xFF for k in range(i % 9)),
            channel=1 if i % 3 == 0 else 0,
            is_rx=True,
        )
        for i in range(n)
    ]


def _read(path: Path) -> list[tuple]:
    with can.LogReader(str(path)) as reader:
        return [
            (round(m.timestamp, 6), m.arbitration_id, m.is_extended_id, bytes(m.data), m.channel)
            for m in reader
        ]


@pytest.mark.parametrize("suffix", [".blf", ".asc", ".log", ".trc"])
def test_the_writer_process_writes_what_python_cans_writer_writes(tmp_path, suffix):
    frames = _frames(3 * BATCH_FRAMES + 17)  # full batches and a partial one
    direct, background = tmp_path / f"direct{suffix}", tmp_path / f"background{suffix}"
    writer = open_writer(direct)
    for m in frames:
        writer.on_message_received(m)
    writer.stop()
    proc = WriterProcess(background)
    for m in frames:
        proc.on_message_received(m)
    proc.stop()
    assert proc.sent == len(frames)
    assert _read(background) == _read(direct)
    assert len(_read(background)) == len(frames)


@pytest.mark.parametrize("chunk", [1, 7, BATCH_FRAMES + 3])
def test_frames_handed_on_in_batches_give_the_same_file(tmp_path, chunk):
    """``on_frames`` (how the run's tap hands frames on) writes what one-by-one does."""
    frames = _frames(2 * BATCH_FRAMES + 11)
    one, batched = tmp_path / "one.blf", tmp_path / "batched.blf"
    proc = WriterProcess(one)
    for m in frames:
        proc.on_message_received(m)
    proc.stop()
    proc = WriterProcess(batched)
    for i in range(0, len(frames), chunk):
        proc.on_frames(frames[i : i + chunk])
    proc.stop()
    assert proc.sent == len(frames)
    assert _read(batched) == _read(one)


def test_an_unwritable_trace_is_refused_before_the_run(tmp_path):
    (tmp_path / "dir.blf").mkdir()
    with pytest.raises(UserError, match="a directory; only regular files are written"):
        WriterProcess(tmp_path / "dir.blf")
    with pytest.raises(ValueError, match="does not exist"):
        WriterProcess(tmp_path / "missing" / "x.blf")
    with pytest.raises(ValueError, match="unsupported trace format"):
        WriterProcess(tmp_path / "x.txt")


@pytest.mark.slow
@pytest.mark.subprocess
def test_the_file_is_closed_and_complete_when_the_run_is_killed(tmp_path):
    """SIGKILL of the run: the child still writes every batch handed over and closes the
    BLF file properly (a BLF written in-process would be left without its final header)."""
    trace = tmp_path / "killed.blf"
    script = textwrap.dedent(f"""
        import os, signal, can
        from pathlib import Path
        from hdhil.can.traces.writer import BATCH_FRAMES, WriterProcess
        w = WriterProcess(Path({str(trace)!r}))
        for i in range(2 * BATCH_FRAMES):
            w.on_message_received(can.Message(timestamp=i * 1e-3, arbitration_id=0x80,
                                              data=bytes([i & 0xFF]), channel=0))
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], timeout=60)
    assert proc.returncode == -9
    # The child finishes on end of input; give it time to write and close the file.
    expected = [bytes([i & 0xFF]) for i in range(2 * BATCH_FRAMES)]
    deadline = time.monotonic() + 30
    frames: list[tuple] = []
    while time.monotonic() < deadline:
        try:
            frames = _read(trace)
        except Exception:  # still being written
            frames = []
        if len(frames) == len(expected):
            break
        time.sleep(0.1)
    assert [f[3] for f in frames] == expected


def test_the_tap_merges_channels_in_time_order_for_every_kind_of_listener():
    """Frames of two channels reach a plain listener one by one and batch listeners
    (``on_frames``) in one call, the same frames in the same (timestamp) order, stamped
    with the tap's channel numbers; a bus without ``trace_channel`` gets stamped copies."""
    clock = SimClock(0.0)
    control = can.Bus(interface="simbus", channel="t-tap-c", clock=clock, trace_channel=0)
    truth = can.Bus(interface="simbus", channel="t-tap-t", clock=clock, bitrate=0)
    tap_c = can.Bus(interface="simbus", channel="t-tap-c")
    tap_t = can.Bus(interface="simbus", channel="t-tap-t")
    plain, counter = FrameRecorder(), FrameCounter()  # one by one, in batches
    tap = BusTap({0: tap_c, 1: tap_t}, [plain, counter])
    try:
        for k in range(3):
            clock.now = k * 1e-3
            control.send(can.Message(arbitration_id=0x080, data=b"\x01", is_extended_id=False))
            truth.send(can.Message(arbitration_id=0x1F0001, data=bytes(8), is_extended_id=True))
        assert tap.poll() == 6 and tap.poll() == 0
        got = [(m.channel, m.arbitration_id) for m in plain.messages]
        assert got == [(1, 0x1F0001), (0, 0x080)] * 3  # truth at t(k), SYNC a frame later
        times = [m.timestamp for m in plain.messages]
        assert times == sorted(times)
        assert counter.counts == {(0, 0x080): 3, (1, 0x1F0001): 3}
    finally:
        for bus in (control, truth, tap_c, tap_t):
            bus.shutdown()


def test_bulk_blf_objects_are_the_bytes_python_can_writes(tmp_path):
    """The writer process packs classical frames into python-can's BLF writer in bulk:
    the file (object headers, container cuts, header dates) is the one the writer's own
    per-message path makes, with error, remote, extended and transmitted frames mixed in
    and batches that end mid-container."""
    from hdhil.can.traces.writer import _FIELDS, _RECORD, _batch_writer, _message

    frames = [
        can.Message(
            timestamp=i * 1e-4,
            arbitration_id=(0x1F0000 + i) if i % 3 == 0 else 0x80 + i % 0x700,
            is_extended_id=i % 3 == 0,
            is_remote_frame=i % 11 == 5,
            is_error_frame=i % 97 == 13,
            is_rx=i % 7 != 0,
            dlc=i % 9,
            data=bytes((i * 7 + k) & 0xFF for k in range(i % 9)),
            channel=i % 2,
        )
        for i in range(6000)  # ~290 kB of objects: more than two 128 kB containers
    ]
    records = [_RECORD.pack(*_FIELDS(m)) for m in frames]
    offset = 1.7e9
    reference = can.Logger(str(tmp_path / "reference.blf"))
    for record in records:
        reference.on_message_received(_message(_RECORD.unpack(record), offset))
    reference.stop()
    bulk = can.Logger(str(tmp_path / "bulk.blf"))
    write = _batch_writer(bulk, offset)
    assert write.__name__ == "<lambda>"  # the bulk path, not the per-message one
    for start in range(0, len(records), 500):
        assert write(b"".join(records[start : start + 500])) == len(records[start : start + 500])
    bulk.stop()
    assert (tmp_path / "bulk.blf").read_bytes() == (tmp_path / "reference.blf").read_bytes()
