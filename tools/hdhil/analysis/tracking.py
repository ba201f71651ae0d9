"""The torque-control tracking figures of a recorded run, from its trace alone
([Vertechy]: e = τs − τsD, the external-torque estimate against the handle's torque,
the motor torque's envelope).

:func:`tracking_from_trace` replays the trace through :class:`hdhil.rig.score.TrackingScorer`:
the desired torque and the estimates come from the controller's ``CTRL_TPDO2``
telemetry, the truth from the truth channel; the firmware configuration supplies the
joint's Jl/Jm and whether the law compensates the friction (Eq. 5).  ``hdhil evaluate``
adds the result to its filter scores.
"""

from __future__ import annotations

from pathlib import Path

from hdhil.firmware.config import FirmwareConfig

__all__ = ["tracking_from_trace"]


def tracking_from_trace(trace: Path, fw: FirmwareConfig, skip_s: float) -> dict | None:
    """[Vertechy] tracking figures from the trace alone (desired torque and estimates from
    the controller's CTRL_TPDO2, truth from the truth channel), or None without
    torque-control telemetry.  The joint's Jl/Jm and whether the law compensates the
    friction (Eq. 5) come from ``fw``; samples before ``skip_s`` are left out."""
    from hdhil.can.tracefile import read_trace
    from hdhil.rig.score import TrackingScorer, trace_time_offset

    c = fw.control
    scorer = TrackingScorer(
        c.joint.Jl / c.joint.Jm, skip_s, c.friction.active, trace_time_offset(trace)
    )
    with read_trace(trace) as frames:
        for msg in frames:
            scorer.on_message_received(msg)
    if not scorer.n:
        return None
    law = c.law.name.lower() if c.active else "(from trace)"
    return {"law": law, **scorer.result().as_dict()}
