"""The frame of the conformance suite: options, the master's context on the bus, the
cases and their runner.

A :class:`Case` is one check, named by its group, the clause or object it tests and a
short title; :func:`build_cases` makes the list from the node's object dictionary (one
case per object where the check is per object), :func:`run_suite` runs them in order
against the node and returns a :class:`SuiteResult`.  Each group starts from a freshly
reset node (NMT reset node, boot-up awaited), so a group's cases do not depend on what
another group left behind, and the suite ends with a reset node too.

The master is ``canopen``'s :class:`~canopen.Network` with a :class:`~canopen.RemoteNode`
built from the EDS/DCF (its SDO client, NMT and EMCY consumer); a listener on the same
notifier records every frame with its arrival time on the monotonic clock, which is what
the timing cases measure (the same on every interface).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import can
import canopen
from canopen.objectdictionary import ObjectDictionary, ODVariable
from canopen.sdo import SdoAbortedError, SdoCommunicationError

__all__ = [
    "GROUPS",
    "Case",
    "CaseFailed",
    "CaseSkipped",
    "Context",
    "Options",
    "Outcome",
    "Recorder",
    "SuiteResult",
    "build_cases",
    "run_suite",
]

#: The groups, in the order they run.
GROUPS: tuple[str, ...] = (
    "nmt",
    "heartbeat",
    "sdo",
    "objects",
    "pdo",
    "sync",
    "emcy",
    "cia402",
    "cst",
    "timing",
)

NMT_COB_ID = 0x000
SYNC_COB_ID_DEFAULT = 0x080
EMCY_BASE = 0x080
SDO_TX_BASE = 0x580
SDO_RX_BASE = 0x600
HEARTBEAT_BASE = 0x700

#: Groups whose cases share one reset node at the group's start (reads and writes that
#: leave the node as it was); every case of the other groups starts from a reset node.
SHARED_RESET_GROUPS = frozenset({"sdo", "objects", "cst"})

#: NMT command specifiers (CiA 301 §7.2.8.3.1).
NMT_START = 0x01
NMT_STOP = 0x02
NMT_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82
#: Heartbeat states (CiA 301 §7.2.8.3.2).
HB_BOOTUP = 0x00
HB_STOPPED = 0x04
HB_OPERATIONAL = 0x05
HB_PRE_OPERATIONAL = 0x7F


class CaseFailed(AssertionError):
    """The node did not do what the clause says (the message says what it did)."""


class CaseSkipped(Exception):
    """The case does not apply to this node (the message says why)."""


@dataclass(frozen=True)
class Options:
    """What the suite runs against and how.

    ``node_id`` is the node under test; ``master_id`` the node-ID whose heartbeat the
    suite produces for the node's heartbeat consumer (0x1016).  ``motion`` False never
    commands *enable operation* (the power stage stays off: cases that need it are
    skipped).  ``only``/``skip`` select groups.  The limits: ``sync_latency_s`` the
    largest median SYNC-to-TPDO latency when 0x1007 is 0 (else the window),
    ``reaction_s`` the largest delay of an EMCY after the deadline it reports,
    ``period_tolerance`` the relative error of a mean period (heartbeat, event timer).
    ``retries``: a failed case runs again (from a reset node) up to this many times and
    passes if a retry does, its detail saying so: a loaded host's scheduling delays do
    not fail a node, while a defect fails every run.
    """

    node_id: int = 2
    master_id: int = 1
    motion: bool = True
    only: tuple[str, ...] = ()
    skip: tuple[str, ...] = ()
    sdo_timeout_s: float = 0.5
    boot_timeout_s: float = 3.0
    sync_latency_s: float = 1e-3
    reaction_s: float = 0.03
    period_tolerance: float = 0.1
    timing_samples: int = 40
    retries: int = 1

    def __post_init__(self) -> None:
        if not 1 <= self.node_id <= 127 or not 1 <= self.master_id <= 127:
            raise ValueError("node-IDs are 1..127")
        if self.retries < 0:
            raise ValueError(f"retries must be >= 0, got {self.retries}")
        if self.node_id == self.master_id:
            raise ValueError(f"the suite's own node-ID {self.master_id} is the node's")
        for name in (*self.only, *self.skip):
            if name not in GROUPS:
                raise ValueError(f"unknown group {name!r}; the groups: {', '.join(GROUPS)}")

    def selected(self, group: str) -> bool:
        return (not self.only or group in self.only) and group not in self.skip


@dataclass(frozen=True)
class Case:
    """One check: ``group``, ``ref`` (the clause or object it tests), ``title``; ``run``
    raises :class:`CaseFailed` or :class:`CaseSkipped`, or returns a detail line.
    ``motion``: the case enables the power stage (skipped without motion)."""

    group: str
    ref: str
    title: str
    run: Callable[[Context], str | None]
    motion: bool = False

    @property
    def name(self) -> str:
        return f"{self.ref} {self.title}"


@dataclass(frozen=True)
class Outcome:
    case: Case
    status: str  # "pass" | "fail" | "skip" | "error"
    detail: str
    seconds: float


@dataclass
class SuiteResult:
    options: Options
    eds: str
    outcomes: list[Outcome] = field(default_factory=list)
    seconds: float = 0.0

    def count(self, status: str) -> int:
        return sum(o.status == status for o in self.outcomes)

    @property
    def ok(self) -> bool:
        return not any(o.status in ("fail", "error") for o in self.outcomes)


# ------------------------------------------------------------------ the bus
class Recorder(can.Listener):
    """Every received frame with its arrival time (``time.monotonic``)."""

    def __init__(self) -> None:
        self.frames: list[tuple[float, can.Message]] = []
        self._cond = threading.Condition()

    def on_message_received(self, msg: can.Message) -> None:
        t = time.monotonic()
        with self._cond:
            self.frames.append((t, msg))
            self._cond.notify_all()

    def mark(self) -> int:
        with self._cond:
            return len(self.frames)

    def clear(self) -> None:
        with self._cond:
            self.frames.clear()

    def wait(
        self, match: Callable[[can.Message], bool], timeout: float, since: int
    ) -> tuple[float, can.Message] | None:
        """The first frame from ``since`` on that ``match``es, waiting up to ``timeout``."""
        deadline = time.monotonic() + timeout
        i = since
        with self._cond:
            while True:
                while i < len(self.frames):
                    t, msg = self.frames[i]
                    i += 1
                    if match(msg):
                        return t, msg
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)

    def since(
        self, since: int, match: Callable[[can.Message], bool]
    ) -> list[tuple[float, can.Message]]:
        with self._cond:
            return [(t, m) for t, m in self.frames[since:] if match(m)]


def cob(arbitration_id: int) -> Callable[[can.Message], bool]:
    return lambda m: m.arbitration_id == arbitration_id and not m.is_remote_frame


class Context:
    """The master on the bus: canopen's network and remote node, raw frames, the
    recorder, the suite's heartbeat and the object dictionary."""

    def __init__(self, bus: can.BusABC, od: ObjectDictionary, options: Options) -> None:
        self.options = options
        self.od = od
        self.node_id = options.node_id
        self.bus = bus
        self.network = canopen.Network(bus)
        self.recorder = Recorder()
        self.network.listeners.append(self.recorder)
        self.network.notifier = can.Notifier(bus, self.network.listeners, 0.05)
        self.node = canopen.RemoteNode(options.node_id, od)
        self.network.add_node(self.node)
        self.node.sdo.RESPONSE_TIMEOUT = options.sdo_timeout_s
        #: The node's heartbeat producer time as last read or written (0x1017, ms).
        self.heartbeat_ms = 0
        self._hb_stop: threading.Event | None = None
        self._hb_thread: threading.Thread | None = None
        #: True once the node answered a reset with its boot-up message.
        self.booted = False

    def close(self) -> None:
        self.stop_heartbeat()
        self.network.notifier.stop()

    # -- raw frames
    def send(self, cob_id: int, data: bytes | Sequence[int] = b"") -> float:
        self.network.send_message(cob_id, bytes(data))
        return time.monotonic()

    def nmt(self, command: int, node_id: int | None = None) -> float:
        return self.send(NMT_COB_ID, (command, self.node_id if node_id is None else node_id))

    @property
    def sync_cob_id(self) -> int:
        if self.variable(0x1005, 0) is None:
            return SYNC_COB_ID_DEFAULT
        return self.boot_value(0x1005, 0) & 0x7FF

    def sync(self, counter: int | None = None) -> float:
        return self.send(self.sync_cob_id, b"" if counter is None else bytes((counter,)))

    def heartbeat_state(self, timeout: float | None = None) -> int | None:
        """The state byte of the node's next heartbeat (None: none came)."""
        wait = timeout or self.heartbeat_wait_s()
        hit = self.recorder.wait(cob(HEARTBEAT_BASE + self.node_id), wait, self.recorder.mark())
        return None if hit is None else hit[1].data[0] & 0x7F

    def heartbeat_wait_s(self) -> float:
        period_ms = self.heartbeat_ms
        if not period_ms:
            raise CaseSkipped("the heartbeat producer is off (0x1017 = 0)")
        return 2.5 * period_ms * 1e-3 + 0.1

    def reset_node(self, command: int = NMT_RESET_NODE) -> float:
        """Reset and wait for the boot-up message; returns its arrival time."""
        self.stop_heartbeat()
        mark = self.recorder.mark()
        self.nmt(command)
        hit = self.recorder.wait(
            lambda m: m.arbitration_id == HEARTBEAT_BASE + self.node_id
            and len(m.data) == 1 and m.data[0] == HB_BOOTUP,
            self.options.boot_timeout_s, mark,
        )  # fmt: skip
        if hit is None:
            raise CaseFailed(
                f"no boot-up message (0x{HEARTBEAT_BASE + self.node_id:03X} 00) within "
                f"{self.options.boot_timeout_s:g} s of NMT 0x{command:02X}"
            )
        time.sleep(0.005)  # let the node finish its start-up before the first request
        self.booted = True
        if self.variable(0x1017, 0) is not None:
            self.heartbeat_ms = self.read_int(0x1017, 0)
        return hit[0]

    def raw_sdo(self, data: Sequence[int], timeout: float | None = None) -> bytes | None:
        """Send an SDO request frame as given; the server's answer (None: none)."""
        mark = self.recorder.mark()
        self.send(SDO_RX_BASE + self.node_id, bytes(data).ljust(8, b"\0"))
        hit = self.recorder.wait(cob(SDO_TX_BASE + self.node_id),
                                 timeout or self.options.sdo_timeout_s, mark)  # fmt: skip
        return None if hit is None else bytes(hit[1].data)

    # -- the suite's heartbeat (the node's heartbeat consumer)
    def start_heartbeat(self, period_s: float, state: int = HB_OPERATIONAL) -> None:
        self.stop_heartbeat()
        stop = threading.Event()
        cob_id = HEARTBEAT_BASE + self.options.master_id

        def beat() -> None:
            while not stop.is_set():
                with contextlib.suppress(can.CanError):
                    self.send(cob_id, (state,))
                self.last_beat = time.monotonic()
                stop.wait(period_s)

        self.last_beat = 0.0
        self._hb_stop = stop
        self._hb_thread = threading.Thread(target=beat, daemon=True, name="conformance-hb")
        self._hb_thread.start()

    def stop_heartbeat(self) -> float:
        """Stop the suite's heartbeat; the time of its last beat."""
        if self._hb_stop is not None and self._hb_thread is not None:
            self._hb_stop.set()
            self._hb_thread.join(2)
            self._hb_stop = self._hb_thread = None
        return getattr(self, "last_beat", 0.0)

    # -- objects
    def variable(self, index: int, sub: int = 0) -> ODVariable | None:
        obj = self.od.get(index)
        if obj is None:
            return None
        if isinstance(obj, ODVariable):
            return obj if sub == 0 else None
        return obj.get(sub) if sub in obj.subindices else None

    def need(self, index: int, sub: int = 0) -> ODVariable:
        var = self.variable(index, sub)
        if var is None:
            raise CaseSkipped(f"the EDS has no 0x{index:04X}:{sub:02X}")
        return var

    def boot_value(self, index: int, sub: int = 0) -> Any:
        """The value the EDS/DCF gives (DCF ParameterValue, else DefaultValue)."""
        var = self.need(index, sub)
        value = getattr(var, "value", None)
        return var.default if value is None else value

    def upload(self, index: int, sub: int = 0) -> bytes:
        return self.node.sdo.upload(index, sub)

    def download(self, index: int, sub: int, data: bytes, force_segment: bool = False) -> None:
        self.node.sdo.download(index, sub, data, force_segment)

    def read_int(self, index: int, sub: int = 0) -> Any:
        var = self.need(index, sub)
        return var.decode_raw(self.upload(index, sub))

    def write(self, index: int, sub: int, value: Any) -> None:
        var = self.need(index, sub)
        self.download(index, sub, var.encode_raw(value))
        if (index, sub) == (0x1017, 0):
            self.heartbeat_ms = int(value)

    def expect_abort(self, call: Callable[[], Any], codes: Iterable[int], what: str) -> str:
        """``call`` must end in an SDO abort with one of ``codes`` (empty: any code)."""
        codes = tuple(codes)
        try:
            call()
        except SdoAbortedError as exc:
            if codes and exc.code not in codes:
                want = " or ".join(f"0x{c:08X}" for c in codes)
                raise CaseFailed(f"{what}: abort 0x{exc.code:08X}, expected {want}") from None
            return f"abort 0x{exc.code:08X}"
        except SdoCommunicationError as exc:
            raise CaseFailed(f"{what}: no abort ({exc})") from None
        want = " or ".join(f"0x{c:08X}" for c in codes) or "an abort"
        raise CaseFailed(f"{what}: accepted, expected {want}")

    def variables(self) -> list[ODVariable]:
        out: list[ODVariable] = []
        for obj in self.od.values():
            out += [obj] if isinstance(obj, ODVariable) else list(obj.values())
        return out


def build_cases(od: ObjectDictionary, options: Options) -> list[Case]:
    """Every case of the selected groups, in running order."""
    from hdhil.conformance import cia301, cia402, timing

    makers = {
        "nmt": cia301.nmt_cases,
        "heartbeat": cia301.heartbeat_cases,
        "sdo": cia301.sdo_cases,
        "objects": cia301.object_cases,
        "pdo": cia301.pdo_cases,
        "sync": cia301.sync_cases,
        "emcy": cia301.emcy_cases,
        "cia402": cia402.state_machine_cases,
        "cst": cia402.cst_cases,
        "timing": timing.timing_cases,
    }
    cases: list[Case] = []
    for group in GROUPS:
        if options.selected(group):
            cases += makers[group](od)
    return cases


def run_suite(
    bus: can.BusABC,
    od: ObjectDictionary,
    options: Options,
    eds_name: str,
    on_case: Callable[[Outcome], None] | None = None,
    cases: Sequence[Case] | None = None,
) -> SuiteResult:
    """Run the cases on ``bus`` against node ``options.node_id``; ``on_case`` is told
    each outcome as it comes (progress)."""
    if cases is None:
        cases = build_cases(od, options)
    result = SuiteResult(options, eds_name)
    start = time.monotonic()
    ctx = Context(bus, od, options)
    try:
        group = None
        setup_error: str | None = None
        dead: str | None = None  # the node never booted: no further resets
        for case in cases:
            if dead is None:
                if case.group != group:
                    group = case.group
                    setup_error = _group_setup(ctx)
                elif case.group not in SHARED_RESET_GROUPS and setup_error is None:
                    setup_error = _group_setup(ctx)
                if setup_error is not None and not ctx.booted:
                    dead = setup_error = f"the node never booted; {setup_error}"
            t0 = time.monotonic()
            if setup_error is not None:
                outcome = Outcome(case, "fail", setup_error, 0.0)
            elif case.motion and not options.motion:
                outcome = Outcome(case, "skip", "--no-motion: needs the power stage", 0.0)
            else:
                status, detail = _run_one(ctx, case)
                for attempt in range(1, options.retries + 1):
                    if status not in ("fail", "error"):
                        break
                    first = detail
                    again = None if case.group in SHARED_RESET_GROUPS else _group_setup(ctx)
                    if again is not None:
                        break
                    status, detail = _run_one(ctx, case)
                    if status == "pass":
                        detail = f"{detail} (passed on retry {attempt}; first: {first})"
                outcome = Outcome(case, status, detail, time.monotonic() - t0)
            result.outcomes.append(outcome)
            if on_case is not None:
                on_case(outcome)
        if dead is None:
            with contextlib.suppress(CaseFailed, can.CanError):
                ctx.reset_node()
    finally:
        ctx.close()
    result.seconds = time.monotonic() - start
    return result


def _group_setup(ctx: Context) -> str | None:
    try:
        ctx.reset_node()
    except CaseFailed as exc:
        return f"group set-up: {exc}"
    ctx.recorder.clear()
    return None


def _run_one(ctx: Context, case: Case) -> tuple[str, str]:
    try:
        detail = case.run(ctx)
    except CaseSkipped as exc:
        return "skip", str(exc)
    except CaseFailed as exc:
        return "fail", str(exc)
    except SdoAbortedError as exc:
        return "fail", f"unexpected SDO abort 0x{exc.code:08X}"
    except SdoCommunicationError as exc:
        return "fail", f"SDO: {exc}"
    except Exception as exc:  # a case's own error: reported, the suite goes on
        return "error", f"{type(exc).__name__}: {exc}"
    finally:
        ctx.stop_heartbeat()
    return "pass", detail or ""
