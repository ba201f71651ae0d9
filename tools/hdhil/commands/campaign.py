"""``hdhil campaign``: a grid of scenario variants in parallel, on a local process pool or
a Dask cluster, with a verdict per variant and a report.

Exit codes: 0 every variant passed every criterion, 1 some variant failed a criterion or
raised, 2 usage or input error (nothing has run or been written: the file, every variant
and ``--out`` are checked first), 130 interrupted by Ctrl-C or SIGTERM (finished variants
are kept; run the same command again to complete the campaign).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hdhil.core import jsonout
from hdhil.core.errors import UserError
from hdhil.core.numbers import arg_int
from hdhil.core.signals import restore_handlers, terminate_as_interrupt

if TYPE_CHECKING:
    from hdhil.rig.campaign import CampaignRun
    from hdhil.rig.campaign_file import Campaign
    from hdhil.rig.campaign_variants import Variant


def register(sub: argparse._SubParsersAction) -> None:
    from hdhil.rig.campaign_file import list_campaigns

    p = sub.add_parser(
        "campaign",
        help="run a campaign (scenario x fault x seed x parameter grid) in parallel",
        description="Run every variant of a campaign file (base scenarios, axes over "
        "scenario keys, criteria over the metrics of `hdhil run --json`) on a local "
        "process pool or a Dask cluster; write results.csv, results.parquet, timings.csv "
        "and report.md with plots. A re-run skips variants already recorded.",
        epilog="exit codes: 0 all variants passed, 1 some variant failed a criterion or "
        "raised, 2 usage or input error, 130 interrupted (finished variants are kept)",
    )
    p.add_argument(
        "campaign",
        metavar="NAME|FILE",
        help=f"campaign name or TOML file (shipped: {', '.join(list_campaigns())})",
    )
    p.add_argument(
        "--workers",
        type=arg_int(1, 4096),
        default=None,
        metavar="N",
        help="local worker processes (default: the machine's cores)",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run on a Dask cluster, e.g. tcp://HOST:8786 (needs pip install 'hdhil[cluster]')",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR",
        help="output directory (default: campaign-NAME); a re-run resumes in it",
    )
    p.add_argument("--json", action="store_true", help="print a JSON summary, no progress bar")
    p.set_defaults(func=run)


class _Progress:
    """A progress bar with ETA and running pass/fail counts (stderr, terminals only)."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.counts = {"pass": 0, "fail": 0, "error": 0}
        self.bar = None
        if enabled:
            try:
                from tqdm import tqdm
            except ImportError:  # pragma: no cover - tqdm is a dependency
                return
            self.bar = tqdm(total=total, unit="variant", file=sys.stderr, dynamic_ncols=True)

    def __call__(self, record: Any) -> None:
        self.counts[record.status] += 1
        if self.bar is not None:
            self.bar.set_postfix_str(
                f"pass {self.counts['pass']} fail {self.counts['fail']} "
                f"error {self.counts['error']}",
                refresh=False,
            )
            self.bar.update(1)

    def warn(self, message: str) -> None:
        line = f"hdhil: warning: {message}"
        if self.bar is not None:
            self.bar.write(line, file=sys.stderr)
        else:
            print(line, file=sys.stderr)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _dask_executor(address: str) -> tuple[Any, Any, tuple[type[BaseException], ...]]:
    try:
        from distributed import Client
        from distributed.scheduler import KilledWorker
    except ImportError:
        raise UserError(
            "--scheduler needs Dask distributed: pip install 'hdhil[cluster]'"
        ) from None
    try:
        client = Client(address, timeout="15s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise UserError(f"cannot reach the Dask scheduler at {address}: {exc}") from None
    return client, (lambda: client.get_executor(pure=False)), (KilledWorker,)


#: What a campaign writes in ``--out``: directories, and files it replaces.
_OUT_DIRS = ("runs", "traces", "plots")
_OUT_FILES = ("results.csv", "results.parquet", "timings.csv", "report.md")


def _check_out(out: Path) -> None:
    """Refuse an ``--out`` the campaign could not write its results in, before anything
    runs, in one line; writes nothing."""
    from hdhil.rig.campaign_file import printable

    try:
        _check_out_dir(out)
    except UserError as exc:
        raise UserError(printable(str(exc))) from None


def _check_out_dir(out: Path) -> None:
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise UserError(f"--out {out} exists and is not a directory")
        for name in _OUT_DIRS:
            entry = out / name
            if (entry.exists() or entry.is_symlink()) and not entry.is_dir():
                raise UserError(f"--out {out}: {name} exists and is not a directory")
        for name in _OUT_FILES:
            entry = out / name
            if entry.is_symlink() or (entry.exists() and not entry.is_file()):
                raise UserError(f"--out {out}: {name} exists and is not a regular file")
        where = out
    else:
        where = out.parent
        if not where.exists():
            ancestor = next((p for p in where.parents if p.exists()), None)
            if ancestor is not None and not ancestor.is_dir():
                raise UserError(f"cannot write in --out {out}: {ancestor} is not a directory")
            raise UserError(f"--out {out}: its parent directory {where} does not exist")
        if not where.is_dir():
            raise UserError(f"cannot write in --out {out}: {where} is not a directory")
    try:  # permissions, a read-only file system: what os.access cannot tell for root
        with tempfile.TemporaryFile(dir=where, prefix=".hdhil-probe-"):
            pass
    except OSError as exc:
        raise UserError(f"cannot write in --out {out}: {exc.strerror or exc}") from None


def run(args: argparse.Namespace) -> int:
    from hdhil.rig.campaign import local_executor
    from hdhil.rig.campaign_file import load_campaign
    from hdhil.rig.campaign_variants import expand

    campaign = load_campaign(args.campaign)
    variants = expand(campaign)
    if args.workers is not None and args.scheduler is not None:
        raise UserError("--workers is for the local pool; a Dask cluster has its own workers")
    workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
    if workers < 1:
        raise UserError(f"--workers must be >= 1, got {workers}")
    out = args.out if args.out is not None else Path(f"campaign-{campaign.name}")
    _check_out(out)
    client = None
    lost: tuple[type[BaseException], ...] = ()
    if args.scheduler is not None:
        client, make_executor, lost = _dask_executor(args.scheduler)
    else:

        def make_executor() -> Any:
            return local_executor(workers)

    created = not os.path.lexists(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create --out {out}: {exc}") from None
    try:
        return _run(args, campaign, variants, out, make_executor, lost, client)
    except (UserError, OSError):
        if created:  # a campaign that wrote nothing (a full disk) leaves no folder either
            _remove_empty_tree(out)
        raise


def _remove_empty_tree(out: Path) -> None:
    """Remove ``out`` and the folders in it if none holds anything but empty folders."""
    walk = list(os.walk(out, topdown=False))
    if any(files for _, _, files in walk):
        return
    for folder, _, _ in walk:
        with contextlib.suppress(OSError):
            os.rmdir(folder)


def _run(
    args: argparse.Namespace,
    campaign: Campaign,
    variants: list[Variant],
    out: Path,
    make_executor: Any,
    lost: tuple[type[BaseException], ...],
    client: Any,
) -> int:
    """Run the campaign into ``out`` (checked and created), report it; the exit code."""
    from hdhil.rig.campaign import run_campaign

    progress = _Progress(len(variants), enabled=sys.stderr.isatty() and not args.json)
    previous = terminate_as_interrupt((signal.SIGTERM,))  # as Ctrl-C: finished variants kept
    try:
        try:
            result = run_campaign(
                campaign, variants, out, make_executor, progress, lost, on_warning=progress.warn
            )
        finally:
            progress.close()
            restore_handlers(previous)
            if client is not None:
                client.close()
        code = _report(args, campaign, variants, result, out)
    except KeyboardInterrupt:  # outside the runs (the results being written): the same
        code = 130
    if code == 130:
        kept = sum(1 for v in variants if (out / "runs" / f"{v.digest}.json").is_file())
        print(
            f"hdhil: interrupted; {kept} of {len(variants)} variants finished and are kept "
            f"in {out / 'runs'}; run the same command again to complete the campaign",
            file=sys.stderr,
        )
    return code


def _report(args: argparse.Namespace, campaign: Campaign, variants: list[Variant],
            result: CampaignRun, out: Path) -> int:  # fmt: skip
    """Write the outputs, print the summary; the exit code."""
    from hdhil.rig.campaign_report import write_outputs

    summary = write_outputs(campaign, variants, result, out)
    code = 130 if result.interrupted else (0 if summary["passed"] == len(variants) else 1)
    summary["exit_code"] = code
    if args.json:
        jsonout.dump(summary, sys.stdout, indent=2)
        print()
    else:
        print(
            f"hdhil campaign {campaign.name}: {summary['variants']} variants, "
            f"passed {summary['passed']}, failed {summary['failed']}, errors "
            f"{summary['errors']}, not run {summary['not_run']} "
            f"(run now {summary['ran']}, from earlier runs {summary['resumed']}) "
            f"in {summary['wall_s']:.1f} s"
        )
        for text, counts in summary["criteria"].items():
            print(f"  {text:<40} pass {counts['pass']:>4}  fail {counts['fail']:>4}")
        print(f"  results  {out / 'results.csv'}")
        print(f"  report   {out / 'report.md'}")
        for note in summary["notes"]:
            print(f"  note: {note}")
    return code
