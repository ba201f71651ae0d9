"""CiA 301 cases: NMT, heartbeat, SDO, the object dictionary against the EDS, PDOs, SYNC
and EMCY.  Clauses are those of CiA 301 v4.2."""

from __future__ import annotations

import itertools
import struct
import time
from collections.abc import Callable
from typing import Any

from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable
from canopen.objectdictionary import datatypes as dt
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from hdhil.conformance.suite import (
    EMCY_BASE,
    HB_OPERATIONAL,
    HB_PRE_OPERATIONAL,
    HB_STOPPED,
    HEARTBEAT_BASE,
    NMT_PRE_OPERATIONAL,
    NMT_RESET_COMMUNICATION,
    NMT_START,
    NMT_STOP,
    Case,
    CaseFailed,
    CaseSkipped,
    Context,
    cob,
)

__all__ = [
    "emcy_cases",
    "heartbeat_cases",
    "nmt_cases",
    "object_cases",
    "pdo_cases",
    "sdo_cases",
    "sync_cases",
]

# SDO abort codes (CiA 301 §7.2.4.3.17).
TOGGLE = 0x05030000
COMMAND = 0x05040001
UNSUPPORTED = 0x06010000
WRITE_ONLY = 0x06010001
READ_ONLY = 0x06010002
NO_OBJECT = 0x06020000
NOT_MAPPABLE = 0x06040041
PDO_LENGTH = 0x06040042
INCOMPATIBLE = 0x06040043
LENGTH = 0x06070010
LENGTH_HIGH = 0x06070012
LENGTH_LOW = 0x06070013
NO_SUB = 0x06090011
INVALID = 0x06090030
TOO_HIGH = 0x06090031
TOO_LOW = 0x06090032
STORE = 0x08000020

PDO_NOT_VALID = 1 << 31
#: Signature objects: 0x1010 store and 0x1011 restore (CiA 301 §7.5.2.13/14).
SIGNATURE_OBJECTS = (0x1010, 0x1011)


def _hex(index: int, sub: int) -> str:
    return f"0x{index:04X}:{sub:02X}"


_INTEGER_TYPES = frozenset(dt.INTEGER_TYPES)


def _int_types() -> frozenset[int]:
    return _INTEGER_TYPES


# ------------------------------------------------------------------ helpers
def heartbeat_is(ctx: Context, state: int, what: str) -> str:
    got = ctx.heartbeat_state()
    if got is None:
        raise CaseFailed(f"{what}: no heartbeat")
    if got != state:
        raise CaseFailed(f"{what}: heartbeat state 0x{got:02X}, expected 0x{state:02X}")
    return f"heartbeat state 0x{got:02X}"


def tpdo_comm_indices(ctx: Context) -> list[int]:
    return [i for i in range(0x1800, 0x1A00) if ctx.variable(i, 1) is not None]


def rpdo_comm_indices(ctx: Context) -> list[int]:
    return [i for i in range(0x1400, 0x1600) if ctx.variable(i, 1) is not None]


def live_layout(ctx: Context, comm: int) -> tuple[int, bool, int, list[tuple[int, int, int]]]:
    """(COB-ID, valid, transmission type, entries) of a PDO, read by SDO now."""
    cob_id = ctx.read_int(comm, 1)
    trans = ctx.read_int(comm, 2)
    mapping = comm + 0x200
    count = ctx.read_int(mapping, 0) if ctx.variable(mapping, 0) is not None else 0
    entries = []
    for sub in range(1, count + 1):
        v = ctx.read_int(mapping, sub)
        entries.append((v >> 16, (v >> 8) & 0xFF, v & 0xFF))
    return cob_id & 0x7FF, not cob_id & PDO_NOT_VALID, trans, entries


def synchronous_tpdos(ctx: Context) -> list[tuple[int, int]]:
    """(comm index, COB-ID) of the valid TPDOs sent on every SYNC (type 1)."""
    out = []
    for comm in tpdo_comm_indices(ctx):
        cob_id, valid, trans, entries = live_layout(ctx, comm)
        if valid and trans == 1 and entries:
            out.append((comm, cob_id))
    return out


def first_sync_tpdo(ctx: Context) -> tuple[int, int]:
    found = synchronous_tpdos(ctx)
    if not found:
        raise CaseSkipped("no valid TPDO with transmission type 1 at boot")
    return found[0]


def syncs_answered(ctx: Context, cob_id: int, n: int, period: float = 0.005) -> int:
    mark = ctx.recorder.mark()
    for _ in range(n):
        ctx.sync()
        time.sleep(period)
    time.sleep(0.05)
    return len(ctx.recorder.since(mark, cob(cob_id)))


def emcy_wait(ctx: Context, match: Callable[[int], bool], timeout: float, since: int
              ) -> tuple[float, int, int, bytes] | None:  # fmt: skip
    """The first EMCY of the node from ``since`` whose code ``match``es: (arrival time,
    code, error register, manufacturer bytes)."""
    emcy_id = emcy_cob_id(ctx)

    def ok(m: Any) -> bool:
        return m.arbitration_id == emcy_id and len(m.data) == 8 and match(
            int.from_bytes(m.data[0:2], "little"))  # fmt: skip

    hit = ctx.recorder.wait(ok, timeout, since)
    if hit is None:
        return None
    t, m = hit
    return t, int.from_bytes(m.data[0:2], "little"), m.data[2], bytes(m.data[3:8])


def emcy_cob_id(ctx: Context) -> int:
    """The EMCY COB-ID of the EDS/DCF (the suite never changes 0x1014)."""
    if ctx.variable(0x1014, 0) is None:
        return EMCY_BASE + ctx.node_id
    return ctx.boot_value(0x1014, 0) & 0x7FF


def consumer_entry(ctx: Context) -> int:
    """The 0x1016 sub-index the suite configures for its own heartbeat."""
    ctx.need(0x1016, 1)
    subs = [s for s in ctx.od[0x1016].subindices if s > 0]
    for sub in subs:  # an entry already on the suite's node-ID, else the first
        if ctx.read_int(0x1016, sub) >> 16 & 0x7F == ctx.options.master_id:
            return sub
    return subs[0]


def heartbeat_loss(ctx: Context, timeout_ms: int = 100) -> tuple[float, float, int]:
    """Configure the consumer for the suite's heartbeat, beat, stop: (time of the last
    beat, deadline, recorder mark at the stop)."""
    sub = consumer_entry(ctx)
    ctx.write(0x1016, sub, ctx.options.master_id << 16 | timeout_ms)
    ctx.start_heartbeat(timeout_ms * 0.25e-3)
    time.sleep(timeout_ms * 1.2e-3)
    mark = ctx.recorder.mark()
    last = ctx.stop_heartbeat()
    return last, last + timeout_ms * 1e-3, mark


def case(
    group: str, ref: str, title: str, motion: bool = False
) -> Callable[[Callable[[Context], str | None]], Case]:
    """A decorator making a :class:`Case` of a check function."""

    def wrap(fn: Callable[[Context], str | None]) -> Case:
        return Case(group, ref, title, fn, motion)

    return wrap


# ------------------------------------------------------------------ NMT
def nmt_cases(od: ObjectDictionary) -> list[Case]:
    g = "nmt"

    def bootup(ctx: Context) -> str:
        ctx.reset_node()
        return "boot-up 00 after NMT reset node"

    def preop(ctx: Context) -> str:
        return heartbeat_is(ctx, HB_PRE_OPERATIONAL, "after boot-up")

    def sdo_preop(ctx: Context) -> str:
        ctx.upload(0x1000, 0)
        return "0x1000 uploaded"

    def no_pdo_preop(ctx: Context) -> str:
        _comm, cob_id = first_sync_tpdo(ctx)
        n = syncs_answered(ctx, cob_id, 5)
        if n:
            raise CaseFailed(f"{n} TPDO frames 0x{cob_id:03X} on 5 SYNC in PRE-OPERATIONAL")
        return "no TPDO on SYNC"

    def start(ctx: Context) -> str:
        ctx.nmt(NMT_START)
        return heartbeat_is(ctx, HB_OPERATIONAL, "after NMT start")

    def pdo_operational(ctx: Context) -> str:
        _comm, cob_id = first_sync_tpdo(ctx)
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        n = syncs_answered(ctx, cob_id, 5)
        if n != 5:
            raise CaseFailed(f"{n} TPDO frames 0x{cob_id:03X} on 5 SYNC in OPERATIONAL")
        return f"TPDO 0x{cob_id:03X} on each SYNC"

    def stop(ctx: Context) -> str:
        ctx.nmt(NMT_STOP)
        return heartbeat_is(ctx, HB_STOPPED, "after NMT stop")

    def sdo_stopped(ctx: Context) -> str:
        ctx.nmt(NMT_STOP)
        time.sleep(0.02)
        answer = ctx.raw_sdo((0x40, 0x00, 0x10, 0x00), timeout=0.2)
        if answer is not None:
            raise CaseFailed(f"SDO answered in STOPPED: {answer.hex(' ')}")
        return "no SDO answer"

    def no_pdo_stopped(ctx: Context) -> str:
        _comm, cob_id = first_sync_tpdo(ctx)
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        ctx.nmt(NMT_STOP)
        time.sleep(0.02)
        n = syncs_answered(ctx, cob_id, 5)
        if n:
            raise CaseFailed(f"{n} TPDO frames on 5 SYNC in STOPPED")
        return "no TPDO on SYNC"

    def stopped_to_preop(ctx: Context) -> str:
        ctx.nmt(NMT_STOP)
        time.sleep(0.02)
        ctx.nmt(NMT_PRE_OPERATIONAL)
        detail = heartbeat_is(ctx, HB_PRE_OPERATIONAL, "after enter pre-operational")
        ctx.upload(0x1000, 0)
        return detail + ", SDO served again"

    def broadcast(ctx: Context) -> str:
        ctx.nmt(NMT_START, node_id=0)
        detail = heartbeat_is(ctx, HB_OPERATIONAL, "after NMT start to all nodes (0)")
        ctx.nmt(NMT_PRE_OPERATIONAL, node_id=0)
        return detail

    def other_node(ctx: Context) -> str:
        other = ctx.node_id % 127 + 1
        if other == ctx.options.master_id:
            other = other % 127 + 1
        ctx.nmt(NMT_STOP, node_id=other)
        return heartbeat_is(ctx, HB_PRE_OPERATIONAL, f"after NMT stop to node {other}")

    def unknown_command(ctx: Context) -> str:
        ctx.send(0x000, (0x99, ctx.node_id))
        detail = heartbeat_is(ctx, HB_PRE_OPERATIONAL, "after NMT command 0x99")
        ctx.upload(0x1000, 0)
        return detail

    def reset_comm(ctx: Context) -> str:
        ctx.need(0x1017, 0)
        boot = ctx.boot_value(0x1017, 0)
        changed = boot + 7 if boot < 60000 else boot - 7
        ctx.write(0x1017, 0, changed)
        ctx.reset_node(NMT_RESET_COMMUNICATION)
        got = ctx.read_int(0x1017, 0)
        if got != boot:
            raise CaseFailed(f"0x1017 is {got} after reset communication, boot value {boot}")
        return "boot-up; 0x1017 restored"

    def reset_app(ctx: Context) -> str:
        var = application_parameter(ctx)
        boot = ctx.boot_value(var.index, var.subindex)
        other = boot + 1 if var.max is None or boot + 1 <= var.max else boot - 1
        ctx.write(var.index, var.subindex, other)
        ctx.reset_node()
        got = ctx.read_int(var.index, var.subindex)
        if got != boot:
            raise CaseFailed(f"{_hex(var.index, var.subindex)} is {got} after reset node, "
                             f"boot value {boot}")  # fmt: skip
        return f"{_hex(var.index, var.subindex)} restored"

    def reset_comm_keeps_app(ctx: Context) -> str:
        var = application_parameter(ctx)
        boot = ctx.boot_value(var.index, var.subindex)
        other = boot + 1 if var.max is None or boot + 1 <= var.max else boot - 1
        ctx.write(var.index, var.subindex, other)
        ctx.reset_node(NMT_RESET_COMMUNICATION)
        got = ctx.read_int(var.index, var.subindex)
        if got != other:
            raise CaseFailed(f"{_hex(var.index, var.subindex)} is {got} after reset "
                             f"communication, written {other}")  # fmt: skip
        return f"{_hex(var.index, var.subindex)} kept"

    return [
        case(g, "§7.3.2.2", "boot-up message after reset node")(bootup),
        case(g, "§7.3.2.2", "PRE-OPERATIONAL after boot-up")(preop),
        case(g, "§7.3.2.2", "SDO served in PRE-OPERATIONAL")(sdo_preop),
        case(g, "§7.3.2.2", "no PDO in PRE-OPERATIONAL")(no_pdo_preop),
        case(g, "§7.2.8.3.1", "start remote node -> OPERATIONAL")(start),
        case(g, "§7.3.2.2", "PDOs in OPERATIONAL")(pdo_operational),
        case(g, "§7.2.8.3.1", "stop remote node -> STOPPED")(stop),
        case(g, "§7.3.2.2", "no SDO in STOPPED")(sdo_stopped),
        case(g, "§7.3.2.2", "no PDO in STOPPED")(no_pdo_stopped),
        case(g, "§7.2.8.3.1", "enter pre-operational from STOPPED")(stopped_to_preop),
        case(g, "§7.2.8.3.1", "command to all nodes (node-ID 0)")(broadcast),
        case(g, "§7.2.8.3.1", "command to another node-ID ignored")(other_node),
        case(g, "§7.2.8.3.1", "unknown command specifier ignored")(unknown_command),
        case(g, "§7.3.2.2.2", "reset communication restores 0x1000-0x1FFF")(reset_comm),
        case(g, "§7.3.2.2.2", "reset node restores the application")(reset_app),
        case(g, "§7.3.2.2.2", "reset communication keeps the application")(reset_comm_keeps_app),
    ]


def application_parameter(ctx: Context) -> ODVariable:
    """A writable integer application parameter with limits (0x6000-0x9FFF first, then
    0x2000-0x5FFF), not mappable: what a reset node must restore."""
    for lo, hi in ((0x6000, 0xA000), (0x2000, 0x6000)):
        for var in ctx.variables():
            limited = var.min is not None and var.max is not None and var.max > var.min
            if (lo <= var.index < hi and var.writable and var.readable and limited
                    and var.data_type in _int_types() and not var.pdo_mappable):  # fmt: skip
                return var
    raise CaseSkipped("no writable integer application parameter with limits in the EDS")


# ------------------------------------------------------------------ heartbeat
def heartbeat_cases(od: ObjectDictionary) -> list[Case]:
    g = "heartbeat"

    def producer_boot(ctx: Context) -> str:
        ctx.need(0x1017, 0)
        period = ctx.read_int(0x1017, 0)
        if not period:
            raise CaseSkipped("0x1017 = 0 at boot")
        state = ctx.heartbeat_state()
        if state is None:
            raise CaseFailed(f"no heartbeat within {2.5 * period:g} ms")
        return f"0x1017 = {period} ms"

    def producer_change(ctx: Context) -> str:
        ctx.need(0x1017, 0)
        ctx.write(0x1017, 0, 40)
        times, gaps = arrival_gaps(ctx, HEARTBEAT_BASE + ctx.node_id, 0.05, 0.3)
        if len(gaps) < 4:
            raise CaseFailed(f"{len(times)} heartbeats in 0.3 s after 0x1017 = 40")
        mean = mean_period(gaps, 0.040, max(ctx.options.period_tolerance, 0.25),
                           "mean heartbeat period {} ms after 0x1017 = 40")  # fmt: skip
        return f"mean period {mean * 1e3:.1f} ms"

    def producer_off(ctx: Context) -> str:
        ctx.need(0x1017, 0)
        boot = ctx.read_int(0x1017, 0)
        ctx.write(0x1017, 0, 0)
        time.sleep(0.02)
        mark = ctx.recorder.mark()
        time.sleep(max(0.3, 2.5 * boot * 1e-3))
        n = len(ctx.recorder.since(mark, cob(HEARTBEAT_BASE + ctx.node_id)))
        if n:
            raise CaseFailed(f"{n} heartbeats after 0x1017 = 0")
        ctx.write(0x1017, 0, boot)
        if ctx.heartbeat_state() is None:
            raise CaseFailed("no heartbeat after 0x1017 was set again")
        return "silent at 0, resumes"

    def consumer_format(ctx: Context) -> str:
        ctx.need(0x1016, 1)
        subs = [s for s in ctx.od[0x1016].subindices if s > 0]
        for sub in subs:
            v = ctx.read_int(0x1016, sub)
            if v >> 24:
                raise CaseFailed(f"0x1016:{sub:02X} = 0x{v:08X}: bits 24-31 are reserved (0)")
        return f"{len(subs)} entries"

    def consumer_loss(ctx: Context) -> str:
        ctx.need(0x1016, 1)
        last, deadline, mark = heartbeat_loss(ctx)
        hit = emcy_wait(ctx, lambda c: c == 0x8130, 1.0, mark)
        if hit is None:
            raise CaseFailed("no EMCY 0x8130 after the consumed heartbeat stopped")
        t = hit[0]
        if t < deadline - 0.01:
            raise CaseFailed(f"EMCY 0x8130 {(deadline - t) * 1e3:.0f} ms before the timeout")
        return f"EMCY 0x8130 {(t - last) * 1e3:.0f} ms after the last beat (timeout 100 ms)"

    def consumer_resume(ctx: Context) -> str:
        ctx.need(0x1016, 1)
        _, _, mark = heartbeat_loss(ctx)
        if emcy_wait(ctx, lambda c: c == 0x8130, 1.0, mark) is None:
            raise CaseFailed("no EMCY 0x8130 after the consumed heartbeat stopped")
        mark = ctx.recorder.mark()
        ctx.start_heartbeat(0.025)
        if emcy_wait(ctx, lambda c: c == 0x0000, 1.0, mark) is None:
            raise CaseFailed("no EMCY 0x0000 (error reset) when the heartbeat came back")
        return "EMCY 0x0000 on return"

    def consumer_zero(ctx: Context) -> str:
        sub = consumer_entry(ctx)
        ctx.write(0x1016, sub, ctx.options.master_id << 16)  # time 0: not monitored
        ctx.start_heartbeat(0.02)
        time.sleep(0.08)
        mark = ctx.recorder.mark()
        ctx.stop_heartbeat()
        hit = emcy_wait(ctx, lambda c: c == 0x8130, 0.3, mark)
        if hit is not None:
            raise CaseFailed("EMCY 0x8130 with consumer time 0 (entry not used)")
        return "no EMCY"

    def consumer_duplicate(ctx: Context) -> str:
        ctx.need(0x1016, 2)
        ctx.write(0x1016, 1, ctx.options.master_id << 16 | 100)
        return ctx.expect_abort(
            lambda: ctx.write(0x1016, 2, ctx.options.master_id << 16 | 200), (INCOMPATIBLE,),
            "a second entry for the same node-ID",
        )  # fmt: skip

    return [
        case(g, "0x1017", "producer at its boot value")(producer_boot),
        case(g, "0x1017", "producer follows a new period")(producer_change),
        case(g, "0x1017", "producer off at 0, on again")(producer_off),
        case(g, "0x1016", "consumer entries: reserved bits 0")(consumer_format),
        case(g, "0x1016 §7.2.8.3.2", "consumer timeout -> EMCY 0x8130")(consumer_loss),
        case(g, "0x1016 §7.2.7.1", "consumer return -> EMCY 0x0000")(consumer_resume),
        case(g, "0x1016", "consumer time 0 is not monitored")(consumer_zero),
        case(g, "0x1016 §7.5.2.32", "two entries for one node-ID refused")(consumer_duplicate),
    ]


def arrivals(ctx: Context, cob_id: int, settle_s: float, window_s: float) -> list[float]:
    """Arrival times of frame ``cob_id`` over ``window_s`` after ``settle_s``."""
    time.sleep(settle_s)
    mark = ctx.recorder.mark()
    time.sleep(window_s)
    return [t for t, _ in ctx.recorder.since(mark, cob(cob_id))]


def arrival_gaps(
    ctx: Context, cob_id: int, settle_s: float, window_s: float
) -> tuple[list[float], list[float]]:
    """:func:`arrivals` and the gaps between them (s)."""
    times = arrivals(ctx, cob_id, settle_s, window_s)
    return times, [b - a for a, b in itertools.pairwise(times)]


def mean_period(gaps: list[float], expected_s: float, tolerance: float, failed: str) -> float:
    """The mean of ``gaps``; :class:`CaseFailed` with ``failed`` (its ``{}`` the mean in ms)
    when it is more than ``tolerance`` (relative) off ``expected_s``."""
    mean = sum(gaps) / len(gaps)
    if abs(mean - expected_s) > expected_s * tolerance:
        raise CaseFailed(failed.format(f"{mean * 1e3:.1f}"))
    return mean


# ------------------------------------------------------------------ SDO
def sdo_cases(od: ObjectDictionary) -> list[Case]:
    g = "sdo"

    def expedited_upload(ctx: Context) -> str:
        answer = ctx.raw_sdo((0x40, 0x00, 0x10, 0x00))
        if answer is None:
            raise CaseFailed("no answer")
        if answer[0] & 0xE3 != 0x43 or (answer[0] >> 2) & 3 != 0:
            raise CaseFailed(f"0x1000 upload answered {answer.hex(' ')}, expected 43 ...")
        return answer.hex(" ")

    def expedited_download(ctx: Context) -> str:
        var = ctx.need(0x1017, 0)
        data = ctx.upload(0x1017, 0)
        size = len(var) // 8
        cs = 0x23 | (4 - size) << 2
        answer = ctx.raw_sdo((cs, 0x17, 0x10, 0x00, *data.ljust(4, b"\0")))
        if answer is None or answer[:4] != bytes((0x60, 0x17, 0x10, 0x00)):
            raise CaseFailed(f"answered {answer.hex(' ') if answer else 'nothing'}")
        return "60 17 10 00"

    def segmented_upload(ctx: Context) -> str:
        var = _long_string(ctx)
        got = var.decode_raw(ctx.upload(var.index, var.subindex))
        want = ctx.boot_value(var.index, var.subindex)
        if got != want:
            raise CaseFailed(f"{_hex(var.index, var.subindex)} = {got!r}, EDS {want!r}")
        return f"{_hex(var.index, var.subindex)} = {got!r}"

    def segmented_download(ctx: Context) -> str:
        var = _rw_number(ctx)
        data = ctx.upload(var.index, var.subindex)
        ctx.download(var.index, var.subindex, data, force_segment=True)
        back = ctx.upload(var.index, var.subindex)
        if back != data:
            raise CaseFailed(f"read back {back.hex()} after writing {data.hex()}")
        return f"{_hex(var.index, var.subindex)} written in segments"

    def toggle(ctx: Context) -> str:
        var = _long_string(ctx)
        answer = ctx.raw_sdo((0x40, var.index & 0xFF, var.index >> 8, var.subindex))
        if answer is None or answer[0] & 0xE2 != 0x40 or answer[0] & 0x02:
            raise CaseSkipped("the long string is not uploaded in segments")
        answer = ctx.raw_sdo((0x70,))  # toggle 1 on the first segment
        return _abort_in(answer, (TOGGLE,), "a first segment with toggle 1")

    def block(ctx: Context, request: tuple[int, ...], ok_cs: int, what: str) -> str:
        answer = ctx.raw_sdo(request)
        if answer is None:
            raise CaseFailed(f"{what}: no answer")
        if answer[0] & 0xE0 == ok_cs:
            ctx.raw_sdo((0x80, *request[1:4], *COMMAND.to_bytes(4, "little")), timeout=0.1)
            return "block transfer supported"
        return _abort_in(answer, (COMMAND,), what)

    def block_upload(ctx: Context) -> str:
        return block(ctx, (0xA0, 0x00, 0x10, 0x00, 0x7F, 0x00), 0xC0, "block upload initiate")

    def block_download(ctx: Context) -> str:
        return block(ctx, (0xC2, 0x17, 0x10, 0x00, 0x02, 0, 0, 0), 0xA0,
                     "block download initiate")  # fmt: skip

    def no_object(ctx: Context) -> str:
        index = next(i for i in range(0x5FFF, 0x1FFF, -1) if i not in ctx.od)
        return ctx.expect_abort(lambda: ctx.upload(index, 0), (NO_OBJECT,),
                                f"upload of 0x{index:04X}")  # fmt: skip

    def no_sub(ctx: Context) -> str:
        for obj in ctx.od.values():
            if isinstance(obj, ODRecord | ODArray):
                sub = max(obj.subindices) + 1
                if sub <= 0xFF:
                    what = f"upload of {_hex(obj.index, sub)}"
                    return ctx.expect_abort(lambda o=obj, s=sub: ctx.upload(o.index, s),
                                            (NO_SUB,), what)  # fmt: skip
        raise CaseSkipped("no record or array")

    def read_only(ctx: Context) -> str:
        data = ctx.upload(0x1000, 0)
        return ctx.expect_abort(lambda: ctx.download(0x1000, 0, data), (READ_ONLY,),
                                "download to 0x1000")  # fmt: skip

    def write_only(ctx: Context) -> str:
        var = next((v for v in ctx.variables() if v.access_type == "wo"), None)
        if var is None:
            raise CaseSkipped("no write-only object in the EDS")
        return ctx.expect_abort(lambda: ctx.upload(var.index, var.subindex), (WRITE_ONLY,),
                                f"upload of {_hex(var.index, var.subindex)}")  # fmt: skip

    def too_long(ctx: Context) -> str:
        var = _rw_number(ctx, max_bits=16)
        data = ctx.upload(var.index, var.subindex) + b"\0\0"
        return ctx.expect_abort(lambda: ctx.download(var.index, var.subindex, data),
                                (LENGTH_HIGH, LENGTH), f"{len(data)} bytes to "
                                f"{_hex(var.index, var.subindex)}")  # fmt: skip

    def too_short(ctx: Context) -> str:
        var = _rw_number(ctx, min_bits=32)
        data = ctx.upload(var.index, var.subindex)[:1]
        return ctx.expect_abort(lambda: ctx.download(var.index, var.subindex, data),
                                (LENGTH_LOW, LENGTH), f"1 byte to "
                                f"{_hex(var.index, var.subindex)}")  # fmt: skip

    def bad_command(ctx: Context) -> str:
        return _abort_in(ctx.raw_sdo((0xE0, 0x00, 0x10, 0x00)), (COMMAND,),
                         "command specifier 7")  # fmt: skip

    def stray_upload_segment(ctx: Context) -> str:
        ctx.upload(0x1000, 0)
        return _abort_in(ctx.raw_sdo((0x60,)), (COMMAND,), "upload segment, no transfer open")

    def stray_download_segment(ctx: Context) -> str:
        ctx.upload(0x1000, 0)
        return _abort_in(ctx.raw_sdo((0x00, 1, 2, 3, 4, 5, 6, 7)), (COMMAND,),
                         "download segment, no transfer open")  # fmt: skip

    def history_write(ctx: Context) -> str:
        ctx.need(0x1003, 0)
        return ctx.expect_abort(lambda: ctx.write(0x1003, 0, 1), (INVALID,),
                                "0x1003:00 = 1")  # fmt: skip

    def signature(ctx: Context, index: int) -> str:
        ctx.need(index, 1)
        return ctx.expect_abort(lambda: ctx.write(index, 1, 0x12345678), (STORE,),
                                f"a wrong signature to 0x{index:04X}:01")  # fmt: skip

    cases = [
        case(g, "§7.2.4.3.3", "expedited upload")(expedited_upload),
        case(g, "§7.2.4.3.2", "expedited download")(expedited_download),
        case(g, "§7.2.4.3.5", "segmented upload")(segmented_upload),
        case(g, "§7.2.4.3.4", "segmented download")(segmented_download),
        case(g, "§7.2.4.3.5", "toggle bit not alternated -> 0x05030000")(toggle),
        case(g, "§7.2.4.3.9", "block upload refused or served")(block_upload),
        case(g, "§7.2.4.3.9", "block download refused or served")(block_download),
        case(g, "§7.2.4.3.17", "no object -> 0x06020000")(no_object),
        case(g, "§7.2.4.3.17", "no sub-index -> 0x06090011")(no_sub),
        case(g, "§7.2.4.3.17", "write read-only -> 0x06010002")(read_only),
        case(g, "§7.2.4.3.17", "read write-only -> 0x06010001")(write_only),
        case(g, "§7.2.4.3.17", "length too high -> 0x06070012")(too_long),
        case(g, "§7.2.4.3.17", "length too low -> 0x06070013")(too_short),
        case(g, "§7.2.4.3.17", "unknown command specifier -> 0x05040001")(bad_command),
        case(g, "§7.2.4.3.17", "upload segment, no transfer -> 0x05040001")(stray_upload_segment),
        case(g, "§7.2.4.3.17", "download segment, no transfer -> 0x05040001")(
            stray_download_segment
        ),
        case(g, "0x1003 §7.5.2.5", "history: non-zero write -> 0x06090030")(history_write),
        case(g, "0x1010 §7.5.2.13", "store: wrong signature -> 0x08000020")(
            lambda ctx: signature(ctx, 0x1010)
        ),
        case(g, "0x1011 §7.5.2.14", "restore: wrong signature -> 0x08000020")(
            lambda ctx: signature(ctx, 0x1011)
        ),
    ]
    # The EDS limits, one case per limited writable object and side.
    for var in _variables(od):
        if not var.writable or var.data_type not in _int_types():
            continue
        lo, hi = _type_range(var.data_type)
        if var.max is not None and var.max < hi:
            cases.append(_range_case(g, var, var.max + 1, TOO_HIGH, "above HighLimit"))
        if var.min is not None and var.min > lo:
            cases.append(_range_case(g, var, var.min - 1, TOO_LOW, "below LowLimit"))
    return cases


def _range_case(g: str, var: ODVariable, value: int, code: int, title: str) -> Case:
    def run(ctx: Context) -> str:
        before = ctx.upload(var.index, var.subindex)
        # Packed as the type says, without canopen's own range warning on encoding.
        data = ODVariable.STRUCT_TYPES[var.data_type].pack(value)
        detail = ctx.expect_abort(lambda: ctx.download(var.index, var.subindex, data),
                                  (code,), f"{value}")  # fmt: skip
        if ctx.upload(var.index, var.subindex) != before:
            raise CaseFailed("the refused write changed the value")
        return detail

    return Case(g, _hex(var.index, var.subindex), f"{var.name}: {title} -> 0x{code:08X}", run)


def _abort_in(answer: bytes | None, codes: tuple[int, ...], what: str) -> str:
    if answer is None:
        raise CaseFailed(f"{what}: no answer")
    code = struct.unpack_from("<I", answer, 4)[0]
    if answer[0] != 0x80 or code not in codes:
        want = " or ".join(f"0x{c:08X}" for c in codes)
        raise CaseFailed(f"{what}: answered {answer.hex(' ')}, expected abort {want}")
    return f"abort 0x{code:08X}"


def _long_string(ctx: Context) -> ODVariable:
    for var in ctx.variables():
        value = ctx.boot_value(var.index, var.subindex)
        if (var.data_type == dt.VISIBLE_STRING and var.readable
                and isinstance(value, str) and len(value) > 4):  # fmt: skip
            return var
    raise CaseSkipped("no VISIBLE_STRING longer than 4 characters in the EDS")


def _rw_number(ctx: Context, min_bits: int = 0, max_bits: int = 64) -> ODVariable:
    """A plain rw communication parameter (0x1006/0x1017 style) to exercise SDO with."""
    prefer = (0x1017, 0x1006, 0x1007)
    pool = [ctx.variable(i, 0) for i in prefer] + ctx.variables()
    for var in pool:
        if (var is not None and var.writable and var.readable and not var.pdo_mappable
                and var.data_type in _int_types() and min_bits <= len(var) <= max_bits
                and 0x1000 <= var.index < 0x1400 and var.index not in SIGNATURE_OBJECTS
                and var.index not in (0x1003, 0x1005, 0x1014, 0x1016, 0x1029)):  # fmt: skip
            return var
    raise CaseSkipped(f"no rw communication parameter of {min_bits}..{max_bits} bits")


def _type_range(data_type: int) -> tuple[int, int]:
    if data_type in dt.SIGNED_TYPES:
        bits = {dt.INTEGER8: 8, dt.INTEGER16: 16, dt.INTEGER32: 32, dt.INTEGER64: 64}.get(
            data_type, 32
        )
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    bits = {dt.UNSIGNED8: 8, dt.UNSIGNED16: 16, dt.UNSIGNED32: 32, dt.UNSIGNED64: 64}.get(
        data_type, 32
    )
    return 0, (1 << bits) - 1


def _variables(od: ObjectDictionary) -> list[ODVariable]:
    out: list[ODVariable] = []
    for obj in od.values():
        out += [obj] if isinstance(obj, ODVariable) else list(obj.values())
    return out


# ------------------------------------------------------------------ objects
def object_cases(od: ObjectDictionary) -> list[Case]:
    """Per object of the EDS: the uploaded value against the EDS (value, length), and its
    access type (a write of what was read accepted, or refused for ro/const)."""
    cases = []
    for var in _variables(od):
        cases.append(_value_case(var))
        cases.append(_access_case(var))
    return cases


def _live(var: ODVariable) -> bool:
    """Process values (read-only and PDO-mappable: statusword, actual values): their boot
    value is the device's state, only their type and length are checked."""
    return var.access_type == "ro" and var.pdo_mappable


def _value_case(var: ODVariable) -> Case:
    key = _hex(var.index, var.subindex)

    def run(ctx: Context) -> str:
        if not var.readable:
            raise CaseSkipped("write-only")
        with ctx.node.sdo.open(var.index, var.subindex, buffering=0) as fp:
            indicated = fp.size
            data = fp.read()
        if var.fixed_size:
            size = len(var) // 8
            if indicated is not None and indicated != size:
                raise CaseFailed(f"{indicated} bytes indicated, the type has {size}")
            if len(data) < size:
                raise CaseFailed(f"{len(data)} bytes, the type has {size}")
            data = data[:size]
        got = var.decode_raw(data)
        if _live(var):
            return f"process value {got!r} ({len(data)} bytes)"
        want = ctx.boot_value(var.index, var.subindex)
        if want is None:
            return f"{got!r} (no default in the EDS)"
        if var.encode_raw(want) != data:
            raise CaseFailed(f"node {got!r}, EDS {want!r}")
        return f"{got!r}"

    return Case("objects", key, f"{var.name}: boot value, type and length", run)


def _access_case(var: ODVariable) -> Case:
    key = _hex(var.index, var.subindex)
    access = var.access_type

    def run(ctx: Context) -> str:
        if access == "wo":
            return ctx.expect_abort(lambda: ctx.upload(var.index, var.subindex),
                                    (WRITE_ONLY,), "upload")  # fmt: skip
        data = ctx.upload(var.index, var.subindex)
        if access in ("ro", "const"):
            return ctx.expect_abort(lambda: ctx.download(var.index, var.subindex, data),
                                    (READ_ONLY,), "download of the value read")  # fmt: skip
        if var.index in SIGNATURE_OBJECTS and var.subindex > 0:
            raise CaseSkipped("a store/restore signature object (cases in group sdo)")
        refused = _mapping_locked(ctx, var)
        try:
            ctx.download(var.index, var.subindex, data)
        except SdoAbortedError as exc:
            if refused:
                return f"refused while {refused} (abort 0x{exc.code:08X})"
            raise CaseFailed(f"rw, but a write of the value read: abort 0x{exc.code:08X}") from None
        except SdoCommunicationError as exc:
            raise CaseFailed(f"write: {exc}") from None
        if refused:
            raise CaseFailed(f"mapping written while {refused} (CiA 301 §7.5.2.36)")
        back = ctx.upload(var.index, var.subindex)
        if back != data:
            raise CaseFailed(f"read back {back.hex()} after writing {data.hex()}")
        return "written back"

    return Case("objects", key, f"{var.name}: access {access}", run)


def _mapping_locked(ctx: Context, var: ODVariable) -> str | None:
    """Why CiA 301 forbids changing a PDO mapping entry now (None: it may change)."""
    if not (0x1600 <= var.index < 0x1800 or 0x1A00 <= var.index < 0x1C00):
        return None
    comm = var.index - 0x200
    if ctx.variable(comm, 1) is not None and not ctx.read_int(comm, 1) & PDO_NOT_VALID:
        return "the PDO is valid"
    if var.subindex > 0 and ctx.read_int(var.index, 0) != 0:
        return "sub-index 0 is not 0"
    return None


# ------------------------------------------------------------------ PDO
def pdo_cases(od: ObjectDictionary) -> list[Case]:
    g = "pdo"
    cases: list[Case] = []
    for base, kind in ((0x1400, "RPDO"), (0x1800, "TPDO")):
        for comm in range(base, base + 0x200):
            if comm in od:
                cases.append(_layout_case(comm, f"{kind}{comm - base + 1}"))

    def spare(ctx: Context) -> tuple[int, int]:
        """An unused TPDO (not valid at boot): (comm index, a COB-ID for it)."""
        for comm in reversed(tpdo_comm_indices(ctx)):
            cob_id = ctx.read_int(comm, 1)
            if cob_id & PDO_NOT_VALID and ctx.variable(comm + 0x200, 1) is not None:
                return comm, cob_id & 0x7FF
        raise CaseSkipped("no TPDO that is not valid at boot")

    def mappable(ctx: Context, bits: int | None = None, rw: bool | None = None) -> ODVariable:
        for var in ctx.variables():
            if (var.pdo_mappable and var.readable and var.index >= 0x2000
                    and (bits is None or len(var) == bits)
                    and (rw is None or (var.access_type in ("rw", "rww")) == rw)):  # fmt: skip
                return var
        raise CaseSkipped(f"no mappable object of {bits} bits")

    def entry(var: ODVariable) -> int:
        return var.index << 16 | var.subindex << 8 | len(var)

    def procedure(ctx: Context) -> str:
        comm, cob_id = spare(ctx)
        mapping = comm + 0x200
        var = mappable(ctx, rw=False)
        ctx.write(mapping, 0, 0)
        ctx.write(mapping, 1, entry(var))
        ctx.write(mapping, 0, 1)
        ctx.write(comm, 2, 1)
        ctx.write(comm, 1, cob_id)  # valid
        got = live_layout(ctx, comm)
        if got[:2] != (cob_id, True) or got[3] != [(var.index, var.subindex, len(var))]:
            raise CaseFailed(f"layout read back {got}")
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        mark = ctx.recorder.mark()
        ctx.sync()
        hit = ctx.recorder.wait(cob(cob_id), 0.2, mark)
        if hit is None:
            raise CaseFailed(f"the new TPDO 0x{cob_id:03X} not sent on SYNC")
        if len(hit[1].data) != len(var) // 8:
            raise CaseFailed(f"TPDO of {len(hit[1].data)} bytes, mapping {len(var) // 8}")
        return f"0x{cob_id:03X} maps {_hex(var.index, var.subindex)} {var.name}"

    def entries_while_count(ctx: Context) -> str:
        comm, _ = spare(ctx)
        mapping = comm + 0x200
        var = mappable(ctx, rw=False)
        ctx.write(mapping, 0, 0)
        ctx.write(mapping, 1, entry(var))
        ctx.write(mapping, 0, 1)
        return ctx.expect_abort(lambda: ctx.write(mapping, 1, entry(var)), (),
                                "an entry written while sub-index 0 != 0")  # fmt: skip

    def mapping_while_valid(ctx: Context) -> str:
        for comm in tpdo_comm_indices(ctx):
            if not ctx.read_int(comm, 1) & PDO_NOT_VALID and ctx.read_int(comm + 0x200, 0):
                count = ctx.read_int(comm + 0x200, 0)
                return ctx.expect_abort(lambda c=comm, n=count: ctx.write(c + 0x200, 0, n), (),
                                        "sub-index 0 written while the PDO is valid")  # fmt: skip
        raise CaseSkipped("no valid TPDO")

    def not_mappable(ctx: Context) -> str:
        comm, _ = spare(ctx)
        ctx.write(comm + 0x200, 0, 0)
        return ctx.expect_abort(lambda: ctx.write(comm + 0x200, 1, 0x10000020),
                                (NOT_MAPPABLE,), "mapping 0x1000:00")  # fmt: skip

    def missing(ctx: Context) -> str:
        comm, _ = spare(ctx)
        ctx.write(comm + 0x200, 0, 0)
        index = next(i for i in range(0x5FFF, 0x1FFF, -1) if i not in ctx.od)
        return ctx.expect_abort(lambda: ctx.write(comm + 0x200, 1, index << 16 | 0x10),
                                (NO_OBJECT, NOT_MAPPABLE), f"mapping 0x{index:04X}")  # fmt: skip

    def wrong_length(ctx: Context) -> str:
        comm, _ = spare(ctx)
        var = mappable(ctx, rw=False)
        ctx.write(comm + 0x200, 0, 0)
        bad = var.index << 16 | var.subindex << 8 | (len(var) + 8)
        return ctx.expect_abort(lambda: ctx.write(comm + 0x200, 1, bad),
                                (INCOMPATIBLE, NOT_MAPPABLE, PDO_LENGTH),
                                "an entry stating the wrong length")  # fmt: skip

    def too_long(ctx: Context) -> str:
        comm, _ = spare(ctx)
        mapping = comm + 0x200
        if ctx.variable(mapping, 3) is None:
            raise CaseSkipped("fewer than 3 mapping entries")
        var = mappable(ctx, bits=32)
        ctx.write(mapping, 0, 0)
        for sub in (1, 2, 3):
            ctx.write(mapping, sub, entry(var))
        return ctx.expect_abort(lambda: ctx.write(mapping, 0, 3), (PDO_LENGTH,),
                                "96 bits enabled")  # fmt: skip

    def cob_while_valid(ctx: Context) -> str:
        for comm in tpdo_comm_indices(ctx):
            cob_id = ctx.read_int(comm, 1)
            if not cob_id & PDO_NOT_VALID:
                new = (cob_id & 0x7FF) ^ 0x40
                return ctx.expect_abort(lambda c=comm, n=new: ctx.write(c, 1, n), (INVALID,),
                                        "a new COB-ID while valid")  # fmt: skip
        raise CaseSkipped("no valid TPDO")

    def reserved_type(ctx: Context) -> str:
        comm = tpdo_comm_indices(ctx)[0] if tpdo_comm_indices(ctx) else None
        if comm is None:
            raise CaseSkipped("no TPDO")
        return ctx.expect_abort(lambda: ctx.write(comm, 2, 245), (INVALID,),
                                "transmission type 245 (reserved)")  # fmt: skip

    def every_nth(ctx: Context) -> str:
        comm, cob_id = first_sync_tpdo(ctx)
        ctx.write(comm, 2, 3)
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        n = syncs_answered(ctx, cob_id, 12)
        if n != 4:
            raise CaseFailed(f"{n} frames on 12 SYNC with transmission type 3, expected 4")
        return "4 frames on 12 SYNC"

    def every_sync(ctx: Context) -> str:
        _comm, cob_id = first_sync_tpdo(ctx)
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        n = syncs_answered(ctx, cob_id, 10)
        if n != 10:
            raise CaseFailed(f"{n} frames on 10 SYNC with transmission type 1")
        return "10 frames on 10 SYNC"

    def event_tpdo(ctx: Context) -> tuple[int, int]:
        for comm in tpdo_comm_indices(ctx):
            cob_id, valid, trans, entries = live_layout(ctx, comm)
            if valid and trans >= 254 and entries and ctx.variable(comm, 5) is not None:
                return comm, cob_id
        raise CaseSkipped("no valid event-driven TPDO with an event timer")

    def event_timer(ctx: Context) -> str:
        comm, cob_id = event_tpdo(ctx)
        ctx.write(comm, 5, 20)
        ctx.nmt(NMT_START)
        times, gaps = arrival_gaps(ctx, cob_id, 0.05, 0.3)
        if len(gaps) < 5:
            raise CaseFailed(f"{len(times)} frames in 0.3 s with an event timer of 20 ms")
        mean = mean_period(gaps, 0.02, max(ctx.options.period_tolerance, 0.2),
                           "mean period {} ms with event timer 20 ms")  # fmt: skip
        return f"mean period {mean * 1e3:.1f} ms"

    def inhibit(ctx: Context) -> str:
        comm, cob_id = event_tpdo(ctx)
        ctx.need(comm, 3)
        raw = ctx.read_int(comm, 1)
        ctx.write(comm, 1, raw | PDO_NOT_VALID)
        ctx.write(comm, 3, 400)  # 40 ms
        ctx.write(comm, 5, 10)
        ctx.write(comm, 1, raw & ~PDO_NOT_VALID)
        ctx.nmt(NMT_START)
        times, gaps = arrival_gaps(ctx, cob_id, 0.05, 0.3)
        if len(gaps) < 3:
            raise CaseFailed(f"{len(times)} frames in 0.3 s")
        short = min(gaps)
        if short < 0.040 * 0.9:
            raise CaseFailed(f"frames {short * 1e3:.1f} ms apart with inhibit time 40 ms")
        return f"shortest gap {short * 1e3:.1f} ms (inhibit 40 ms, event timer 10 ms)"

    def rpdo_received(ctx: Context) -> str:
        for comm in rpdo_comm_indices(ctx):
            cob_id, valid, trans, entries = live_layout(ctx, comm)
            if valid and entries:
                break
        else:
            raise CaseSkipped("no valid RPDO")
        payload = b""
        for index, sub, bits in entries:
            payload += ctx.upload(index, sub)[: bits // 8]
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        mark = ctx.recorder.mark()
        ctx.send(cob_id, payload)
        if trans <= 240:
            ctx.sync()
        time.sleep(0.05)
        for index, sub, _bits in entries:
            ctx.upload(index, sub)
        emcy = emcy_wait(ctx, lambda c: c != 0, 0.05, mark)
        if emcy is not None:
            raise CaseFailed(f"EMCY 0x{emcy[1]:04X} after a well-formed RPDO")
        return f"RPDO 0x{cob_id:03X} of {len(payload)} bytes accepted"

    cases += [
        case(g, "§7.5.2.36", "mapping procedure on an unused TPDO")(procedure),
        case(g, "§7.5.2.36", "entry refused while sub-index 0 != 0")(entries_while_count),
        case(g, "§7.5.2.36", "mapping refused while the PDO is valid")(mapping_while_valid),
        case(g, "§7.5.2.36", "non-mappable object -> 0x06040041")(not_mappable),
        case(g, "§7.5.2.36", "missing object -> 0x06020000")(missing),
        case(g, "§7.5.2.36", "wrong entry length refused")(wrong_length),
        case(g, "§7.5.2.36", "more than 64 bits -> 0x06040042")(too_long),
        case(g, "§7.5.2.35", "COB-ID change while valid -> 0x06090030")(cob_while_valid),
        case(g, "§7.5.2.35", "reserved transmission type refused")(reserved_type),
        case(g, "§7.2.2.2", "transmission type 1: every SYNC")(every_sync),
        case(g, "§7.2.2.2", "transmission type 3: every 3rd SYNC")(every_nth),
        case(g, "§7.5.2.35", "event timer")(event_timer),
        case(g, "§7.5.2.35", "inhibit time")(inhibit),
        case(g, "§7.2.2", "RPDO received")(rpdo_received),
    ]
    return cases


def _layout_case(comm: int, name: str) -> Case:
    def run(ctx: Context) -> str:
        cob_id, valid, trans, entries = live_layout(ctx, comm)
        bits = 0
        for index, sub, length in entries:
            if 1 <= index <= 7:  # dummy entry
                bits += length
                continue
            var = ctx.variable(index, sub)
            if var is None:
                raise CaseFailed(f"maps {_hex(index, sub)}, not in the EDS")
            if not var.pdo_mappable:
                raise CaseFailed(f"maps {_hex(index, sub)}, not PDO-mappable in the EDS")
            if length != len(var):
                raise CaseFailed(f"maps {_hex(index, sub)} with {length} bits, type {len(var)}")
            bits += length
        if bits > 64:
            raise CaseFailed(f"{bits} bits mapped")
        if valid and not entries:
            raise CaseFailed("valid with no mapped object")
        state = "valid" if valid else "not valid"
        return f"0x{cob_id:03X} {state}, type {trans}, {len(entries)} entries, {bits} bits"

    return Case("pdo", f"0x{comm:04X}", f"{name} layout against the EDS", run)


# ------------------------------------------------------------------ SYNC
def sync_cases(od: ObjectDictionary) -> list[Case]:
    g = "sync"

    def consumer(ctx: Context) -> str:
        ctx.need(0x1005, 0)
        v = ctx.read_int(0x1005, 0)
        if v & (1 << 30):
            raise CaseSkipped("the node is the SYNC producer (0x1005 bit 30)")
        return f"consumer at 0x{v & 0x7FF:03X}"

    def counter(ctx: Context) -> str:
        _comm, cob_id = first_sync_tpdo(ctx)
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        mark = ctx.recorder.mark()
        for k in range(1, 9):
            ctx.sync(counter=k)
            time.sleep(0.005)
        time.sleep(0.05)
        n = len(ctx.recorder.since(mark, cob(cob_id)))
        if n != 8:
            raise CaseFailed(f"{n} TPDO frames on 8 SYNC carrying a counter")
        return "answered 8 of 8"

    def supervision(ctx: Context) -> str:
        ctx.need(0x1006, 0)
        ctx.write(0x1006, 0, 10000)
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        for _ in range(10):
            ctx.sync()
            time.sleep(0.01)
        mark = ctx.recorder.mark()
        last = time.monotonic()
        hit = emcy_wait(ctx, lambda c: c & 0xFF00 == 0x8100, 0.5, mark)
        if hit is None:
            raise CaseFailed("no EMCY 0x81xx when SYNC stopped (0x1006 = 10 ms)")
        return f"EMCY 0x{hit[1]:04X} {(hit[0] - last) * 1e3:.0f} ms after the last SYNC"

    def no_supervision(ctx: Context) -> str:
        ctx.need(0x1006, 0)
        ctx.write(0x1006, 0, 0)
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        for _ in range(5):
            ctx.sync()
            time.sleep(0.01)
        mark = ctx.recorder.mark()
        hit = emcy_wait(ctx, lambda c: c & 0xFF00 == 0x8100, 0.2, mark)
        if hit is not None:
            raise CaseFailed(f"EMCY 0x{hit[1]:04X} with 0x1006 = 0")
        return "no EMCY"

    def window(ctx: Context) -> str:
        ctx.need(0x1007, 0)
        _comm, cob_id = first_sync_tpdo(ctx)
        ctx.write(0x1006, 0, 0)
        ctx.write(0x1007, 0, 5000)
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        late = []
        for _ in range(10):
            mark = ctx.recorder.mark()
            t = ctx.sync()
            hit = ctx.recorder.wait(cob(cob_id), 0.05, mark)
            if hit is None or hit[0] - t > 0.005:
                late.append(None if hit is None else hit[0] - t)
            time.sleep(0.005)
        if len(late) > 1:  # one late frame is the suite's own scheduling, two are not
            raise CaseFailed(f"{len(late)} of 10 TPDOs outside the 5 ms window")
        return f"{10 - len(late)} of 10 within 5 ms"

    return [
        case(g, "0x1005", "SYNC consumer COB-ID")(consumer),
        case(g, "§7.2.5", "SYNC with counter answered")(counter),
        case(g, "0x1006", "SYNC loss supervised -> EMCY 0x81xx")(supervision),
        case(g, "0x1006", "no supervision with period 0")(no_supervision),
        case(g, "0x1007", "synchronous TPDOs within the window")(window),
    ]


# ------------------------------------------------------------------ EMCY
def emcy_cases(od: ObjectDictionary) -> list[Case]:
    g = "emcy"

    def cob_id(ctx: Context) -> str:
        ctx.need(0x1014, 0)
        v = ctx.read_int(0x1014, 0)
        if v & (1 << 31):
            raise CaseFailed("EMCY not valid (0x1014 bit 31)")
        if v & 0x7FF != EMCY_BASE + ctx.node_id:
            return f"0x{v & 0x7FF:03X} (not the pre-defined 0x{EMCY_BASE + ctx.node_id:03X})"
        return f"0x{v & 0x7FF:03X}"

    def clean_boot(ctx: Context) -> str:
        reg = ctx.read_int(0x1001, 0)
        n = ctx.read_int(0x1003, 0) if ctx.variable(0x1003, 0) is not None else 0
        if reg or n:
            raise CaseFailed(f"error register 0x{reg:02X}, {n} errors in 0x1003 after boot")
        return "0x1001 = 0, 0x1003:00 = 0"

    def provoke(ctx: Context) -> tuple[float, int, int, bytes]:
        if ctx.variable(0x1016, 1) is not None:
            _, _, mark = heartbeat_loss(ctx)
            hit = emcy_wait(ctx, lambda c: c != 0, 1.0, mark)
        elif ctx.variable(0x1006, 0) is not None:
            ctx.write(0x1006, 0, 10000)
            ctx.nmt(NMT_START)
            for _ in range(5):
                ctx.sync()
                time.sleep(0.01)
            hit = emcy_wait(ctx, lambda c: c != 0, 1.0, ctx.recorder.mark())
        else:
            raise CaseSkipped("neither 0x1016 nor 0x1006 to provoke an EMCY")
        if hit is None:
            raise CaseFailed("no EMCY for a communication error")
        time.sleep(0.02)
        return hit

    def frame(ctx: Context) -> str:
        _t, code, register, _manufacturer = provoke(ctx)
        if not register & 0x01:
            raise CaseFailed(f"error register 0x{register:02X} in EMCY 0x{code:04X}: bit 0 "
                             "(generic error) clear")  # fmt: skip
        if code & 0xFF00 in (0x8100, 0x8200) and not register & 0x10:
            raise CaseFailed(f"EMCY 0x{code:04X} without error register bit 4 (communication)")
        reg = ctx.read_int(0x1001, 0)
        if reg != register:
            raise CaseFailed(f"0x1001 = 0x{reg:02X}, the EMCY said 0x{register:02X}")
        return f"EMCY 0x{code:04X}, register 0x{register:02X} = 0x1001"

    def history(ctx: Context) -> str:
        ctx.need(0x1003, 1)
        _, code, _, _ = provoke(ctx)
        n = ctx.read_int(0x1003, 0)
        first = ctx.read_int(0x1003, 1)
        if n < 1 or first & 0xFFFF != code:
            raise CaseFailed(f"0x1003:00 = {n}, 0x1003:01 = 0x{first:08X} after EMCY 0x{code:04X}")
        return f"0x1003:01 = 0x{first:08X}"

    def clear(ctx: Context) -> str:
        ctx.need(0x1003, 1)
        provoke(ctx)
        ctx.write(0x1003, 0, 0)
        n = ctx.read_int(0x1003, 0)
        if n:
            raise CaseFailed(f"0x1003:00 = {n} after writing 0")
        return "history cleared"

    def silent_when_stopped(ctx: Context) -> str:
        ctx.need(0x1016, 1)
        ctx.nmt(NMT_STOP)
        time.sleep(0.02)
        _, _, mark = heartbeat_loss_stopped(ctx)
        hit = emcy_wait(ctx, lambda c: True, 0.3, mark)
        if hit is not None:
            raise CaseFailed(f"EMCY 0x{hit[1]:04X} in STOPPED")
        return "no EMCY in STOPPED"

    return [
        case(g, "0x1014", "EMCY COB-ID valid")(cob_id),
        case(g, "0x1001 0x1003", "no error after boot")(clean_boot),
        case(g, "§7.2.7.3.1", "EMCY frame: register bits, equals 0x1001")(frame),
        case(g, "0x1003 §7.5.2.5", "pre-defined error field records it")(history),
        case(g, "0x1003 §7.5.2.5", "writing 0 clears the history")(clear),
        case(g, "§7.3.2.2", "no EMCY in STOPPED")(silent_when_stopped),
    ]


def heartbeat_loss_stopped(ctx: Context) -> tuple[float, float, int]:
    """:func:`heartbeat_loss` configured before NMT stop (no SDO in STOPPED)."""
    ctx.nmt(NMT_PRE_OPERATIONAL)
    time.sleep(0.02)
    sub = consumer_entry(ctx)
    ctx.write(0x1016, sub, ctx.options.master_id << 16 | 100)
    ctx.nmt(NMT_STOP)
    ctx.start_heartbeat(0.025)
    time.sleep(0.12)
    mark = ctx.recorder.mark()
    last = ctx.stop_heartbeat()
    return last, last + 0.1, mark
