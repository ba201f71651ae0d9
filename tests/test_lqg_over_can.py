"""[Vertechy] §VI over the CAN link: the four control laws side by side from one command."""

from __future__ import annotations

import json

import pytest

from hdhil.cli import main

pytestmark = [pytest.mark.slow]


@pytest.fixture(scope="module")
def laws(tmp_path_factory):
    out = tmp_path_factory.mktemp("lqg") / "track.blf"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(["run", "--scenario", "lqg-tracking", "--duration", "3", "--compare-laws",
                     "--trace", str(out), "--json"])  # fmt: skip
    assert code == 0
    report = json.loads(buf.getvalue())
    return {row["law"]: row for row in report["laws"]}, out


def test_jtf1_beats_jtf3_beats_jtf2(laws):
    rows, _ = laws
    assert rows["JTF1"]["max_abs_error"] < rows["JTF3"]["max_abs_error"]
    assert rows["JTF3"]["max_abs_error"] < rows["JTF2"]["max_abs_error"]
    assert rows["JTF1"]["rms_error"] < rows["JTF3"]["rms_error"] < rows["JTF2"]["rms_error"]


def test_jtf1_with_feedforward_tracks_within_0_3_nm(laws):
    rows, _ = laws
    ff = rows["JTF1 + feedforward"]
    assert ff["samples"] >= 1900
    assert ff["max_abs_error"] <= 0.3
    # Its disturbance observer (V = 1e7) also tracks the external torque more closely.
    assert ff["rms_disturbance_error"] < rows["JTF1"]["rms_disturbance_error"]


def test_each_law_leaves_its_own_trace(laws):
    rows, out = laws
    for row in rows.values():
        assert row["trace"].startswith(str(out.with_suffix("")))
    assert len({row["trace"] for row in rows.values()}) == len(rows) == 6
