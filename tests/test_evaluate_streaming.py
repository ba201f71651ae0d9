"""The evaluation scored as the run goes, in chunks, against the one over the whole
recording: the same numbers (to the last bits summation order moves), the same samples
(the firmware's, from its first to its last answered row), and state that does not grow
with the run."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from hdhil.firmware.config import FirmwareConfig
from hdhil.rig.evaluate import (
    COLUMNS,
    LiveEvaluation,
    Recording,
    StreamingEvaluation,
    evaluate,
)
from hdhil.rig.request import resolve
from tests.runs import lockstep

pytestmark = pytest.mark.slow

SKIP_S = 0.3


@pytest.fixture(scope="module")
def run() -> tuple[Recording, FirmwareConfig]:
    result = lockstep("chirp", duration_s=1.2, seed=1)  # a truth varying enough for a lag
    assert result.recording is not None
    return result.recording, resolve("chirp").scenario.firmware


def _rows(rec: Recording) -> list[tuple[float, ...]]:
    return list(zip(*(rec.column(name).tolist() for name in COLUMNS), strict=True))


def _live(
    rows: list[tuple[float, ...]], fw: FirmwareConfig, chunk: int, keep: bool = False
) -> tuple[dict[str, Any], LiveEvaluation]:
    """Rows appended one by one, as the recorder appends them, scored every ``chunk``."""
    rec = Recording(fw.sample_period_s)
    live = LiveEvaluation(rec, fw, SKIP_S, keep=keep, chunk_rows=chunk)
    next_check = live.next_check
    for row in rows:
        rec.append_row(row)
        if len(rec) >= next_check:
            next_check = live.advance()
    return live.finish(), live


def _flat(value: Any, path: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        return {k: v for key, x in value.items() for k, v in _flat(x, f"{path}/{key}").items()}
    if isinstance(value, list):
        return {k: v for i, x in enumerate(value) for k, v in _flat(x, f"{path}/{i}").items()}
    return {path: value}


def _assert_same(got: dict[str, Any], want: dict[str, Any]) -> None:
    g, w = _flat(got), _flat(want)
    assert g.keys() == w.keys()
    for key, expected in w.items():
        value = g[key]
        if isinstance(expected, float) and math.isnan(expected):
            assert isinstance(value, float) and math.isnan(value), key
        elif isinstance(expected, float):
            assert value == pytest.approx(expected, rel=1e-12), key
        else:
            assert value == expected, key


@pytest.mark.parametrize("chunk", [1, 7, 1000])
def test_chunks_score_what_the_whole_recording_scores(run, chunk: int) -> None:
    rec, fw = run
    want = evaluate(rec, fw, SKIP_S)
    assert want["samples"] > 500 and len(want["candidates"]) >= 8
    assert all(c["lag_ms"] is not None for c in want["candidates"])
    assert all(not math.isnan(c["harmonics"]["2x motor"]) for c in want["candidates"])
    got, live = _live(_rows(rec), fw, chunk)
    _assert_same(got, want)
    assert len(live.rec) == 0  # every row scored (or dropped) and forgotten


def test_only_the_firmwares_samples_are_scored(run) -> None:
    """Rows the telemetry did not answer before the first and after the last answered
    row are left out, as :meth:`Recording.operation` leaves them out; rows in between
    are scored. Without any answer every row is scored."""
    rec, fw = run
    rows = _rows(rec)
    tele = COLUMNS.index("T_meas_tele")

    def unanswered(row: tuple[float, ...]) -> tuple[float, ...]:
        return (*row[:tele], math.nan, *row[tele + 1 :])

    trimmed = [unanswered(r) for r in rows[:40]] + rows[40:-30]
    trimmed += [unanswered(r) for r in rows[-30:]]
    trimmed[500:520] = [unanswered(r) for r in trimmed[500:520]]  # telemetry lost
    whole = Recording(fw.sample_period_s)
    for row in trimmed:
        whole.append_row(row)
    want = evaluate(whole, fw, SKIP_S)
    assert want["samples"] == len(rows) - 70 - round(SKIP_S / fw.sample_period_s)
    for chunk in (7, 300):
        _assert_same(_live(trimmed, fw, chunk)[0], want)
    silent = [unanswered(r) for r in rows]
    whole = Recording(fw.sample_period_s)
    for row in silent:
        whole.append_row(row)
    want = evaluate(whole, fw, SKIP_S)
    assert want["samples"] == len(rows) - round(SKIP_S / fw.sample_period_s)
    _assert_same(_live(silent, fw, 300)[0], want)


def _array_sizes(obj: Any, seen: set[int] | None = None) -> list[int]:
    """Sizes of every numpy array and sequence held by ``obj``'s attributes, recursively."""
    seen = set() if seen is None else seen
    if id(obj) in seen or isinstance(obj, (str, bytes, int, float, type(None))):
        return []
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        return [obj.size]
    if isinstance(obj, dict):
        return [n for v in obj.values() for n in _array_sizes(v, seen)] + [len(obj)]
    if isinstance(obj, (list, tuple)):
        return [n for v in obj for n in _array_sizes(v, seen)] + [len(obj)]
    state = getattr(obj, "__dict__", None)
    if state is None or type(obj).__module__.startswith("hdhil.firmware.config"):
        return []
    if type(obj).__name__ == "_PerCount":
        return []  # a table per distinct ADC count: bounded by the converter's range
    return _array_sizes(state, seen)


def test_the_state_does_not_grow_with_the_run(run) -> None:
    """Without ``keep`` the recording holds only rows not yet scored and the evaluation
    nothing the length of the run: twice the rows, the same largest state."""
    rec, fw = run
    rows = _rows(rec)
    sizes = []
    for n in (len(rows) // 2, len(rows)):
        _, live = _live(rows[:n], fw, 64)
        evaluation = live._main
        assert isinstance(evaluation, StreamingEvaluation) and evaluation.n > 64 * 4
        sizes.append(max(_array_sizes(evaluation.__dict__)))
    assert sizes[0] == sizes[1]
    assert sizes[1] < 64 * 4


def test_a_run_without_its_recording_scores_the_same() -> None:
    """``keep_recording=False`` (what ``hdhil run`` uses): no recording in the result,
    and the evaluation the run keeping its recording gets."""
    kept = lockstep("free-motion", duration_s=0.6, seed=2)
    flat = lockstep("free-motion", duration_s=0.6, seed=2, keep_recording=False)
    assert kept.recording is not None and flat.recording is None
    assert flat.evaluation is not None and flat.evaluation["samples"] > 0
    assert flat.evaluation == kept.evaluation


def test_frames_handed_on_in_batches_record_what_one_by_one_records(tmp_path) -> None:
    """The run's tap hands the recorder a poll's frames at once (``on_frames``): the same
    rows as frame by frame (how a trace is read), malformed frames skipped alike."""
    import can

    from hdhil.can.traces.reader import read_trace
    from hdhil.dbc import codec
    from hdhil.rig.evaluate import RecordingListener

    path = tmp_path / "run.blf"
    lockstep("free-motion", duration_s=0.3, seed=3, trace=path)
    with read_trace(path) as trace:
        frames = list(trace)
    sensor_id = codec("control", "DRIVE_TPDO1").frame_id
    sensor = next(m for m in frames if m.arbitration_id == sensor_id and not m.is_extended_id)
    short = can.Message(arbitration_id=sensor_id, is_extended_id=False, data=b"\x01",
                        timestamp=sensor.timestamp)  # fmt: skip
    frames.insert(len(frames) // 2, short)
    fw = resolve("free-motion").scenario.firmware
    one = RecordingListener(fw.sample_period_s, firmware=fw, keep=True)
    batched = RecordingListener(fw.sample_period_s, firmware=fw, keep=True)
    for msg in frames:
        one.on_message_received(msg)
    for i in range(0, len(frames), 16):
        batched.on_frames(frames[i : i + 16])
    assert len(one.recording) > 100
    for name in COLUMNS:
        np.testing.assert_array_equal(batched.recording.column(name), one.recording.column(name))
    assert batched.live is not None and one.live is not None
    _assert_same(batched.live.finish(), one.live.finish())
