"""The drive node: the plant emulator behind the drive's synchronous PDOs.

Timing (DESIGN.md, "Timing semantics"): on SYNC k the drive integrates the plant from
t(k-1) to t(k) holding the command active since SYNC k-1 (zero-order hold), samples its
sensors at t(k), sends the sensor TPDO and the ground-truth frames, then activates the
command latched during cycle k-1 (CiA 301 synchronous RPDO, "actuate at next SYNC").
With ``actuation="immediate"`` a command is active as soon as it is received instead.

Delays this gives for a command computed from the sample at t(k):
- ``next-sync`` (default, CANopen transmission type 1): applied from t(k+1), i.e. one
  full period of transport delay plus the zero-order hold;
- ``immediate``: applied from t(k), i.e. the seed's DSP case (``write_dac0`` at the end of
  the interrupt) with the compute and bus latency neglected.

The plant clock is the SYNC count times the sample period, so the drive stays in step with
whatever produces SYNC, including real firmware.  Ground truth goes to a separate bus
(``truth.dbc``), never to the control bus: every SYNC, right after the sensor TPDO,
``TRUTH_TORQUE`` (torque and ripple), ``TRUTH_MOTION`` (angles and velocities) and
``TRUTH_JOINT`` (``tau_ext = tau_l + tau_g`` and ``tau_d`` of seed 003 Eq. 1, ``tau_m``
acting and commanded), all sampled at
t(k) like the sensors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import can

from hdhil.dbc import codec
from hdhil.node import CanNode
from hostsim.plant import Plant

TWO_PI = 2.0 * math.pi

#: CiA 402 controlword bits "switch on", "enable voltage", "quick stop", "enable operation".
_ENABLE_MASK = 0x000F


@dataclass(frozen=True)
class DriveConfig:
    """How the drive node runs the plant against the bus."""

    sample_period_s: float = 1e-3
    actuation: Literal["next-sync", "immediate"] = "next-sync"

    def __post_init__(self) -> None:
        if not 0 < self.sample_period_s <= 1:
            raise ValueError(f"sample_period_s must be in (0, 1] s, got {self.sample_period_s}")
        if self.actuation not in ("next-sync", "immediate"):
            raise ValueError(
                f"actuation must be 'next-sync' or 'immediate', got {self.actuation!r}"
            )


@dataclass
class DriveDiagnostics:
    syncs: int = 0
    commands: int = 0
    malformed_frames: int = 0


class DriveNode(CanNode):
    """Drive emulator node (CANopen node-ID 2): amplifier, harmonic drive, sensors."""

    def __init__(
        self,
        bus: can.BusABC,
        plant: Plant,
        config: DriveConfig | None = None,
        truth_bus: can.BusABC | None = None,
    ) -> None:
        super().__init__(bus)
        self.truth_bus = truth_bus
        self.plant = plant
        self.config = config or DriveConfig()
        self.diagnostics = DriveDiagnostics()
        self._dac = plant.cfg.dac
        self._active_V = 0.0
        self._latched_V = 0.0
        self._enabled = False
        self._sync = codec("control", "SYNC")
        self._sensor = codec("control", "DRIVE_TPDO1")
        self._command = codec("control", "DRIVE_RPDO1")
        self._truth_codecs = (
            codec("truth", "TRUTH_TORQUE"),
            codec("truth", "TRUTH_MOTION"),
            codec("truth", "TRUTH_JOINT"),
        )
        self._sensor_msg = can.Message(
            arbitration_id=self._sensor.frame_id,
            is_extended_id=False,
            dlc=self._sensor.length,
            check=False,
        )
        self._truth_msgs = tuple(
            can.Message(arbitration_id=c.frame_id, is_extended_id=True, dlc=c.length, check=False)
            for c in self._truth_codecs
        )
        self.handle(self._sync.frame_id, self._on_sync)
        self.handle(self._command.frame_id, self._on_command)

    @property
    def amplifier_input_V(self) -> float:
        """The voltage the amplifier follows now (0 V while not enabled)."""
        return self._active_V if self._enabled else 0.0

    def _on_sync(self, msg: can.Message) -> None:
        if self.diagnostics.syncs:
            self.plant.advance(self.amplifier_input_V, self.config.sample_period_s)
        self.diagnostics.syncs += 1
        self._sensor_msg.data = self._sensor.encode(*self.plant.sample())
        self.bus.send(self._sensor_msg)
        if self.truth_bus is not None:
            self._publish_truth()
        if self.config.actuation == "next-sync":
            self._active_V = self._latched_V

    def _on_command(self, msg: can.Message) -> None:
        if msg.is_remote_frame or len(msg.data) != self._command.length:
            self.diagnostics.malformed_frames += 1
            return
        dac_counts, controlword, _cycle = self._command.decode(msg.data)
        self.diagnostics.commands += 1
        self._enabled = (controlword & _ENABLE_MASK) == _ENABLE_MASK
        self._latched_V = self._dac.to_volts(dac_counts)
        if self.config.actuation == "immediate":
            self._active_V = self._latched_V

    def _publish_truth(self) -> None:
        p = self.plant
        torque, motion, joint = self._truth_codecs
        m_torque, m_motion, m_joint = self._truth_msgs
        m_torque.data = torque.encode(p.T_true, p.T_ripple)
        m_motion.data = motion.encode(p.theta_motor, p.theta_output, p.omega_motor, p.omega_output)
        m_joint.data = joint.encode(
            p.external_torque,
            p.motor_disturbance,
            p.motor_torque_output,
            p.motor_torque_command_output,
        )
        send = self.truth_bus.send
        send(m_torque)
        send(m_motion)
        send(m_joint)
