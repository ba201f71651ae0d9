"""Timing cases: SYNC-to-TPDO latency, heartbeat period accuracy, EMCY reaction time and
the RPDO deadline (event timer of a received PDO).  Times are arrival times of the
frames at the suite (the monotonic clock), the same on every interface."""

from __future__ import annotations

import time

from canopen.objectdictionary import ObjectDictionary

from hdhil.conformance.cia301 import (
    arrival_gaps,
    emcy_wait,
    first_sync_tpdo,
    heartbeat_loss,
    live_layout,
    rpdo_comm_indices,
)
from hdhil.conformance.suite import (
    HEARTBEAT_BASE,
    NMT_START,
    Case,
    CaseFailed,
    CaseSkipped,
    Context,
    cob,
)

__all__ = ["timing_cases"]


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def timing_cases(od: ObjectDictionary) -> list[Case]:
    g = "timing"

    def latency(ctx: Context) -> str:
        _comm, cob_id = first_sync_tpdo(ctx)
        window_us = ctx.read_int(0x1007, 0) if ctx.variable(0x1007) is not None else 0
        limit = window_us * 1e-6 if window_us else ctx.options.sync_latency_s
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        lat: list[float] = []
        for _ in range(ctx.options.timing_samples):
            mark = ctx.recorder.mark()
            t = ctx.sync()
            hit = ctx.recorder.wait(cob(cob_id), 0.1, mark)
            if hit is None:
                raise CaseFailed("a SYNC without its TPDO")
            lat.append(hit[0] - t)
            time.sleep(0.004)
        median = _percentile(lat, 0.5)
        p90 = _percentile(lat, 0.9)
        detail = (f"median {median * 1e3:.2f} ms, p90 {p90 * 1e3:.2f} ms, "
                  f"max {max(lat) * 1e3:.2f} ms (limit {limit * 1e3:g} ms)")  # fmt: skip
        if median > limit:
            raise CaseFailed(detail)
        return detail

    def heartbeat_period(ctx: Context) -> str:
        ctx.need(0x1017)
        period_ms = ctx.read_int(0x1017, 0)
        if not period_ms:
            raise CaseSkipped("0x1017 = 0")
        n = max(4, min(20, int(0.6 / (period_ms * 1e-3))))
        window_s = (n + 1.5) * period_ms * 1e-3
        times, gaps = arrival_gaps(ctx, HEARTBEAT_BASE + ctx.node_id, 0.0, window_s)
        if len(gaps) < n - 1:
            raise CaseFailed(f"{len(times)} heartbeats in {(n + 1.5) * period_ms:g} ms")
        mean = sum(gaps) / len(gaps)
        err = (mean - period_ms * 1e-3) / (period_ms * 1e-3)
        detail = (f"mean {mean * 1e3:.2f} ms ({err:+.1%}), longest {max(gaps) * 1e3:.1f} ms, "
                  f"0x1017 = {period_ms} ms")  # fmt: skip
        if abs(err) > ctx.options.period_tolerance or max(gaps) > 2 * period_ms * 1e-3:
            raise CaseFailed(detail)
        return detail

    def emcy_reaction(ctx: Context) -> str:
        ctx.need(0x1016, 1)
        _last, deadline, mark = heartbeat_loss(ctx)
        hit = emcy_wait(ctx, lambda c: c == 0x8130, 1.0, mark)
        if hit is None:
            raise CaseFailed("no EMCY 0x8130")
        late = hit[0] - deadline
        detail = f"EMCY {late * 1e3:+.1f} ms after the consumer deadline"
        if late > ctx.options.reaction_s or late < -0.01:
            raise CaseFailed(detail + f" (limit {ctx.options.reaction_s * 1e3:g} ms)")
        return detail

    def rpdo_deadline(ctx: Context) -> str:
        for comm in rpdo_comm_indices(ctx):
            cob_id, valid, _trans, entries = live_layout(ctx, comm)
            if valid and entries and ctx.variable(comm, 5) is not None:
                break
        else:
            raise CaseSkipped("no valid RPDO with an event timer (sub-index 5)")
        payload = b"".join(ctx.upload(i, s)[: b // 8] for i, s, b in entries)
        ctx.write(comm, 5, 50)
        ctx.nmt(NMT_START)
        time.sleep(0.02)
        for _ in range(5):
            ctx.send(cob_id, payload)
            time.sleep(0.01)
        mark = ctx.recorder.mark()
        last = ctx.send(cob_id, payload)
        hit = emcy_wait(ctx, lambda c: c == 0x8250, 0.5, mark)
        if hit is None:
            raise CaseFailed("no EMCY 0x8250 when the RPDO stopped (event timer 50 ms)")
        late = hit[0] - (last + 0.05)
        detail = f"EMCY 0x8250 {late * 1e3:+.1f} ms after the 50 ms deadline"
        if late > ctx.options.reaction_s or late < -0.01:
            raise CaseFailed(detail + f" (limit {ctx.options.reaction_s * 1e3:g} ms)")
        return detail

    return [
        Case(g, "0x1007 §7.2.5", "SYNC-to-TPDO latency", latency),
        Case(g, "0x1017", "heartbeat period accuracy", heartbeat_period),
        Case(g, "0x1016 §7.2.7", "EMCY reaction time (heartbeat loss)", emcy_reaction),
        Case(g, "0x1400:05", "RPDO deadline (event timer) -> EMCY 0x8250", rpdo_deadline),
    ]
