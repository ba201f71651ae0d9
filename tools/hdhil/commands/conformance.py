"""``hdhil conformance``: the CiA 301 + CiA 402 conformance and timing suite against one
node on any python-can interface (:mod:`hdhil.conformance`; docs/conformance.md).

Here: the options, the EDS/DCF, the bus, progress, the report and the exit code (0 all
cases passed or were skipped, 1 a case failed, 2 bad input)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from hdhil.commands.options import add_bus_options, open_bus, refuse_simbus
from hdhil.commands.progress import add_quiet_argument, progress
from hdhil.core.errors import UserError
from hdhil.core.files import check_input, check_output, write_text
from hdhil.core.numbers import arg_float, arg_int

if TYPE_CHECKING:
    from canopen.objectdictionary import ObjectDictionary


def _groups(values: list[str] | None) -> tuple[str, ...]:
    from hdhil.conformance import GROUPS

    out: list[str] = []
    for value in values or ():
        for name in filter(None, (v.strip() for v in value.split(","))):
            if name not in GROUPS:
                raise UserError(f"unknown group {name!r}; the groups: {', '.join(GROUPS)}")
            out.append(name)
    return tuple(out)


def _object_dictionary(text: str | None, node_id: int) -> tuple[ObjectDictionary, str]:
    import canopen

    from hdhil.dbc import eds_path

    path = eds_path("drive") if text is None else check_input(text, "EDS/DCF")
    try:
        return canopen.import_od(str(path), node_id), Path(path).name
    except Exception as exc:  # canopen raises what its parsers raise
        raise UserError(f"EDS/DCF {path}: cannot be read ({type(exc).__name__}: {exc})") from None


def run_conformance(args: argparse.Namespace) -> int:
    import logging

    from hdhil.conformance import Options, build_cases, junit_xml, run_suite, text_report

    refuse_simbus(args, "conformance")
    only, skip = _groups(args.only), _groups(args.skip)
    if args.junit is not None:
        check_output(args.junit, "--junit")
    od, name = _object_dictionary(args.eds, args.node)
    try:
        options = Options(node_id=args.node, master_id=args.master_id,
                          motion=not args.no_motion, only=only, skip=skip,
                          retries=args.retries,
                          boot_timeout_s=args.boot_timeout)  # fmt: skip
    except ValueError as exc:
        raise UserError(str(exc)) from None
    cases = build_cases(od, options)
    if not cases:
        raise UserError("no case selected (--only/--skip leave no group)")
    bus, _ = open_bus(args, "control bus")
    canopen_log = logging.getLogger("canopen")
    level = canopen_log.level
    canopen_log.setLevel(logging.CRITICAL)  # the suite reports the aborts it provokes
    try:
        with progress(args, len(cases), "conformance", unit="case") as bar:

            def told(outcome: object) -> None:
                bar.describe(outcome.case.group)  # type: ignore[attr-defined]
                bar.advance()

            result = run_suite(bus, od, options, name, told, cases)
    finally:
        canopen_log.setLevel(level)
        bus.shutdown()
    sys.stdout.write(text_report(result, verbose=args.verbose))
    if args.junit is not None:
        write_text(args.junit, junit_xml(result), "--junit")
    return 0 if result.ok else 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "conformance",
        help="CiA 301 + CiA 402 conformance and timing suite against a node",
        description="Run the CiA 301 + CiA 402 conformance and timing cases against one "
        "node, driven by its EDS or DCF. Exit 0 when every case passed (or was skipped), "
        "1 when any failed, 2 on bad input.",
    )
    add_bus_options(p, title="control bus (python-can; else CAN_INTERFACE, CAN_CHANNEL, "
                    "CAN_BITRATE, then python-can's configuration file)")  # fmt: skip
    p.add_argument("--node", type=arg_int(1, 127), default=2,
                   help="node-ID under test (default 2, the emulated drive)")  # fmt: skip
    p.add_argument("--eds", metavar="FILE", default=None,
                   help="the node's EDS or DCF (default: the shipped drive.eds)")  # fmt: skip
    p.add_argument("--master-id", type=arg_int(1, 127), default=1,
                   help="node-ID of the heartbeat the suite produces for the node's "
                   "consumer 0x1016 (default 1)")  # fmt: skip
    p.add_argument("--only", action="append", metavar="GROUPS",
                   help="run these groups only (comma-separated; repeatable)")  # fmt: skip
    p.add_argument("--skip", action="append", metavar="GROUPS",
                   help="leave these groups out (comma-separated; repeatable)")  # fmt: skip
    p.add_argument("--no-motion", action="store_true",
                   help="never command enable operation: the power stage stays off "
                   "(for a drive on a machine)")  # fmt: skip
    p.add_argument("--retries", type=arg_int(0, 10), default=1,
                   help="run a failed case again up to this many times, from a reset node; "
                   "it passes if a retry does, and the report says so (default 1)")  # fmt: skip
    p.add_argument("--boot-timeout", type=arg_float(0.01, 60.0), default=3.0, metavar="S",
                   help="how long to wait for the node's boot-up message after an NMT "
                   "reset (default 3 s); a node that never boots fails every case after "
                   "one wait")  # fmt: skip
    p.add_argument("--junit", metavar="FILE", default=None, help="write JUnit XML here")
    p.add_argument("--verbose", "-v", action="store_true",
                   help="list every case, not only the failed ones")  # fmt: skip
    add_quiet_argument(p)
    p.set_defaults(func=run_conformance)
