"""CiA 402 cases: the PDS state machine (every transition), quick stop and the 0x605A
options, the abort connection option 0x6007, modes of operation, and the cyclic
synchronous torque objects' types and units.  The controlword is written by SDO
(0x6040), the statusword read by SDO (0x6041).  Transitions are numbered as in
CiA 402-2 "PDS finite state automaton"."""

from __future__ import annotations

import time

from canopen.objectdictionary import ObjectDictionary
from canopen.objectdictionary import datatypes as dt

from hdhil.conformance.cia301 import emcy_wait
from hdhil.conformance.suite import (
    NMT_PRE_OPERATIONAL,
    NMT_START,
    Case,
    CaseFailed,
    CaseSkipped,
    Context,
)

__all__ = ["cst_cases", "state_machine_cases"]

CONTROLWORD = 0x6040
STATUSWORD = 0x6041

#: State -> (statusword mask, pattern) (CiA 402-2 table "statusword bits").
STATES: dict[str, tuple[int, int]] = {
    "NOT READY TO SWITCH ON": (0x4F, 0x00),
    "SWITCH ON DISABLED": (0x4F, 0x40),
    "READY TO SWITCH ON": (0x6F, 0x21),
    "SWITCHED ON": (0x6F, 0x23),
    "OPERATION ENABLED": (0x6F, 0x27),
    "QUICK STOP ACTIVE": (0x6F, 0x07),
    "FAULT REACTION ACTIVE": (0x4F, 0x0F),
    "FAULT": (0x4F, 0x08),
}
SOD, RTSO, SO, OE, QSA, FAULT = (
    "SWITCH ON DISABLED",
    "READY TO SWITCH ON",
    "SWITCHED ON",
    "OPERATION ENABLED",
    "QUICK STOP ACTIVE",
    "FAULT",
)
#: Controlword commands (CiA 402-2 "command coding").
SHUTDOWN, SWITCH_ON, ENABLE, DISABLE_VOLTAGE, QUICK_STOP, DISABLE_OP, RESET = (
    0x06, 0x07, 0x0F, 0x00, 0x02, 0x07, 0x80,
)  # fmt: skip
#: The walk from SWITCH ON DISABLED to each state.
WALK: dict[str, tuple[int, ...]] = {
    SOD: (),
    RTSO: (SHUTDOWN,),
    SO: (SHUTDOWN, SWITCH_ON),
    OE: (SHUTDOWN, SWITCH_ON, ENABLE),
}

#: CiA 402-2 data types of the objects the suite checks (object dictionary clause).
CIA402_TYPES: dict[int, tuple[str, int]] = {
    0x603F: ("error code", dt.UNSIGNED16),
    0x6040: ("controlword", dt.UNSIGNED16),
    0x6041: ("statusword", dt.UNSIGNED16),
    0x6007: ("abort connection option code", dt.INTEGER16),
    0x605A: ("quick stop option code", dt.INTEGER16),
    0x605E: ("fault reaction option code", dt.INTEGER16),
    0x6060: ("modes of operation", dt.INTEGER8),
    0x6061: ("modes of operation display", dt.INTEGER8),
    0x6064: ("position actual value", dt.INTEGER32),
    0x606C: ("velocity actual value", dt.INTEGER32),
    0x6071: ("target torque", dt.INTEGER16),
    0x6072: ("max torque", dt.UNSIGNED16),
    0x6076: ("motor rated torque", dt.UNSIGNED32),
    0x6077: ("torque actual value", dt.INTEGER16),
    0x6502: ("supported drive modes", dt.UNSIGNED32),
}
#: Objects CiA 402-2 requires to be mappable for cyclic synchronous torque.
CST_MAPPABLE = (0x6040, 0x6041, 0x6071, 0x6077, 0x6064)
CST_MODE = 10


def state_of(statusword: int) -> str:
    for name, (mask, pattern) in STATES.items():
        if statusword & mask == pattern:
            return name
    return f"unknown (0x{statusword:04X})"


def statusword(ctx: Context) -> int:
    return ctx.read_int(STATUSWORD, 0)


def state(ctx: Context) -> str:
    return state_of(statusword(ctx))


def command(ctx: Context, word: int) -> None:
    ctx.write(CONTROLWORD, 0, word)


def await_state(ctx: Context, want: str | tuple[str, ...], timeout: float = 0.5) -> str:
    wants = (want,) if isinstance(want, str) else want
    end = time.monotonic() + timeout
    while True:
        got = state(ctx)
        if got in wants or time.monotonic() > end:
            return got
        time.sleep(0.005)


def expect(ctx: Context, want: str | tuple[str, ...], what: str, timeout: float = 0.5) -> str:
    got = await_state(ctx, want, timeout)
    wants = (want,) if isinstance(want, str) else want
    if got not in wants:
        raise CaseFailed(f"{what}: {got}, expected {' or '.join(wants)}")
    return got


def walk(ctx: Context, to: str) -> None:
    """From SWITCH ON DISABLED to ``to``, each step checked."""
    ctx.need(CONTROLWORD)
    expect(ctx, SOD, "before the walk")
    for word, step in zip(WALK[to], (RTSO, SO, OE), strict=False):
        command(ctx, word)
        expect(ctx, step, f"controlword 0x{word:04X}")


def transition(number: int, start: str, word: int, end: str | tuple[str, ...],
               motion: bool = False, title: str = "") -> Case:  # fmt: skip
    ends = end if isinstance(end, str) else " or ".join(end)

    def run(ctx: Context) -> str:
        walk(ctx, start)
        command(ctx, word)
        got = expect(ctx, end, f"controlword 0x{word:04X} in {start}")
        command(ctx, DISABLE_VOLTAGE)
        return got

    name = title or f"{start} --0x{word:04X}--> {ends}"
    return Case("cia402", f"transition {number}", name, run, motion)


def fault(ctx: Context) -> int:
    """Fault the drive with the abort connection option 1 (fault) and an NMT
    pre-operational from OPERATIONAL; returns 0x603F."""
    ctx.need(0x6007)
    ctx.write(0x6007, 0, 1)
    ctx.nmt(NMT_START)
    time.sleep(0.02)
    walk(ctx, SO)
    ctx.nmt(NMT_PRE_OPERATIONAL)
    expect(ctx, FAULT, "abort connection with 0x6007 = 1", timeout=1.0)
    return ctx.read_int(0x603F, 0) if ctx.variable(0x603F) is not None else 0


def state_machine_cases(od: ObjectDictionary) -> list[Case]:
    g = "cia402"
    if CONTROLWORD not in od or STATUSWORD not in od:
        return []

    def boot(ctx: Context) -> str:
        return expect(ctx, SOD, "after boot (transitions 0 and 1)")

    def no_switch_on(ctx: Context) -> str:
        command(ctx, SWITCH_ON)
        time.sleep(0.05)
        return expect(ctx, SOD, "switch on in SWITCH ON DISABLED", timeout=0.0)

    def no_enable(ctx: Context) -> str:
        walk(ctx, RTSO)
        command(ctx, ENABLE)
        got = await_state(ctx, (RTSO, OE), 0.05)
        command(ctx, DISABLE_VOLTAGE)
        if got not in (RTSO, OE):  # 3+4 at once is allowed (CiA 402-2 note on 0x0F)
            raise CaseFailed(f"enable operation in READY TO SWITCH ON: {got}")
        return got

    def t11(ctx: Context) -> str:
        ctx.need(0x605A)
        ctx.write(0x605A, 0, 6)
        walk(ctx, OE)
        command(ctx, QUICK_STOP)
        got = expect(ctx, QSA, "quick stop with 0x605A = 6")
        command(ctx, DISABLE_VOLTAGE)
        return got

    def t12(ctx: Context) -> str:
        ctx.need(0x605A)
        ctx.write(0x605A, 0, 6)
        walk(ctx, OE)
        command(ctx, QUICK_STOP)
        expect(ctx, QSA, "quick stop with 0x605A = 6")
        command(ctx, DISABLE_VOLTAGE)
        return expect(ctx, SOD, "disable voltage in QUICK STOP ACTIVE")

    def t16(ctx: Context) -> str:
        ctx.need(0x605A)
        ctx.write(0x605A, 0, 6)
        walk(ctx, OE)
        command(ctx, QUICK_STOP)
        expect(ctx, QSA, "quick stop with 0x605A = 6")
        command(ctx, ENABLE)
        got = expect(ctx, OE, "enable operation in QUICK STOP ACTIVE")
        command(ctx, DISABLE_VOLTAGE)
        return got

    def t13_14(ctx: Context) -> str:
        code = fault(ctx)
        sw = statusword(ctx)
        if not sw & 0x08:
            raise CaseFailed(f"statusword 0x{sw:04X}: fault bit 3 clear")
        return f"FAULT, 0x603F = 0x{code:04X}"

    def t15(ctx: Context) -> str:
        fault(ctx)
        ctx.nmt(NMT_START)
        command(ctx, DISABLE_VOLTAGE)
        command(ctx, RESET)
        return expect(ctx, SOD, "fault reset (rising edge of bit 7)")

    def error_code(ctx: Context) -> str:
        ctx.need(0x603F)
        ctx.need(0x6007)
        ctx.write(0x6007, 0, 1)
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        walk(ctx, SO)
        mark = ctx.recorder.mark()
        ctx.nmt(NMT_PRE_OPERATIONAL)
        hit = emcy_wait(ctx, lambda c: c != 0, 0.5, mark)
        expect(ctx, FAULT, "abort connection with 0x6007 = 1", timeout=1.0)
        code = ctx.read_int(0x603F, 0)
        if hit is None:
            raise CaseFailed("no EMCY when the drive faulted")
        if code != hit[1]:
            raise CaseFailed(f"0x603F = 0x{code:04X}, EMCY 0x{hit[1]:04X}")
        return f"0x603F = EMCY = 0x{code:04X}"

    def reset_needs_edge(ctx: Context) -> str:
        fault(ctx)
        ctx.nmt(NMT_START)
        command(ctx, SHUTDOWN)  # no bit 7: no reset
        time.sleep(0.05)
        return expect(ctx, FAULT, "shutdown in FAULT", timeout=0.0)

    cases = [
        Case(g, "transitions 0, 1", "SWITCH ON DISABLED after boot", boot),
        transition(2, SOD, SHUTDOWN, RTSO),
        transition(3, RTSO, SWITCH_ON, SO),
        transition(4, SO, ENABLE, OE, motion=True),
        transition(5, OE, DISABLE_OP, SO, motion=True),
        transition(6, SO, SHUTDOWN, RTSO),
        transition(7, RTSO, DISABLE_VOLTAGE, SOD),
        transition(7, RTSO, QUICK_STOP, SOD, title="READY TO SWITCH ON --quick stop--> SOD"),
        transition(8, OE, SHUTDOWN, RTSO, motion=True),
        transition(9, OE, DISABLE_VOLTAGE, SOD, motion=True),
        transition(10, SO, DISABLE_VOLTAGE, SOD),
        transition(10, SO, QUICK_STOP, SOD, title="SWITCHED ON --quick stop--> SOD"),
        Case(g, "transition 11", "OPERATION ENABLED --quick stop--> QUICK STOP ACTIVE", t11,
             motion=True),
        Case(g, "transition 12", "QUICK STOP ACTIVE --disable voltage--> SOD", t12,
             motion=True),
        Case(g, "transition 16", "QUICK STOP ACTIVE --enable operation--> OPERATION ENABLED",
             t16, motion=True),
        Case(g, "transitions 13, 14", "fault -> FAULT REACTION ACTIVE -> FAULT", t13_14),
        Case(g, "transition 15", "FAULT --fault reset--> SWITCH ON DISABLED", t15),
        Case(g, "transition 15", "no reset without the bit 7 edge", reset_needs_edge),
        Case(g, "0x603F", "error code equals the EMCY code", error_code),
        Case(g, "command coding", "switch on in SWITCH ON DISABLED: no transition",
             no_switch_on),
        Case(g, "command coding", "enable operation in READY TO SWITCH ON", no_enable,
             motion=True),
    ]  # fmt: skip
    cases += quick_stop_cases(od) + abort_connection_cases(od) + mode_cases(od)
    return cases


def _option_range(od: ObjectDictionary, index: int, lo: int, hi: int) -> range:
    var = od.get(index)
    if var is None:
        return range(0)
    low = lo if var.min is None else max(lo, var.min)
    high = hi if var.max is None else min(hi, var.max)
    return range(low, high + 1)


def quick_stop_cases(od: ObjectDictionary) -> list[Case]:
    """One case per 0x605A option the EDS allows: 0-4 end in SWITCH ON DISABLED, 5-8
    stay in QUICK STOP ACTIVE."""
    cases = []
    for option in _option_range(od, 0x605A, 0, 8):
        stays = option >= 5

        def run(ctx: Context, option: int = option, stays: bool = stays) -> str:
            ctx.write(0x605A, 0, option)
            walk(ctx, OE)
            command(ctx, QUICK_STOP)
            if stays:
                expect(ctx, QSA, "quick stop")
                time.sleep(0.2)
                got = expect(ctx, QSA, "0.2 s after the quick stop", timeout=0.0)
            else:
                got = expect(ctx, SOD, "after the quick stop", timeout=1.0)
            command(ctx, DISABLE_VOLTAGE)
            return got

        end = "stays in QUICK STOP ACTIVE" if stays else "ends in SWITCH ON DISABLED"
        cases.append(Case("cia402", "0x605A", f"option {option}: {end}", run, motion=True))
    return cases


def abort_connection_cases(od: ObjectDictionary) -> list[Case]:
    """One case per 0x6007 option the EDS allows, the abort connection event being an
    NMT enter pre-operational from OPERATIONAL (PDOs stop), in SWITCHED ON (no motion):
    0 no action, 1 fault, 2 disable voltage, 3 quick stop (both lead to SWITCH ON
    DISABLED from SWITCHED ON)."""
    ends = {0: (SO,), 1: (FAULT,), 2: (SOD,), 3: (SOD, QSA)}
    cases = []
    for option in _option_range(od, 0x6007, 0, 3):

        def run(ctx: Context, option: int = option) -> str:
            ctx.write(0x6007, 0, option)
            ctx.nmt(NMT_START)
            time.sleep(0.02)
            walk(ctx, SO)
            ctx.nmt(NMT_PRE_OPERATIONAL)
            time.sleep(0.05)
            return expect(ctx, ends[option], "after the connection was aborted", timeout=0.5)

        names = {0: "no action", 1: "fault", 2: "disable voltage", 3: "quick stop"}
        cases.append(Case("cia402", "0x6007", f"option {option}: {names[option]}", run))
    return cases


def mode_cases(od: ObjectDictionary) -> list[Case]:
    if 0x6060 not in od:
        return []

    def cst(ctx: Context) -> str:
        supported = ctx.read_int(0x6502, 0) if ctx.variable(0x6502) is not None else None
        if supported is not None and not supported >> (CST_MODE - 1) & 1:
            raise CaseSkipped("CST not in 0x6502")
        ctx.write(0x6060, 0, CST_MODE)
        shown = ctx.read_int(0x6061, 0)
        if shown != CST_MODE:
            raise CaseFailed(f"0x6061 = {shown} after 0x6060 = {CST_MODE}")
        return "0x6061 = 10"

    def unsupported(ctx: Context) -> str:
        ctx.need(0x6502)
        supported = ctx.read_int(0x6502, 0)
        mode = next((m for m in range(1, 11) if not supported >> (m - 1) & 1), None)
        if mode is None:
            raise CaseSkipped("every mode 1-10 is supported")
        before = ctx.read_int(0x6061, 0)
        try:
            ctx.write(0x6060, 0, mode)
        except Exception as exc:
            return f"refused ({exc})"
        time.sleep(0.02)
        shown = ctx.read_int(0x6061, 0)
        if shown == mode:
            raise CaseFailed(f"0x6061 shows mode {mode}, which 0x6502 says is not supported")
        return f"0x6061 stays {before}"

    return [
        Case("cia402", "0x6060 0x6061", "CST mode selected and displayed", cst),
        Case("cia402", "0x6060 0x6502", "an unsupported mode is not taken", unsupported),
    ]


def cst_cases(od: ObjectDictionary) -> list[Case]:
    """The CiA 402 objects present in the EDS: their data types and PDO mapping as
    CiA 402-2 defines them, and the torque units (per mille of 0x6076)."""
    cases = []
    for index, (name, data_type) in CIA402_TYPES.items():
        if index not in od:
            continue

        def run(ctx: Context, index: int = index, data_type: int = data_type) -> str:
            var = ctx.need(index)
            if var.data_type != data_type:
                raise CaseFailed(f"EDS type 0x{var.data_type:04X}, CiA 402 0x{data_type:04X}")
            data = ctx.upload(index, 0)
            if len(data) != len(var) // 8:
                raise CaseFailed(f"{len(data)} bytes uploaded")
            return f"type 0x{data_type:04X}, {len(data)} bytes"

        cases.append(Case("cst", f"0x{index:04X}", f"{name}: CiA 402 data type", run))
    for index in CST_MAPPABLE:
        if index not in od:
            continue

        def mappable(ctx: Context, index: int = index) -> str:
            if not ctx.need(index).pdo_mappable:
                raise CaseFailed("not PDO-mappable in the EDS (CST needs it in a PDO)")
            return "mappable"

        cases.append(Case("cst", f"0x{index:04X}", "PDO-mappable", mappable))

    def rated(ctx: Context) -> str:
        value = ctx.read_int(0x6076, 0)
        if value <= 0:
            raise CaseFailed(f"0x6076 = {value}: the torque unit (per mille of it) is undefined")
        return f"{value} mNm"

    def actual_within_max(ctx: Context) -> str:
        actual = ctx.read_int(0x6077, 0)
        limit = ctx.read_int(0x6072, 0) if ctx.variable(0x6072) is not None else 1000
        if abs(actual) > max(limit, 1000):
            raise CaseFailed(f"0x6077 = {actual} per mille, 0x6072 = {limit}")
        return f"0x6077 = {actual} per mille at rest"

    def target_refused_above_limits(ctx: Context) -> str:
        var = ctx.need(0x6072)
        if var.max is None:
            raise CaseSkipped("0x6072 has no HighLimit")
        return f"0x6072 HighLimit {var.max} per mille"

    for index, title, fn in (
        (0x6076, "motor rated torque > 0 (mNm)", rated),
        (0x6077, "torque actual within max torque (per mille)", actual_within_max),
        (0x6072, "max torque limited in the EDS (per mille)", target_refused_above_limits),
    ):
        if index in od:
            cases.append(Case("cst", f"0x{index:04X}", title, fn))
    return cases
