"""Generate the README's fidelity table: per paper figure, the paper's value, an
independent computation's and hdhil's, with the command for each.

- the paper's values are quoted (they are text, not computed);
- the independent column comes from ``tools/docs/independent/`` (numpy and scipy only,
  no hdhil code), "—" where no independent computation exists;
- hdhil's column comes from running the row's command with ``--json`` (seed 1, each
  scenario's default duration).

Run ``python tools/docs/fidelity.py`` to rewrite the table in README.md between
``<!-- generated: fidelity -->`` and ``<!-- end generated -->``; ``--check`` exits 1 if
the README's table differs from what the commands give now.  The table is also the
block ``fidelity`` of ``tools/docs/figures.py``, which rewrites every generated block;
``tests/test_fidelity.py`` checks the independent column in the fast tier, and
``tests/test_figures.py`` the whole table with the other blocks in the slow tier.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

REPO = Path(__file__).resolve().parents[2]
README = REPO / "README.md"
INDEPENDENT = Path(__file__).resolve().parent / "independent"
BEGIN = "<!-- generated: fidelity -->"
END = "<!-- end generated -->"
NONE = "—"


def independent(name: str) -> ModuleType:
    """A module of ``tools/docs/independent/`` by file, so this script runs from a checkout
    without installing anything beyond numpy and scipy."""
    path = INDEPENDENT / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"hdhil_independent_{name}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while defined
    spec.loader.exec_module(module)
    return module


def hdhil_json(*args: str) -> Any:
    """``hdhil ARGS --json``'s output, parsed (a failing command raises)."""
    proc = subprocess.run(
        [sys.executable, "-m", "hdhil", *args, "--json"],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"hdhil {' '.join(args)}: exit {proc.returncode}: {proc.stderr}")
    return json.loads(proc.stdout)


def _run(scenario: str) -> Any:
    return hdhil_json("run", "--scenario", scenario, "--trace", "")


def _candidate(evaluation: dict[str, Any], word: str) -> dict[str, Any]:
    """The evaluation's first candidate filter whose name contains ``word``."""
    return next(c for c in evaluation["candidates"] if word in c["name"])


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


# -- hdhil's column ------------------------------------------------------------------


def hdhil_calibration() -> str:
    r = hdhil_json("calibrate")
    return f"{r['gain_Nm_per_V']:.3f} Nm/V, consistency {r['consistency_pct']:.2f} %"


def hdhil_free_motion() -> str:
    r = _run("free-motion")
    paper = _candidate(r["evaluation"], "paper")
    db = paper["reduction_dB"]
    return (
        f"{r['velocity_final']:.1f} rad/s; the paper's filter leaves "
        f"{_pct(paper['rms_ratio'])} of the raw error, −{db['2x motor']:.0f} / "
        f"−{db['4x motor']:.0f} dB at 2x / 4x"
    )


def hdhil_misalignment() -> str:
    ev = _run("misalignment")["evaluation"]
    raw = _candidate(ev, "raw")["misalignment_pp"]
    paper = _candidate(ev, "paper")["misalignment_pp"]
    return f"{raw:.1f} Nm p-p, {paper:.3f} Nm p-p left by the paper's filter"


def hdhil_fig5() -> str:
    with tempfile.TemporaryDirectory() as tmp:
        trace = str(Path(tmp) / "c.blf")
        subprocess.run(
            [sys.executable, "-m", "hdhil", "run", "--scenario", "chirp", "--trace", trace],
            capture_output=True,
            check=True,
        )
        m = hdhil_json("identify", trace)["methods"]
    hp, exact = m["half_power"], m["half_power_exact"]
    return (
        f"half-power: {hp['fn_Hz']:.2f} Hz, {hp['c_Nms_per_rad']:.2f} Nms/rad; exact second "
        f"order: {exact['fn_Hz']:.2f} Hz, {exact['c_Nms_per_rad']:.2f}"
    )


def _gains(k: list[float], L: list[float]) -> str:
    text = f"k {k[0]:.2f}, {k[1]:.3f}, {k[2]:.3f}, {k[3]:.3f}; L {L[0]:.1f}, {L[1]:.0f}, {L[2]:.1f}"
    return text.replace("-", "−")  # the paper's minus sign


def hdhil_gains() -> str:
    d = hdhil_json("design", "lqg")
    return _gains([d["k1"], d["k2"], d["k3"], d["k4"]], d["L"])


def hdhil_fig7() -> str:
    laws = {row["law"]: row for row in hdhil_json(
        "run", "--scenario", "lqg-tracking", "--compare-laws", "--trace", "")["laws"]}  # fmt: skip
    slow = _run("lqg-tracking-slow-link")["tracking"]["max_abs_error"]
    squared = _run("lqg-tracking-squared-weights")["tracking"]["max_abs_error"]
    e = {name: laws[name]["max_abs_error"] for name in ("JTF1", "JTF2", "JTF3")}
    return (
        f"JTF1 {e['JTF1']:.2f} Nm (JTF3 {e['JTF3']:.2f}, JTF2 {e['JTF2']:.2f}); "
        f"link at 0.5 Hz {slow:.2f}; Eq. 6 squared {squared:.2f}"
    )


def hdhil_fig8() -> str:
    t = _run("lqg-experiment")["tracking"]
    return (
        f"e within ±0.5 Nm: {_pct(t['share_within_goal'])} true, "
        f"{_pct(t['share_within_goal_measured'])} measured; max |τ̂l − τl^m| "
        f"{t['max_external_error']:.1f} Nm; max |τm| {t['max_abs_tau_m']:.1f} Nm"
    )


# -- the independent column -----------------------------------------------------------


def independent_fig5() -> str:
    m = independent("vertechy_fig5")
    fp, c = m.half_power()
    return (
        f"√(k/J)/2π = {m.natural_frequency_Hz():.2f} Hz; half-power on Eq. 2: "
        f"{fp:.2f} Hz, {c:.2f} Nms/rad"
    )


def independent_gains() -> str:
    m = independent("vertechy_gains")
    return _gains(list(m.lq_gains()), list(m.kalman_gain()))


def independent_fig7() -> str:
    f = independent("vertechy_fig7").figures()
    return (
        f"perfect state estimates {f['perfect_state']:.2f} Nm; ideal continuous LQG "
        f"{f['ideal_lqg']:.2f} (JTF3 {f['ideal_jtf3']:.2f}, JTF2 {f['ideal_jtf2']:.2f}); "
        f"link at 0.5 Hz {f['slow_link']:.2f}; Eq. 6 squared {f['squared_weights']:.2f}"
    )


def independent_fig8() -> str:
    r = independent("vertechy_fig8").simulate()
    return (
        f"e within ±0.5 Nm: {_pct(r.within_true)} true, {_pct(r.within_measured)} measured; "
        f"max |τ̂l − τl^m| {r.max_abs_tau_l_err:.1f} Nm; max |τm| {r.max_abs_tau_m:.1f} Nm"
    )


def no_independent() -> str:
    return NONE


# -- the table -----------------------------------------------------------------------


@dataclass(frozen=True)
class Row:
    """One paper figure: its name, the paper's value (quoted), how the independent and
    hdhil's values are computed, and the command that gives hdhil's."""

    figure: str
    paper: str
    independent: Callable[[], str]
    hdhil: Callable[[], str]
    command: str
    #: the independent computation takes seconds (a closed-loop simulation): checked in
    #: the slow tier only
    slow: bool = False


ROWS: tuple[Row, ...] = (
    Row("[Taghirad97] Figs. 6-7, Table 1", "6.60 Nm/V, consistency 2 %", no_independent,
        hdhil_calibration, "`hdhil calibrate`"),
    Row("[Taghirad97] Figs. 8-9", "≈ 156 rad/s; ripple at 2x, 4x filtered "
        "\"quite fast and accurate\"", no_independent, hdhil_free_motion, "`hdhil run`"),
    Row("[Taghirad97] Figs. 10-11", "10 Nm p-p, cancelled \"quite accurately\"",
        no_independent, hdhil_misalignment, "`hdhil run --scenario misalignment`"),
    Row("[Vertechy] Fig. 5", "≈ 17 Hz, c = 11.8 Nms/rad", independent_fig5, hdhil_fig5,
        "`hdhil run --scenario chirp --trace c.blf && hdhil identify c.blf`"),
    Row("[Vertechy] §VI gains", "k −18.3, −0.33, −2.81, 3.62; L 199, 19854, 289",
        independent_gains, hdhil_gains, "`hdhil design lqg`"),
    Row("[Vertechy] Fig. 7", "JTF1 \\|e\\| ≤ 0.3 Nm; JTF1 < JTF3 < JTF2", independent_fig7,
        hdhil_fig7, "`hdhil run --scenario lqg-tracking --compare-laws`; `hdhil run "
        "--scenario lqg-tracking-slow-link` (and `lqg-tracking-squared-weights`)"),
    Row("[Vertechy] Fig. 8", "e within ±0.5 Nm; τ̂l − τl^m ≈ ±3 Nm; τm within ±40 Nm",
        independent_fig8, hdhil_fig8, "`hdhil run --scenario lqg-experiment`", slow=True),
)  # fmt: skip

HEAD = ("paper figure", "paper", "independent (numpy/scipy)", "hdhil", "command")


def _cell(text: str) -> str:
    """Computed text as a Markdown table cell (pipes escaped)."""
    return text.replace("|", "\\|")


def cells(row: Row, *, project: bool = True) -> list[str]:
    """The row's five cells; with ``project`` False hdhil's cell is left empty (the cheap
    part, for the fast tier)."""
    return [
        row.figure,
        row.paper,
        _cell(row.independent()),
        _cell(row.hdhil()) if project else "",
        row.command,
    ]


def table(*, project: bool = True) -> str:
    """The whole table; the rows' commands run two at a time (each is its own process)."""
    with ThreadPoolExecutor(max_workers=2) as pool:
        body = list(pool.map(lambda r: cells(r, project=project), ROWS))
    lines = ["| " + " | ".join(HEAD) + " |", "|" + " --- |" * len(HEAD)]
    lines += ["| " + " | ".join(row) + " |" for row in body]
    return "\n".join(lines) + "\n"


def readme_table(text: str) -> str:
    """The table between the markers of README.md's text."""
    start = text.index(BEGIN)
    end = text.index(END, start)
    return text[start + len(BEGIN) : end].strip("\n") + "\n"


def readme_rows(text: str) -> list[list[str]]:
    """The README table's body rows, split into cells."""
    rows = []
    for line in readme_table(text).splitlines()[2:]:
        parts = [p.strip() for p in line.strip().strip("|").split(" | ")]
        rows.append(parts)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if README.md differs")
    args = parser.parse_args(argv)
    text = README.read_text(encoding="utf-8")
    new = table()
    if args.check:
        if readme_table(text) != new:
            print("README.md's fidelity table is out of date: python tools/docs/fidelity.py")
            return 1
        return 0
    start = text.index(BEGIN)
    end = text.index(END, start)
    # the layout of every generated block (tools/docs/figures.py): a blank line each side
    README.write_text(
        text[: start + len(BEGIN)] + "\n\n" + new + "\n" + text[end:], encoding="utf-8"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
