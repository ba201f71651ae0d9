"""What a run did: :class:`RunResult`, every figure computed from the run itself, and its
text report (:func:`format_result`, with the tracking table :func:`format_tracking`).

The figures the result takes from the nodes themselves (the controller's counters and
the health of its filter's covariance, the drive's counters, the names of the frames on
the buses) are read here, so the report and the ``hdhil run --json`` summary come from
one place. The run (:func:`hdhil.rig.runner.run_lockstep`) fills the result in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hdhil.can.busload import LOAD_LIMIT
from hdhil.dbc import CHANNEL_NUMBER, database
from hdhil.firmware.controller import ControllerNode
from hdhil.hostsim.drive import DriveNode
from hdhil.rig.evaluate import format_evaluation
from hdhil.rig.headline import format_headline
from hdhil.rig.realtime_stats import format_realtime
from hdhil.rig.verdict import format_verdict


@dataclass
class RunResult:
    """What a run did, every figure computed from the run itself."""

    scenario: str
    seed: int
    interface: str
    actuation: str
    cycles: int
    sample_period_s: float
    simulated_s: float
    wall_s: float
    interrupted: bool
    frames: dict[str, int]
    frames_total: int
    frames_sent: dict[str, int]
    startup_cycles: int
    stop_cycles: int
    worst_case_load: float
    bitrate: int
    torque: dict[str, float]
    velocity_final: float
    velocity_peak: float
    trace: str | None
    evaluation: dict[str, Any] | None = None
    tracking: dict[str, Any] | None = None
    faults: dict[str, int] | None = None
    controller: dict[str, Any] = field(default_factory=dict)
    drive: dict[str, Any] = field(default_factory=dict)
    realtime: dict[str, Any] | None = None
    #: Unix time of simulated time 0 in the trace (the wall clock at the run's start,
    #: or ``start_time``); ``None`` in real time on another interface than ``simbus``
    #: (:attr:`hdhil.rig.runner.RunPlan.clock_time`).
    start_time: float | None = None
    #: The per-cycle recording (:class:`hdhil.rig.evaluate.Recording`) when the run
    #: evaluated; not part of :meth:`as_dict`.
    recording: Any = field(default=None, repr=False)
    #: Why the run stopped before its planned end (:func:`hdhil.rig.verdict.stop_verdict`),
    #: ``None`` when it completed or was interrupted.
    verdict: dict[str, Any] | None = None
    #: The run's one figure (:func:`hdhil.rig.headline.headline`), None without one.
    headline: dict[str, Any] | None = None
    #: What the run's scenario scores (:attr:`hdhil.rig.scenario.Scenario.scored`).
    scored: tuple[str, ...] = ("ripple",)

    @property
    def real_time_factor(self) -> float:
        return self.simulated_s / self.wall_s if self.wall_s > 0 else float("inf")

    def as_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        del d["recording"]
        if d["verdict"] is None:
            del d["verdict"]  # a completed run: the summary keeps its keys
        d["real_time_factor"] = self.real_time_factor
        return d


def frame_names(drive_node_id: int = 2, controller_node_id: int = 1) -> dict[tuple[int, int], str]:
    """``(channel, identifier)`` -> ``"bus 0xID NAME"`` of every frame of the run's buses:
    the project DBCs, or for a drive or controller at other node-IDs the database of that
    layout (:func:`hdhil.canopen.rigdb.single_joint_databases`)."""
    if (drive_node_id, controller_node_id) == (2, 1):
        databases = {bus: database(bus) for bus in CHANNEL_NUMBER}
    else:
        from hdhil.canopen.rigdb import single_joint_databases

        databases = single_joint_databases(drive_node_id, controller_node_id)
    names = {}
    for bus, channel in CHANNEL_NUMBER.items():
        for msg in databases[bus].messages:
            names[(channel, msg.frame_id)] = f"{bus} 0x{msg.frame_id:03X} {msg.name}"
    return names


def controller_diagnostics(controller: ControllerNode) -> dict[str, Any]:
    """The controller's counters and the health of its filter's covariance (the
    firmware's own interrupt handler; a handler of the user's reports the counters)."""
    d = controller.diagnostics
    counters = {
        "syncs_sent": d.syncs_sent,
        "sensor_frames": d.sensor_frames,
        "malformed_frames": d.malformed_frames,
        "unknown_frames": sum(controller.unknown_frames.values()),
    }
    chain = getattr(controller.isr, "chain", None)
    if chain is None:
        return counters
    kalman = chain.kalman
    P = np.asarray(kalman.P)
    finite = bool(np.all(np.isfinite(P)))
    return {
        **counters,
        "filter_mode": controller.config.ripple.mode,
        "filter_states": int(P.shape[0]),
        "kalman_skipped": kalman.skipped,
        "tacho_rejections": d.tacho_rejections,
        "encoder_rejections": d.encoder_rejections,
        "tacho_reseeds": d.tacho_reseeds,
        "encoder_reseeds": d.encoder_reseeds,
        "plausibility_errors": d.plausibility_errors,
        "stuck_sensor_events": d.stuck_sensor_events,
        "stuck_tacho_events": d.stuck_tacho_events,
        "covariance_resets": getattr(kalman, "covariance_resets", 0),
        "covariance_finite": finite,
        "covariance_min_eigenvalue": (
            float(np.linalg.eigvalsh((P + P.T) / 2).min()) if finite else math.nan
        ),
        "covariance_asymmetry": float(np.abs(P - P.T).max()) if finite else math.nan,
    }


def drive_diagnostics(drive: DriveNode) -> dict[str, Any]:
    d = drive.diagnostics
    return {
        "syncs": d.syncs,
        "commands": d.commands,
        "malformed_frames": d.malformed_frames,
        "unknown_frames": sum(drive.unknown_frames.values()),
    }


def format_result(r: RunResult) -> str:
    t = r.torque
    lines = [
        f"hdhil run: scenario {r.scenario}, seed {r.seed}, "
        f"{'real time' if r.realtime is not None else 'lockstep'} on {r.interface}"
        f" ({r.actuation} actuation)" + ("  [INTERRUPTED]" if r.interrupted else ""),
        f"  simulated time     {r.simulated_s:.3f} s ({r.cycles} cycles of "
        f"{r.sample_period_s * 1e3:g} ms in operation; start-up {r.startup_cycles}, "
        f"stop {r.stop_cycles} cycles)",
        f"  wall time          {r.wall_s:.3f} s",
        f"  real-time factor   {r.real_time_factor:.1f}x",
        f"  motor velocity     final {r.velocity_final:.1f} rad/s, peak {r.velocity_peak:.1f} rad/s"
        " (telemetry)",
        format_headline(r.headline),
        "  frames on the buses:",
    ]
    lines += [f"    {name:<34} {n:>8}" for name, n in r.frames.items()]
    lines.append(f"    {'total':<34} {r.frames_total:>8}")
    verdict = "ok" if r.worst_case_load <= LOAD_LIMIT else "OVER the 60 % budget"
    lines.append(
        f"  control bus load   {r.worst_case_load:.1%} worst case at "
        f"{r.bitrate / 1e6:g} Mbit/s ({verdict})"
    )
    if "ripple" not in r.scored:
        pass  # the telemetry's torque is the law's estimate: no filter to score
    elif t["samples"]:
        lines.append(
            f"  whole run          {t['samples']} telemetry samples: RMS true torque "
            f"{t['rms_true']:.4f} Nm; RMS error raw {t['rms_error_raw']:.4f} Nm, filtered "
            f"{t['rms_error_filtered']:.4f} Nm ({t['filtered_to_raw']:.1%} of raw)"
        )
    else:
        lines.append("  whole run          no telemetry/truth pairs were seen")
    if r.faults is not None:
        injected = ", ".join(f"{kind} {n}" for kind, n in r.faults.items()) or "none"
        lines.append(f"  faults injected    {injected}")
    c = r.controller
    if c.get("tacho_rejections") or c.get("encoder_rejections") or c.get("plausibility_errors"):
        lines.append(
            f"  plausibility       replaced {c['tacho_rejections']} tacho samples and "
            f"{c['encoder_rejections']} encoder increments; {c['tacho_reseeds']} / "
            f"{c['encoder_reseeds']} accepted as a new level (tacho / encoder); "
            f"{c['plausibility_errors']} sensor errors (EMCY)"
        )
    if r.tracking is not None:
        lines.append(format_tracking([r.tracking]))
    if r.evaluation is not None:
        lines.append(format_evaluation(r.evaluation))
    if r.realtime is not None:
        lines.append(format_realtime(r.realtime))
    if r.trace:
        lines.append(f"  trace              {r.trace} ({r.frames_total} frames)")
    if r.verdict is not None:
        lines.append(f"  verdict            {format_verdict(r.verdict)}")
    return "\n".join(lines)


def format_tracking(rows: list[dict[str, Any]]) -> str:
    """The tracking table: per law, the error e against the desired torque on the true,
    the measured and the estimated torque; the observer's exogenous-torque estimate
    against its truth (τlgd, or τlg with Eq. 5) and against the true external torque
    τl + τg (the handle torque of [Vertechy]'s experiment); and the envelope of the
    commanded motor torque (:class:`hdhil.rig.score.TrackingScore`)."""
    nan = math.nan
    w = max([22, *(len(str(r["law"])) for r in rows)])
    lines = [
        "  torque tracking (e = torque − T_desired on the true, measured and estimated "
        "torque; τ̂: the observer's τlgd, τlg with Eq. 5)",
        f"    {'law':<{w}} {'e on':<9} {'max |e|/Nm':>10} {'RMS e/Nm':>9} {'|e|≤0.5':>8} "
        f"{'max |τ̂−τl|/Nm':>14} {'RMS τ̂ err/Nm':>13} {'max |τm|/Nm':>11} {'samples':>8}",
    ]
    for r in rows:
        lines.append(
            f"    {r['law']:<{w}} {'true':<9} {r['max_abs_error']:10.3f} {r['rms_error']:9.3f} "
            f"{100 * r.get('share_within_goal', nan):7.1f}% "
            f"{r.get('max_external_error', nan):14.3f} {r['rms_disturbance_error']:13.3f} "
            f"{r.get('max_abs_tau_m', nan):11.1f} {r['samples']:8d}"
        )
        for which in ("measured", "estimated"):
            lines.append(
                f"    {'':<{w}} {which:<9} {r.get(f'max_abs_error_{which}', nan):10.3f} "
                f"{r.get(f'rms_error_{which}', nan):9.3f} "
                f"{100 * r.get(f'share_within_goal_{which}', nan):7.1f}%"
            )
    return "\n".join(lines)
