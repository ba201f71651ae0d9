"""What the controller node did: the counters and times a run reports.

One record for the whole node, filled by its parts (boot sequencer, cyclic I/O,
supervision, live parameters) and read by the runner's summary, the verdict and the
tests; never reset during a run.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hdhil.firmware.controller.phases import PhaseChange

__all__ = ["ControllerDiagnostics"]


@dataclass
class ControllerDiagnostics:
    """What the node did (never reset during a run).

    The CiA 301 counters of the services (EMCY sent/received) are copied here at every
    ``tick``.  Times are the ``now`` of the latest ``tick``/``boot`` (cycle starts).
    """

    syncs_sent: int = 0
    #: Sensor frames handled in any commanding phase (the walk's too).
    sensor_frames: int = 0
    #: SDO writes of the drive's DCF done at boot (0 without a DCF).
    dcf_writes: int = 0
    #: Sensor frames beyond the first of an operational cycle (ignored).
    extra_sensor_frames: int = 0
    #: DRIVE_RPDO1 frames sent (walk and operation).
    commands_sent: int = 0
    malformed_frames: int = 0
    control_frames_sent: int = 0
    #: PDOs received while the controller may not process them (NMT state, phase).
    pdos_ignored: int = 0
    phase_history: list[PhaseChange] = field(default_factory=list)
    #: When the drive's boot-up (or first sign of life) was seen; None before.
    boot_time_s: float | None = None
    #: When the drive first reported OPERATION ENABLED.
    operational_at_s: float | None = None
    #: SYNCs sent from NMT start of the drive until it reported OPERATION ENABLED.
    startup_cycles: int | None = None
    statusword_frames: int = 0
    #: Walk steps that waited ``STATUSWORD_TIMEOUT_S`` without a statusword.
    statusword_timeouts: int = 0
    #: Statusword reads by SDO (0x6041 of the drive) and their answers / aborts.
    statusword_sdo_reads: int = 0
    statusword_sdo_answers: int = 0
    sdo_aborts: int = 0
    invalid_statuswords: int = 0
    fault_resets: int = 0
    #: A stop that the drive did not confirm within ``WALK_TIMEOUT_S``.
    stop_timeouts: int = 0
    heartbeat_losses: int = 0
    heartbeat_lost_at_s: float | None = None
    #: Operational SYNC cycles without a sensor frame, in total and the longest run.
    sensor_frames_missed: int = 0
    sensor_hold_longest: int = 0
    emcy_sent: int = 0
    emcy_received: int = 0
    #: Accepted SDO writes of firmware parameters, and what they rebuilt.
    parameter_writes: int = 0
    parameter_updates_applied: int = 0
    filter_restarts: int = 0
    control_rebuilds: int = 0
    #: Plausibility stage (:class:`firmware.stages.SensorPlausibility`): velocity samples
    #: and encoder increments replaced by the prediction, implausible values accepted as
    #: the new level after ``max_rejections`` in a row, errors announced by EMCY.
    tacho_rejections: int = 0
    encoder_rejections: int = 0
    tacho_reseeds: int = 0
    encoder_reseeds: int = 0
    plausibility_errors: int = 0
    #: Stuck sensor channels (torque or tacho reading unchanged while the motor turned,
    #: :class:`firmware.stages.StuckChannels`), each announced by an EMCY: torque 0x7300,
    #: tacho 0x7301 (manufacturer byte 0: the channel, 1 torque, 2 tacho).
    stuck_sensor_events: int = 0
    #: Of those, the tacho's.
    stuck_tacho_events: int = 0
    safe_reason: str | None = None
