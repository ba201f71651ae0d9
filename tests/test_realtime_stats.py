"""The real-time statistics (:mod:`hdhil.rig.realtime_stats`) on synthetic time stamps.

Each figure's min, percentiles, max and mean come from the same samples, and a latency
pairs a command with the sensor frame it answers; no paced run is needed for either.
"""

from __future__ import annotations

import math
from array import array

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hdhil.rig.realtime_stats import (
    PERCENTILE_KEYS,
    CycleStamps,
    CycleStats,
    format_realtime,
    percentiles,
)

PERIOD_NS = 1_000_000  # 1 kHz
T0_NS = 10_000_000


def _cycle(stats: CycleStats, stamps: CycleStamps, k: int, events: list[tuple[str, int]]) -> None:
    """Cycle ``k``: its events at offsets (ns) from the deadline, as the controller calls
    the probe, then recorded as the pacer records it."""
    deadline = T0_NS + k * PERIOD_NS
    stamps.clear()
    for kind, offset in events:
        t = deadline + offset
        if kind == "sync":
            stamps.on_sync_sent(t)
        elif kind == "sensor":
            stamps.on_sensor(t)
        elif kind == "command":
            stamps.on_command_sent(t)
        else:  # the interrupt, 10 µs just before the command
            stamps.on_interrupt(t - 10_000, t)
    stats.record(deadline, deadline - 600_000, deadline + 500_000, 2_000, 600_000, False, stamps)


def _ordered(p: dict[str, float]) -> bool:
    return (
        p["min"] <= p["p50"] <= p["p99"] <= p["p99.9"] <= p["max"]
        and p["min"] <= p["mean"] <= p["max"]
    )


def test_latency_pairs_each_command_with_the_frame_it_answers() -> None:
    stats, stamps = CycleStats(PERIOD_NS), CycleStamps()
    normal = [("sync", 5_000), ("sensor", 100_000), ("isr", 125_000), ("command", 130_000)]
    _cycle(stats, stamps, 0, normal)
    # Cycle 1's sensor frame is late: it arrives in cycle 2, where the controller answers
    # it at once; cycle 2's own frame then comes after that command and is ignored (one
    # interrupt per SYNC).  The same holds for a duplicated frame after the command.
    _cycle(stats, stamps, 1, [("sync", 5_000)])
    _cycle(stats, stamps, 2, [("sync", 5_000), ("sensor", 20_000), ("isr", 45_000),
                              ("command", 50_000), ("sensor", 400_000)])  # fmt: skip
    _cycle(stats, stamps, 3, [*normal, ("sensor", 700_000)])
    # a sensor frame answered by no command (a malformed one) starts no latency
    _cycle(stats, stamps, 4, [("sync", 5_000), ("sensor", 90_000), *normal[1:]])
    assert list(stats.latency_us) == pytest.approx([30.0, 30.0, 30.0, 30.0])
    rt = stats.summary()
    assert rt["latency_us"]["min"] == pytest.approx(30.0)
    assert rt["latency_us"]["mean"] == pytest.approx(30.0)
    assert rt["deadline_misses"] == 1  # cycle 1: no command before cycle 2's deadline


def test_a_command_without_a_sensor_frame_has_no_latency() -> None:
    stats, stamps = CycleStats(PERIOD_NS), CycleStamps()
    _cycle(stats, stamps, 0, [("sync", 5_000), ("command", 30_000)])
    # a frame from before the cycle's start (cleared with it) answers nothing either
    stamps.on_sensor(T0_NS + PERIOD_NS - 1_000)
    _cycle(stats, stamps, 1, [("sync", 5_000), ("command", 30_000)])
    assert len(stats.latency_us) == 0
    assert math.isnan(stats.summary()["latency_us"]["mean"])


_samples = st.lists(
    st.one_of(
        st.floats(min_value=-1e9, max_value=1e9, allow_nan=False),
        st.just(math.nan),  # a cycle without the event (no SYNC, no sleep)
    ),
    max_size=300,
)


@settings(max_examples=60, deadline=None)
@given(_samples)
def test_percentiles_are_consistent_and_from_the_same_samples(values: list[float]) -> None:
    p = percentiles(array("d", values))
    assert tuple(p) == PERCENTILE_KEYS
    kept = sorted(v for v in values if not math.isnan(v))
    if not kept:
        assert all(math.isnan(v) for v in p.values())
        return
    assert _ordered(p), p
    assert p["min"] == kept[0] and p["max"] == kept[-1]
    assert all(p[q] in kept for q in ("p50", "p99", "p99.9"))


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.integers(-50_000, 3 * PERIOD_NS),  # SYNC after the deadline (0: none)
            st.integers(0, 900_000),  # sensor frame
            st.integers(0, 200_000),  # interrupt to command
            st.integers(-1, 800_000),  # sleep overshoot (-1: no sleep)
            st.booleans(),  # a second frame after the command
        ),
        min_size=1,
        max_size=40,
    )
)
def test_cycle_summary_figures_are_consistent(
    cycles: list[tuple[int, int, int, int, bool]],
) -> None:
    stats, stamps = CycleStats(PERIOD_NS), CycleStamps()
    for k, (sync, sensor, answer, overshoot, extra) in enumerate(cycles):
        deadline = T0_NS + 4 * k * PERIOD_NS
        stamps.clear()
        if sync:
            stamps.on_sync_sent(deadline + sync)
        stamps.on_sensor(deadline + sensor)
        stamps.on_interrupt(deadline + sensor + 1, deadline + sensor + 1 + answer // 2)
        stamps.on_command_sent(deadline + sensor + answer)
        if extra:
            stamps.on_sensor(deadline + sensor + answer + 1)
        end = deadline + sensor + answer + 2
        stats.record(deadline, deadline - 600_000, end, overshoot, 600_000, False, stamps)
    rt = stats.summary()
    for key in ("jitter_us", "latency_us", "isr_us", "cycle_work_us", "sleep_overshoot_us"):
        p = rt[key]
        if all(math.isnan(v) for v in p.values()):
            continue  # no sample (no cycle slept)
        assert all(math.isfinite(v) for v in p.values()) and _ordered(p), (key, p)
    assert rt["latency_us"]["min"] >= 0
    assert len(stats.latency_us) == len(cycles)
    assert rt["sleeps"] == sum(c[3] >= 0 for c in cycles)


def test_text_report_shows_min_and_mean_beside_the_percentiles() -> None:
    stats, stamps = CycleStats(PERIOD_NS), CycleStamps()
    for k, command in enumerate((130_000, 150_000, 170_000)):
        _cycle(stats, stamps, k, [("sync", 5_000), ("sensor", 100_000), ("isr", command),
                                  ("command", command)])  # fmt: skip
    rt = {**stats.summary(), "applied": [], "refused": [], "steal": None, "floor": None,
          "pacing": {"spin_us": 600.0, "spin_us_range": [600.0, 600.0], "spin_source": "x",
                     "cpu_share": 0.5, "rt_share_limit": 0.95}}  # fmt: skip
    lines = format_realtime(rt).splitlines()
    (header,) = [line for line in lines if "p99.9" in line]
    assert header.split()[1:] == list(PERCENTILE_KEYS)
    (row,) = [line for line in lines if "sensor frame -> command" in line]
    assert row.split()[-6:] == ["30.0", "50.0", "70.0", "70.0", "70.0", "50.0"]
