"""Score a trace as its run was scored: the one evaluation of ``hdhil evaluate`` and the API.

The trace's sidecar gives the run's request (:func:`hdhil.rig.sidecar.request_for_trace`):
its firmware configuration, what the scenario scores and from when. The ripple
evaluation replays the recording through :func:`hdhil.rig.evaluate.evaluate`, the same
function a live run calls on its own recording; the tracking figures come from the same
:class:`~hdhil.rig.score.TrackingScorer` the live run listens with, fed the trace's
frames. So ``hdhil run`` and ``hdhil evaluate`` of its trace print the same numbers,
headline first (:func:`hdhil.rig.headline.headline`).

A rig's trace (:mod:`hdhil.rig.rigrun`) is scored per joint by the scorers its run
listened with (:func:`hdhil.rig.rigrun.joint_scoring`), each fed the trace's frames of
its joint's bus and the truth (:func:`score_rig_trace`): the run's table per joint and
its worst joint, to the last bit.
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
from hdhil.rig.request import RunRequest
from hdhil.rig.sidecar import request_for_trace

__all__ = ["score_rig_trace", "score_trace", "tracking_from_trace"]

#: Frames handed to the scorers in one call while a rig's trace is read.
_BATCH = 4096


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
    if request is not None and request.scenario.is_rig:
        return score_rig_trace(trace, request, skip_s)
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


def score_rig_trace(
    trace: Path, request: RunRequest, skip_s: float | None = None
) -> tuple[dict[str, Any], str]:
    """The scores per joint of a rig's trace and the damage note of its reader ("" for an
    intact trace): each joint's scorers as its run built them
    (:func:`hdhil.rig.rigrun.joint_scoring`, at the joint's identifiers from the layout,
    :func:`~hdhil.rig.rigrun.joint_links`) fed the frames of its bus's channel and the
    truth in the trace's order, then the worst joint. The tracking counts from
    ``skip_s`` (default: the run's evaluation start), the torque from the first frame, as
    in the run. ``hdhil run`` prints the same figures for the run that wrote ``trace``."""
    from hdhil.can.traces.reader import read_trace
    from hdhil.rig.rigrun import (
        JointScores,
        bus_channel,
        candidates_scored,
        joint_links,
        joint_scoring,
        scored_channels,
        worst_joint,
    )

    s = request.scenario
    skip = request.evaluate_from_s if skip_s is None else skip_s
    bus_index = {name: i for i, (name, _) in enumerate(s.buses)}
    specs = dict(s.buses)
    scorings = []
    deliver = []
    for index, (spec, link) in enumerate(zip(s.joints, joint_links(s), strict=True)):
        scoring = joint_scoring(request, index, link, skip, candidates=candidates_scored(s))
        scorings.append(scoring)
        deliver += [x.on_frames for x in scoring.listeners(scored_channels(bus_index[spec.bus]))]
    with read_trace(trace) as frames:
        batch: list[Any] = []
        for msg in frames:
            batch.append(msg)
            if len(batch) >= _BATCH:
                for on_frames in deliver:
                    on_frames(batch)
                batch = []
        for on_frames in deliver:
            on_frames(batch)
        damage = "; ".join(d.describe(str(trace)) for d in frames.damage)
    rows = []
    for index, (spec, scoring) in enumerate(zip(s.joints, scorings, strict=True)):
        torque, tracking = scoring.results()
        rows.append(JointScores(spec.name, spec.bus, spec.node_id, spec.controller_node_id,
                                index, torque, tracking, scoring.evaluation()))  # fmt: skip
    if not any(r.torque["samples"] for r in rows):
        raise UserError(
            f"{trace}: no joint's telemetry with its ground truth (CTRL_TPDO1 and "
            "TRUTH_TORQUE frames of the rig's layout); nothing to score"
        )
    out = {
        "scenario": s.name,
        "seed": request.seed,
        "skip_s": skip,
        "scored": list(s.scored),
        "buses": {name: {"channel": bus_channel(i), "fd": specs[name].fd,
                         "joints": [j.name for j in s.joints if j.bus == name]}
                  for name, i in bus_index.items() if any(j.bus == name for j in s.joints)},
        "joints": [dict(r.__dict__) for r in rows],
        "worst_joint": worst_joint(rows, "ripple" in s.scored),
    }  # fmt: skip
    return out, damage
