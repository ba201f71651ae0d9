"""``hdhil run``: a full emulated run in one process, lockstep on the simulated bus.

Three nodes share two python-can channels and nothing else:

- the controller (:class:`firmware.controller.ControllerNode`) on the control bus,
- the drive emulator (:class:`hostsim.drive.DriveNode`) on the control bus, publishing
  ground truth on the truth channel,
- the host tap (:class:`hdhil.can.trace.BusTap`) listening on both: trace writer, frame
  counter and the scorer that compares telemetry with truth.

Lockstep (DESIGN.md): SYNC k is sent at simulated time k*Ts; every node then handles what
the bus delivers until the cycle is quiet, and SYNC k+1 follows at once.  The result is
deterministic and bit-identical for a given seed, and as fast as the host allows.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np
from threadpoolctl import threadpool_limits

from hdhil.can.busload import LOAD_LIMIT, schedule_load
from hdhil.can.faults import FaultInjector, FaultLog
from hdhil.can.simbus import SimBus, SimClock
from hdhil.can.trace import BusTap, FrameCounter, WriterProcess
from hdhil.core.dataconf import ConfigError, from_dict, merge
from hdhil.dbc import CHANNEL_NUMBER, database
from hdhil.firmware.config import FirmwareConfig, Law
from hdhil.firmware.controller import ControllerNode
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant
from hdhil.hostsim.scenario import Scenario
from hdhil.rig.evaluate import RecordingListener, format_evaluation
from hdhil.rig.evaluate import evaluate as evaluate_recording
from hdhil.rig.realtime import RealtimeConfig, RealtimeLoop, WallClock, format_realtime
from hdhil.rig.score import TorqueScorer, TrackingScorer

_run_ids = itertools.count(1)


@dataclass
class RunResult:
    """What a run did, every figure computed from the run itself."""

    scenario: str
    seed: int
    interface: str
    actuation: str
    cycles: int
    sample_period_s: float
    simulated_s: float
    wall_s: float
    interrupted: bool
    frames: dict[str, int]
    frames_total: int
    frames_sent: dict[str, int]
    startup_cycles: int
    stop_cycles: int
    worst_case_load: float
    bitrate: int
    torque: dict[str, float]
    velocity_final: float
    velocity_peak: float
    trace: str | None
    evaluation: dict[str, Any] | None = None
    tracking: dict[str, Any] | None = None
    faults: dict[str, int] | None = None
    controller: dict[str, Any] = field(default_factory=dict)
    drive: dict[str, Any] = field(default_factory=dict)
    realtime: dict[str, Any] | None = None

    @property
    def real_time_factor(self) -> float:
        return self.simulated_s / self.wall_s if self.wall_s > 0 else float("inf")

    def as_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["real_time_factor"] = self.real_time_factor
        return d


def _frame_names() -> dict[tuple[int, int], str]:
    names = {}
    for bus, channel in CHANNEL_NUMBER.items():
        for msg in database(bus).messages:
            names[(channel, msg.frame_id)] = f"{bus} 0x{msg.frame_id:03X} {msg.name}"
    return names


#: In lockstep on the simulated bus the tap drains its queues every this many cycles
#: (and before a monitor call and at the end): its listeners see the same frames in
#: the same order, with less work per frame.  Every cycle in real-time mode and on
#: other interfaces.
TAP_EVERY_CYCLES = 16

#: A cycle that has not completed after this long (wall time) means a silent peer.
CYCLE_TIMEOUT_S = 1.0


class SilentPeerError(ConfigError):
    """A node did not answer within the cycle timeout."""


def _complete_cycle(controller: ControllerNode, drive: DriveNode, tap: BusTap,
                    control: SimBus | None) -> None:  # fmt: skip
    """Let the nodes handle the current cycle's frames.

    On the simulated bus (``control``) delivery is immediate: pump the two nodes until a
    round in which neither requested a control-bus frame (after such a round both
    nodes' queues are empty).  The tap is left to the caller: frames wait in its queues,
    in order, until it drains them (:data:`TAP_EVERY_CYCLES`).  On a real interface
    frames take time to come back, so wait (briefly sleeping) until the controller has
    answered this cycle's sensor frame, with a timeout that names the silent node,
    draining the tap as frames come.  During start-up (no sensor frames yet) the wait
    is short.
    """
    if control is not None:
        while True:
            before = control.frames_requested
            drive.poll()
            controller.poll()
            if control.frames_requested == before:
                return
    answered = controller.diagnostics.commands_sent
    while drive.poll() + controller.poll() + tap.poll():
        pass
    operational = controller.phase == "operational"
    deadline = time.monotonic() + (CYCLE_TIMEOUT_S if operational else 0.005)
    while controller.diagnostics.commands_sent <= answered:
        if drive.poll() + controller.poll() + tap.poll():
            continue
        if time.monotonic() > deadline:
            if operational:
                raise SilentPeerError(
                    f"the drive sent no sensor frame within {CYCLE_TIMEOUT_S:g} s of SYNC"
                )
            break
        time.sleep(50e-6)


#: Cycles allowed from power-on to "operation enabled" (NMT start and the CiA 402 walk
#: take a handful) and back to "stopped".
MAX_STARTUP_CYCLES = 500
MAX_STOP_CYCLES = 200


def read_toml(path: Path) -> dict[str, Any]:
    """A TOML override file as nested dicts, with one-line errors."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"override file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read override file {path}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from None


def _controller_diagnostics(controller: ControllerNode) -> dict[str, Any]:
    """The controller's counters and the health of its filter's covariance."""
    d = controller.diagnostics
    kalman = controller.isr.chain.kalman
    P = np.asarray(kalman.P)
    finite = bool(np.all(np.isfinite(P)))
    return {
        "syncs_sent": d.syncs_sent,
        "sensor_frames": d.sensor_frames,
        "malformed_frames": d.malformed_frames,
        "unknown_frames": sum(controller.unknown_frames.values()),
        "filter_mode": controller.config.ripple.mode,
        "filter_states": int(P.shape[0]),
        "kalman_skipped": kalman.skipped,
        "tacho_rejections": d.tacho_rejections,
        "encoder_rejections": d.encoder_rejections,
        "tacho_reseeds": d.tacho_reseeds,
        "encoder_reseeds": d.encoder_reseeds,
        "plausibility_errors": d.plausibility_errors,
        "covariance_resets": getattr(kalman, "covariance_resets", 0),
        "covariance_finite": finite,
        "covariance_min_eigenvalue": (
            float(np.linalg.eigvalsh((P + P.T) / 2).min()) if finite else math.nan
        ),
        "covariance_asymmetry": float(np.abs(P - P.T).max()) if finite else math.nan,
    }


def _frames_sent(control: can.BusABC, truth: can.BusABC) -> dict[str, int]:
    """Frames each channel carried, as counted by the bus itself (simbus only)."""
    return {
        name: bus.frames_sent
        for name, bus in (("control", control), ("truth", truth))
        if hasattr(bus, "frames_sent")
    }


def run_lockstep(
    scenario: Scenario,
    duration_s: float | None = None,
    seed: int | None = None,
    trace: Path | None = None,
    interface: str | None = "simbus",
    actuation: str = "next-sync",
    bitrate: int = 1_000_000,
    channel: str | None = None,
    stop_requested: Callable[[], bool] | None = None,
    evaluate: bool = True,
    evaluate_skip_s: float = 0.0,
    fault_log: Path | None = None,
    realtime: bool = False,
    extra_listeners: Sequence[can.Listener] = (),
    monitor: Callable[[ControllerNode], None] | None = None,
    monitor_every: int = 1000,
    realtime_config: RealtimeConfig | None = None,
) -> RunResult:
    """Run ``scenario`` in lockstep and return the scored result.

    ``stop_requested`` is polled at every cycle boundary; when it returns True the run
    ends there, after the cycle's frames are all handled and logged (how Ctrl-C and
    SIGTERM end a run without losing a frame).

    ``evaluate`` records every cycle (96 bytes per cycle) and, after the run, scores the
    firmware's filter against truth side by side with the paper/recommended Kalman modes
    and the baselines (:mod:`hdhil.rig.evaluate`).  Without it memory stays flat and only the
    streaming RMS score is kept.

    ``realtime`` paces SYNC by the wall clock at the sample period instead of running as
    fast as possible, and reports jitter, latency and deadline misses
    (:mod:`hdhil.rig.realtime`); ``realtime_config`` sets its spin window and machine-floor
    reference.

    ``extra_listeners`` are added to the host tap after the run's own (they see every frame
    of both buses, as a logger does).  ``monitor`` is called with the controller at
    the cycle boundary after every ``monitor_every`` samples in operation; on the
    simulated bus the tap has then seen every frame of those samples (how
    :mod:`hdhil.commands.soak` reads the firmware's filter health per block).
    """
    fw_config = from_dict(FirmwareConfig, scenario.firmware, "firmware")
    Ts = fw_config.sample_period_s
    duration = scenario.duration_s if duration_s is None else duration_s
    if not duration > 0:
        raise ConfigError(f"duration must be > 0 s, got {duration}")
    seed = scenario.seed if seed is None else seed
    cycles = round(duration / Ts)
    if fw_config.num_samples:
        cycles = min(cycles, fw_config.num_samples)
    load = schedule_load("control", bitrate, Ts)
    if load.worst_case_load > 1.0:
        raise ConfigError(
            f"the cyclic schedule needs {load.worst_case_load:.0%} of a "
            f"{bitrate} bit/s bus at {Ts * 1e3:g} ms: it cannot run"
        )
    drive_config = DriveConfig(sample_period_s=Ts, actuation=actuation)  # type: ignore[arg-type]
    pacer = RealtimeLoop(Ts, realtime_config) if realtime else None  # checks its options

    run_id = next(_run_ids)
    # Injected faults (the scenario's [faults] table), reproducible by their seed and logged.
    injector = (
        FaultInjector(scenario.faults, FaultLog(fault_log)) if scenario.faults is not None else None
    )
    control_faults = injector.channel("control") if injector is not None else None
    truth_faults = injector.channel("truth") if injector is not None else None
    clock = WallClock() if realtime else SimClock()
    simulated = interface == "simbus"

    def control_bus() -> can.BusABC:
        if simulated:
            return can.Bus(
                interface="simbus",
                channel=channel or f"hdhil-{run_id}-control",
                bitrate=bitrate,
                clock=clock,
                trace_channel=CHANNEL_NUMBER["control"],
                faults=control_faults,
            )
        if interface == "virtual":
            return can.Bus(interface="virtual", channel=channel or f"hdhil-{run_id}-control")
        try:
            # Any python-can interface; None falls back to python-can's configuration
            # (~/can.conf, CAN_INTERFACE / CAN_CHANNEL environment variables).
            return can.Bus(interface=interface, channel=channel, bitrate=bitrate)
        except (can.CanError, ImportError, OSError, ValueError, TypeError) as exc:
            raise ConfigError(
                f"cannot open the control bus ({interface} {channel}): {exc}"
            ) from None

    def truth_bus() -> can.BusABC:
        # Ground truth is simulation-only: it stays in-process whatever the control bus is.
        return can.Bus(
            interface="simbus",
            channel=f"hdhil-{run_id}-truth",
            bitrate=0,
            clock=clock,
            trace_channel=CHANNEL_NUMBER["truth"],
            faults=truth_faults,
        )

    if monitor is not None and monitor_every < 1:
        raise ConfigError(f"monitor_every must be >= 1 sample, got {monitor_every}")
    # One BLAS thread for the run: the matrices here are at most 7x7, so BLAS threads
    # only spin and take the core the trace writer runs on; and a thread pool created
    # under SCHED_FIFO on one pinned CPU (OpenBLAS restarts its pool lazily after the
    # writer's fork) starves its own workers and livelocks the real-time loop.
    blas = threadpool_limits(limits=1)
    buses: list[can.BusABC] = []
    listeners: list[can.Listener] = []
    interrupted = False
    done = 0
    wall = 0.0
    frames_sent: dict[str, int] = {}
    startup_cycles = stop_cycles = 0
    recorder: RecordingListener | None = None
    tracking: TrackingScorer | None = None
    try:
        for make in (control_bus, control_bus, truth_bus, control_bus, truth_bus):
            buses.append(make())
        ctrl_bus, drive_bus, drive_truth, tap_control, tap_truth = buses
        controller = ControllerNode(ctrl_bus, fw_config)
        drive = DriveNode(
            drive_bus,
            Plant(scenario.plant, seed, faults=injector.sensors() if injector else None),
            drive_config,
            truth_bus=drive_truth,
            faults=injector,
        )
        counter = FrameCounter()
        scorer = TorqueScorer()
        listeners += [counter, scorer]
        control = fw_config.control
        if control.law != Law.NONE:
            tracking = TrackingScorer(control.joint.Jl / control.joint.Jm, evaluate_skip_s)
            listeners.append(tracking)
        if evaluate:
            recorder = RecordingListener(Ts)
            listeners.append(recorder)
        if trace is not None:
            listeners.insert(0, WriterProcess(trace))
        listeners += extra_listeners
        tap = BusTap(
            {CHANNEL_NUMBER["control"]: tap_control, CHANNEL_NUMBER["truth"]: tap_truth}, listeners
        )
        pumped = ctrl_bus if simulated else None
        assert pumped is None or isinstance(pumped, SimBus)
        tap_every = TAP_EVERY_CYCLES if simulated and pacer is None else 1
        if pacer is not None:
            pacer.instrument(controller)
            pacer.enter()
        wall0 = time.perf_counter()
        k = 0

        def cycle() -> None:
            nonlocal k
            if pacer is not None:
                pacer.wait(k)  # wall clock: the simbus clock reads real time by itself
            else:
                clock.now = k * Ts
            now = clock.now if simulated else time.monotonic()
            drive.tick(now)
            controller.tick(now)
            controller.send_sync()  # the controller decides by its phase whether SYNC goes out
            _complete_cycle(controller, drive, tap, pumped)
            if k % tap_every == 0:
                tap.poll()
            if pacer is not None:
                pacer.end_cycle()
            k += 1

        try:
            if pacer is not None:
                assert isinstance(clock, WallClock)
                clock.restart(pacer.start())
            # Power-on: both nodes boot; the controller starts the drive (NMT) and walks it
            # to "operation enabled" (CiA 402) over the PDOs.
            drive.boot(clock.now if simulated else time.monotonic())
            controller.boot(clock.now if simulated else time.monotonic())
            while controller.phase != "operational":
                if controller.boot_error:
                    raise ConfigError(controller.boot_error)
                if controller.phase == "safe" or k >= MAX_STARTUP_CYCLES:
                    raise ConfigError(
                        f"the drive did not reach operation enabled within {k} cycles "
                        f"(controller phase {controller.phase}, drive {drive.drive_state})"
                    )
                cycle()
            startup_cycles = k
            next_monitor = monitor_every
            if pacer is not None:
                pacer.begin_recording()  # statistics cover the cycles in operation
            # The run lasts until the interrupt has handled ``cycles`` samples.
            while controller.isr.samplecount < cycles:
                if stop_requested is not None and stop_requested():
                    interrupted = True
                    break
                if controller.phase != "operational":
                    break
                cycle()
                if monitor is not None and controller.isr.samplecount >= next_monitor:
                    next_monitor += monitor_every
                    tap.poll()  # the listeners have seen every frame of those samples
                    monitor(controller)
            done = controller.isr.samplecount
            operation_end = k
            if pacer is not None:
                pacer.end_recording()
            # Walk the drive back (disable operation, shut down) before the buses close.
            controller.request_stop()
            for _ in range(MAX_STOP_CYCLES):
                if controller.phase in ("stopped", "safe"):
                    break
                cycle()
            stop_cycles = k - operation_end
            if pacer is not None and not interrupted:
                pacer.measure_floor()  # the bare loop in the same process state
        except KeyboardInterrupt:
            interrupted = True
        finally:
            if pacer is not None:
                pacer.exit()
        wall = time.perf_counter() - wall0
        tap.poll()
        frames_sent = _frames_sent(ctrl_bus, drive_truth)
    finally:
        # Close the trace (flush, valid file) and release the buses whatever happened.
        try:
            for listener in listeners:
                listener.stop()
        finally:
            for bus in buses:
                bus.shutdown()
            if injector is not None:
                injector.log.close()  # every injected fault is on disk
            blas.restore_original_limits()

    evaluation = (
        evaluate_recording(recorder.recording, fw_config, evaluate_skip_s)
        if recorder is not None and not interrupted
        else None
    )
    names = _frame_names()
    frames = {
        names.get(key, f"channel {key[0]} 0x{key[1]:X}"): n
        for key, n in sorted(counter.counts.items())
    }
    return RunResult(
        scenario=scenario.name,
        seed=seed,
        interface=interface or "python-can configuration",
        actuation=actuation,
        cycles=done,
        sample_period_s=Ts,
        simulated_s=done * Ts,
        wall_s=wall,
        interrupted=interrupted,
        frames=frames,
        frames_total=counter.total,
        frames_sent=frames_sent,
        startup_cycles=startup_cycles,
        stop_cycles=stop_cycles,
        worst_case_load=load.worst_case_load,
        bitrate=bitrate,
        torque={**scorer.result().as_dict(), "rms_filtered_per_minute": scorer.block_rms},
        velocity_final=scorer.velocity_final,
        velocity_peak=scorer.velocity_peak,
        trace=str(trace) if trace is not None else None,
        evaluation=evaluation,
        faults=injector.summary() if injector is not None else None,
        tracking=(
            {"law": fw_config.control.law.name.lower(), **tracking.result().as_dict()}
            if tracking is not None
            else None
        ),
        controller=_controller_diagnostics(controller),
        drive={
            "syncs": drive.diagnostics.syncs,
            "commands": drive.diagnostics.commands,
            "malformed_frames": drive.diagnostics.malformed_frames,
            "unknown_frames": sum(drive.unknown_frames.values()),
        },
        realtime=pacer.result() if pacer is not None else None,
    )


def format_result(r: RunResult) -> str:
    t = r.torque
    lines = [
        f"hdhil run: scenario {r.scenario}, seed {r.seed}, "
        f"{'real time' if r.realtime is not None else 'lockstep'} on {r.interface}"
        f" ({r.actuation} actuation)" + ("  [INTERRUPTED]" if r.interrupted else ""),
        f"  simulated time     {r.simulated_s:.3f} s ({r.cycles} cycles of "
        f"{r.sample_period_s * 1e3:g} ms in operation; start-up {r.startup_cycles}, "
        f"stop {r.stop_cycles} cycles)",
        f"  wall time          {r.wall_s:.3f} s",
        f"  real-time factor   {r.real_time_factor:.1f}x",
        f"  motor velocity     final {r.velocity_final:.1f} rad/s, peak {r.velocity_peak:.1f} rad/s"
        " (telemetry)",
        "  frames on the buses:",
    ]
    lines += [f"    {name:<34} {n:>8}" for name, n in r.frames.items()]
    lines.append(f"    {'total':<34} {r.frames_total:>8}")
    verdict = "ok" if r.worst_case_load <= LOAD_LIMIT else "OVER the 60 % budget"
    lines.append(
        f"  control bus load   {r.worst_case_load:.1%} worst case at "
        f"{r.bitrate / 1e6:g} Mbit/s ({verdict})"
    )
    if t["samples"]:
        lines.append(
            f"  torque vs truth    {t['samples']} samples: RMS true torque {t['rms_true']:.4f} Nm;"
            f" RMS error raw {t['rms_error_raw']:.4f} Nm, filtered {t['rms_error_filtered']:.4f}"
            f" Nm ({t['filtered_to_raw']:.1%} of raw)"
        )
    else:
        lines.append("  torque vs truth    no telemetry/truth pairs were seen")
    if r.faults is not None:
        injected = ", ".join(f"{kind} {n}" for kind, n in r.faults.items()) or "none"
        lines.append(f"  faults injected    {injected}")
    c = r.controller
    if c.get("tacho_rejections") or c.get("encoder_rejections") or c.get("plausibility_errors"):
        lines.append(
            f"  plausibility       replaced {c['tacho_rejections']} tacho samples and "
            f"{c['encoder_rejections']} encoder increments; {c['tacho_reseeds']} / "
            f"{c['encoder_reseeds']} accepted as a new level (tacho / encoder); "
            f"{c['plausibility_errors']} sensor errors (EMCY)"
        )
    if r.tracking is not None:
        lines.append(format_tracking([r.tracking]))
    if r.evaluation is not None:
        lines.append(format_evaluation(r.evaluation))
    if r.realtime is not None:
        lines.append(format_realtime(r.realtime))
    if r.trace:
        lines.append(f"  trace              {r.trace} ({r.frames_total} frames)")
    return "\n".join(lines)


#: The laws ``--compare-laws`` runs, as ``[firmware.control]`` overrides: the seed's three
#: (seed 003 §IV: JTF1 = Eq. 4 with the LQ design, JTF2 k3 = 0, k4 = 1 + Jm/Jl, JTF3
#: k3 = 0, k4 = 1) and JTF1 with desired-torque-derivative feedforward tuned for the
#: tracking scenario (:data:`firmware.config.JTF1_FF_TRACKING`: exact feedforward gains,
#: V = 1e7).
COMPARED_LAWS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("JTF1", {"law": "jtf1"}),
    ("JTF2", {"law": "jtf2"}),
    ("JTF3", {"law": "jtf3"}),
    ("JTF1 + feedforward", {"law": "jtf1_ff", "feedforward": "exact", "weights": {"V": 1e7}}),
)


def format_tracking(rows: list[dict[str, Any]]) -> str:
    lines = [
        "  torque tracking vs truth (e = T_true − T_desired)",
        f"    {'law':<22} {'max |e|/Nm':>10} {'RMS e/Nm':>9} {'RMS τlgd err/Nm':>16} "
        f"{'samples':>8}",
    ]
    for r in rows:
        lines.append(
            f"    {r['law']:<22} {r['max_abs_error']:10.3f} {r['rms_error']:9.3f} "
            f"{r['rms_disturbance_error']:16.3f} {r['samples']:8d}"
        )
    return "\n".join(lines)


def compare_laws(scenario: Scenario, **kwargs: Any) -> list[dict[str, Any]]:
    """Run ``scenario`` once per law of :data:`COMPARED_LAWS`, each closed over the bus."""
    rows = []
    trace: Path | None = kwargs.pop("trace", None)
    for label, control in COMPARED_LAWS:
        firmware = merge(scenario.firmware, {"control": control})
        law_trace = (
            trace.with_name(f"{trace.stem}-{control['law']}{trace.suffix}") if trace else None
        )
        r = run_lockstep(dataclasses.replace(scenario, firmware=firmware), trace=law_trace,
                         evaluate=False, **kwargs)  # fmt: skip
        if r.tracking is None:
            raise ConfigError(f"{scenario.name}: no tracking telemetry for {label}")
        rows.append({**r.tracking, "law": label, "trace": str(law_trace) if law_trace else None,
                     "real_time_factor": r.real_time_factor})  # fmt: skip
        if r.interrupted:
            break
    return rows


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """Turn the first SIGINT/SIGTERM into a stop request (the run ends cleanly at the next
    cycle boundary, trace closed); a second SIGINT interrupts at once."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def request_stop(signum: int, frame: object) -> None:
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
