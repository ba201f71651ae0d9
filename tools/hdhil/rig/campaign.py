"""Campaigns: one firmware against a grid of scenario variants, run in parallel, each
given a verdict.

:func:`run_campaign` runs the variants of a campaign (:mod:`hdhil.rig.campaign_file`,
expanded by :func:`hdhil.rig.campaign_variants.expand`) that have no stored result yet.
Each record is judged (:func:`hdhil.rig.campaign_metrics.judge`) and stored as
``DIR/runs/<digest>.json`` the moment it arrives, so an interrupted campaign keeps what
finished and a re-run only runs what has no result yet.

Execution goes through a :class:`concurrent.futures.Executor`: a local process pool or
a Dask cluster (``distributed.Client.get_executor()``), so both share this code. A
variant that raises is recorded with its error and never stops the campaign; a variant
whose worker was lost is submitted again.
"""

from __future__ import annotations

import concurrent.futures as cf
import gc
import json
import math
import multiprocessing
import os
import socket
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hdhil.can.traces.sidecar import metadata_path
from hdhil.core import jsonout
from hdhil.core.dataconf import ConfigError
from hdhil.core.errors import UserError
from hdhil.core.files import read_config
from hdhil.core.signals import die_with_parent, leave_interrupt_to_parent
from hdhil.rig.campaign_file import Campaign, printable
from hdhil.rig.campaign_metrics import judge
from hdhil.rig.campaign_variants import Variant
from hdhil.rig.variant import WALL_CLOCK_KEYS, RunSettings, run_settings

__all__ = [
    "MAX_ATTEMPTS",
    "CampaignRun",
    "Record",
    "execute_variant",
    "local_executor",
    "run_campaign",
]


def _worker_init(parent_pid: int) -> None:
    """Start of a local pool worker: leave Ctrl-C to the campaign (it cancels and keeps
    results), end when the campaign's process ends, even killed (Linux), and move the
    objects inherited from the parent out of the garbage collector's reach (a forked
    worker would otherwise traverse, and so copy, the parent's whole heap at every full
    collection)."""
    leave_interrupt_to_parent()
    die_with_parent(parent_pid)
    gc.freeze()


def execute_variant(settings: RunSettings) -> dict[str, Any]:
    """Run one variant where the executor put it; never raises for the run's own errors
    (they come back as ``error``)."""
    t0 = time.perf_counter()
    result: dict[str, Any] | None = None
    trace: bytes | None = None
    sidecar: bytes | None = None
    error = None
    try:
        if settings.trace_suffix and multiprocessing.current_process().daemon:
            raise RuntimeError(
                "the trace writer cannot start its process in a daemonic worker (Dask: "
                "start the workers with DASK_DISTRIBUTED__WORKER__DAEMON=False)"
            )
        result, trace, sidecar = run_settings(settings)
        result = {k: v for k, v in result.items() if k not in WALL_CLOCK_KEYS}
    except Exception as exc:  # a variant's failure is data, not the campaign's
        error = f"{type(exc).__name__}: {exc}".splitlines()[0]
    return {
        "result": result,
        "error": error,
        "trace": trace,
        "sidecar": sidecar,
        "wall_s": time.perf_counter() - t0,
        "worker": f"{socket.gethostname()}:{os.getpid()}",
    }


def local_executor(workers: int) -> cf.Executor:
    """A process pool of ``workers`` processes (forked where the platform can: they
    start with hdhil already imported); on Linux they end with the calling process."""
    methods = multiprocessing.get_all_start_methods()
    ctx = multiprocessing.get_context("fork" if "fork" in methods else None)
    return cf.ProcessPoolExecutor(
        max_workers=workers, mp_context=ctx, initializer=_worker_init, initargs=(os.getpid(),)
    )


#: Submissions of one variant whose worker was lost before it is recorded as an error.
MAX_ATTEMPTS = 3


@dataclass
class Record:
    """A variant's outcome as the campaign keeps it."""

    variant: Variant
    result: dict[str, Any] | None
    error: str | None
    wall_s: float
    worker: str
    resumed: bool = False
    metrics: dict[str, Any] = field(default_factory=dict)
    verdicts: dict[str, bool] = field(default_factory=dict)
    reasons: list[str] = field(default_factory=list)

    @property
    def status(self) -> str:
        if self.error is not None:
            return "error"
        return "pass" if all(self.verdicts.values()) else "fail"


@dataclass
class CampaignRun:
    """What :func:`run_campaign` did."""

    records: dict[str, Record]
    ran: int
    resumed: int
    interrupted: bool
    lost: int
    wall_s: float


def _write_atomic(path: Path, data: bytes) -> None:
    """Write ``path`` whole or not at all; only a regular file is ever replaced."""
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise ConfigError(f"{path} exists and is not a regular file: not overwriting it")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _load_stored(path: Path, variant: Variant) -> tuple[dict[str, Any] | None, str | None]:
    """A stored record, or None and why it cannot be used (None when there is none)."""
    if not os.path.lexists(path):
        return None, None
    try:  # a regular file of UTF-8 text, size capped: a record is a few kB
        text = read_config(path)
    except UserError as exc:
        return None, str(exc).removeprefix(f"{path}: ")
    try:
        stored = jsonout.restore(json.loads(text))
    except (ValueError, RecursionError):  # truncated, not JSON, nested beyond the stack
        return None, "not JSON"
    if not isinstance(stored, dict):
        return None, "not a JSON object"
    if stored.get("digest") != variant.digest:
        return None, f"records another variant (digest {stored.get('digest')!r})"
    wall = stored.get("wall_s")
    if isinstance(wall, bool) or not isinstance(wall, (int, float)) or not 0 <= wall < math.inf:
        return None, f"wall_s is {wall!r}, not a number of seconds"
    for key in ("result", "error", "worker"):
        value = stored.get(key)
        wanted = dict if key == "result" else str
        if value is not None and not isinstance(value, wanted):
            return None, f"{key} is a {type(value).__name__}"
    return stored, None


def run_campaign(
    campaign: Campaign,
    variants: list[Variant],
    out: Path,
    make_executor: Callable[[], cf.Executor],
    on_record: Callable[[Record], None] | None = None,
    lost_errors: tuple[type[BaseException], ...] = (),
    on_warning: Callable[[str], None] | None = None,
) -> CampaignRun:
    """Run every variant without a stored record through executors from
    ``make_executor``; store each record as it arrives (``DIR/runs/<digest>.json``).

    ``lost_errors``: exception types a future raises when its worker is gone (besides a
    broken local pool); such a variant is submitted again, up to :data:`MAX_ATTEMPTS`
    times, then recorded as an error for this invocation only (not stored, so a re-run
    retries it).  Ctrl-C cancels what has not started and returns with ``interrupted``.
    A stored record that cannot be used (not JSON, a field missing or of the wrong type)
    is reported, one line, to ``on_warning`` (default :func:`warnings.warn`) and its
    variant run again.
    """
    warn = on_warning if on_warning is not None else _warn
    t0 = time.perf_counter()
    runs_dir = out / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    trace_dir = out / "traces"
    records: dict[str, Record] = {}
    todo: list[Variant] = []
    damaged: list[str] = []  # warned about once the store is known to take the re-runs
    for v in variants:
        path = runs_dir / f"{v.digest}.json"
        stored, damage = _load_stored(path, v)
        if damage is not None:
            damaged.append(f"{path}: {damage}: variant {v.id} is run again")
        if (
            stored is None
            or stored.get("error") is not None  # may come from the worker's environment
            or (campaign.keep_trace and not _trace_path(trace_dir, v).is_file())
        ):
            todo.append(v)
            continue
        rec = Record(v, stored.get("result"), stored.get("error"), float(stored["wall_s"]),
                     str(stored.get("worker") or ""), resumed=True)  # fmt: skip
        try:
            rec.metrics, rec.verdicts, rec.reasons = judge(
                v, rec.result, rec.error, campaign.criteria
            )
        except (KeyError, TypeError, ValueError, AttributeError, ArithmeticError) as exc:
            damaged.append(
                f"{path}: damaged result ({type(exc).__name__}): variant {v.id} is run again"
            )
            todo.append(v)
            continue
        records[v.id] = rec
    resumed = len(records)
    for v in todo:  # where a run's files go must take them: checked before any runs
        targets = [runs_dir / f"{v.digest}.json"]
        if campaign.keep_trace:
            targets += [_trace_path(trace_dir, v), metadata_path(_trace_path(trace_dir, v))]
        for target in targets:
            if target.is_symlink() or (target.exists() and not target.is_file()):
                raise ConfigError(printable(
                    f"{target} exists and is not a regular file: variant {v.id} cannot be "
                    "stored there; remove it"
                ))  # fmt: skip
    for message in damaged:
        warn(printable(message))
    if on_record is not None:
        for rec in records.values():
            on_record(rec)

    def finish(v: Variant, outcome: dict[str, Any], store: bool) -> None:
        if outcome.get("trace") is not None:
            trace_dir.mkdir(exist_ok=True)
            _write_atomic(_trace_path(trace_dir, v), outcome["trace"])
            if outcome.get("sidecar") is not None:
                _write_atomic(metadata_path(_trace_path(trace_dir, v)), outcome["sidecar"])
        rec = Record(v, outcome["result"], outcome["error"], outcome["wall_s"], outcome["worker"])
        rec.metrics, rec.verdicts, rec.reasons = judge(v, rec.result, rec.error, campaign.criteria)
        if store:
            stored = {
                "digest": v.digest,
                "variant": v.id,
                "settings": {
                    "scenario": v.settings.scenario,
                    "duration_s": v.settings.duration_s,
                    "seed": v.settings.seed,
                    "trace": v.settings.trace_suffix,
                },
                "result": rec.result,
                "error": rec.error,
                "wall_s": rec.wall_s,
                "worker": rec.worker,
            }
            _write_atomic(runs_dir / f"{v.digest}.json", jsonout.dumps(stored, indent=1).encode())
        records[v.id] = rec
        if on_record is not None:
            on_record(rec)

    lost_types = (cf.BrokenExecutor, *lost_errors)
    attempts: dict[str, int] = {}
    interrupted = False
    lost = 0
    remaining = todo
    while remaining and not interrupted:
        retry: list[Variant] = []
        executor = make_executor()
        futures: dict[cf.Future, Variant] = {}
        try:
            futures = {executor.submit(execute_variant, v.settings): v for v in remaining}
            for fut in cf.as_completed(futures):
                v = futures.pop(fut)  # a finished future holds its trace: let it go
                try:
                    outcome = fut.result()
                except lost_types as exc:
                    lost += 1
                    attempts[v.id] = attempts.get(v.id, 0) + 1
                    if attempts[v.id] < MAX_ATTEMPTS:
                        retry.append(v)
                        continue
                    why = f"worker lost {attempts[v.id]} times ({type(exc).__name__}: {exc})"
                    finish(v, _failed(why.splitlines()[0]), store=False)
                    continue
                except cf.CancelledError:
                    continue
                if outcome["result"] is not None and outcome["result"].get("interrupted"):
                    retry.append(v)  # a worker stopped mid-run: its partial result is no result
                    continue
                finish(v, outcome, store=True)
        except KeyboardInterrupt:
            interrupted = True
            for fut in futures:
                fut.cancel()
        finally:
            # Dask's executor takes no cancel_futures; what is left was cancelled above.
            executor.shutdown(wait=not interrupted)
        remaining = retry
    return CampaignRun(records, len(records) - resumed, resumed, interrupted, lost,
                       time.perf_counter() - t0)  # fmt: skip


def _warn(message: str) -> None:
    warnings.warn(message, RuntimeWarning, stacklevel=3)


def _failed(error: str) -> dict[str, Any]:
    return {"result": None, "error": error, "trace": None, "wall_s": 0.0, "worker": ""}


def _trace_path(trace_dir: Path, v: Variant) -> Path:
    return trace_dir / f"{v.id}-{v.digest}{v.settings.trace_suffix}"
