"""A listener run in the trace writer's process: the frames it gets, its result, its
failures, and the run scored there giving the evaluation scored in the run's process."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
from pathlib import Path

import can
import pytest

from hdhil.can.traces.writer import BATCH_FRAMES, ChildListenerError, WriterProcess
from hdhil.rig import wiring
from hdhil.rig.request import resolve
from hdhil.rig.runner import run_lockstep


def _frames(n: int) -> list[can.Message]:
    return [
        can.Message(
            timestamp=0.25 + i * 1e-4,
            arbitration_id=0x1F0001 if i % 3 == 0 else 0x182,
            is_extended_id=i % 3 == 0,
            is_remote_frame=i % 11 == 5,
            is_error_frame=i % 13 == 7,
            data=b"" if i % 11 == 5 else bytes((i + k) & 0xFF for k in range(i % 9)),
            dlc=i % 9,
            channel=1 if i % 3 == 0 else 0,
            is_rx=i % 2 == 0,
        )
        for i in range(n)
    ]


def _fields(m: can.Message) -> tuple:
    return (m.timestamp, m.arbitration_id, m.is_extended_id, m.is_remote_frame,
            m.is_error_frame, m.is_rx, m.dlc, m.channel, bytes(m.data))  # fmt: skip


class Collect:
    """Keeps every frame's fields; its result is the list of them."""

    def __init__(self, batched: bool = True) -> None:
        self.seen: list[tuple] = []
        if not batched:
            self.on_frames = None  # type: ignore[assignment]

    def on_frames(self, frames: list) -> None:
        self.seen.extend(_fields(f) for f in frames)

    def on_message_received(self, msg: can.Message) -> None:
        self.seen.append(_fields(msg))

    def result(self) -> list[tuple]:
        return self.seen

    def stop(self) -> None:
        pass


class FailsAfter(Collect):
    """Raises once it has seen ``n`` frames."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.n = n

    def on_frames(self, frames: list) -> None:
        super().on_frames(frames)
        if len(self.seen) >= self.n:
            raise ZeroDivisionError("the listener's own bug")


class DiesAtTheEnd(Collect):
    def result(self) -> list[tuple]:
        os._exit(3)


@pytest.mark.parametrize("batched", [True, False])
def test_the_child_listener_sees_every_frame_as_handed_over(tmp_path, batched):
    frames = _frames(2 * BATCH_FRAMES + 33)
    proc = WriterProcess(tmp_path / "t.blf", time_offset=1.7e9,
                         child_listener=lambda: Collect(batched))  # fmt: skip
    assert proc.child_listening
    proc.on_frames(frames[:100])
    for m in frames[100:]:
        proc.on_message_received(m)
    proc.stop()
    # the timestamps as handed over, without the trace's offset; every field, in order
    assert proc.child_result() == [_fields(m) for m in frames]
    with can.LogReader(str(tmp_path / "t.blf")) as reader:
        assert sum(1 for _ in reader) == len(frames)


def test_a_failing_child_listener_gives_a_clear_error_and_the_trace_is_written(tmp_path):
    frames = _frames(3 * BATCH_FRAMES)
    proc = WriterProcess(tmp_path / "t.blf", child_listener=lambda: FailsAfter(BATCH_FRAMES))
    proc.on_frames(frames)
    proc.stop()  # the trace is fine
    with pytest.raises(ChildListenerError, match=r"failed: ZeroDivisionError: the listener's"):
        proc.child_result()
    with can.LogReader(str(tmp_path / "t.blf")) as reader:
        assert sum(1 for _ in reader) == len(frames)


def test_a_child_that_dies_before_its_result_gives_a_clear_error(tmp_path):
    proc = WriterProcess(tmp_path / "t.blf", child_listener=DiesAtTheEnd)
    proc.on_frames(_frames(10))
    proc.stop()
    with pytest.raises(ChildListenerError, match=r"exit code 3"):
        proc.child_result()
    assert not proc._proc.is_alive()
    with can.LogReader(str(tmp_path / "t.blf")) as reader:
        assert sum(1 for _ in reader) == 10


def test_a_factory_that_cannot_start_gives_a_clear_error(tmp_path):
    def broken() -> Collect:
        raise RuntimeError("no such configuration")

    proc = WriterProcess(tmp_path / "t.blf", child_listener=broken)
    proc.on_frames(_frames(10))
    proc.stop()
    with pytest.raises(ChildListenerError, match="could not start: RuntimeError: no such"):
        proc.child_result()


def test_a_result_not_collected_is_discarded_without_waiting(tmp_path):
    proc = WriterProcess(tmp_path / "t.blf", child_listener=Collect)
    proc.on_frames(_frames(10))
    proc.stop()
    proc.discard_child_result()
    assert not proc._proc.is_alive()
    with pytest.raises(ChildListenerError, match="no child listener result"):
        proc.child_result()


@pytest.mark.slow
def test_under_spawn_an_unpicklable_factory_is_not_taken(tmp_path, monkeypatch):
    monkeypatch.setattr(multiprocessing, "get_all_start_methods", lambda: ["spawn"])
    proc = WriterProcess(tmp_path / "t.blf", child_listener=lambda: Collect())
    assert not proc.child_listening
    proc.on_frames(_frames(10))
    proc.stop()
    picklable = WriterProcess(tmp_path / "u.blf", child_listener=Collect)
    assert picklable.child_listening
    picklable.on_frames(_frames(10))
    picklable.stop()
    assert len(picklable.child_result()) == 10


# ---------------------------------------------------------------------- in a run
def _evaluation(tmp_path: Path, name: str, request, **kw) -> dict:
    result = run_lockstep(request, trace=tmp_path / f"{name}.blf", start_time=0.0, **kw)
    assert result.evaluation is not None and result.evaluation["samples"] > 0
    return result.evaluation


@pytest.mark.slow
@pytest.mark.parametrize(
    ("scenario", "faults"),
    [
        ("free-motion", ()),
        ("free-motion", ("control.loss_rate=0.05",)),
        ("torque-steps", ("truth.loss_rate=0.03", "control.loss_rate=0.02")),
    ],
)
def test_the_evaluation_in_the_writer_process_is_the_runs_own(tmp_path, scenario, faults):
    request = resolve(scenario, duration_s=1.5, seed=11, faults=faults)
    # keep_recording: scored in this process, by the recorder of the run's tap
    here = _evaluation(tmp_path, "here", request, keep_recording=True)
    there = _evaluation(tmp_path, "there", request, keep_recording=False)
    # as JSON: the NaN of a harmonic a faulty truth leaves undefined compares equal so
    assert json.dumps(there, sort_keys=True) == json.dumps(here, sort_keys=True)
    assert (tmp_path / "here.blf").read_bytes() == (tmp_path / "there.blf").read_bytes()
    assert not multiprocessing.active_children()


@pytest.mark.slow
def test_a_writer_that_cannot_take_the_evaluation_leaves_it_to_the_run(tmp_path, monkeypatch):
    request = resolve("free-motion", duration_s=1.5, seed=11)
    there = _evaluation(tmp_path, "there", request, keep_recording=False)

    class Refusing(WriterProcess):
        def __init__(self, *args, child_listener=None, **kw) -> None:
            super().__init__(*args, **kw)  # as under spawn with an unpicklable factory

    monkeypatch.setattr(wiring, "WriterProcess", Refusing)
    here = _evaluation(tmp_path, "here", request, keep_recording=False)
    assert json.dumps(here, sort_keys=True) == json.dumps(there, sort_keys=True)


@pytest.mark.slow
def test_a_run_whose_evaluation_fails_in_the_writer_says_so(tmp_path, monkeypatch):
    def failing(*args):  # as LiveEvaluationFactory: a factory of the listener
        return lambda: FailsAfter(1)

    monkeypatch.setattr(wiring, "LiveEvaluationFactory", failing)
    request = resolve("free-motion", duration_s=0.5, seed=11)
    with pytest.raises(ChildListenerError, match="ZeroDivisionError"):
        run_lockstep(request, trace=tmp_path / "t.blf", keep_recording=False)
    assert (tmp_path / "t.blf").exists()  # the trace is complete all the same
    assert not multiprocessing.active_children()


@pytest.mark.slow
def test_an_interrupted_run_leaves_no_writer_behind(tmp_path):
    request = resolve("free-motion", duration_s=2.0, seed=11)
    polls = iter(range(10**9))
    result = run_lockstep(request, trace=tmp_path / "t.blf", keep_recording=False,
                          stop_requested=lambda: next(polls) > 700)  # fmt: skip
    assert result.interrupted and result.evaluation is None
    assert not multiprocessing.active_children()
    assert dataclasses.is_dataclass(result)
