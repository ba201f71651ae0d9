"""The phases of a run: start-up, operation and stop, in the one node loop.

:func:`start_up` boots every node and waits for the controller to walk the drives to
"operation enabled" (NMT start, CiA 402); :func:`operate` cycles until the interrupt has
handled the planned samples, the controller leaves operation or a stop is requested;
:func:`shut_down` walks the drives back before the buses close. :func:`run_phases` runs
the three and counts their cycles (:class:`PhaseCounts`); a start-up that fails is a stop
like any other, reported as the run's verdict. The loop itself is
:class:`hdhil.rig.loop.NodeLoop`; the nodes come from :func:`hdhil.rig.wiring.build_nodes`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from hdhil.canopen.cia402 import State
from hdhil.core.dataconf import ConfigError
from hdhil.firmware.controller import ControllerNode
from hdhil.hostsim.drive import DriveNode
from hdhil.rig.loop import NodeLoop
from hdhil.rig.realtime import RealtimeLoop
from hdhil.rig.verdict import dcf_refused
from hdhil.rig.wiring import RigNodes

#: Cycles allowed from power-on to "operation enabled" (NMT start and the CiA 402 walk
#: take a handful) and back to "stopped".
MAX_STARTUP_CYCLES = 500
MAX_STOP_CYCLES = 200


class SilentPeerError(ConfigError):
    """A drive stopped answering SYNC on a non-simulated bus and the controller went
    safe (its sensor hold)."""


@dataclass
class PhaseCounts:
    """Cycles per phase of a run and how it ended."""

    startup: int = 0
    operation: int = 0  # interrupts run in operation
    stop: int = 0
    interrupted: bool = False
    #: Why start-up failed (the drive never reached "operation enabled"), else None.
    startup_failure: str | None = None
    #: The node that failed to start (the first drive not in operation enabled).
    startup_node: int | None = None
    #: Ended by ``KeyboardInterrupt`` (Ctrl-C with no stop request polled, or a second one).
    keyboard: bool = False


def _node_id(drive: DriveNode) -> int | None:
    return getattr(getattr(drive, "config", None), "node_id", None)


def start_up(
    loop: NodeLoop, controller: ControllerNode, drives: Sequence[DriveNode]
) -> tuple[str, int | None] | None:
    """Power-on: every node boots; the controller starts the drives (NMT) and walks them to
    "operation enabled" (CiA 402) over the PDOs.

    Returns None once the controller is operational, else ``(why, node)``: a start-up that
    fails (no boot-up, a drive that never reaches operation enabled, e.g. under heavy
    frame loss) is a stop like any other, reported as the run's verdict (exit code 1).  A
    drive refusing a value of the user's DCF is an input error (:class:`ConfigError`,
    exit code 2): the file has to change, not the bus."""
    loop.boot()
    while controller.phase != "operational":
        if dcf_refused(controller):
            raise ConfigError(controller.boot_error)
        failed = [d for d in drives if d.drive_state != State.OPERATION_ENABLED]
        node = _node_id(failed[0]) if failed else None
        if controller.boot_error:
            return controller.boot_error, node
        if controller.phase == "safe" or loop.k >= MAX_STARTUP_CYCLES:
            states = ", ".join(
                f"node {_node_id(d)} {getattr(d.drive_state, 'name', d.drive_state)}"
                for d in drives
            )
            return (
                f"the drive did not reach operation enabled within {loop.k} start-up cycles "
                f"(controller phase {controller.phase}, drive {states})"
            ), node
        loop.cycle()
    return None


def operate(
    loop: NodeLoop,
    controller: ControllerNode,
    cycles: int,
    stop_requested: Callable[[], bool] | None,
    monitor: Callable[[ControllerNode], None] | None,
    monitor_every: int,
) -> bool:
    """Cycles until the interrupt has handled ``cycles`` samples, the controller leaves
    operation or a stop is requested (polled at every cycle boundary; returns True
    then). ``monitor`` is called every ``monitor_every`` samples, after the tap has
    handed every frame of those samples to its listeners."""
    isr = controller.isr
    next_monitor = monitor_every
    while isr.samplecount < cycles:
        if stop_requested is not None and stop_requested():
            return True
        if controller.phase != "operational":
            break
        loop.cycle()
        if monitor is not None and isr.samplecount >= next_monitor:
            next_monitor += monitor_every
            loop.drain()  # the listeners have seen every frame of those samples
            monitor(controller)
    return False


def shut_down(loop: NodeLoop, controller: ControllerNode) -> None:
    """Walk the drives back (disable operation, shut down) before the buses close."""
    controller.request_stop()
    for _ in range(MAX_STOP_CYCLES):
        if controller.phase in ("stopped", "safe"):
            break
        loop.cycle()


def run_phases(
    loop: NodeLoop,
    nodes: RigNodes,
    cycles: int,
    pacer: RealtimeLoop | None,
    stop_requested: Callable[[], bool] | None,
    monitor: Callable[[ControllerNode], None] | None,
    monitor_every: int,
    lossy: bool = False,
) -> PhaseCounts:
    """Start-up, operation and stop, with the pacer's statistics covering operation.

    ``lossy``: the nodes drop some of their own frames on purpose (faults on a
    non-simulated bus), so cycles that timed out do not make a silent peer: the
    controller's own reason for its safe state is the verdict."""
    counts = PhaseCounts()
    controller = nodes.controller
    try:
        failure = start_up(loop, controller, nodes.drives)
        counts.startup = loop.k
        if failure is not None:
            counts.startup_failure, counts.startup_node = failure
            operation_end = loop.k
            shut_down(loop, controller)  # NMT stop / disable whatever did start
            counts.stop = loop.k - operation_end
            return counts
        if pacer is not None:
            pacer.begin_recording()  # statistics cover the cycles in operation
        counts.interrupted = operate(
            loop, controller, cycles, stop_requested, monitor, monitor_every
        )
        counts.operation = controller.isr.samplecount
        if loop.timeouts and controller.phase == "safe" and not lossy:
            raise SilentPeerError(
                f"the drive went silent: {loop.timeouts} cycles without its sensor frame "
                f"within {loop.timeout_s:g} s of SYNC, the controller went safe"
            )
        operation_end = loop.k
        if pacer is not None:
            pacer.end_recording()
        shut_down(loop, controller)
        counts.stop = loop.k - operation_end
        if pacer is not None and not counts.interrupted:
            pacer.measure_floor()  # the bare loop in the same process state
    except KeyboardInterrupt:
        counts.interrupted = counts.keyboard = True
    return counts
