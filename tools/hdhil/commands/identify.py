"""``hdhil identify TRACE``: the flexible joint's natural frequency and damping from a
trace of an open-loop chirp (``hdhil run --scenario chirp``), [Vertechy] Fig. 5.

The analysis is :mod:`hdhil.analysis.identification`; this module reads the options,
takes the firmware configuration, the actuator's torque per volt and the inertias from
the scenario (or ``--torque-per-volt``/``--inertias``), and prints the summary or JSON
(``--plot``: the Bode plot).  Exit codes: 0 done, 1 done on a damaged trace, 2 input
error (one line).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from hdhil.analysis.identification import (
    DEFAULT_SEGMENT_S,
    chirp_data_from_trace,
    format_identification,
    identify,
    make_figure,
    model_values,
)
from hdhil.commands.progress import add_quiet_argument, progress
from hdhil.core import jsonout
from hdhil.core.errors import UserError
from hdhil.core.files import atomic_path, check_output
from hdhil.core.numbers import FLOAT32_MAX, arg_float, arg_seconds
from hdhil.rig.scenario import list_scenarios, load_scenario


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "identify",
        help="natural frequency and damping of the joint from a chirp trace ([Vertechy] Fig. 5)",
        description="Estimate the frequency response sensor torque / motor torque command "
        "(Welch H1) from a trace of an open-loop chirp (hdhil run --scenario chirp), and the "
        "joint's natural frequency, damping ratio and damping coefficient by the half-power "
        "bandwidth method, cross-checked by the logarithmic decrement ([Vertechy] §II).",
    )
    p.add_argument("trace", type=Path, help="trace written by hdhil run")
    p.add_argument(
        "--scenario",
        default="chirp",
        help="scenario of the run: firmware calibration, DAC, actuator torque per volt, "
        f"inertias (default: %(default)s; shipped: {', '.join(list_scenarios())})",
    )
    p.add_argument(
        "--torque-per-volt",
        type=arg_float(-FLOAT32_MAX, FLOAT32_MAX),
        default=None,
        metavar="NM_PER_V",
        help="motor torque at the output per DAC volt (default: the scenario's)",
    )
    p.add_argument(
        "--inertias",
        type=arg_float(0.0, FLOAT32_MAX, lo_open=True),
        nargs=2,
        default=None,
        metavar=("JM", "JL"),
        help="motor and link inertia reduced to the output, kg m² (default: the scenario's)",
    )
    p.add_argument(
        "--segment",
        type=arg_seconds(),
        default=DEFAULT_SEGMENT_S,
        metavar="S",
        help="Welch segment length in s (default: %(default)s)",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    add_quiet_argument(p)
    p.add_argument("--plot", type=Path, default=None, metavar="FIG", help="write the Bode plot")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    firmware = scenario.firmware
    plant = scenario.plant
    per_volt = plant.torque_per_volt if args.torque_per_volt is None else args.torque_per_volt
    if not (math.isfinite(per_volt) and per_volt != 0.0):
        raise UserError(f"--torque-per-volt must be a non-zero number, got {per_volt!r}")
    jm, jl = (
        (plant.drivetrain.J_motor, plant.drivetrain.J_load)
        if args.inertias is None
        else tuple(args.inertias)
    )
    if args.plot is not None and args.plot.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise UserError(f"--plot {args.plot}: use a .png, .pdf or .svg file name")
    if args.plot is not None:
        check_output(args.plot, "--plot")
        from hdhil.commands.options import check_outputs, scenario_inputs, trace_inputs

        check_outputs([(args.plot, "--plot")], [*trace_inputs(args.trace), *scenario_inputs(args)])
    from hdhil.commands.options import require_raw_sensor_frames

    require_raw_sensor_frames(args.trace, "identify")
    with progress(args, 3 if args.plot is not None else 2, "hdhil identify", "step") as bar:
        bar.describe("hdhil identify: reading the trace")
        data = chirp_data_from_trace(args.trace, firmware, per_volt)
        bar.advance()
        bar.describe("hdhil identify: frequency response and fits")
        ident = identify(data, jm, jl, args.segment, model_values(plant))
        bar.advance()
        if args.plot is not None:
            bar.describe("hdhil identify: plotting")
            try:
                with atomic_path(args.plot, "--plot") as tmp:
                    make_figure(ident).savefig(tmp, dpi=100)
            except OSError as exc:
                reason = exc.strerror or exc
                raise UserError(f"--plot {args.plot}: cannot write ({reason})") from None
            bar.advance()
    if args.json:
        out = ident.as_dict()
        out.update(trace=str(args.trace), scenario=scenario.name, plot=args.plot and str(args.plot))
        jsonout.dump(out, sys.stdout, indent=2)
        print()
    else:
        print(format_identification(ident, f"{args.trace} (scenario {scenario.name})"))
        if args.plot is not None:
            print(f"  plot               {args.plot}")
    if data.damage:
        print(f"hdhil: warning: {data.damage}", file=sys.stderr)
        return 1
    return 0
