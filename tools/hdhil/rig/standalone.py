"""One node per process on buses the caller opened: the drive emulator, the controller
firmware and the logger of ``hdhil emulate``, ``hdhil firmware`` and ``hdhil log``.

The commands open the buses, stop on signals and print; here each node is built for a
:class:`~hdhil.rig.request.RunRequest`, given the faults that arise in its own process,
booted and run in the one node loop (:mod:`hdhil.rig.loop`) until ``stop()``, and summed
up as the JSON summary the command prints (with its verdict when the run stopped early).
The firmware paces SYNC by the pacer of ``hdhil run --realtime`` (the command's default)
or, for tests and emulated drives, in network lockstep (SYNC k+1 once the drive's cycle
k is answered, or after the loop's cycle timeout);
a drive that never boots or answers is a start-up verdict. The logger taps the buses into
a trace whose sidecar says what was recorded from where and, for a known run, its request
(so that ``hdhil evaluate`` scores the trace with its settings).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import can

from hdhil.can.faults import FaultLog, FaultyTransmitBus, check_node_transmit_faults
from hdhil.can.traces.tap import BusTap, FrameCounter
from hdhil.can.traces.writer import WriterError, WriterProcess
from hdhil.canopen.nmt import state_name as nmt_state_name
from hdhil.core.dataconf import ConfigError
from hdhil.core.errors import UserError
from hdhil.dbc import CHANNEL_NUMBER, known_frames
from hdhil.dbc import node_ids as dbc_node_ids
from hdhil.firmware.controller import ControllerNode
from hdhil.hostsim.drive import DriveConfig, DriveNode
from hdhil.hostsim.plant import Plant
from hdhil.rig.faults import FaultConfig, FaultInjector, parse_fault_flags
from hdhil.rig.loop import NodeLoop, controller_expects_answer, serve
from hdhil.rig.realtime import RealtimeLoop
from hdhil.rig.request import RunRequest
from hdhil.rig.session import SessionLog, end_session, start_session
from hdhil.rig.sidecar import run_metadata
from hdhil.rig.verdict import dcf_refused, drive_verdict, startup_verdict, stop_verdict

#: The logger's pause when no frame is waiting (s): short against a 1 ms cycle.
IDLE_SLEEP_S = 0.0002
#: The controller's node-ID (control.dbc's node CONTROLLER).
CONTROLLER_NODE_ID = dbc_node_ids("control")["CONTROLLER"]
#: SYNC cycles allowed for walking the drive back to "stopped" after the run.
MAX_STOP_CYCLES = 2000


# ------------------------------------------------------------------ faults
def drive_faults(
    request: RunRequest, flags: Sequence[str], fault_log: str | Path | None, truth: bool
) -> FaultInjector:
    """The faults of the drive's process (``hdhil emulate``): the sensors' and the drive's
    own transmissions on the control bus (and with ``truth`` on the truth bus)."""
    acts_on = ("sensors", "control", "truth") if truth else ("sensors", "control")
    return _process_faults("emulate", request.scenario.faults, flags, fault_log, "drive", acts_on)


def controller_faults(
    request: RunRequest, flags: Sequence[str], fault_log: str | Path | None
) -> FaultInjector:
    """The faults of the controller's process (``hdhil firmware``): its own transmissions."""
    return _process_faults(
        "firmware", request.scenario.faults, flags, fault_log, "controller", ("control",)
    )


def _process_faults(
    command: str,
    faults: FaultConfig | None,
    flags: Sequence[str],
    fault_log: str | Path | None,
    stream: str,
    acts_on: tuple[str, ...],
) -> FaultInjector:
    """The process's faults: ``faults`` (the request's table, ``--fault`` flags merged);
    flags for parts that do not act in this process are refused."""
    flagged = sorted(set(parse_fault_flags(flags)) - {"seed", *acts_on})
    if flagged:
        raise ConfigError(
            f"--fault {flagged[0]}.*: these faults do not act in hdhil {command} "
            f"(it injects {', '.join(acts_on)})"
        )
    config = faults or FaultConfig()
    for role in ("control", "truth"):
        if role in acts_on:
            check_node_transmit_faults(config, role)  # type: ignore[arg-type]
    try:
        log = FaultLog(fault_log, keep=False)
    except OSError as exc:
        raise ConfigError(f"cannot write the fault log {fault_log}: {exc}") from None
    return FaultInjector(config, log, stream=stream)


def _with_faults(
    bus: can.BusABC | None,
    injector: FaultInjector,
    role: Literal["control", "truth"],
    node_id: int,
) -> Any:
    """``bus``, or its :class:`~hdhil.can.faults.FaultyTransmitBus` when the own frames of
    node ``node_id`` on channel ``role`` are to be faulted (a silence of that node stops
    all of them)."""
    hook = injector.channel(role)
    if bus is None or hook is None:
        return bus
    return FaultyTransmitBus(bus, hook, node_id=node_id)


def _flush(*buses: Any) -> None:
    """Send what the faulty buses among ``buses`` still hold back (delayed frames)."""
    for bus in buses:
        if isinstance(bus, FaultyTransmitBus):
            bus.flush()


# ------------------------------------------------------------------ the drive
class StandaloneDrive:
    """The drive emulator of ``hdhil emulate`` on ``bus`` (and the ground truth on
    ``truth``): built here, booted and served by :meth:`serve`, summed up by
    :meth:`summary`."""

    def __init__(
        self,
        request: RunRequest,
        bus: can.BusABC,
        truth: can.BusABC | None,
        injector: FaultInjector,
    ) -> None:
        request.require_one_joint("hdhil emulate")
        layout = request.layout  # the drive at its node-ID (hdhil emulate --node-id)
        config = DriveConfig(
            sample_period_s=request.firmware.sample_period_s,
            node_id=layout.drives[0].node_id,
            controller_node_id=layout.controller_node_id,
        )
        self.injector = injector
        self.bus = _with_faults(bus, injector, "control", config.node_id)
        self.truth = _with_faults(truth, injector, "truth", config.node_id)
        self.node = DriveNode(
            self.bus,
            Plant(request.scenario.plant, request.seed, faults=injector.sensors()),
            config,
            truth_bus=self.truth,
            faults=injector,
        )
        self.sessions = SessionLog(self.node)

    def serve(self, stop: Callable[[], bool], duration_s: float | None = None) -> None:
        """Boot the drive and serve it until ``stop()`` or ``duration_s`` wall seconds
        (none: until a stop)."""
        t_end = time.monotonic() + duration_s if duration_s else float("inf")
        self.sessions.origin = now = time.monotonic()
        self.node.boot(now)
        serve(self.node, stop, lambda: time.monotonic() >= t_end)

    def summary(self) -> dict[str, Any]:
        """Flush the delayed frames; the JSON summary, with the ``verdict`` of a drive
        that went to a fault or lost its master."""
        _flush(self.bus, self.truth)
        drive = self.node
        d = drive.diagnostics
        verdict = drive_verdict(drive)
        summary = {"node": "drive", "syncs": d.syncs, "commands": d.commands,
                   "nmt_state": nmt_state_name(drive.nmt_state),
                   "drive_state": getattr(drive.drive_state, "name", str(drive.drive_state)),
                   "plant_time_s": drive.plant.time, "faults": self.injector.summary(),
                   "sessions": len(self.sessions.sessions),
                   "session_log": self.sessions.summary()}  # fmt: skip
        if verdict is not None:
            summary["verdict"] = verdict
        return summary


# ------------------------------------------------------------------ the controller
class StandaloneController:
    """The controller firmware of ``hdhil firmware`` on ``bus``: built here (a drive DCF it
    cannot use is a :class:`UserError`), booted with the drive by :meth:`boot`, run for
    the request's cycles by :meth:`run`, summed up by :meth:`summary`."""

    def __init__(
        self,
        request: RunRequest,
        bus: can.BusABC,
        injector: FaultInjector,
        boot_timeout_s: float,
    ) -> None:
        request.require_one_joint("hdhil firmware")
        self.request = request
        self.injector = injector
        self.bus = _with_faults(bus, injector, "control", CONTROLLER_NODE_ID)
        try:
            self.node = ControllerNode(
                self.bus,
                request.firmware,
                node_id=CONTROLLER_NODE_ID,
                drive_node_id=request.layout.drives[0].node_id,  # --drive-node-id
                boot_timeout_s=boot_timeout_s,
                drive_dcf=request.mapping.dcf,
            )
        except ValueError as exc:
            raise UserError(str(exc)) from None
        self.pacer: RealtimeLoop | None = None
        self.operational_cycles = 0
        #: The start-up check's line for stderr (a drive found in FAULT was reset), or None.
        self.recovery: str | None = None
        #: Whether the session ended clean (the drive's 0x1016 entry cleared).
        self.ended_clean = False

    def boot(self, stop: Callable[[], bool]) -> dict[str, Any] | None:
        """Boot and wait for the drive's boot-up (or the timeout) while producing
        heartbeats. A DCF the drive refused is a :class:`UserError` (the user's file has
        to change); a drive that never booted or answered (without a stop) gives the JSON
        summary with its start-up verdict, returned; else None."""
        ctrl = self.node
        self.recovery = start_session(self.bus, ctrl.drive_node_id, CONTROLLER_NODE_ID)
        ctrl.boot(time.monotonic())
        serve(ctrl, stop, lambda: ctrl.phase != "wait-boot" or bool(ctrl.boot_error))
        if dcf_refused(ctrl):
            raise UserError(ctrl.boot_error)
        if ctrl.boot_error and not stop():
            return self._boot_failed()
        return None

    def _boot_failed(self) -> dict[str, Any]:
        ctrl = self.node
        d = ctrl.diagnostics
        node = ctrl.drive_node_id if hasattr(ctrl, "drive_node_id") else None
        verdict = startup_verdict(ctrl, str(ctrl.boot_error), node, 0, self.request.cycles,
                                  ctrl.config.sample_period_s)  # fmt: skip
        return {"node": "controller", "operational_cycles": 0, "syncs_sent": d.syncs_sent,
                "sensor_frames": d.sensor_frames, "phase": str(ctrl.phase.value),
                "safe_reason": d.safe_reason, "faults": self.injector.summary(),
                "verdict": verdict}  # fmt: skip

    def run(self, stop: Callable[[], bool], realtime: bool = False) -> int:
        """Produce SYNC until the request's cycles found the controller operational, it
        went safe, or ``stop()``; then walk the drive back to "stopped". ``realtime``: at
        the sample period on the monotonic clock (its statistics start with operation,
        as in ``hdhil run --realtime``), else in network lockstep. Returns the
        operational cycles."""
        ctrl = self.node
        Ts = self.request.sample_period_s
        pacer = self.pacer = RealtimeLoop(Ts) if realtime else None
        loop = NodeLoop(
            [ctrl],
            producer=ctrl,
            answers=lambda: ctrl.diagnostics.commands_sent,
            expects_answer=lambda: controller_expects_answer(ctrl),
            period_s=Ts,
            pacer=pacer,
        )
        if pacer is not None:
            pacer.instrument(ctrl)
            pacer.enter()
            pacer.start()
        try:
            self.operational_cycles = _sync_cycles(loop, ctrl, stop, self.request.cycles, pacer)
            if pacer is not None:
                pacer.end_recording()
            ctrl.request_stop()  # walk the drive back to "stopped"
            for _ in range(MAX_STOP_CYCLES):
                if ctrl.phase in ("stopped", "safe"):
                    break
                loop.cycle()
        finally:
            if pacer is not None:
                pacer.exit()
        self.ended_clean = end_session(
            self.bus, ctrl.drive_node_id, CONTROLLER_NODE_ID, ctrl.services.produce_heartbeat
        )
        return self.operational_cycles

    def summary(self, stopped: bool) -> dict[str, Any]:
        """Flush the delayed frames; the JSON summary, with the ``verdict`` of a run that
        ended early (none after a stop by the user: ``stopped``)."""
        _flush(self.bus)
        ctrl = self.node
        d = ctrl.diagnostics
        done = self.operational_cycles
        Ts = self.request.sample_period_s
        verdict = None if stopped else stop_verdict(ctrl, self.request.cycles, done, Ts)
        summary = {"node": "controller", "operational_cycles": done,
                   "syncs_sent": d.syncs_sent, "sensor_frames": d.sensor_frames,
                   "phase": str(ctrl.phase.value), "mapping": ctrl.sensor_mapping,
                   "faults": self.injector.summary(), "ended_clean": self.ended_clean}  # fmt: skip
        if self.recovery is not None:
            summary["recovery"] = self.recovery
        if ctrl.rated_torque_Nm is not None:
            summary["rated_torque_Nm"] = ctrl.rated_torque_Nm
        if ctrl.phase == "safe":
            summary["safe_reason"] = d.safe_reason
        if self.pacer is not None:  # the real-time statistics, as in hdhil run --json
            summary["realtime"] = self.pacer.result()
        if verdict is not None:
            summary["verdict"] = verdict
        return summary


def _sync_cycles(
    loop: NodeLoop,
    ctrl: ControllerNode,
    stop: Callable[[], bool],
    cycles: int,
    pacer: RealtimeLoop | None = None,
) -> int:
    """Run the loop's SYNC cycles until ``cycles`` of them found the controller
    operational, it went safe, or a stop; return the operational cycles.  The pacer's
    statistics start with operation, as in ``hdhil run --realtime``."""
    operational = 0
    while operational < cycles and not stop():
        if ctrl.phase == "safe":
            break
        loop.cycle()
        if ctrl.phase == "operational":
            if pacer is not None and not pacer.recording:
                pacer.begin_recording()
            operational += 1
    return operational


# ------------------------------------------------------------------ the logger
def log_metadata(control: Mapping[str, Any], request: RunRequest | None) -> dict[str, Any]:
    """The sidecar of a logged trace: what was recorded from where (``control``: the
    control bus's resolved configuration) and, with ``request``, the run's request."""
    meta: dict[str, Any] = {
        "recorded_by": "hdhil log",
        "interface": control.get("interface"),
        "channel": control.get("channel"),
        "bitrate": control.get("bitrate"),
        "channels": dict(CHANNEL_NUMBER),
        "time_offset_s": 0.0,
    }
    if request is not None:
        meta.update(
            scenario=request.name,
            seed=request.seed,
            sample_period_s=request.sample_period_s,
            **run_metadata(request),
        )
    return meta


@dataclass(frozen=True)
class Recording:
    """What :func:`record` wrote: the frames, and whether ``stop()`` ended it."""

    frames: int
    stopped: bool


class OwnBusFrames:
    """Hands on each bus's own frames only: a truth frame received on the control bus, or a
    control frame on the truth bus, is dropped.  python-can's udp_multicast delivers every
    group that any socket of the host joined on its port to each of them, so a logger of
    two groups would record every frame twice, once on the wrong bus."""

    def __init__(self, listeners: Sequence[Any]) -> None:
        self.listeners = list(listeners)
        self._truth = known_frames("truth")
        self._channel = CHANNEL_NUMBER["truth"]

    def on_frames(self, frames: list[can.Message]) -> None:
        truth, channel = self._truth, self._channel
        own = [
            m
            for m in frames
            if ((m.arbitration_id, m.is_extended_id) in truth) == (m.channel == channel)
        ]
        if own:
            for listener in self.listeners:
                listener.on_frames(own)

    def on_message_received(self, msg: can.Message) -> None:
        self.on_frames([msg])

    def stop(self) -> None:
        for listener in self.listeners:
            listener.stop()


def record(
    trace: Path,
    control: can.BusABC,
    truth: can.BusABC | None,
    metadata: dict[str, Any],
    stop: Callable[[], bool],
    duration_s: float | None = None,
) -> Recording:
    """Record the control bus (and ``truth``) to ``trace`` with ``metadata`` in its sidecar
    until ``stop()`` or ``duration_s`` wall seconds. The trace is written to a temporary
    and renamed into place when complete, also after a stop; a trace that cannot be
    written is a :class:`UserError`."""
    buses = {CHANNEL_NUMBER["control"]: control}
    if truth is not None:
        buses[CHANNEL_NUMBER["truth"]] = truth
    counter = FrameCounter()
    try:
        writer = WriterProcess(trace, metadata=metadata)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    listeners: list[Any] = [writer, counter]
    tap = BusTap(buses, [OwnBusFrames(listeners)] if truth is not None else listeners)
    t_end = time.monotonic() + duration_s if duration_s else float("inf")
    try:
        while not stop() and time.monotonic() < t_end:
            if not tap.poll():
                time.sleep(IDLE_SLEEP_S)
        stopped = stop()
        tap.poll()
    finally:
        try:
            tap.stop()  # flushes and closes the trace, renames it into place
        except WriterError as exc:
            raise UserError(str(exc)) from None
    return Recording(counter.total, stopped)
