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

Signals: Ctrl-C (``KeyboardInterrupt`` in the calling thread; the command turns SIGTERM
and SIGHUP into it) ends the campaign wherever it is: what has not started is cancelled
and the local pool's workers are ended at once (:data:`WORKER_GRACE_S`). A local worker
answers SIGTERM and SIGHUP itself, whoever sends them: its variant unwinds (trace writer
closed, temporary files removed) and the process exits without returning anything, so a
variant cut short is never recorded, neither as a result nor as an error, and is run
again. Ctrl-C reaches the whole process group; the workers leave it to the campaign.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import gc
import json
import math
import multiprocessing
import os
import signal
import socket
import sys
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
from hdhil.core.signals import TERMINATING_SIGNALS, die_with_parent, leave_interrupt_to_parent
from hdhil.rig.campaign_file import Campaign, printable
from hdhil.rig.campaign_metrics import judge
from hdhil.rig.campaign_variants import Variant
from hdhil.rig.variant import WALL_CLOCK_KEYS, RunSettings, run_settings

__all__ = [
    "MAX_ATTEMPTS",
    "WORKER_GRACE_S",
    "CampaignRun",
    "Record",
    "execute_variant",
    "local_executor",
    "run_campaign",
]


#: Seconds a broken pool's workers are given to end before the campaign judges how
#: they ended (:meth:`_LocalPool.lost_to_a_signal`).
LOST_WORKER_WAIT_S = 1.0
#: Seconds a local worker has to end after SIGTERM when the campaign is interrupted
#: before it is killed (SIGKILL): a stopped (SIGSTOP) or hung worker ends after this.
WORKER_GRACE_S = 1.0

#: A local pool worker's state: whether it runs a variant now, and the stopping signal
#: it received (None: none).
_busy = False
_stopping: int | None = None


def _worker_stop(signum: int, frame: object) -> None:
    """SIGTERM or SIGHUP in a local pool worker: a running variant unwinds
    (``KeyboardInterrupt``, then :func:`execute_variant` exits the process); an idle
    worker exits at once. Either way nothing goes back to the campaign, whose pool then
    counts the worker as lost and runs its variant again."""
    global _stopping
    _stopping = signum
    if _busy:
        raise KeyboardInterrupt
    os._exit(128 + signum)


def _worker_unraisable(unraisable: Any) -> None:
    """A local pool worker's ``sys.unraisablehook``: the ``KeyboardInterrupt`` of
    :func:`_worker_stop` that lands in a finaliser (a ``__del__`` run by the garbage
    collector, which cannot pass an exception on) is not printed: the worker is stopping
    anyway, and :func:`execute_variant` exits without a result once the variant returns
    (or the campaign ends the worker after :data:`WORKER_GRACE_S`). Anything else goes
    to Python's own hook."""
    if _stopping is not None and isinstance(unraisable.exc_value, KeyboardInterrupt):
        return
    sys.__unraisablehook__(unraisable)


def _worker_init(parent_pid: int) -> None:
    """Start of a local pool worker: leave Ctrl-C to the campaign (it cancels and keeps
    results), end on SIGTERM and SIGHUP without returning a result (the handlers
    inherited from the campaign's process would send ``KeyboardInterrupt`` back as the
    variant's outcome), end when the campaign's process ends, even killed, and move the
    objects inherited from the parent out of the garbage collector's reach (a forked
    worker would otherwise traverse, and so copy, the parent's whole heap at every full
    collection)."""
    leave_interrupt_to_parent()
    for sig in TERMINATING_SIGNALS:
        signal.signal(sig, _worker_stop)
    sys.unraisablehook = _worker_unraisable
    die_with_parent(parent_pid)
    gc.freeze()


def execute_variant(settings: RunSettings) -> dict[str, Any]:
    """Run one variant where the executor put it; never raises for the run's own errors
    (they come back as ``error``). In a local pool worker told to stop (SIGTERM, SIGHUP)
    the process exits instead of returning."""
    global _busy
    outcome: dict[str, Any] | None = None
    try:
        _busy = True
        outcome = _execute(settings)
    except KeyboardInterrupt:
        if _stopping is None:
            raise
    finally:
        _busy = False
    if _stopping is not None:
        os._exit(128 + _stopping)
    assert outcome is not None
    return outcome


def _execute(settings: RunSettings) -> dict[str, Any]:
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


#: Exit codes of a worker that someone stopped (SIGTERM, SIGHUP, Ctrl-C): its own
#: handler's (128 + the signal) or the signal's default action's (minus the signal).
_STOPPED_EXITS = frozenset(
    code for sig in (signal.SIGINT, *TERMINATING_SIGNALS) for code in (128 + sig, -sig)
)


class _LocalPool(cf.ProcessPoolExecutor):
    """A process pool whose workers can be ended at once (:meth:`stop_workers`)."""

    _stopped: tuple[list[Any], Any] | None = None

    def lost_to_a_signal(self) -> bool:
        """Whether the workers that have ended (the pool is broken) were all stopped by
        a signal meant to stop them (SIGTERM, SIGHUP, SIGINT), none crashed or killed
        (SIGKILL, also the out-of-memory killer's)."""
        procs = list((getattr(self, "_processes", None) or {}).values())
        # The pool reports itself broken as soon as a worker's pipe closes, which can be
        # before that worker is reaped: its exit code is read once it has ended (the
        # broken pool ends the others too), within LOST_WORKER_WAIT_S.
        _wait_ended(procs, LOST_WORKER_WAIT_S)
        ended = [p.exitcode for p in procs if p.exitcode is not None]
        return bool(ended) and all(code in _STOPPED_EXITS for code in ended)

    def stop_workers(self, grace_s: float = WORKER_GRACE_S) -> None:
        """Cancel what has not started and end every worker now: SIGTERM and SIGCONT (a
        stopped worker acts on it once continued); a worker still there ``grace_s``
        later is killed. Returns once the pool is shut down; called again (another
        Ctrl-C meanwhile), it goes on with the same workers."""
        if self._stopped is None:
            # What shutdown() lets go of: the workers and the thread that manages them.
            procs = list((getattr(self, "_processes", None) or {}).values())
            self._stopped = (procs, getattr(self, "_executor_manager_thread", None))
            self.shutdown(wait=False, cancel_futures=True)  # before a worker ends the pool
        procs, manager = self._stopped
        for p in procs:
            with contextlib.suppress(OSError, ValueError, AttributeError):  # ended
                if p.exitcode is None:
                    p.terminate()
                    if hasattr(signal, "SIGCONT"):
                        os.kill(p.pid, signal.SIGCONT)
        left = _wait_ended(procs, grace_s)
        for p in left:
            with contextlib.suppress(OSError, ValueError, AttributeError):
                p.kill()
        _wait_ended(left, WORKER_GRACE_S)
        if manager is not None:
            manager.join(WORKER_GRACE_S)  # it ends once it has seen every worker end


def _wait_ended(procs: list[Any], timeout_s: float) -> list[Any]:
    """Wait up to ``timeout_s`` for the processes to end; those still running."""
    from multiprocessing.connection import wait

    deadline = time.monotonic() + timeout_s
    left = [p for p in procs if p.exitcode is None]
    while left:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            break
        wait([p.sentinel for p in left], remaining)
        left = [p for p in left if p.exitcode is None]
    return left


def local_executor(workers: int) -> cf.Executor:
    """A process pool of ``workers`` processes (forked where the platform can: they
    start with hdhil already imported); they end with the calling process, and at once
    when a campaign is interrupted."""
    methods = multiprocessing.get_all_start_methods()
    ctx = multiprocessing.get_context("fork" if "fork" in methods else None)
    return _LocalPool(
        max_workers=workers, mp_context=ctx, initializer=_worker_init, initargs=(os.getpid(),)
    )


#: Submissions of one variant whose worker was lost before it is recorded as an error.
#: Only losses that may be the variant's doing count: a crash, SIGKILL (the kernel's
#: out-of-memory killer sends it), a lost Dask worker; not a worker stopped by SIGTERM,
#: SIGHUP or SIGINT.
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
    """Write ``path`` whole or not at all; only a regular file is ever replaced. A write
    that fails (a full disk) leaves ``path`` as it was and no temporary, and raises a
    one-line :class:`UserError` naming the file."""
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise ConfigError(f"{path} exists and is not a regular file: not overwriting it")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise UserError(f"cannot write {path}: {exc.strerror or exc}") from None
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


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
    if stored.get("result") is None and stored.get("error") is None:
        return None, "holds neither a result nor an error"
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
    times (workers stopped by a signal do not count), then recorded as an error for this
    invocation only (not stored, so a re-run retries it).  Ctrl-C (``KeyboardInterrupt``)
    anywhere cancels what has not started, ends the local workers and returns with
    ``interrupted``.
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
        executor: cf.Executor | None = None
        futures: dict[cf.Future, Variant] = {}
        ended = False
        stopped: bool | None = None
        try:
            executor = make_executor()
            futures = {executor.submit(execute_variant, v.settings): v for v in remaining}
            for fut in cf.as_completed(futures):
                v = futures.pop(fut)  # a finished future holds its trace: let it go
                try:
                    outcome = fut.result()
                except lost_types as exc:
                    lost += 1
                    if stopped is None:  # once per pool, when it breaks
                        stopped = _lost_to_a_signal(executor)
                    if not stopped:  # a crash, SIGKILL: maybe the variant's doing
                        attempts[v.id] = attempts.get(v.id, 0) + 1
                    if attempts.get(v.id, 0) < MAX_ATTEMPTS:
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
            executor.shutdown(wait=True)
            ended = True
        except KeyboardInterrupt:  # anywhere, the pool's shut-down included
            interrupted = True
        finally:
            if executor is not None and not ended:  # interrupted, or an error
                _abandon(executor, futures)
        remaining = retry
    return CampaignRun(records, len(records) - resumed, resumed, interrupted, lost,
                       time.perf_counter() - t0)  # fmt: skip


def _lost_to_a_signal(executor: cf.Executor) -> bool:
    """Whether a broken executor's workers were stopped by a signal meant to stop them
    (a local pool's; a lost Dask worker counts against its variants)."""
    check = getattr(executor, "lost_to_a_signal", None)
    return bool(check is not None and check())


def _abandon(executor: cf.Executor, futures: dict[cf.Future, Variant]) -> None:
    """Leave an executor whose work is no longer wanted (an interrupt, an error): cancel
    what has not started; a local pool's workers are ended (:data:`WORKER_GRACE_S`), a
    Dask cluster's are its own. Another Ctrl-C meanwhile kills the workers at once."""
    grace = WORKER_GRACE_S
    while True:
        try:
            stop = getattr(executor, "stop_workers", None)
            if stop is not None:
                stop(grace)
            else:  # Dask's executor takes no cancel_futures
                for fut in futures:
                    fut.cancel()
                executor.shutdown(wait=False)
            return
        except KeyboardInterrupt:
            grace = 0.0


def _warn(message: str) -> None:
    warnings.warn(message, RuntimeWarning, stacklevel=3)


def _failed(error: str) -> dict[str, Any]:
    return {"result": None, "error": error, "trace": None, "wall_s": 0.0, "worker": ""}


def _trace_path(trace_dir: Path, v: Variant) -> Path:
    return trace_dir / f"{v.id}-{v.digest}{v.settings.trace_suffix}"
