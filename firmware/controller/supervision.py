"""The controller's supervision: the drive's and its own NMT health, the sensors' EMCYs.

What can take the link out of service besides the walk: a lost heartbeat of the drive,
a boot-up of the drive while it is commanded, NMT commands from another master, and what
the interrupt handler's plausibility and stuck-channel stages flag, which go on the bus
as EMCY.  The services call it back (heartbeat, boot-up, NMT); the node's ``tick`` asks
it once per cycle about the sensors.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from hdhil.canopen.services import EmcyCode, NmtState, ResetKind
from hdhil.firmware.controller.phases import COMMANDING, FINAL, Phase

if TYPE_CHECKING:
    from hdhil.firmware.controller.joint import ControllerJoint

__all__ = ["Supervision"]


class Supervision:
    """Faults that end in "safe", and the sensor errors that do not.

    The drive's heartbeat times out (250 ms, monitored from its first heartbeat; the check
    runs in ``tick``, so it is detected within one tick): EMCY 0x8130 with the drive's
    node-ID in manufacturer byte 0, phase "safe".  A boot-up of the drive while it is
    commanded (it was reset), and NMT commands from another master that take the
    controller out of OPERATIONAL (or reset it), also lead to "safe".

    Sensor plausibility (:class:`hdhil.firmware.stages.SensorPlausibility`) does not stop
    the controller: replaced tacho samples and encoder increments are counted in the
    diagnostics, and when a channel is replaced ``max_rejections`` times in a row the next
    ``tick`` sends EMCY 0x7301 "tacho fault" or 0x7305 "incremental sensor 1 fault"
    (CiA 402), once; EMCY 0x0000 follows when the channel is plausible again.  Stuck
    channels (:class:`hdhil.firmware.stages.StuckChannels`) are announced the same way.
    """

    def __init__(self, node: ControllerJoint) -> None:
        self.node = node
        self.plausibility_revision = 0
        self.stuck_revision = 0
        self.plausibility_emcy: set[int] = set()  # EMCY codes of active sensor errors
        #: In a node of several joints the sensor EMCYs name the joint's drive: its
        #: node-ID in manufacturer byte 4 (bytes 0-3 as in a node of one joint).
        several = len(node.controller.joints) > 1
        self.emcy_tag = bytes((node.drive_node_id,)) if several else b""
        services = node.services
        services.on_boot(self.on_boot)
        services.on_heartbeat_lost(self.on_heartbeat_lost)
        services.on_state_change(self.on_nmt_state)  # on_reset: called by the node

    # ------------------------------------------------------------ NMT, heartbeat

    def on_boot(self, node_id: int) -> None:
        node = self.node
        if node_id != node.drive_node_id:
            return
        if node.phase is Phase.WAIT_BOOT and node.services.state is not NmtState.INITIALISING:
            node.sequencer.drive_seen()
        elif node.phase in COMMANDING:
            node.enter_safe(
                f"drive (node {node_id}) sent a boot-up while {node.phase}: it was reset"
            )

    def on_heartbeat_lost(self, node_id: int) -> None:
        node = self.node
        if node_id != node.drive_node_id:
            return
        monitor = node.services.heartbeat_consumer.monitored[node_id]
        d = node.diagnostics
        d.heartbeat_losses += 1
        d.heartbeat_lost_at_s = monitor.lost_at
        if node.phase not in FINAL:
            node.enter_safe(
                f"heartbeat of drive (node {node_id}) lost: none for "
                f"{monitor.timeout_s * 1e3:g} ms, detected at {monitor.lost_at:.3f} s"
            )

    def on_nmt_state(self, old: NmtState, new: NmtState) -> None:
        """NMT commands from another master that take the controller out of service."""
        node = self.node
        if node.own_nmt or node.phase in FINAL or new is NmtState.INITIALISING:
            return
        if any(m.status == "lost" and m.lost_at == node.now
               for m in node.services.heartbeat_consumer.monitored.values()):  # fmt: skip
            return  # 0x1029 error behaviour on heartbeat loss: on_heartbeat_lost follows
        if new is NmtState.STOPPED or (old is NmtState.OPERATIONAL and node.phase in COMMANDING):
            node.enter_safe(f"NMT {new.name} commanded by another master")

    def on_reset(self, kind: ResetKind) -> None:
        """NMT reset of the controller by another master: OD values back to what the node
        runs, then "safe"."""
        node = self.node
        node.restore_after_reset(kind)
        if node.phase not in FINAL:
            node.enter_safe(f"NMT reset ({kind}) of the controller by another master")

    # ------------------------------------------------------------------ sensors

    def check_sensors(self) -> None:
        """Once per tick, with the firmware's own handler: its plausibility and
        stuck-channel flags, when they changed."""
        isr: Any = self.node.isr
        if isr.chain.plausibility.revision != self.plausibility_revision:
            self.report_plausibility()
        stuck = isr.stuck
        if stuck is not None and stuck.revision != self.stuck_revision:
            self.report_stuck(stuck)

    def manufacturer(self, data: bytes) -> bytes:
        """A sensor EMCY's manufacturer bytes, with the joint's tag in a node of several."""
        tag = self.emcy_tag
        return data.ljust(4, b"\0") + tag if tag else data

    def report_stuck(self, stuck: Any) -> None:
        """An EMCY when a channel gets stuck, cleared when it reads again; the diagnostic
        counters follow.  Codes (CiA 402 / IEC 61800-7-201, "sensor" family 0x73xx), with
        the channel in manufacturer byte 0: torque 0x7300 "sensor error" with 1 (no more
        specific code exists for a torque bridge), tacho 0x7301 "tacho fault" with 2."""
        node = self.node
        self.stuck_revision = stuck.revision
        node.diagnostics.stuck_sensor_events = stuck.events
        node.diagnostics.stuck_tacho_events = getattr(stuck, "tacho_events", 0)
        emcy = node.services.emcy
        for code, channel, flag in (
            (EmcyCode.SENSOR, 1, stuck.torque_stuck),
            (EmcyCode.TACHO_FAULT, 2, stuck.tacho_stuck),
        ):
            if flag:
                emcy.raise_error(code, manufacturer=self.manufacturer(bytes((channel,))))
            else:
                emcy.clear(code, self.manufacturer(bytes((channel,))))

    def report_plausibility(self) -> None:
        """The plausibility stage's counters into the diagnostics, and its error flags on
        the bus (CiA 301 §7.2.7: an EMCY when an error occurs, EMCY 0x0000 "error reset
        or no error" when it goes away; not one per replaced sample).

        Codes (CiA 402 / IEC 61800-7-201 table of error codes, "sensor" family 0x73xx):
        0x7301 "tacho fault" for the velocity and 0x7305 "incremental sensor 1 fault" for
        the encoder.  Both are more specific than 0x7300 "sensor", which the drive
        already sends for a saturated ADC channel, so a host can tell the two apart.
        """
        node = self.node
        check = node.isr.chain.plausibility  # type: ignore[attr-defined]
        self.plausibility_revision = check.revision
        d = node.diagnostics
        d.tacho_rejections = check.tacho_rejections
        d.encoder_rejections = check.encoder_rejections
        d.tacho_reseeds = check.tacho_reseeds
        d.encoder_reseeds = check.encoder_reseeds
        d.plausibility_errors = check.errors_raised
        active = self.plausibility_emcy
        emcy = node.services.emcy
        for code, error in (
            (EmcyCode.TACHO_FAULT, check.tacho_error),
            (EmcyCode.INCREMENTAL_SENSOR_1, check.encoder_error),
        ):
            if error and code not in active:
                active.add(code)
                emcy.raise_error(code, manufacturer=self.manufacturer(b""))
            elif not error and code in active:
                active.discard(code)
                emcy.clear(code, self.manufacturer(b""))  # not the stuck tacho's 0x7301
