"""Traces are written atomically: to a temporary beside the target, renamed into place when
complete; an interrupted or killed run still leaves a valid trace of what happened (read
back with python-can's own readers) and its sidecar; an existing trace is never half
overwritten; temporaries never stay behind."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import can
import pytest

from hdhil.can.traces.sidecar import metadata_path
from hdhil.can.traces.writer import BATCH_FRAMES, WriterError, WriterProcess


def _command() -> list[str]:
    script = Path(sys.executable).with_name("hdhil")
    return [str(script)] if script.exists() else [sys.executable, "-m", "hdhil"]


def _temporaries(directory: Path) -> list[str]:
    return [p.name for p in directory.iterdir() if ".hdhil-" in p.name]


def _wait_for_temporary(directory: Path, proc: subprocess.Popen, timeout: float = 60) -> None:
    """Until the run's trace temporary exists (the run is under way)."""
    deadline = time.monotonic() + timeout
    while not _temporaries(directory):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the run never started its trace"
        time.sleep(0.02)


def _wait_for_frames(
    directory: Path, name: str, proc: subprocess.Popen, timeout: float = 60
) -> None:
    """Until the writer has put frames into the run's trace temporary (the file inside it
    is no longer empty): the run is in its loop, whatever the machine's load."""
    deadline = time.monotonic() + timeout
    while not any(
        (d / name).exists() and (d / name).stat().st_size > 0
        for d in directory.iterdir()
        if ".hdhil-" in d.name and d.is_dir()
    ):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the run never wrote a frame"
        time.sleep(0.02)


def _read_all(path: Path) -> list[can.Message]:
    with can.LogReader(str(path)) as reader:
        return list(reader)


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize(
    ("suffix", "sig"),
    [(".blf", signal.SIGINT), (".asc", signal.SIGTERM), (".log.gz", signal.SIGINT)],
)
def test_an_interrupted_run_keeps_a_valid_trace_and_its_sidecar(tmp_path, suffix, sig):
    trace = tmp_path / f"run{suffix}"
    old = b"the previous trace\n"
    trace.write_bytes(old)
    proc = subprocess.Popen(
        [*_command(), "run", "--duration", "60", "--no-evaluate", "--trace", str(trace)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        _wait_for_temporary(tmp_path, proc)
        time.sleep(0.8)
        # While the run writes, the old trace is untouched (never half overwritten).
        assert trace.read_bytes() == old
        proc.send_signal(sig)
        _out, err = proc.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    frames = _read_all(trace)
    assert len(frames) > 100  # the trace of what happened, not the old file
    syncs = [m for m in frames if m.arbitration_id == 0x080 and not m.is_extended_id]
    assert syncs and len(syncs) < 60_000  # stopped early: fewer SYNCs than 60 s
    times = [m.timestamp for m in frames]
    assert times == sorted(times)
    sidecar = json.loads(metadata_path(trace).read_text())
    assert sidecar["scenario"] == "free-motion"
    assert not _temporaries(tmp_path)


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_blf_trace_of_a_run_interrupted_twice_is_complete(tmp_path):
    """A second Ctrl-C interrupts at once: the writer still closes the BLF file properly
    (python-can's BLFReader reads it to the end) and renames it into place."""
    trace = tmp_path / "twice.blf"
    proc = subprocess.Popen(
        [*_command(), "run", "--duration", "60", "--no-evaluate", "--trace", str(trace)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        _wait_for_frames(tmp_path, trace.name, proc)
        proc.send_signal(signal.SIGINT)
        time.sleep(0.01)  # the second Ctrl-C lands while the run is ending
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    with can.BLFReader(str(trace)) as reader:
        frames = list(reader)
    assert frames
    assert metadata_path(trace).exists()
    assert not _temporaries(tmp_path)


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_killed_run_leaves_the_complete_trace_in_place(tmp_path):
    """SIGKILL of the run: the writer process reads every batch handed over, closes the
    file and renames it over the old trace; the temporary is gone."""
    trace = tmp_path / "killed.blf"
    trace.write_bytes(b"old")
    script = textwrap.dedent(f"""
        import os, signal, can
        from pathlib import Path
        from hdhil.can.traces.writer import BATCH_FRAMES, WriterProcess
        w = WriterProcess(Path({str(trace)!r}), metadata={{"kind": "test"}})
        for i in range(2 * BATCH_FRAMES):
            w.on_message_received(can.Message(timestamp=i * 1e-3, arbitration_id=0x80,
                                              data=bytes([i & 0xFF]), channel=0))
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], timeout=60)
    assert proc.returncode == -9
    deadline = time.monotonic() + 30
    while (_temporaries(tmp_path) or not metadata_path(trace).exists()) and (
        time.monotonic() < deadline
    ):
        time.sleep(0.05)
    with can.BLFReader(str(trace)) as reader:
        data = [bytes(m.data) for m in reader]
    assert data == [bytes([i & 0xFF]) for i in range(2 * BATCH_FRAMES)]
    assert json.loads(metadata_path(trace).read_text()) == {"kind": "test"}
    assert not _temporaries(tmp_path)


class _Interrupted(Exception):
    """What this test's SIGINT handler raises (not KeyboardInterrupt, which ends pytest)."""


def test_a_ctrl_c_as_a_batch_is_handed_over_neither_loses_nor_repeats_frames(tmp_path):
    """Ctrl-C lands the moment a batch has gone into the pipe, before it is counted: the
    handler runs once the batch is counted, so ``stop`` sends nothing twice and the trace
    holds every frame exactly once (before, the batch went again: "wrote 1024 of 512")."""
    trace = tmp_path / "race.blf"
    w = WriterProcess(trace)
    pipe = w._frames

    class InterruptedAfterWrite:
        closed = property(lambda self: pipe.closed)

        def send_bytes(self, data: bytes) -> None:
            pipe.send_bytes(data)
            os.kill(os.getpid(), signal.SIGINT)

        def close(self) -> None:
            pipe.close()

    def interrupt(signum: int, frame: object) -> None:
        raise _Interrupted

    previous = signal.signal(signal.SIGINT, interrupt)
    try:
        w._frames = InterruptedAfterWrite()  # type: ignore[assignment]
        with pytest.raises(_Interrupted):
            for i in range(BATCH_FRAMES):
                w.on_message_received(
                    can.Message(timestamp=i * 1e-3, arbitration_id=0x80,
                                data=i.to_bytes(2, "big"), channel=0)
                )  # fmt: skip
        assert i == BATCH_FRAMES - 1  # the handler ran once the batch was out
    finally:
        signal.signal(signal.SIGINT, previous)
        w._frames = pipe
    w.stop()
    with can.BLFReader(str(trace)) as reader:
        data = [bytes(m.data) for m in reader]
    assert data == [i.to_bytes(2, "big") for i in range(BATCH_FRAMES)]
    assert not _temporaries(tmp_path)


def test_a_ctrl_c_amid_a_poll_of_frames_keeps_every_frame_handed_over(tmp_path):
    """Ctrl-C lands while ``on_frames`` appends a poll's frames to the batch: the frames
    appended so far are written and counted alike (before, they were written but not
    counted: "wrote 5 of 0 frames" when the trace was closed)."""
    trace = tmp_path / "amid.blf"
    w = WriterProcess(trace)

    class SignalsWhenRead(can.Message):
        armed = False

        @property
        def data(self) -> bytearray:  # type: ignore[override]
            if self.armed:
                os.kill(os.getpid(), signal.SIGINT)  # handled at the next call: mid-loop
            return bytearray(b"\x05")

        @data.setter
        def data(self, value: object) -> None:
            pass

    def interrupt(signum: int, frame: object) -> None:
        raise _Interrupted

    frames = [can.Message(timestamp=i * 1e-3, arbitration_id=0x80, data=bytes([i]), channel=0)
              for i in range(5)]  # fmt: skip
    signalling = SignalsWhenRead(timestamp=5e-3, arbitration_id=0x80, channel=0)
    frames.append(signalling)
    frames += [can.Message(timestamp=6e-3, arbitration_id=0x80, data=b"\x06", channel=0)]
    previous = signal.signal(signal.SIGINT, interrupt)
    try:
        signalling.armed = True
        with pytest.raises(_Interrupted):
            w.on_frames(frames)
    finally:
        signal.signal(signal.SIGINT, previous)
    w.stop()
    with can.BLFReader(str(trace)) as reader:
        written = [bytes(m.data) for m in reader]
    assert written[:5] == [bytes([i]) for i in range(5)]  # none lost
    assert w.sent == len(written) >= 5  # and every one written counted
    assert not _temporaries(tmp_path)


def test_a_failed_writer_leaves_the_old_trace_and_no_temporary(tmp_path):
    """The writer process dies mid-run (killed): the run is told (WriterError), the old
    trace is kept byte for byte, and the half-written temporary is removed."""
    trace = tmp_path / "old.blf"
    trace.write_bytes(b"previous")
    w = WriterProcess(trace, metadata={"kind": "test"})
    for i in range(BATCH_FRAMES + 1):
        w.on_message_received(
            can.Message(timestamp=i * 1e-3, arbitration_id=0x80, data=b"\x01", channel=0)
        )
    assert _temporaries(tmp_path)
    os.kill(w._proc.pid, signal.SIGKILL)
    w._proc.join(30)
    with pytest.raises(WriterError):
        w.stop()
    assert trace.read_bytes() == b"previous"
    assert not metadata_path(trace).exists()
    assert not _temporaries(tmp_path)


def test_a_trace_that_became_a_fifo_is_not_replaced(tmp_path):
    """The target is checked again when the finished trace is renamed: a path that is no
    longer a regular file is left alone and the trace discarded, with an error."""
    trace = tmp_path / "swap.blf"
    w = WriterProcess(trace)
    w.on_message_received(can.Message(arbitration_id=0x80, data=b"", channel=0))
    os.mkfifo(trace)
    with pytest.raises(WriterError, match="FIFO"):
        w.stop()
    assert trace.is_fifo()
    assert not _temporaries(tmp_path)


@pytest.mark.slow
@pytest.mark.subprocess
def test_log_interrupted_keeps_a_valid_trace(tmp_path):
    """``hdhil log`` writes through the same writer: Ctrl-C gives a valid trace."""
    trace = tmp_path / "log.asc"
    channel = f"hdhil-atomic-log-{time.monotonic_ns()}"
    proc = subprocess.Popen(
        [*_command(), "log", "--interface", "virtual", "--channel", channel, str(trace)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        _wait_for_temporary(tmp_path, proc)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
    assert proc.returncode == 0, err  # a clean stop of a server, as can.logger
    assert json.loads(out)["frames"] == 0
    with can.ASCReader(str(trace)) as reader:
        assert list(reader) == []
    assert not _temporaries(tmp_path)


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_second_signal_while_the_first_sets_the_stop_request_does_not_hang():
    """Two stopping signals back to back: the second one's handler runs while the first
    one's is setting the stop request (holding the event's lock, which is not reentrant).
    Before, it set the event again and waited for that lock for ever."""
    script = textwrap.dedent("""
        import os, signal, threading
        from hdhil.core.signals import stop_on_signals

        class SecondSignalInside(type(threading.Condition())):
            def __enter__(self):
                held = super().__enter__()
                os.kill(os.getpid(), signal.SIGTERM)  # arrives while the lock is held
                return held

        with stop_on_signals() as stop:
            stop._cond = SecondSignalInside(threading.Lock())
            os.kill(os.getpid(), signal.SIGTERM)
        print("stopped" if stop.is_set() else "not stopped")
    """)
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "stopped"
