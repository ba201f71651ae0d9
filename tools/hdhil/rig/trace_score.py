"""Score a trace as its run was scored: the one evaluation of ``hdhil evaluate`` and the API.

The trace's sidecar gives the run's request (:func:`hdhil.rig.sidecar.request_for_trace`):
its firmware configuration, what the scenario scores and from when. The ripple
evaluation replays the recording through :func:`hdhil.rig.evaluate.evaluate`, the same
function a live run calls on its own recording; the tracking figures come from the same
:class:`~hdhil.rig.score.TrackingScorer` the live run listens with, fed the trace's
frames. So ``hdhil run`` and ``hdhil evaluate`` of its trace print the same numbers,
headline first (:func:`hdhil.rig.headline.headline`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from hdhil.core.errors import UserError
from hdhil.firmware.config import FirmwareConfig
from hdhil.hostsim.plant import LinkMotionConfig
from hdhil.rig.evaluate import evaluate, recording_from_trace
from hdhil.rig.headline import headline
from hdhil.rig.sidecar import request_for_trace

__all__ = ["score_trace", "tracking_from_trace"]


def tracking_from_trace(
    trace: Path, fw: FirmwareConfig, skip_s: float, handle: LinkMotionConfig | None = None
) -> dict[str, Any] | None:
    """[Vertechy] tracking figures from the trace alone (desired torque and estimates from
    the controller's CTRL_TPDO2, truth from the truth channel), or None without
    torque-control telemetry.  ``handle``: the run's link (``[plant.link]``), whose
    bearing friction separates the handle torque from ``TRUTH_JOINT.tau_ext``
    (:class:`~hdhil.rig.score.TrackingScorer`)."""
    from hdhil.can.traces.reader import read_trace
    from hdhil.rig.score import TrackingScorer

    c = fw.control
    scorer = TrackingScorer(
        c.joint.Jl / c.joint.Jm, skip_s, c.friction.active, fw.sample_period_s, handle
    )
    with read_trace(trace) as frames:
        for msg in frames:
            scorer.on_message_received(msg)
    if not scorer.n:
        return None
    law = c.law.name.lower() if c.active else "(from trace)"
    return {"law": law, **scorer.result().as_dict()}


def score_trace(
    trace: Path, scenario: str | None = None, skip_s: float | None = None
) -> tuple[dict[str, Any], str]:
    """The evaluation of ``trace`` (as ``hdhil evaluate --json`` prints it) and the
    damage note of its reader ("" for an intact trace). ``scenario`` replaces the run
    recorded in the sidecar; ``skip_s`` the run's evaluation start."""
    request = request_for_trace(trace, scenario)
    if request is not None:
        request.require_one_joint("hdhil evaluate")  # a rig's scores: hdhil run
    fw = request.firmware if request is not None else FirmwareConfig()
    scored = request.scenario.scored if request is not None else ("ripple", "tracking")
    if skip_s is None:
        skip_s = request.evaluate_from_s if request is not None else 0.0
    rec, damage = recording_from_trace(trace, fw.sample_period_s)
    if len(rec) == 0:
        raise UserError(f"{trace}: no drive sensor frames (DRIVE_TPDO1) to evaluate")
    if not np.isfinite(rec.column("T_true")).any():
        raise UserError(
            f"{trace}: no ground truth (TRUTH_TORQUE frames on the truth channel); "
            "nothing to score against (`hdhil filter` runs the filter without truth)"
        )
    out: dict[str, Any] = evaluate(rec, fw, skip_s) if "ripple" in scored else {"skip_s": skip_s}
    handle = request.scenario.plant.link if request is not None else None
    tracking = tracking_from_trace(trace, fw, skip_s, handle) if "tracking" in scored else None
    if tracking is not None:
        out["tracking"] = tracking
    out["scored"] = list(scored)
    out["headline"] = headline(scored, out if "ripple" in scored else None, tracking, skip_s)
    return out, damage
