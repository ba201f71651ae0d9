"""Duplicated or reordered frames on the control bus never move the plant by more time
than really passed, so the filtered torque error stays that of a clean run (issue goal:
at most 1.1x the clean error with 1 % of the frames duplicated or reordered)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.subprocess]


def _filtered_error(cwd, *flags: str) -> tuple[float, dict]:
    out = subprocess.run(
        [sys.executable, "-m", "hdhil", "run", "--duration", "2", "--json", *flags],
        capture_output=True, text=True, timeout=300, check=True, cwd=cwd,
    )  # fmt: skip
    summary = json.loads(out.stdout)
    return summary["torque"]["rms_error_filtered"], summary


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> float:
    return _filtered_error(tmp_path_factory.mktemp("clean"))[0]


@pytest.mark.parametrize("fault", ["control.duplicate_rate=0.01", "control.reorder_rate=0.01"])
def test_one_percent_duplicated_or_reordered_frames_cost_at_most_ten_percent(
    clean, fault, tmp_path
):
    error, summary = _filtered_error(tmp_path, "--fault", fault)
    injected = summary["faults"]
    assert sum(injected.values()) > 0, f"no fault injected: {summary['faults']}"
    assert error <= 1.1 * clean, f"{fault}: {error:.4f} Nm against {clean:.4f} Nm clean"
