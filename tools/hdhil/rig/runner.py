"""``hdhil run``: a full emulated run in one process, lockstep on the simulated bus.

The nodes share python-can channels and nothing else: the controller
(:class:`firmware.controller.ControllerNode`) and the drives
(:class:`hostsim.drive.DriveNode`, publishing ground truth on the truth channel) on the
control bus, and the host tap (:class:`hdhil.can.traces.tap.BusTap`: trace writer, frame
counter, scorers) listening on both. The runner builds no node itself: they come from
factories (:mod:`hdhil.rig.factories`), one per slot of the request's layout, and run in
the one node loop (:mod:`hdhil.rig.loop`). A :class:`~hdhil.rig.request.RunRequest` is
planned (:func:`plan_run`), its buses opened and its nodes built (:mod:`hdhil.rig.wiring`),
then it goes through start-up, operation and stop (:mod:`hdhil.rig.phases`) and is scored
once into a :class:`~hdhil.rig.result.RunResult` (headline first).

Lockstep (``docs/design.md``, "Timing semantics"): SYNC k is sent at simulated time
k·Ts; every node handles what the bus delivers until the cycle is quiet, and SYNC k+1
follows at once: deterministic for a given seed, as fast as the host allows.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
from threadpoolctl import threadpool_limits

from hdhil.can.busload import ScheduleLoad, schedule_load
from hdhil.can.faults import FaultLog
from hdhil.can.groups import GroupChannel
from hdhil.can.simbus import SimBus, SimClock
from hdhil.can.traces.tap import BusTap
from hdhil.core.dataconf import ConfigError
from hdhil.core.errors import UserError
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.controller import ControllerNode
from hdhil.rig.evaluate import evaluate_listener as evaluate_recording
from hdhil.rig.factories import (
    ControllerFactory,
    DriveFactory,
    RigLayout,
    dcf_controller,
    scenario_controller,
    scenario_drive,
)
from hdhil.rig.faults import FaultInjector
from hdhil.rig.headline import headline
from hdhil.rig.loop import NodeLoop, controller_expects_answer
from hdhil.rig.phases import PhaseCounts, run_phases
from hdhil.rig.realtime import RealtimeConfig, RealtimeLoop, WallClock
from hdhil.rig.request import RunRequest
from hdhil.rig.result import RunResult, controller_diagnostics, drive_diagnostics, frame_names
from hdhil.rig.scenario import Scenario
from hdhil.rig.sidecar import run_metadata
from hdhil.rig.verdict import startup_verdict, stop_verdict, with_plant_failure
from hdhil.rig.wiring import RigBuses, RigNodes, RunListeners, build_listeners, build_nodes

#: In lockstep on the simulated bus the tap drains its queues every this many cycles
#: (and before a monitor call and at the end): its listeners see the same frames in
#: the same order, with less work per frame.  Every cycle in real-time mode and on
#: other interfaces.
TAP_EVERY_CYCLES = 16
#: The cycle timeout of a run whose nodes fault their own frames on a non-simulated bus
#: (s): every node is in this process, so an answer that has not come by then was dropped.
FAULTY_CYCLE_TIMEOUT_S = 0.02


def _frames_sent(control: can.BusABC, truth: can.BusABC | GroupChannel) -> dict[str, int]:
    """Frames each channel carried, as counted by the bus itself (simbus and frame groups only)."""
    return {
        name: bus.frames_sent
        for name, bus in (("control", control), ("truth", truth))
        if hasattr(bus, "frames_sent")
    }


# ---------------------------------------------------------------------- the plan
@dataclass(frozen=True)
class RunPlan:
    """Where and how a :class:`RunRequest` will run, checked before anything is opened
    (every check that can fail without a bus fails here)."""

    request: RunRequest
    interface: str | None
    channel: str | None
    realtime: bool
    load: ScheduleLoad

    @property
    def scenario(self) -> Scenario:
        return self.request.scenario

    @property
    def firmware(self) -> FirmwareConfig:
        return self.request.firmware

    @property
    def seed(self) -> int:
        return self.request.seed

    @property
    def cycles(self) -> int:
        return self.request.cycles

    @property
    def bitrate(self) -> int:
        return self.request.bitrate

    @property
    def actuation(self) -> str:
        return self.request.actuation

    @property
    def layout(self) -> RigLayout:
        return self.request.layout

    @property
    def sample_period_s(self) -> float:
        return self.request.sample_period_s

    @property
    def simulated(self) -> bool:
        """The control bus is the in-process simulated bus (lockstep in simulated time)."""
        return self.interface == "simbus"

    @property
    def clock_time(self) -> bool:
        """Every frame the tap hands on carries the run's clock (the cycle time ``k * Ts``
        in lockstep): always on the simulated bus; on any other interface in lockstep,
        where the tap stamps the control frames itself (:class:`CycleStampedTap`).  Not
        for another interface in real time, whose frames keep the interface's own
        (wall-clock or hardware) timestamps."""
        return self.simulated or not self.realtime


def plan_run(
    request: RunRequest, interface: str | None, channel: str | None, realtime: bool
) -> RunPlan:
    """Check that ``request``'s cyclic schedule fits its bus (one-line :class:`ConfigError`
    otherwise)."""
    if not isinstance(request, RunRequest):
        raise TypeError(
            f"run_lockstep takes a RunRequest (hdhil.rig.request.resolve), got "
            f"{type(request).__name__}"
        )
    request.require_one_joint("run_lockstep (hdhil.rig.rigrun.run_rig runs a rig)")
    Ts = request.sample_period_s
    layout = request.layout
    db = None
    if (layout.drives[0].node_id, layout.controller_node_id) != (2, 1):
        from hdhil.canopen.rigdb import single_joint_databases

        # the drive's and the controller's identifiers at their node-IDs
        db = single_joint_databases(layout.drives[0].node_id, layout.controller_node_id)
        db = db["control"]
    load = schedule_load("control", request.bitrate, Ts, db=db)
    if load.worst_case_load > 1.0:
        raise ConfigError(
            f"the cyclic schedule needs {load.worst_case_load:.0%} of a "
            f"{request.bitrate} bit/s bus at {Ts * 1e3:g} ms: it cannot run"
        )
    return RunPlan(request=request, interface=interface, channel=channel, realtime=realtime,
                   load=load)  # fmt: skip


# ---------------------------------------------------------------------- the run
def run_lockstep(
    request: RunRequest,
    *,
    trace: Path | None = None,
    interface: str | None = "simbus",
    channel: str | None = None,
    open_control_bus: Callable[[], can.BusABC] | None = None,
    realtime: bool = False,
    realtime_config: RealtimeConfig | None = None,
    evaluate: bool = True,
    keep_recording: bool = True,
    stop_requested: Callable[[], bool] | None = None,
    monitor: Callable[[ControllerNode], None] | None = None,
    monitor_every: int = 1000,
    extra_listeners: Sequence[can.Listener] = (),
    fault_log: Path | None = None,
    controller_factory: ControllerFactory | None = None,
    drive_factories: Sequence[DriveFactory] | None = None,
    start_time: float | None = None,
    metadata: dict[str, Any] | None = None,
) -> RunResult:
    """Run ``request`` (:func:`hdhil.rig.request.resolve`) and return the scored result.

    Where: ``interface`` (``simbus``, the in-process simulated bus, by default; any
    python-can interface, opened by ``open_control_bus`` when given) and ``channel``;
    ``realtime`` paces SYNC by the wall clock instead of lockstep (``realtime_config``:
    spin window, machine-floor reference). ``trace`` writes a trace and its sidecar
    JSON, which carries the request (``start_time``: Unix time of simulated time 0).

    ``evaluate`` scores the run (:mod:`hdhil.rig.evaluate`; in lockstep as it goes) and
    keeps every cycle in ``result.recording``; without ``keep_recording`` (or without
    ``evaluate``) memory stays flat. ``stop_requested`` is
    polled at every cycle boundary (how Ctrl-C ends a run without losing a frame);
    ``monitor`` gets the controller every ``monitor_every`` samples; ``extra_listeners``
    see every frame of both buses. The nodes come from factories
    (:mod:`hdhil.rig.factories`): by default the firmware's controller (configuring its
    drive from the request's DCF, if any) and one emulated drive per layout slot.
    """
    plan = plan_run(request, interface, channel, realtime)
    if monitor is not None and monitor_every < 1:
        raise ConfigError(f"monitor_every must be >= 1 sample, got {monitor_every}")
    scenario = request.scenario
    Ts = plan.sample_period_s
    pacer = RealtimeLoop(Ts, realtime_config) if realtime else None  # checks its options
    factories = drive_factories or [scenario_drive(scenario)]
    if controller_factory is None:
        dcf = request.mapping.dcf
        controller_factory = dcf_controller(dcf) if dcf is not None else scenario_controller
    metadata = {**run_metadata(request), **(metadata or {})}
    evaluate_skip_s = request.evaluate_from_s
    # Injected faults (the scenario's [faults] table), reproducible by their seed and logged.
    # The fault log is written whenever it is asked for: empty for a run without faults
    # (an old log never passes for this run's).
    fault_file = FaultLog(fault_log) if fault_log is not None else None
    try:
        injector = (
            FaultInjector(scenario.faults, fault_file or FaultLog())
            if scenario.faults is not None
            else None
        )
        clock = WallClock() if realtime else SimClock()
        buses = RigBuses(plan, clock, injector, open_control_bus)
    except BaseException:
        if fault_file is not None:
            fault_file.discard()  # nothing ran: no temporary left behind
        raise
    # One BLAS thread for the run: the matrices here are at most 7x7, so BLAS threads
    # only spin and take the core the trace writer runs on; and a thread pool created
    # under SCHED_FIFO on one pinned CPU (OpenBLAS restarts its pool lazily after the
    # writer's fork) starves its own workers and livelocks the real-time loop.
    blas = threadpool_limits(limits=1)
    if start_time is None:
        start_time = round(time.time(), 3)  # whole ms: the resolution of BLF's header date
    listening: RunListeners | None = None
    listeners: list[can.Listener] = []
    wall = 0.0
    frames_sent: dict[str, int] = {}
    completed = False
    try:
        nodes = build_nodes(plan, buses, controller_factory, factories, injector)
        # The fault log is renamed into place with the trace (one output: both or none).
        log_file = fault_file.hand_over() if fault_file is not None and trace else None
        listening = build_listeners(plan, trace, evaluate, evaluate_skip_s, extra_listeners,
                                    start_time, metadata, keep_recording,
                                    (log_file,) if log_file else ())  # fmt: skip
        listeners = listening.all
        tap = BusTap(nodes.tap_buses, listeners)
        controller = nodes.controller
        pumped = nodes.controller_bus if plan.simulated else None
        in_cycle_time = buses.faulty_transmit and pacer is None
        assert pumped is None or isinstance(pumped, SimBus)
        loop = NodeLoop(
            [*nodes.drives, controller],
            producer=controller,
            answers=lambda: controller.diagnostics.commands_sent,
            expects_answer=lambda: controller_expects_answer(controller),
            listeners=[tap],
            listen_every=TAP_EVERY_CYCLES if plan.simulated and pacer is None else 1,
            period_s=Ts,
            sim_clock=clock,
            # None: the sim clock; also on another interface when the nodes put their own
            # frames through faults (lockstep over a lossy link: a dropped answer closes
            # its cycle after a short wait and costs one cycle of the nodes' time, as on
            # the simulated bus, not half a second of their heartbeat timers).
            node_time=None if plan.simulated or in_cycle_time else time.monotonic,
            pump=pumped,
            pacer=pacer,
            timeout_s=FAULTY_CYCLE_TIMEOUT_S if in_cycle_time else None,
        )
        if pacer is not None:
            pacer.instrument(controller)
            pacer.enter()
        wall0 = time.perf_counter()
        try:
            if pacer is not None:
                assert isinstance(clock, WallClock)
                clock.restart(pacer.start())
            counts = run_phases(loop, nodes, plan.cycles, pacer, stop_requested, monitor,
                                monitor_every, lossy=in_cycle_time)  # fmt: skip
        finally:
            if pacer is not None:
                pacer.exit()
        wall = time.perf_counter() - wall0
        tap.poll()
        frames_sent = _frames_sent(nodes.controller_bus, nodes.truth_bus)
        completed = True
    finally:
        # Close the trace (flush, valid file) and release the buses whatever happened;
        # the run's outputs (trace, sidecar, fault log) land together or not at all.
        try:
            _finish_outputs(listening, listeners, fault_file)
        except BaseException:
            completed = False
            raise
        finally:
            if not completed and listening is not None:
                discard_evaluation(listening)
            buses.shutdown()
            if fault_file is not None:
                fault_file.close()  # every injected fault is on disk (or none is)
            blas.restore_original_limits()
    try:
        if counts.keyboard and stop_requested is None:
            # A caller that polls no stop request (bench, tune, a script) gets Ctrl-C as it
            # came, once the trace is closed and the buses released: a loop around runs
            # must end, not start the next run.
            raise KeyboardInterrupt
        result = _result(plan, nodes, listening, counts, wall, frames_sent, trace, injector,
                         pacer, evaluate_skip_s)  # fmt: skip
    finally:
        discard_evaluation(listening)  # not collected (interrupted, failed): none comes
    result.start_time = start_time if plan.clock_time else None
    return result


def _finish_outputs(
    listening: RunListeners | None,
    listeners: Sequence[can.Listener],
    log: FaultLog | None,
) -> None:
    """Stop the listeners: the trace writer renames the trace, its sidecar and the fault
    log into place.  A fault log that could not be written (disk full) stops the writer
    without renaming anything (the old files stay as they were) and is the error; a run
    that failed before its listeners were built keeps no fault log either."""
    log_error: UserError | None = None
    if log is not None and (listening is None or (log.handed_over and listening.writer is None)):
        log.discard()  # the run never started its outputs: nothing to keep
    if log is not None:
        try:
            log.finish()  # every line in the file before the writer renames it
        except UserError as exc:
            log_error = exc
        if log.error is not None and log_error is None:
            log_error = UserError(log.error)
    writer = listening.writer if listening is not None else None
    if log_error is not None and writer is not None:
        writer.abort()
    try:
        for listener in listeners:
            if listener is not writer or log_error is None:
                listener.stop()
    finally:
        if log_error is not None:
            raise log_error


def collect_evaluation(listening: RunListeners) -> dict[str, Any]:
    """The evaluation the trace writer's process made of a finished run (its listeners
    stopped): waits for the child to send it.  Raises
    :class:`hdhil.can.traces.writer.ChildListenerError` if it failed or died."""
    writer = listening.evaluating_writer
    assert writer is not None
    return writer.child_result()  # type: ignore[no-any-return]


def discard_evaluation(listening: RunListeners) -> None:
    """Let the trace writer's process end without sending its evaluation (a no-op when
    it was collected or none was made)."""
    if listening.evaluating_writer is not None:
        listening.evaluating_writer.discard_child_result()


def _result(
    plan: RunPlan,
    nodes: RigNodes,
    listening: RunListeners,
    counts: PhaseCounts,
    wall: float,
    frames_sent: dict[str, int],
    trace: Path | None,
    injector: FaultInjector | None,
    pacer: RealtimeLoop | None,
    evaluate_skip_s: float,
) -> RunResult:
    """The scored result of a finished run, every figure from the run itself."""
    recorder, tracking = listening.recorder, listening.tracking
    scored = plan.scenario.scored
    wanted = not counts.interrupted and "ripple" in scored
    evaluation = None
    if wanted and recorder is not None:
        evaluation = evaluate_recording(recorder, plan.firmware, evaluate_skip_s)
    elif wanted and listening.evaluating_writer is not None:
        evaluation = collect_evaluation(listening)
    tracked = (
        {"law": plan.firmware.control.law.name.lower(), **tracking.result().as_dict()}
        if tracking is not None
        else None
    )
    layout = plan.layout
    names = frame_names(layout.drives[0].node_id, layout.controller_node_id)
    counter = listening.counter
    frames = {
        names.get(key, f"channel {key[0]} 0x{key[1]:X}"): n
        for key, n in sorted(counter.counts.items())
    }
    drives = nodes.drives
    drive = (
        drive_diagnostics(drives[0])
        if len(drives) == 1
        else {f"node {d.config.node_id}": drive_diagnostics(d) for d in drives}
    )
    Ts = plan.sample_period_s
    done = counts.operation
    scorer = listening.scorer
    return RunResult(
        scenario=plan.scenario.name,
        seed=plan.seed,
        interface=plan.interface or "python-can configuration",
        actuation=plan.actuation,
        cycles=done,
        sample_period_s=Ts,
        simulated_s=done * Ts,
        wall_s=wall,
        interrupted=counts.interrupted,
        frames=frames,
        frames_total=counter.total,
        frames_sent=frames_sent,
        startup_cycles=counts.startup,
        stop_cycles=counts.stop,
        worst_case_load=plan.load.worst_case_load,
        bitrate=plan.bitrate,
        torque={**scorer.result().as_dict(), "rms_filtered_per_minute": scorer.block_rms},
        velocity_final=scorer.velocity_final,
        velocity_peak=scorer.velocity_peak,
        trace=str(trace) if trace is not None else None,
        evaluation=evaluation,
        faults=injector.summary() if injector is not None else None,
        tracking=tracked,
        headline=headline(scored, evaluation, tracked, evaluate_skip_s),
        scored=scored,
        controller=controller_diagnostics(nodes.controller),
        drive=drive,
        realtime=pacer.result() if pacer is not None else None,
        recording=(
            recorder.recording if recorder is not None and listening.keep_recording else None
        ),
        verdict=with_plant_failure(
            None
            if counts.interrupted
            else startup_verdict(
                nodes.controller,
                counts.startup_failure,
                counts.startup_node,
                counts.startup,
                plan.cycles,
                Ts,
            )
            if counts.startup_failure is not None
            else stop_verdict(nodes.controller, plan.cycles, done, Ts),
            drives,
            plan.cycles,
            done,
            Ts,
        ),
    )
