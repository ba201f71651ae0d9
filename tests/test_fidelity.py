"""README.md's fidelity table (``tools/docs/fidelity.py``): its numbers are what the
independent scripts and the commands give now."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _fidelity() -> ModuleType:
    path = ROOT / "tools" / "docs" / "fidelity.py"
    spec = importlib.util.spec_from_file_location("hdhil_docs_fidelity", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while defined
    spec.loader.exec_module(module)
    return module


fidelity = _fidelity()


def test_every_paper_figure_has_one_row_with_a_command() -> None:
    rows = fidelity.readme_rows(README.read_text(encoding="utf-8"))
    assert [r[0] for r in rows] == [r.figure for r in fidelity.ROWS]
    for cells, row in zip(rows, fidelity.ROWS, strict=True):
        assert len(cells) == 5, cells
        assert cells[1] == row.paper and cells[4] == row.command
        assert cells[4].startswith("`hdhil ")


def test_independent_column_is_what_the_independent_scripts_give() -> None:
    """The cheap part: each row's independent cell recomputed (numpy/scipy, < 1 s).  The
    whole table, hdhil's column and the closed-loop independent computations included, is
    the README's block ``fidelity`` of ``tools/docs/figures.py``: its check in the slow
    tier (tests/test_figures.py) fails when a number drifts."""
    rows = fidelity.readme_rows(README.read_text(encoding="utf-8"))
    for cells, row in zip(rows, fidelity.ROWS, strict=True):
        if not row.slow:
            assert cells[2] == fidelity.cells(row, project=False)[2], row.figure


def test_a_changed_number_is_caught() -> None:
    text = README.read_text(encoding="utf-8")
    changed = text.replace("perfect state estimates 0.75 Nm", "perfect state estimates 0.30 Nm")
    assert changed != text
    row = next(r for r in fidelity.ROWS if r.figure == "[Vertechy] Fig. 7")
    i = [r.figure for r in fidelity.ROWS].index(row.figure)
    assert fidelity.readme_rows(changed)[i][2] != fidelity.cells(row, project=False)[2]
