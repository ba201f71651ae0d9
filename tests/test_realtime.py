"""``hdhil run --realtime``: pacing by the wall clock and its statistics.

No timing thresholds: the machine is shared, so only the structure and the consistency of
the figures are checked, never their size.
"""

from __future__ import annotations

import errno
import gc
import json
import math
import os
import sys
from array import array
from types import SimpleNamespace

import can
import pytest
from runs import lockstep

from hdhil.cli import main
from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.isr import AdcSample, InterruptHandler, TorqueFilterChain
from hdhil.firmware.ripple import HarmonicKalman, RippleKalman
from hdhil.firmware.stages import Differentiator, ReferenceGenerator, SensorPlausibility
from hdhil.rig import ostuning as ostuning
from hdhil.rig import realtime_stats
from hdhil.rig.realtime import (
    RT_SHARE_MARGIN,
    SPIN_FRACTION,
    RealtimeConfig,
    RealtimeLoop,
    SpinPlan,
    WallClock,
)
from hdhil.rig.realtime_stats import HISTOGRAM_EDGES_US, STAGES, histogram, percentiles
from hdhil.rig.scenario import load_scenario

STAT_KEYS = ("jitter_us", "latency_us", "isr_us", "cycle_work_us", "sleep_overshoot_us")
PCT_KEYS = {"min", "p50", "p99", "p99.9", "max", "mean"}


def _ordered(p: dict) -> bool:
    return (
        p["min"] <= p["p50"] <= p["p99"] <= p["p99.9"] <= p["max"]
        and p["min"] <= p["mean"] <= p["max"]
    )


def _check_stats(rt, cycles):
    assert rt["cycles"] == cycles, rt
    assert 0 <= rt["deadline_misses"] <= rt["cycles"], rt
    assert rt["misses_per_100k"] == pytest.approx(1e5 * rt["deadline_misses"] / cycles)
    assert rt["syncs_missing"] == 0, rt
    assert 0 <= rt["late_starts"] <= cycles and 0 <= rt["late_wakeups"] <= cycles
    # Cycles that start within the spin window (or late, catching up after a stall of
    # the machine) do not sleep; the others do.
    assert 0 <= rt["sleeps"] <= cycles
    for key in STAT_KEYS:
        p = rt[key]
        assert set(p) == PCT_KEYS
        if key == "sleep_overshoot_us" and not rt["sleeps"]:
            assert all(math.isnan(v) for v in p.values())
            continue
        assert all(math.isfinite(v) for v in p.values()), (key, p)
        assert _ordered(p), (key, p)
    assert rt["isr_us"]["p50"] > 0
    # The interrupt runs inside the sensor-to-command span and inside the cycle's work,
    # so per cycle both are longer, and so is every order statistic.
    for key in ("latency_us", "cycle_work_us"):
        for q in ("min", "p50", "p99", "p99.9", "max"):
            assert rt[key][q] >= rt["isr_us"][q], (key, q, rt[key], rt["isr_us"])
    assert sum(b["count"] for b in rt["jitter_histogram"]) == rt["cycles"]
    assert len(rt["jitter_histogram"]) == len(HISTOGRAM_EDGES_US) + 1
    assert rt["applied"]  # at least gc.disable is always possible
    # one interrupt per cycle on a fault-free bus; every stage timed in every interrupt
    assert rt["interrupts"] == cycles
    stages = rt["stages_us"]
    assert list(stages) == [key for key, _ in STAGES]
    for key, label in STAGES:
        assert stages[key]["label"] == label
        assert set(stages[key]) == PCT_KEYS | {"label"}
        assert _ordered(stages[key]) and stages[key]["p50"] >= 0, (key, stages[key])
    # the stages are contiguous: per cycle they add up to the interrupt's time
    total = sum(s["mean"] for s in stages.values())
    assert total == pytest.approx(rt["isr_us"]["mean"], rel=1e-9, abs=1e-6)
    pace = rt["pacing"]
    lo, hi = pace["spin_us_range"]
    assert 0 <= lo <= pace["spin_us"] <= hi < rt["sample_period_s"] * 1e6
    assert 0 < pace["rt_share_limit"] <= 1
    assert pace["cpu_share"] > 0


def _floor_ok(floor, seconds, period_s=1e-3):
    assert floor["cycles"] == round(seconds / period_s)
    assert sum(b["count"] for b in floor["jitter_histogram"]) == floor["cycles"]
    assert _ordered(floor["jitter_us"]) and _ordered(floor["sleep_overshoot_us"])
    assert 0 <= floor["deadline_misses"] <= floor["cycles"]
    assert floor["jitter_us"]["p50"] >= 0  # the loop never starts work before the deadline
    assert floor["work_us"] >= 0


def _vm_locked_kb() -> int | None:
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmLck:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


@pytest.mark.slow
@pytest.mark.realtime
def test_realtime_cli_run_reports_statistics(tmp_path, capsys):
    assert gc.isenabled()
    affinity = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    slack = ostuning.get_timer_slack()
    code = main(["run", "--realtime", "--duration", "0.3", "--no-evaluate", "--json",
                 "--floor-s", "0.1", "--mlock", "--trace", str(tmp_path / "rt.blf")])  # fmt: skip
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert result["cycles"] == 300
    rt = result["realtime"]
    _check_stats(rt, 300)
    _floor_ok(rt["floor"], 0.1)
    assert rt["floor"]["spin_us"] == rt["pacing"]["spin_us"]
    if os.path.exists("/proc/stat"):  # steal time where the kernel accounts it
        pinned = [a for a in rt["applied"] if a.startswith("affinity: CPU ")]
        for steal in (rt["steal"], rt["floor"]["steal"]):
            assert steal["ms"] >= 0 and 0 <= steal["share"] <= 1
            if pinned:
                assert pinned[0].startswith(f"affinity: CPU {steal['cpu']}")
    assert any(a.startswith("mlockall") for a in rt["applied"] + rt["refused"])
    # Everything the loop changed is undone.
    assert gc.isenabled()
    if affinity is not None:
        assert os.sched_getaffinity(0) == affinity
    if hasattr(os, "sched_getscheduler"):
        assert os.sched_getscheduler(0) == os.SCHED_OTHER
    assert ostuning.get_timer_slack() == slack
    if _vm_locked_kb() is not None:
        assert _vm_locked_kb() == 0
    assert (tmp_path / "rt.blf").stat().st_size > 0


@pytest.mark.slow
@pytest.mark.realtime
def test_realtime_text_output_has_tables_histogram_and_floor(capsys):
    assert main(["run", "--realtime", "--duration", "0.05", "--no-evaluate", "--trace", "",
                 "--floor-s", "0.02"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "real time on simbus" in out
    assert "SYNC jitter (late)" in out and "SYNC jitter histogram" in out
    assert "deadline misses" in out and "applied:" in out and "per 100 000" in out
    assert "spin window" in out and "RT throttling limit" in out
    for _, label in STAGES:
        assert label in out
    assert "machine floor" in out
    if os.path.exists("/proc/stat"):
        assert out.count("hypervisor steal time on") == 2  # the run and the floor


def _fake_stat(path, cpu1_steal_ticks: int) -> None:
    # user nice system idle iowait irq softirq steal guest guest_nice
    (path / "stat").write_text(
        "cpu  100 0 50 900 5 0 1 70 0 0\n"
        "cpu0 50 0 25 450 2 0 1 20 0 0\n"
        f"cpu1 50 0 25 450 3 0 0 {cpu1_steal_ticks} 0 0\n"
        "intr 12345 0 0\n"
    )


def test_steal_time_is_read_per_cpu_from_proc_stat(tmp_path):
    tick_ns = 1_000_000_000 // os.sysconf("SC_CLK_TCK")
    _fake_stat(tmp_path, 50)
    assert ostuning.cpu_steal_ns(1, str(tmp_path)) == 50 * tick_ns
    assert ostuning.cpu_steal_ns(0, str(tmp_path)) == 20 * tick_ns
    assert ostuning.cpu_steal_ns(None, str(tmp_path)) == 70 * tick_ns
    assert ostuning.cpu_steal_ns(7, str(tmp_path)) is None  # no such CPU
    assert ostuning.cpu_steal_ns(0, str(tmp_path / "none")) is None  # no procfs
    (tmp_path / "stat").write_text("cpu0 50 0 25 450\n")  # a kernel without the column
    assert ostuning.cpu_steal_ns(0, str(tmp_path)) is None


def test_steal_report_over_an_interval():
    r = ostuning.steal_report(1_000_000_000, 1_250_000_000, 1, 10.0)
    assert r == {"cpu": 1, "ms": pytest.approx(250.0), "share": pytest.approx(0.025)}
    everywhere = ostuning.steal_report(0, 400_000_000, None, 10.0)
    assert everywhere["cpu"] == "all"
    assert everywhere["share"] == pytest.approx(0.4 / (10.0 * (os.cpu_count() or 1)))
    assert ostuning.steal_report(None, 5, 0, 1.0) is None
    text = realtime_stats.format_steal(r)
    assert "CPU 1" in text and "250 ms" in text and "2.50%" in text


@pytest.mark.realtime
def test_fixed_spin_window_is_used():
    r = lockstep(load_scenario("free-motion"), duration_s=0.05, evaluate=False,
                     realtime=True, realtime_config=RealtimeConfig(spin_us=150))  # fmt: skip
    pace = r.realtime["pacing"]
    assert pace["spin_us"] == 150 and pace["spin_us_range"] == [150, 150]
    assert "fixed" in pace["spin_source"]
    assert r.realtime["floor"] is None


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["--spin-us", "-1"], "--spin-us"),
        (["--spin-us", "1000"], "below the sample period"),  # the period itself
        (["--spin-us", "nan"], "--spin-us"),
        (["--spin-us", "inf"], "--spin-us"),
        (["--floor-s", "-2"], "--floor-s"),
        (["--floor-s", "nan"], "--floor-s"),
    ],
)
def test_bad_realtime_options_are_one_line_errors(argv, fragment, capsys, tmp_path):
    trace = tmp_path / "never.blf"
    code = main(["run", "--realtime", "--duration", "0.05", "--trace", str(trace), *argv])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("hdhil: error:") and err.count("\n") == 1 and fragment in err, err
    assert not trace.exists()  # refused before anything ran


@pytest.mark.parametrize("option", [["--spin-us", "100"], ["--floor-s", "1"], ["--mlock"]])
def test_realtime_options_need_realtime(option, capsys):
    assert main(["run", "--duration", "0.05", "--trace", "", *option]) == 2
    assert "need --realtime" in capsys.readouterr().err


def test_config_check_accepts_the_range():
    RealtimeConfig(spin_us=0).check(1e-3)
    RealtimeConfig(spin_us=999.9, floor_s=0).check(1e-3)
    with pytest.raises(ConfigError, match="500 µs"):
        RealtimeConfig(spin_us=500).check(0.5e-3)


def _refuse(exc_errno: int):
    def refuse(*args, **kwargs):
        raise OSError(exc_errno, os.strerror(exc_errno))

    return refuse


@pytest.mark.slow
@pytest.mark.realtime
def test_refused_privileges_are_reported_and_the_run_goes_on(monkeypatch):
    """Without root: affinity, SCHED_FIFO, timer slack and mlockall each refused, the run
    still paces and measures, and the collector is back on afterwards."""
    if hasattr(os, "sched_setaffinity"):
        monkeypatch.setattr(os, "sched_setaffinity", _refuse(errno.EPERM))
    if hasattr(os, "sched_setscheduler"):
        monkeypatch.setattr(os, "sched_setscheduler", _refuse(errno.EPERM))
    monkeypatch.setattr(ostuning, "set_timer_slack", _refuse(errno.EPERM))
    monkeypatch.setattr(ostuning, "lock_memory", _refuse(errno.ENOMEM))
    r = lockstep(load_scenario("free-motion"), duration_s=0.1, evaluate=False,
                     realtime=True, realtime_config=RealtimeConfig(mlock=True))  # fmt: skip
    rt = r.realtime
    _check_stats(rt, 100)
    refused = " | ".join(rt["refused"])
    for what in ("affinity", "SCHED_FIFO", "timer slack", "mlockall"):
        assert what in refused, refused
    assert os.strerror(errno.EPERM) in refused and os.strerror(errno.ENOMEM) in refused
    assert rt["applied"] == ["gc disabled during the loop (collected before)"]
    assert gc.isenabled()


@pytest.mark.skipif(not hasattr(os, "SCHED_RESET_ON_FORK"), reason="Linux only")
def test_threads_started_during_the_loop_do_not_inherit_sched_fifo():
    """A helper thread (or process) started while the loop runs gets the normal policy:
    inheriting SCHED_FIFO on the loop's CPU, it could only run while the loop sleeps."""
    import threading

    loop = RealtimeLoop(1e-3, RealtimeConfig(affinity=False, mlock=False))
    seen: list[int] = []
    loop.enter()
    try:
        main_policy = os.sched_getscheduler(0)
        thread = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0)))
        thread.start()
        thread.join()
    finally:
        loop.exit()
    if not any(a.startswith("SCHED_FIFO") for a in loop.applied):
        assert any(r.startswith("SCHED_FIFO") for r in loop.refused)
        return  # not permitted here: nothing to inherit
    assert main_policy & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO
    assert seen == [os.SCHED_OTHER]
    assert "reset on fork" in " ".join(loop.applied)
    assert os.sched_getscheduler(0) == os.SCHED_OTHER


@pytest.mark.slow
@pytest.mark.realtime
def test_switched_off_measures_are_neither_applied_nor_refused():
    cfg = RealtimeConfig(affinity=False, timer_slack=False, fifo=False, mlock=False)
    r = lockstep(load_scenario("free-motion"), duration_s=0.05, evaluate=False,
                     realtime=True, realtime_config=cfg)  # fmt: skip
    assert r.realtime["refused"] == []
    assert r.realtime["applied"] == ["gc disabled during the loop (collected before)"]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux only")
def test_timer_slack_roundtrip():
    before = ostuning.get_timer_slack()
    previous = ostuning.set_timer_slack(ostuning.TIMER_SLACK_NS)
    try:
        assert previous == before
        assert ostuning.get_timer_slack() in (ostuning.TIMER_SLACK_NS, 0)  # 0 for RT tasks
    finally:
        ostuning.set_timer_slack(previous)
    assert ostuning.get_timer_slack() == before


def _fake_task(proc, pid, tid, comm, flags, cpu, policy):
    fields = [str(tid), f"({comm})"] + ["0"] * 50  # fields 1, 2, then 3..52
    fields[9 - 1], fields[39 - 1], fields[41 - 1] = str(flags), str(cpu), str(policy)
    task = proc / str(pid) / "task" / str(tid)
    task.mkdir(parents=True)
    (task / "stat").write_text(" ".join(fields) + "\n")


def test_rt_tasks_per_cpu_counts_other_user_space_rt_threads(tmp_path):
    big = 99_999_990  # above any pid_max: sched_getaffinity finds no such task
    _fake_task(tmp_path, big, big, "py thon (rt) x", 0, 1, 1)  # SCHED_FIFO on CPU 1
    _fake_task(tmp_path, big, big + 1, "worker", 0, 1, 2)  # SCHED_RR thread, CPU 1
    _fake_task(tmp_path, big + 2, big + 2, "rr", 0, 0, 2)  # SCHED_RR on CPU 0
    _fake_task(tmp_path, big + 3, big + 3, "kthread", ostuning.PF_KTHREAD, 0, 1)
    _fake_task(tmp_path, big + 4, big + 4, "normal", 0, 0, 0)  # SCHED_OTHER
    _fake_task(tmp_path, os.getpid(), big + 5, "me", 0, 0, 1)  # this process
    (tmp_path / "self").mkdir()
    (tmp_path / str(big + 6)).mkdir()  # a process that exited: no task directory
    assert ostuning.rt_tasks_per_cpu(str(tmp_path)) == {1: 2, 0: 1}
    assert ostuning.rt_tasks_per_cpu(str(tmp_path / "none")) == {}


@pytest.mark.realtime
@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no affinity API")
def test_affinity_avoids_a_cpu_with_another_rt_task(monkeypatch):
    allowed = sorted(os.sched_getaffinity(0))
    busy_cpu = allowed[-1]
    monkeypatch.setattr(ostuning, "rt_tasks_per_cpu", lambda: {busy_cpu: 3})
    r = lockstep(load_scenario("free-motion"), duration_s=0.02, evaluate=False,
                     realtime=True)  # fmt: skip
    chosen = allowed[-2] if len(allowed) > 1 else busy_cpu
    affinity = [a for a in r.realtime["applied"] if a.startswith("affinity")]
    assert affinity == [f"affinity: CPU {chosen} (other real-time tasks: 3 on CPU {busy_cpu})"]
    assert sorted(os.sched_getaffinity(0)) == allowed


def test_spin_plan_stays_within_the_rt_budget():
    period = 1_000_000
    plan = SpinPlan(period, 0.95)
    assert plan.budget_ns == round((0.95 - RT_SHARE_MARGIN) * period)
    assert plan.spin_ns(0) == round(SPIN_FRACTION * period)
    for work in (0, 50_000, 150_000, 300_000, 700_000, 900_000, 2_000_000):
        spin = plan.spin_ns(work)
        assert 0 <= spin <= SPIN_FRACTION * period
        assert spin + work <= plan.budget_ns or spin == 0, work
    widths = [plan.spin_ns(w) for w in range(0, 1_000_000, 10_000)]
    assert widths == sorted(widths, reverse=True)  # more work, narrower window
    assert SpinPlan(period, 0.95, fixed_ns=123_000).spin_ns(900_000) == 123_000


def test_rt_share_limit_from_sysctl_files(tmp_path):
    (tmp_path / "sched_rt_runtime_us").write_text("800000\n")
    (tmp_path / "sched_rt_period_us").write_text("1000000\n")
    share, source = ostuning.rt_share_limit(str(tmp_path))
    assert share == pytest.approx(0.8) and "800000" in source
    (tmp_path / "sched_rt_runtime_us").write_text("-1\n")
    assert ostuning.rt_share_limit(str(tmp_path))[0] == 1.0
    share, source = ostuning.rt_share_limit(str(tmp_path / "missing"))
    assert share == ostuning.RT_SHARE_DEFAULT and "default" in source
    share, _ = ostuning.rt_share_limit()  # this machine's
    assert 0 < share <= 1


def _adc_samples(n: int) -> list[AdcSample]:
    return [AdcSample(torque=2048 + (k * 37) % 300, tacho=2300 + k % 7, current=2048,
                      encoder=(k * 211) & 0xFFFF) for k in range(n)]  # fmt: skip


def test_stage_timing_leaves_the_interrupt_unchanged_and_follows_swapped_stages():
    """The instrumented handler computes exactly what the plain one does; a filter chain
    the controller swaps in at run time (new parameters over SDO) is timed from the next
    interrupt on; after the run everything is unwrapped."""
    cfg = from_dict(FirmwareConfig, load_scenario("free-motion").firmware, "firmware")
    plain = InterruptHandler(cfg)
    bus = can.Bus(interface="virtual", channel="rt-stage-test")
    try:
        handler = InterruptHandler(cfg)

        def on_message(msg: can.Message) -> None:
            pass

        controller = SimpleNamespace(bus=bus, isr=handler, on_message=on_message)
        loop = RealtimeLoop(cfg.sample_period_s, RealtimeConfig(spin_us=0))
        loop.instrument(controller)
        loop.start()
        loop.begin_recording()
        samples = _adc_samples(40)
        for k, sample in enumerate(samples):
            if k == 20:  # the controller's _apply_pending swaps a new chain in
                inner = controller.isr
                new_chain = TorqueFilterChain(cfg)
                new_chain.differentiator = inner.chain.differentiator
                inner.chain = new_chain
                plain_chain = TorqueFilterChain(cfg)
                plain_chain.differentiator = plain.chain.differentiator
                plain.chain = plain_chain
            loop.wait(k)
            got = controller.isr(sample)
            assert got == plain(sample), k
            loop.end_cycle()
        rt = loop.result()
        assert rt["cycles"] == rt["interrupts"] == len(samples)
        assert all(len(loop.stats.stage_us[key]) == len(samples) for key, _ in STAGES)
        # the Kalman filter of the swapped-in chain was timed too
        assert all(v > 0 for v in loop.stats.stage_us["ripple_kalman"][20:])
        for a, *stages in zip(
            loop.stats.isr_us, *(loop.stats.stage_us[k] for k, _ in STAGES), strict=True
        ):
            assert math.fsum(stages) == pytest.approx(a, abs=1e-6)
        # timed while the run lasts through the handler's stage hook; its classes untouched
        assert controller.isr is handler and type(handler) is InterruptHandler
        assert handler.stage_hook is not None
        assert type(handler.chain.kalman) in (HarmonicKalman, RippleKalman)
        loop.exit()
        isr = controller.isr
        assert isr is handler and isr.stage_hook is None  # the hook removed again
        assert type(isr.chain) is TorqueFilterChain
        assert type(isr.chain.kalman) in (HarmonicKalman, RippleKalman)
        assert type(isr.chain.differentiator) is Differentiator
        assert type(isr.chain.plausibility) is SensorPlausibility
        assert type(isr.reference) is ReferenceGenerator
        assert "send" not in vars(bus) and controller.on_message is on_message
    finally:
        bus.shutdown()


@pytest.mark.slow
@pytest.mark.realtime
def test_realtime_trace_timestamps_are_wall_time(tmp_path):
    """The simbus clock follows wall time: the trace spans at least the paced duration
    (pacing never runs early; checked loosely, no upper bound)."""
    trace = tmp_path / "rt.blf"
    r = lockstep(load_scenario("free-motion"), duration_s=0.1, trace=trace,
                     evaluate=False, realtime=True)  # fmt: skip
    why = (r.interrupted, r.controller, r.drive, r.realtime)
    assert r.cycles == 100, why
    assert r.wall_s >= 0.1, why
    _check_stats(r.realtime, 100)
    stamps = [msg.timestamp for msg in can.LogReader(str(trace))]
    assert stamps and max(stamps) - min(stamps) >= 0.1, (len(stamps), stamps[:3], stamps[-3:])


def test_lockstep_run_has_no_realtime_section():
    r = lockstep(load_scenario("free-motion"), duration_s=0.02, evaluate=False)
    assert r.realtime is None


@pytest.mark.slow
@pytest.mark.realtime
def test_realtime_on_the_virtual_interface():
    """Documented choice: --realtime works on any python-can interface, virtual included;
    the statistics cover every cycle in which the interrupt ran."""
    r = lockstep(load_scenario("free-motion"), duration_s=0.1, interface="virtual",
                     evaluate=False, realtime=True)  # fmt: skip
    assert r.cycles == 100
    _check_stats(r.realtime, 100)


@pytest.mark.realtime
def test_lqg_run_times_the_control_stage():
    r = lockstep(load_scenario("lqg-tracking"), duration_s=0.05, evaluate=False,
                     realtime=True)  # fmt: skip
    _check_stats(r.realtime, 50)
    assert r.realtime["stages_us"]["control_reference"]["p50"] > 0


def test_wall_clock_reads_real_time():
    clock = WallClock()
    a = clock.now
    b = clock.now
    assert 0 <= a <= b


def test_percentiles_and_histogram_helpers():
    values = array("d", [0.5, 1.5, 3.0, 7.0, 15.0, 30.0, 70.0, 20000.0, -3.0])
    p = percentiles(values)
    assert _ordered(p) and p["max"] == 20000.0
    assert p["mean"] == pytest.approx(sum(values) / len(values))
    bins = histogram(values)
    assert sum(b["count"] for b in bins) == len(values)
    assert bins[0]["count"] == 2  # early and sub-µs in the first bin
    assert bins[-1]["count"] == 1
    empty = percentiles(array("d"))
    assert all(math.isnan(v) for v in empty.values())


@pytest.mark.parametrize("n", [1, 1000])
def test_percentile_ranks_are_values(n):
    values = array("d", range(n))
    p = percentiles(values)
    assert p["max"] == n - 1 and p["p50"] in values
