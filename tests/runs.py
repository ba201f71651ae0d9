"""A lockstep run in a test: a scenario (name, path or typed) and the run's settings,
resolved into a :class:`hdhil.rig.request.RunRequest` as ``hdhil run`` resolves its
options, then run by :func:`hdhil.rig.runner.run_lockstep`."""

from __future__ import annotations

from typing import Any

from hdhil.rig.request import resolve
from hdhil.rig.result import RunResult
from hdhil.rig.runner import run_lockstep


def lockstep(
    scenario: Any = "free-motion",
    duration_s: float | None = None,
    seed: int | None = None,
    trace: Any = None,
    interface: str | None = "simbus",
    actuation: str | None = None,
    bitrate: int | None = None,
    channel: str | None = None,
    *,
    evaluate_skip_s: float | None = None,
    layout: Any = None,
    **run: Any,
) -> RunResult:
    request = resolve(
        scenario,
        duration_s=duration_s,
        seed=seed,
        evaluate_from_s=evaluate_skip_s,
        actuation=actuation,
        bitrate=bitrate,
        layout=layout,
    )
    return run_lockstep(request, trace=trace, interface=interface, channel=channel, **run)
