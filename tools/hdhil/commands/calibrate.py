"""``hdhil calibrate``: calibrate the emulated torque sensor and write the calibration file."""

from __future__ import annotations

import argparse
import math

from hdhil.commands.progress import add_quiet_argument, progress
from hdhil.core import jsonout
from hdhil.core.errors import UserError
from hdhil.core.files import (
    AtomicOutput,
    atomic_path,
    check_output,
    commit_outputs,
    discard_outputs,
)
from hdhil.core.numbers import arg_int
from hdhil.hostsim.calibration import CalibrationRig, calibrate
from hdhil.rig.calibration import (
    GOAL,
    format_result,
    write_calibration,
)
from hdhil.rig.scenario import list_scenarios, load_scenario


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate the emulated torque sensor (arm and weights, [Taghirad97] §3)",
        description="Emulate the torque-sensor calibration of [Taghirad97] §3 on a scenario's "
        "drive: wave generator locked, known torques loaded and unloaded in both directions "
        "at several flexspline positions, low range (5 Nm) and full range (40 Nm).  Prints "
        "the gain (mean of the least-squares slopes), the consistency measure (std / mean) "
        "and, since this is an emulator, the sensor's true gain and the error.",
    )
    p.add_argument(
        "--scenario",
        default="free-motion",
        help="scenario name or TOML file whose drive is calibrated "
        f"(default: %(default)s; shipped: {', '.join(list_scenarios())})",
    )
    p.add_argument(
        "--seed",
        type=arg_int(0, 2**63 - 1),
        default=None,
        help="noise seed (default: the scenario's)",
    )
    p.add_argument(
        "--positions",
        type=arg_int(1, 1000),
        default=CalibrationRig.positions,
        help="flexspline positions; two experiments each (default: %(default)s)",
    )
    p.add_argument(
        "--samples",
        type=arg_int(1, 10_000_000),
        default=CalibrationRig.samples,
        help="ADC samples averaged per load step (default: %(default)s)",
    )
    p.add_argument(
        "--lever-error",
        type=float,
        default=CalibrationRig.lever_error,
        metavar="FRACTION",
        help="relative standard deviation of the arm's effective length per mounting "
        "(default: %(default)s; 0.02 reproduces [Taghirad97] Table 1's 2 %% consistency)",
    )
    p.add_argument(
        "--plot",
        metavar="FIG.png",
        default=None,
        help="draw [Taghirad97] Figs. 6-7 (torque against bridge voltage per experiment, "
        "low range and full range) into FIG (.png, .pdf, .svg)",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    add_quiet_argument(p)
    p.add_argument(
        "--out",
        metavar="FILE",
        default=None,
        help="write the calibrated gain as a firmware override ([firmware.calibration] "
        "volt2Nm; JSON if FILE ends in .json, else TOML)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    seed = scenario.seed if args.seed is None else args.seed
    if seed < 0:
        raise UserError(f"--seed must be >= 0, got {seed}")
    try:
        rig = CalibrationRig(
            positions=args.positions, samples=args.samples, lever_error=args.lever_error
        )
    except ValueError as exc:
        msg = str(exc).replace("CalibrationRig.", "--")
        raise UserError(msg) from None
    if args.out:
        check_output(args.out, "--out")  # before the work, not after
    from hdhil.commands.options import check_outputs, scenario_inputs

    check_outputs([(args.out, "--out"), (args.plot, "--plot")], scenario_inputs(args))
    total = rig.positions * len(rig.ranges_Nm)
    with progress(args, total, "hdhil calibrate", "experiment") as bar:
        result = calibrate(scenario.plant, rig, seed, on_experiment=lambda n, _t: bar.update_to(n))
        bar.update_to(total)
    if not math.isfinite(result.gain_Nm_per_V):
        raise UserError("the calibration gave no finite gain (is the torque channel saturated?)")
    # --plot and --out land together or not at all (a full disk: neither replaced)
    outputs: list[AtomicOutput] = []
    try:
        if args.plot:
            outputs.append(AtomicOutput(args.plot, "--plot", open_file=False, deferred=True))
            _plot(args.plot, result, scenario.name, outputs[-1])
        if args.out:
            outputs.append(AtomicOutput(args.out, "--out", deferred=True))
            write_calibration(args.out, result, scenario.name, deferred=outputs[-1])
        commit_outputs(outputs)
    except BaseException:
        discard_outputs(outputs)
        raise
    if args.json:
        out = result.as_dict()
        out.update(
            scenario=scenario.name,
            consistency_pct=100 * result.consistency,
            error_pct=100 * result.error,
            within_goal=abs(result.error) <= GOAL,
            out=args.out,
        )
        print(jsonout.dumps(out, indent=2))
    else:
        print(format_result(result, scenario.name))
        if args.out:
            gain = result.gain_Nm_per_V
            print(f"  wrote {args.out}: [firmware.calibration] volt2Nm = {gain:.6g}")
        if args.plot:
            print(f"  wrote {args.plot}: [Taghirad97] Figs. 6-7")
    return 0


def _plot(path: str, result: object, scenario: str, deferred: AtomicOutput) -> None:
    """[Taghirad97] Figs. 6-7 into ``path``
    (:func:`hdhil.analysis.paper_figures.make_calibration_figure`)."""
    from pathlib import Path

    from hdhil.analysis.paper_figures import make_calibration_figure
    from hdhil.analysis.ripple_figures import FORMATS

    out = Path(path)
    if out.suffix.lower() not in FORMATS:
        raise UserError(f"--plot {path}: use one of {', '.join(FORMATS)}")
    check_output(out, "--plot")  # a regular file or a new one, in an existing directory
    r = result
    title = (
        f"hdhil calibrate: scenario {scenario}, seed {r.seed}: gain {r.gain_Nm_per_V:.4f} N·m/V, "  # type: ignore[attr-defined]
        f"consistency {100 * r.consistency:.2f} % ([Taghirad97] Table 1: 6.60 N·m/V, 2 %)"  # type: ignore[attr-defined]
    )
    fig = make_calibration_figure(result, title)
    try:
        with atomic_path(out, "--plot", deferred=deferred) as tmp:
            fig.savefig(tmp, dpi=100)
    except (OSError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise UserError(f"--plot {path}: cannot write ({reason})") from None
