"""SyncMonitor.accept against the plain rule it specialises: the duplicate, stale and
restart checks, then ``on_sync_frame`` for every frame that passes."""

from __future__ import annotations

import random

import can

from hdhil.canopen.sync import SyncMonitor


def _reference_accept(m: SyncMonitor, msg: can.Message, now: float) -> int | None:
    data = msg.data
    counter = data[0] if len(data) == 1 else None
    last = m.last_counter
    if counter is not None and last is not None and m.overflow and 1 <= counter <= m.overflow:
        behind = (last - counter) % m.overflow
        if behind == 0:
            m.duplicates += 1
            return None
        if behind <= m.STALE_WINDOW:
            m.stale += 1
            return None
        if counter == 1 and (counter - last) % m.overflow > m.STALE_WINDOW:
            m.restarts += 1
            m.last_counter = None
    return m.on_sync_frame(msg, now)


def _state(m: SyncMonitor) -> tuple:
    return (m.syncs, m.missed_syncs, m.length_errors, m.missing_commands, m.last_counter,
            m.last_sync_time, m.duplicates, m.stale, m.restarts)  # fmt: skip


def test_accept_matches_the_reference_on_random_frames() -> None:
    rng = random.Random(7)
    for overflow in (0, 2, 16, 240):
        for period in (None, 1e-3):
            fast = SyncMonitor(period_s=period, overflow=overflow)
            ref = SyncMonitor(period_s=period, overflow=overflow)
            counter = 1
            for k in range(3000):
                now = k * 1e-3
                roll = rng.random()
                if roll < 0.05:
                    data = bytes(rng.randrange(256) for _ in range(rng.choice((0, 2, 3))))
                elif roll < 0.15:
                    data = bytes((rng.randrange(256),))
                else:
                    counter = counter + rng.choice((1, 1, 1, 2, 0, -1)) if overflow else 0
                    counter = (counter - 1) % overflow + 1 if overflow else 0
                    data = bytes((counter,)) if overflow else b""
                msg = can.Message(arbitration_id=0x80, is_extended_id=False, data=data)
                if rng.random() < 0.5:
                    fast.on_command(now)
                    ref.on_command(now)
                assert fast.accept(msg, now) == _reference_accept(ref, msg, now), (overflow, k)
                assert _state(fast) == _state(ref)
