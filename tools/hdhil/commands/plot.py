"""``hdhil plot TRACE --out FIG.png``: the papers' torque figures drawn from a trace:
[Taghirad97] Figs. 8-11 (:mod:`hdhil.analysis.ripple_figures`, the default) or, with
``--figure fig8``, [Vertechy] Fig. 8 (:mod:`hdhil.analysis.paper_figures`).

This module reads the options, finds the trace's scenario (``--scenario`` or the
sidecar), titles the figure and writes it through the output helper.  Exit codes: 0
written, 1 written from a damaged trace, 2 input error (one line).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

from hdhil.analysis.ripple_figures import FORMATS, has_misalignment, make_figure, plot_data
from hdhil.can.traces.sidecar import read_metadata
from hdhil.core.errors import UserError
from hdhil.core.files import atomic_path, check_output, display_name
from hdhil.core.numbers import arg_seconds
from hdhil.firmware.config import FirmwareConfig


# -------------------------------------------------------------------------------- CLI
def _check_out(path: Path) -> None:
    if path.suffix.lower() not in FORMATS:
        raise UserError(
            f"--out {path}: unsupported figure format {path.suffix or '(no extension)'!r}; "
            f"use {', '.join(FORMATS)}"
        )
    check_output(path, "--out")  # a regular file or a new one, in an existing directory


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``hdhil plot`` to the command line."""
    p = subparsers.add_parser(
        "plot",
        help="draw the seed's torque figures (Figs. 8-11) from a trace",
        description="Measured torque and velocity, the torque spectrum at constant speed "
        "with 2x/4x velocity markers, measured vs filtered (and true) torque, and the "
        "misalignment view against the output angle ([Taghirad97] Figs. 8-11).",
    )
    p.add_argument("trace", type=Path, help="trace file (.blf, .asc, .log, .csv, .trc)")
    p.add_argument(
        "--out", type=Path, required=True, metavar="FIG.png", help="figure file (.png, .pdf, .svg)"
    )
    p.add_argument(
        "--scenario",
        default=None,
        help="scenario whose firmware configuration the trace was recorded with "
        "(default: the one in the trace's sidecar TRACE.json, else the firmware defaults)",
    )
    p.add_argument(
        "--figure",
        choices=("ripple", "fig8"),
        default="ripple",
        help="ripple: [Taghirad97] Figs. 8-11 (default); fig8: [Vertechy] Fig. 8, the four "
        "panels of the LQG experiment (needs a torque-control trace, e.g. scenario "
        "lqg-experiment)",
    )
    p.add_argument(
        "--window",
        nargs=2,
        type=arg_seconds(lo_open=False),
        metavar=("T0", "T1"),
        default=None,
        help="time window (s) of the spectrum (default: the flattest 0.3 s of velocity)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``hdhil plot``: 0 written, 1 written from a damaged trace (2 via UserError)."""
    from hdhil.commands.options import check_outputs, scenario_inputs, trace_inputs
    from hdhil.rig.evaluate import recording_from_trace
    from hdhil.rig.sidecar import request_for_trace

    _check_out(args.out)
    check_outputs([(args.out, "--out")], [*trace_inputs(args.trace), *scenario_inputs(args)])
    request = request_for_trace(args.trace, args.scenario)
    meta = read_metadata(args.trace) or {}
    if isinstance(meta.get("rig"), dict) or (request is not None and request.scenario.is_rig):
        return _run_rig(args, request, meta)
    scenario = request.scenario if request is not None else None
    if args.figure == "fig8":
        return _run_fig8(args, scenario)
    fw = scenario.firmware if scenario is not None else FirmwareConfig()
    rec, damage = recording_from_trace(args.trace, fw.sample_period_s)
    data = plot_data(rec, fw)
    name = scenario.name if scenario else "(firmware defaults)"
    truth = "with ground truth" if data.T_true is not None else "no ground truth"
    run = _run_words(meta)
    trace_name = display_name(args.trace.name)  # a figure's text must be valid Unicode
    title = (
        f"{trace_name}: scenario {name}{run}, {len(data)} samples, {data.mode} filter, "
        f"{truth}\nafter [Taghirad97] (Taghirad, CIM-TR-97-06) Figs. 8-11"
    )
    window = tuple(args.window) if args.window is not None else None
    fig = make_figure(
        data,
        title,
        window,  # type: ignore[arg-type]
        misalignment=has_misalignment(scenario) if scenario is not None else None,
        steady_from_s=scenario.evaluate_from_s if scenario is not None else None,
    )
    return _save(fig, args.out, damage)


def _run_words(meta: dict[str, Any]) -> str:
    """The run's seed and start time from the trace's sidecar, for a figure's title."""
    run = ""
    if meta.get("seed") is not None:
        run += f", seed {meta['seed']}"
    if meta.get("start_time_utc"):
        run += f", recorded {meta['start_time_utc']}"
    return run


def _run_rig(args: argparse.Namespace, request: Any, meta: dict[str, Any]) -> int:
    """``hdhil plot`` of a rig's trace: one row per joint (:func:`hdhil.analysis.
    ripple_figures.make_rig_figure`), each joint decoded at its own identifiers on its
    bus's channel with its own truth (:func:`hdhil.rig.evaluate.rig_recordings_from_trace`)
    and drawn with its own firmware configuration."""
    from hdhil.analysis.ripple_figures import JointRow, configs_have_misalignment, make_rig_figure
    from hdhil.rig.evaluate import rig_recordings_from_trace
    from hdhil.rig.rigrun import rig_metadata

    if args.figure == "fig8":
        raise UserError(
            f"{display_name(str(args.trace))}: --figure fig8 draws one joint's torque-control "
            "run; a rig's trace is drawn per joint by the default figure (--figure ripple)"
        )
    if request is None or not request.scenario.is_rig:
        given = f"scenario {request.name} is a single joint" if request else "no scenario"
        raise UserError(
            f"{display_name(str(args.trace))}: the trace's sidecar lays out a rig of several "
            f"joints, but {given}; give the rig's scenario (--scenario) or leave it out"
        )
    scenario = request.scenario
    rig = meta["rig"] if isinstance(meta.get("rig"), dict) else rig_metadata(request, 0.0)["rig"]
    try:
        joints, damage = rig_recordings_from_trace(
            args.trace, rig, scenario.firmware.sample_period_s
        )
    except ValueError as exc:
        raise UserError(f"{display_name(str(args.trace))}: {exc}") from None
    configs = {j.name: cfg for j, cfg in zip(scenario.joints, scenario.joint_configs, strict=True)}
    rows = []
    for joint in joints:
        if joint.name not in configs:
            raise UserError(
                f"{display_name(str(args.trace))}: joint {joint.name} of the trace is not a "
                f"joint of scenario {scenario.name} ({', '.join(configs)})"
            )
        plant, fw = configs[joint.name]
        try:
            data = plot_data(joint.recording, fw)
        except UserError as exc:
            raise UserError(f"joint {joint.name}: {exc}") from None
        truth = "with ground truth" if data.T_true is not None else "no ground truth"
        rows.append(JointRow(
            f"joint {joint.name}: bus {joint.bus}, node-ID {joint.node_id}; {len(data)} "
            f"samples, {data.mode} filter, {truth}",
            data, configs_have_misalignment(plant, fw), scenario.evaluate_from_s or None,
        ))  # fmt: skip
    buses = sorted({j.bus for j in joints})
    title = (
        f"{display_name(args.trace.name)}: scenario {scenario.name}{_run_words(meta)}, "
        f"{len(rows)} joints on {len(buses)} bus{'es' if len(buses) != 1 else ''} "
        f"({', '.join(buses)}), one row per joint\n"
        "after [Taghirad97] (Taghirad, CIM-TR-97-06) Figs. 8-11"
    )
    window = tuple(args.window) if args.window is not None else None
    fig = make_rig_figure(rows, title, window)  # type: ignore[arg-type]
    return _save(fig, args.out, damage)


def _save(fig: Figure, out: Path, damage: object) -> int:
    """Write ``fig`` to ``out`` through the output helper (a regular file, replaced
    atomically); exit code 1 when the trace was damaged, else 0."""
    try:
        with atomic_path(out, "--out") as tmp:
            fig.savefig(tmp, dpi=100)
    except (OSError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise UserError(f"--out {out}: cannot write ({reason})") from None
    print(f"hdhil plot: wrote {out}")
    if damage:
        print(f"hdhil: warning: {damage}", file=sys.stderr)
        return 1
    return 0


def _run_fig8(args: argparse.Namespace, scenario: Any) -> int:
    """``hdhil plot --figure fig8``: [Vertechy] Fig. 8 (:mod:`hdhil.analysis.paper_figures`)."""
    from hdhil.analysis.paper_figures import fig8_data, make_fig8

    data, damage = fig8_data(args.trace, scenario.plant.link if scenario is not None else None)
    skip = scenario.evaluate_from_s if scenario is not None else 0.0
    name = scenario.name if scenario else "(not given)"
    trace_name = display_name(args.trace.name)
    start = f"from t >= {skip:g} s (start-up not drawn)" if skip > 0 else "whole run"
    title = (
        f"{trace_name}: scenario {name}, {len(data)} samples; {start}, legend figures "
        "over the samples drawn\n"
        "after [Vertechy] (Vertechy et al.) Fig. 8, seed sign convention"
    )
    fig = make_fig8(data, title, skip)
    return _save(fig, args.out, damage)
