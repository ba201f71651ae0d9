"""The README's torque-steps evaluation is what ``hdhil run --scenario torque-steps``
prints: the block between ``<!-- generated: torque-steps-evaluation -->`` and
``<!-- end generated -->`` is compared with the live output, so it cannot go stale.
``HDHIL_RECORD_README=1`` rewrites the block from the live output."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.subprocess]

README = Path(__file__).parents[1] / "README.md"
BEGIN = "<!-- generated: torque-steps-evaluation -->"
END = "<!-- end generated -->"
COMMAND = ("run", "--scenario", "torque-steps", "--trace", "")


def evaluation_section(output: str) -> list[str]:
    """The evaluation part of ``hdhil run``'s report: from its "evaluation vs truth" line
    to the next line of the report's own indent (or the end)."""
    lines = output.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("  evaluation vs truth"))
    end = next(
        (i for i in range(start + 1, len(lines)) if not lines[i].startswith("   ")), len(lines)
    )
    return lines[start:end]


def readme_block(text: str) -> tuple[int, int, list[str]]:
    """The fenced lines between the markers, and where they sit in ``text``'s lines."""
    lines = text.splitlines()
    begin = lines.index(BEGIN)
    end = lines.index(END, begin)
    assert lines[begin + 1] == "```text" and lines[end - 1] == "```", "a ```text fence"
    return begin + 2, end - 1, lines[begin + 2 : end - 1]


def test_readme_shows_the_live_torque_steps_evaluation() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "hdhil", *COMMAND], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    live = evaluation_section(proc.stdout)
    assert any("butterworth 5 Hz" in line for line in live)
    text = README.read_text(encoding="utf-8")
    first, last, shown = readme_block(text)
    if os.environ.get("HDHIL_RECORD_README") == "1":
        lines = text.splitlines()
        README.write_text("\n".join([*lines[:first], *live, *lines[last:]]) + "\n", "utf-8")
        return
    assert shown == live, (
        "README.md's torque-steps evaluation differs from `hdhil run --scenario "
        "torque-steps`: rewrite it with HDHIL_RECORD_README=1 python -m pytest "
        "tests/test_readme_evaluation.py"
    )
