"""The headline figure of a run or a trace: one number, computed in one place.

A ripple-filter scenario is judged by the RMS error of the torque the firmware filtered
against the true torque, from the scenario's evaluation start (the evaluation's
``firmware`` row, :func:`hdhil.rig.evaluate.evaluate`); a torque-control scenario by the
RMS tracking error ``e = T_true − T_desired`` from the same start
(:class:`hdhil.rig.score.TrackingScore`). What a scenario scores is its own choice
(:attr:`hdhil.rig.scenario.Scenario.scored`). ``hdhil run``, ``hdhil evaluate``, the
Python API, campaigns and ``soak`` all print this one figure, so the same trace gives
the same headline everywhere.
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ["candidate_row", "format_headline", "headline"]


def candidate_row(evaluation: dict[str, Any] | None, prefix: str) -> dict[str, Any] | None:
    """The evaluation's row whose candidate name starts with ``prefix`` (``"firmware"``:
    the filter the firmware ran; ``"raw"``: the unfiltered measurement), or None."""
    for row in (evaluation or {}).get("candidates") or ():
        if str(row.get("name", "")).startswith(prefix):
            return row
    return None


def headline(
    scored: tuple[str, ...],
    evaluation: dict[str, Any] | None,
    tracking: dict[str, Any] | None,
    from_s: float,
) -> dict[str, Any] | None:
    """The headline of a run: what is scored first (``scored[0]``) with its figure, or
    None when the run has none to give (no evaluation, no samples after ``from_s``)."""
    for kind in scored:
        if kind == "tracking" and tracking is not None and tracking.get("samples"):
            return {
                "quantity": "tracking error RMS",
                "value_Nm": float(tracking["rms_error"]),
                "max_abs_Nm": float(tracking["max_abs_error"]),
                "from_s": from_s,
                "samples": int(tracking["samples"]),
            }
        row = candidate_row(evaluation, "firmware")
        if kind == "ripple" and row is not None and evaluation and evaluation.get("samples"):
            ratio = row.get("rms_ratio")
            return {
                "quantity": "filtered torque RMS error",
                "value_Nm": float(row["rms_error"]),
                "to_raw": None if ratio is None or math.isnan(ratio) else float(ratio),
                "from_s": from_s,
                "samples": int(evaluation["samples"]),
            }
    return None


def format_headline(h: dict[str, Any] | None) -> str:
    """One line: the figure, its share of the raw error or its peak, the window."""
    if h is None:
        return "  headline           none (no evaluated samples: run longer, or evaluate)"
    if h["quantity"] == "tracking error RMS":
        extra = f"max |e| {h['max_abs_Nm']:.4f} Nm"
    else:
        ratio = h.get("to_raw")
        extra = f"{ratio:.1%} of raw" if ratio is not None else "no raw reference"
    return (
        f"  headline           {h['quantity']} {h['value_Nm']:.4f} Nm ({extra}); "
        f"{h['samples']} samples from {h['from_s']:g} s"
    )
