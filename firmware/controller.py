"""The controller node: the ported interrupt handler behind a CAN link.

On the seed's DSP a hardware timer fired ``c_int10`` every sample period (seed 000,
listing A.1, ``t1_schedule_intr(c_int10, sample_period)``).  Over CAN the timer becomes
the SYNC the controller produces, and the ADC read becomes the drive's synchronous TPDO:

1. ``send_sync()``: SYNC k (CiA 301, with counter) starts cycle k.
2. The drive samples its sensors at t(k) and answers with ``DRIVE_TPDO1``.
3. ``_on_sensor_frame``: the interrupt body runs on those counts
   (:class:`firmware.isr.InterruptHandler`), then the DAC command goes out in
   ``DRIVE_RPDO1`` and the logged variables in the telemetry ``CTRL_TPDO1``, both before
   SYNC k+1.

With a torque-control law active (seed 003, :class:`firmware.config.ControlConfig`)
``CTRL_TPDO1.T_filtered`` carries the LQG estimate ``τ̂s`` instead of the ripple
filter's torque, and a second telemetry frame ``CTRL_TPDO2`` (0x281) follows with
``τ̂s'``, ``τ̂lgd``, ``τsD`` and the estimated error ``e``.  Without a law ``CTRL_TPDO2`` is
not sent at all: the PDO is not valid, as CANopen marks it with bit 31 of its COB-ID
(``dbc/controller.eds`` object 0x1802 defaults to 0x80000281), and the bus carries
exactly the seed-000 schedule.  Worst-case control-bus load: 44 % without, 57.5 % with
a law (``CTRL_TPDO2`` adds 135 µs per 1 ms cycle at 1 Mbit/s).

This module only moves frames: every computation is in :mod:`firmware.isr` and its stages.
It uses nothing but a python-can bus, so the same node drives the emulator on ``simbus``
or a real drive on SocketCAN/PCAN/Kvaser.  It never subscribes to ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import can

from firmware.config import FirmwareConfig
from firmware.isr import AdcSample, InterruptHandler
from hdhil.dbc import codec
from hdhil.node import CanNode

#: CiA 402 controlword "enable operation" (switch on, enable voltage, quick stop off,
#: enable operation).  The drive amplifier follows the DAC command only while enabled.
CONTROLWORD_ENABLE_OPERATION = 0x000F


@dataclass
class ControllerDiagnostics:
    """Counters a user reads to see what the link did (never reset during a run)."""

    syncs_sent: int = 0
    sensor_frames: int = 0
    commands_sent: int = 0
    malformed_frames: int = 0
    control_frames_sent: int = 0


class ControllerNode(CanNode):
    """SYNC producer and torque-sensing firmware (CANopen node-ID 1)."""

    def __init__(self, bus: can.BusABC, config: FirmwareConfig, sync_overflow: int = 240) -> None:
        if not 2 <= sync_overflow <= 240:
            raise ValueError(f"SYNC counter overflow must be 2..240 (CiA 301), got {sync_overflow}")
        super().__init__(bus)
        self.config = config
        self.isr = InterruptHandler(config)
        self.diagnostics = ControllerDiagnostics()
        self.sync_overflow = sync_overflow
        self._sync_counter = 0
        self._cycle = 0
        self._sync = codec("control", "SYNC")
        self._sensor = codec("control", "DRIVE_TPDO1")
        self._command = codec("control", "DRIVE_RPDO1")
        self._telemetry = codec("control", "CTRL_TPDO1")
        self._control_telemetry = codec("control", "CTRL_TPDO2")
        self._sync_msg = can.Message(
            arbitration_id=self._sync.frame_id, is_extended_id=False, data=bytearray(1), check=False
        )
        self._command_msg = can.Message(
            arbitration_id=self._command.frame_id,
            is_extended_id=False,
            dlc=self._command.length,
            check=False,
        )
        self._telemetry_msg = can.Message(
            arbitration_id=self._telemetry.frame_id,
            is_extended_id=False,
            dlc=self._telemetry.length,
            check=False,
        )
        self._control_msg = can.Message(
            arbitration_id=self._control_telemetry.frame_id,
            is_extended_id=False,
            dlc=self._control_telemetry.length,
            check=False,
        )
        #: CTRL_TPDO2 is valid (sent) only while a control law runs (COB-ID bit 31 clear).
        self.control_pdo_valid = config.control.active
        self.handle(self._sensor.frame_id, self._on_sensor_frame)

    @property
    def done(self) -> bool:
        """True once ``num_samples`` interrupts have run (listing: ``samplecount < numsamples``)."""
        return self.isr.done

    def send_sync(self) -> None:
        """Start a cycle: SYNC with the CiA 301 counter (1..overflow, then wraps to 1)."""
        self._sync_counter = self._sync_counter % self.sync_overflow + 1
        self._sync_msg.data = self._sync.encode(self._sync_counter)
        self.bus.send(self._sync_msg)
        self.diagnostics.syncs_sent += 1

    def _on_sensor_frame(self, msg: can.Message) -> None:
        if msg.is_remote_frame or len(msg.data) != self._sensor.length:
            self.diagnostics.malformed_frames += 1
            return
        torque, tacho, current, encoder = self._sensor.decode(msg.data)
        self.diagnostics.sensor_frames += 1
        out = self.isr(AdcSample(torque=torque, tacho=tacho, current=current, encoder=encoder))
        self._command_msg.data = self._command.encode(
            out.dac_counts, CONTROLWORD_ENABLE_OPERATION, self._cycle & 0xFF
        )
        self.bus.send(self._command_msg)
        if self.control_pdo_valid:
            self._telemetry_msg.data = self._telemetry.encode(
                out.T_meas, out.tau_s_hat, out.velocity, out.current
            )
            self.bus.send(self._telemetry_msg)
            self._control_msg.data = self._control_telemetry.encode(
                out.dtau_s_hat, out.tau_lgd_hat, out.tau_sD, out.e_hat
            )
            self.bus.send(self._control_msg)
            self.diagnostics.control_frames_sent += 1
        else:
            self._telemetry_msg.data = self._telemetry.encode(
                out.T_meas, out.T_filtered, out.velocity, out.current
            )
            self.bus.send(self._telemetry_msg)
        self.diagnostics.commands_sent += 1
        self._cycle += 1
