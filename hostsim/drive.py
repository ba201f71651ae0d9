"""The drive node: the plant emulator behind a CiA 301 / CiA 402 CANopen device.

Timing (docs/design.md, "Timing semantics"): on SYNC k the drive integrates the plant from
t(k-1) to t(k) holding the amplifier input set at SYNC k-1 (zero-order hold), samples its
sensors at t(k), sends the sensor TPDO and the ground-truth frames, then activates the
command latched during cycle k-1 (CiA 301 synchronous RPDO, "actuate at next SYNC").
With ``actuation="immediate"`` a command is active as soon as it is received instead.

Delays this gives for a command computed from the sample at t(k):
- ``next-sync`` (default, CANopen transmission type 1): applied from t(k+1), i.e. one
  full period of transport delay plus the zero-order hold;
- ``immediate``: applied from t(k), i.e. the seed's DSP case (``write_dac0`` at the end of
  the interrupt) with the compute and bus latency neglected.

Ground truth goes to a separate bus (``truth.dbc``), never to the control bus: every SYNC
in OPERATIONAL, right after the sensor TPDO, ``TRUTH_TORQUE`` (torque and ripple),
``TRUTH_MOTION`` (angles and velocities) and ``TRUTH_JOINT`` (``tau_ext = tau_l + tau_g``
and ``tau_d`` of [Vertechy] Eq. 1, ``tau_m`` acting and commanded), all sampled at t(k)
like the sensors.

The CANopen device (node-ID 2, ``dbc/drive.eds``)
-------------------------------------------------
The CiA 301 services (NMT slave, heartbeat producer and consumer, EMCY producer, checked
SDO server) are :class:`hdhil.canopen.services.CanopenServices`; the CiA 402 power drive
system is :class:`hdhil.canopen.cia402.DriveStateMachine`.  This module wires them to the
frames and the plant, and holds no physics itself.  Every received frame goes through
``services.handle`` first, timed with the ``now`` of the latest :meth:`DriveNode.tick`.

**Power-on and NMT** (CiA 301 §7.3.2).  :meth:`DriveNode.boot` sends the boot-up message
(0x702, data 00) and enters PRE-OPERATIONAL; the CiA 402 self-initialisation completes at
once (transition 1: NOT READY TO SWITCH ON -> SWITCH ON DISABLED).  What each NMT state
allows (CiA 301 table "NMT states and communication objects"):

=================  ===================================================================
NMT state          drive behaviour
=================  ===================================================================
INITIALISING       before ``boot`` only: nothing is sent, frames are not processed
PRE-OPERATIONAL    SDO, EMCY, heartbeat; no PDOs: no sensor TPDO, no statusword TPDO,
                   no truth frames, received DRIVE_RPDO1 frames are ignored
OPERATIONAL        everything; entering it sends the statusword TPDO once
STOPPED            heartbeat and NMT only (no SDO answers, no EMCY frames)
=================  ===================================================================

The plant is physics: it advances on **every** SYNC in every NMT state (the network being
pre-operational does not stop the motor), with the amplifier input that the CiA 402
state allows (0 V unless OPERATION ENABLED), and the sensors are sampled every SYNC too
(the noise sequence of a seed does not depend on the NMT history).  Only publishing is
gated by NMT.  The plant clock is the SYNC counter: a SYNC that follows a counter jump
(missed SYNCs, CiA 301 SYNC counter 1..overflow) advances the plant by the missed periods
as well, so it stays in step with the SYNC producer; a counter that restarts at 1 (the
producer restarted) is not a jump.  The very first SYNC only marks t(0).

Leaving OPERATIONAL (NMT stop, enter pre-operational, a reset) is a lost connection for
CiA 402: commands only arrive by PDO, and PDOs stop outside OPERATIONAL.  The drive reacts
as its abort connection option code 0x6007 says (CiA 402-2): 2 (default) "disable
voltage" (the last command is dropped, SWITCH ON DISABLED), 3 "quick stop", 1 "fault
signal" (fault and EMCY 0x8100 "communication - generic", cleared when OPERATIONAL is
entered again), 0 "no action" (the last command stays until the command hold below
faults the drive).  An NMT reset node brings the
application back to power-on: a new CiA 402 machine (SWITCH ON DISABLED), no command, the
emulator parameters (0x2300) back to the values the plant was built with, errors cleared.
An NMT reset communication restores 0x1000-0x1FFF only (CiA 301 §7.3.2.2.2).

**CiA 402** (CiA 402-2, "PDS finite state automaton").  The controlword of DRIVE_RPDO1
drives ``DriveStateMachine.apply_controlword`` with the same timing as the DAC command: at
the next SYNC with synchronous actuation (the whole synchronous RPDO is actuated at SYNC,
CiA 301 §7.2.2.2), on receipt with immediate actuation.  The usual walk is shutdown 0x06
-> switch on 0x07 -> enable operation 0x0F; 0x80 (rising edge) resets a fault.  The
amplifier follows the DAC command only in OPERATION ENABLED in mode CST (0x6060 = 10;
``DriveStateMachine.torque_output``), ramps it down during a quick stop or fault reaction
with a ramp time (``DriveConfig.quick_stop_time_s``, 0 = torque off at once), and gets
0 V otherwise.  Quick stop behaviour follows 0x605A, the fault reaction 0x605E (0 =
disable drive function; 1-4 = ramp over ``quick_stop_time_s``).

When the amplifier input changes: at each SYNC, after the plant step and the sample,
the drive sets the input for the step that starts there from the CiA 402 state at that
moment.  A state change between two SYNCs (a tick that detects a heartbeat loss, an NMT
command, an SDO write) therefore takes effect at the next SYNC, at most one period later;
in lockstep, where the tick at t(k) runs just before SYNC k, a fault detected by that tick
removes the torque from exactly t(k).  With immediate actuation a received command sets
the input of the running step at once (controlword and DAC alike).

**Statusword** (0x6041) goes out in ``DRIVE_TPDO2`` (COB-ID 0x282, TPDO2 0x1801/0x1A01),
event-driven (transmission type 255): when it differs from the last one sent, and once on
entering OPERATIONAL, at most once per inhibit time (0x1801 sub 3, 10 x 100 us = 1 ms): a
change inside the inhibit time is sent at the first tick or frame after it.  Bits 7
(warning: a sensor ADC channel saturated) and 11 (internal limit active: the amplifier at
its current limit) are set by this node.

**Heartbeat** (CiA 301 §7.2.8.3.2): producer 0x1017 = ``heartbeat_ms`` (100 ms); the
consumer 0x1016 monitors the controller (node-ID 1) with ``controller_heartbeat_timeout_ms``
(250 ms), from its first heartbeat on.  On a loss: EMCY 0x8130 (manufacturer byte 0 = the
lost node-ID), and a CiA 402 fault (0x603F = 0x8130; FAULT REACTION ACTIVE -> FAULT, torque
off) that cannot be reset while the heartbeat is missing.  Recovery: the heartbeat
resumes (EMCY 0x0000), then the controller sends a fault reset (0x80 edge) and walks the
drive up again.

**Command hold**: while OPERATION ENABLED, a SYNC cycle in which no DRIVE_RPDO1 arrived
keeps the previous command (zero-order hold).  At the SYNC that ends the
``command_hold_cycles``-th consecutive cycle without one, the drive faults with EMCY 0x8250
"RPDO timeout" (manufacturer byte 0 = the number of cycles) and 0x603F = 0x8250, in place
of activating that cycle's command: with synchronous actuation the last command stays
active for ``command_hold_cycles`` periods in all.  We chose a fault over a quick stop
because a lost command stream is a communication error the controller must acknowledge
(fault reset), as for a lost heartbeat.  The next DRIVE_RPDO1 clears the EMCY (0x0000).
SYNC counter jumps are counted as missed SYNCs, commands arriving more than one period
after their SYNC as late commands (:class:`hdhil.canopen.services.SyncMonitor`).

**Other EMCY** (once on the rising edge, EMCY 0x0000 when the condition goes away):
0x7300 "sensor error" when an ADC channel sits at a code limit (manufacturer byte 0 = the
channel: 1 torque, 2 tacho, 3 current, the sub-indices of 0x2100); 0x2310 "continuous
over current" when the amplifier's current command sits at its current limit.

**SDO**: the checked server of ``CanopenServices`` (types, lengths, access, LowLimit /
HighLimit of the EDS, with CiA 301 abort codes; a refused write changes nothing).  Live
values are read from the node: 0x6041 statusword, 0x6040 controlword (as last applied),
0x6061 mode display, 0x603F error code, 0x2100 ADC counts and 0x2101 encoder count of the
latest sample.  Writable application objects:

- 0x2300 "Emulator" (REAL32): 1 ``ripple_amp2_Nm``, 2 ``ripple_amp4_Nm`` (0..10 Nm),
  3 ``misalignment_pp_Nm`` (0..20 Nm), 4 ``torque_noise_Nm`` (0..5 Nm), 5
  ``tacho_noise_radps`` (0..10 rad/s), 6 ``load_torque_Nm`` (-100..100 Nm, the external
  torque the plant holds, :meth:`hostsim.plant.Plant.set_load_torque`).  Their power-on
  values are the plant's configuration.  A write is applied at the next SYNC, before the
  plant step: the plant's frozen configuration is rebuilt with ``dataclasses.replace``
  and swapped in, so the step ending at that SYNC and its sample use the new values.
- 0x2310 "Fault injection" (:mod:`hdhil.hostsim.sensor_faults`), applied at the next
  SYNC like 0x2300: 1 ``tacho_spike_rate`` (REAL32, 0..1 per sample), 2
  ``tacho_spike_V`` (0..20 V), 3 ``encoder_glitch_rate`` (0..1 per sample), 4
  ``encoder_glitch_counts`` (UNSIGNED16); channel masks (UNSIGNED8, bit 0 torque, 1
  tacho, 2 current, 3 encoder) 5 ``stuck_mask`` (the channel holds its count from the
  next sample on), 6 ``saturated_max_mask`` and 7 ``saturated_min_mask`` (an ADC channel
  at its top or bottom code; the encoder has none, and a channel in both masks is
  refused with abort 0x06090030); 8 ``silence_ms`` (UNSIGNED16): from the next SYNC the
  drive transmits nothing for that long (PDOs, heartbeat, EMCY, SDO answers; a write
  during the silence is applied but not answered; 0 ends it), so the controller's sensor
  hold and heartbeat consumer react as to a drive that fell off the bus.  Power-on
  values: the plant's configured sensor faults (``[faults.sensors]``), no mask, no
  silence.  The faults are drawn from the run's fault seed and every one is recorded in
  its fault log (a silenced frame as ``silence`` on ``control``).  Nothing is installed
  while nothing is switched on: the plant keeps its fault-free path and the bus its own
  ``send``.
- 0x6040 controlword: an SDO write is applied at once, like an immediate RPDO.
- 0x6007 abort connection option code (0..3), 0x605A quick stop option code (0..8),
  0x605E fault reaction option code (0..4), 0x6060 modes of operation (0 or 10, else
  abort 0x06090030).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import can

from hdhil.can.faults import TransmitSilence
from hdhil.can.node import CanNode, pdo_cob_id
from hdhil.canopen.cia402 import (
    CONTROLWORD,
    CONTROLWORD_OBJECT,
    MAX_TORQUE_OBJECT,
    POSITION_ACTUAL_OBJECT,
    RATED_TORQUE_OBJECT,
    STATUSWORD_OBJECT,
    SUPPORTED_MODES,
    TARGET_TORQUE_OBJECT,
    TORQUE_ACTUAL_OBJECT,
    VELOCITY_ACTUAL_OBJECT,
    Command,
    DriveStateMachine,
    State,
)
from hdhil.canopen.od import index_of, variable
from hdhil.canopen.pdo import (
    MAX_PDOS,
    PdoLayout,
    Tpdo,
    decode_to_od,
    encode_from_od,
    read_layout,
)
from hdhil.canopen.services import (
    ABORT_DEVICE_STATE,
    ABORT_INVALID_VALUE,
    TIME_EPSILON,
    CanopenServices,
    EmcyCode,
    NmtState,
    ResetKind,
    SyncMonitor,
)
from hdhil.core.faultbase import FaultLog
from hdhil.dbc import codec, eds_path
from hdhil.hostsim.plant import Plant, PlantConfig
from hdhil.hostsim.plant_model import PlantModel, Truth
from hdhil.hostsim.sensor_faults import (
    SensorFaultInjector,
    SensorFaults,
    SensorFaultSource,
    SensorHook,
    SensorWindow,
)

TWO_PI = 2.0 * math.pi

#: Object indices the node serves (CiA 301 / CiA 402 / manufacturer area).
OD_ABORT_CONNECTION = 0x6007
OD_ERROR_CODE = 0x603F
OD_QUICK_STOP_OPTION = 0x605A
OD_FAULT_REACTION_OPTION = 0x605E
OD_MODES_OF_OPERATION = 0x6060
OD_MODES_DISPLAY = 0x6061
OD_ADC_COUNTS = 0x2100
OD_ENCODER = 0x2101
OD_EMULATOR = 0x2300
OD_FAULTS = 0x2310
OD_DAC_COMMAND = 0x2200
OD_SYNC_PERIOD = 0x1006
OD_SYNC_WINDOW = 0x1007
#: EMCY 0x8100 manufacturer byte 0 for a SYNC timeout (CANopenNode's "SYNC time out").
_SYNC_TIMEOUT_INFO = b"\x01"

#: 0x2300 sub-index -> (plant sub-configuration, field); "load" is the held load torque.
EMULATOR_KNOBS: dict[int, tuple[str, str]] = {
    1: ("ripple", "amp2_Nm"),
    2: ("ripple", "amp4_Nm"),
    3: ("ripple", "misalignment_pp_Nm"),
    4: ("sensors", "torque_noise_Nm"),
    5: ("sensors", "tacho_noise_radps"),
    6: ("load", "torque_Nm"),
}

#: 0x2310 sub-index -> the :class:`hdhil.hostsim.sensor_faults.SensorFaults` field it sets.
FAULT_FIELDS: dict[int, str] = {
    1: "tacho_spike_rate",
    2: "tacho_spike_V",
    3: "encoder_glitch_rate",
    4: "encoder_glitch_counts",
}
#: 0x2310 channel masks: sub-index -> (fault, saturation level).
FAULT_MASKS: dict[int, tuple[str, str]] = {
    5: ("stuck", "max"),
    6: ("saturated", "max"),
    7: ("saturated", "min"),
}
#: 0x2310 sub-index of the drive's silence (ms).
FAULT_SILENCE_MS = 8
#: Bit n of a 0x2310 channel mask is sensor channel n (DRIVE_TPDO1 order).
MASK_CHANNELS = ("torque", "tacho", "current", "encoder")

#: ADC channels in DRIVE_TPDO1 order; the number is the 0x2100 sub-index and the EMCY
#: 0x7300 manufacturer byte 0.
ADC_CHANNELS = (1, 2, 3)

# What the per-cycle code tests for, as module globals: an attribute of an Enum class
# (``NmtState.OPERATIONAL``) is looked up through ``EnumType.__getattr__``'s slow path in
# Python 3.11, several times slower than a global.
_INITIALISING = NmtState.INITIALISING
_OPERATIONAL = NmtState.OPERATIONAL
_OPERATION_ENABLED = State.OPERATION_ENABLED
_RPDO_TIMEOUT = EmcyCode.RPDO_TIMEOUT


def _check_int(obj: object, name: str, lo: int, hi: int) -> None:
    value = getattr(obj, name)
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ValueError(
            f"{type(obj).__name__}.{name} must be an integer {lo}..{hi}, got {value!r}"
        )


@dataclass(frozen=True)
class DriveConfig:
    """How the drive node runs the plant against the bus, and its CANopen settings.

    ``heartbeat_ms`` is the producer time (0x1017, 0 = off); the drive consumes the
    heartbeat of ``controller_node_id`` with ``controller_heartbeat_timeout_ms`` (0x1016,
    0 = not monitored).  ``command_hold_cycles`` SYNC cycles without a command in
    OPERATION ENABLED fault the drive (0 = never).  ``sync_overflow`` is the SYNC
    producer's counter overflow (its 0x1019; 0 = SYNC without counter).
    ``quick_stop_time_s`` is the torque ramp-down time of a quick stop (0x605A 1-8) and
    of a fault reaction (0x605E 1-4); 0 turns the torque off at once.
    """

    sample_period_s: float = 1e-3
    actuation: Literal["next-sync", "immediate"] = "next-sync"
    node_id: int = 2
    heartbeat_ms: int = 100
    controller_node_id: int = 1
    controller_heartbeat_timeout_ms: int = 250
    command_hold_cycles: int = 10
    sync_overflow: int = 240
    quick_stop_time_s: float = 0.0

    def __post_init__(self) -> None:
        if not 0 < self.sample_period_s <= 1:
            raise ValueError(f"sample_period_s must be in (0, 1] s, got {self.sample_period_s}")
        if self.actuation not in ("next-sync", "immediate"):
            raise ValueError(
                f"actuation must be 'next-sync' or 'immediate', got {self.actuation!r}"
            )
        _check_int(self, "node_id", 1, 127)
        _check_int(self, "controller_node_id", 1, 127)
        if self.controller_node_id == self.node_id:
            raise ValueError(f"DriveConfig: controller and drive share node-ID {self.node_id}")
        _check_int(self, "heartbeat_ms", 0, 0xFFFF)
        _check_int(self, "controller_heartbeat_timeout_ms", 0, 0xFFFF)
        _check_int(self, "command_hold_cycles", 0, 255)
        _check_int(self, "sync_overflow", 0, 240)
        if self.sync_overflow == 1:
            raise ValueError("DriveConfig.sync_overflow must be 0 or 2..240 (CiA 301 0x1019)")
        q = self.quick_stop_time_s
        if isinstance(q, bool) or not isinstance(q, (int, float)) or not 0 <= q < math.inf:
            raise ValueError(f"DriveConfig.quick_stop_time_s must be >= 0 s, got {q!r}")


@dataclass(frozen=True)
class EmcyRecord:
    """An error this drive signalled (``sent`` is False when NMT did not allow the frame)."""

    time: float
    code: int
    manufacturer: bytes
    sent: bool


@dataclass
class DriveDiagnostics:
    """What the drive node did (cumulative; NMT resets do not clear it)."""

    syncs: int = 0
    #: DRIVE_RPDO1 frames processed (in OPERATIONAL).
    commands: int = 0
    malformed_frames: int = 0
    #: DRIVE_RPDO1 frames received outside OPERATIONAL (CiA 301: not processed).
    pdos_ignored: int = 0
    sensor_frames: int = 0
    statusword_frames: int = 0
    #: SYNCs missing before a received one (counter jumps).
    missed_syncs: int = 0
    #: SYNCs ignored because their counter repeated the previous one, or lay behind it.
    duplicate_syncs: int = 0
    stale_syncs: int = 0
    #: SYNCs whose length or counter did not fit ``sync_overflow``.
    sync_errors: int = 0
    #: Commands that arrived more than one period after their SYNC.
    late_commands: int = 0
    #: Command-hold faults (EMCY 0x8250).
    command_timeouts: int = 0
    #: RPDO event-timer deadlines missed (EMCY 0x8250, manufacturer byte 0 = RPDO number).
    rpdo_timeouts: int = 0
    #: SYNC timeouts (1.5 x 0x1006 without a SYNC; EMCY 0x8100).
    sync_timeouts: int = 0
    heartbeat_losses: int = 0
    adc_saturations: int = 0
    overcurrents: int = 0
    nmt_resets: int = 0
    #: EMCY error events raised by this drive (not counting the 0x0000 "cleared" frames).
    emcy_sent: int = 0
    emcy_log: deque[EmcyRecord] = field(default_factory=lambda: deque(maxlen=256))


def _retune_plant(plant: Plant, cfg: PlantConfig) -> None:
    """Swap in ``cfg``, which may differ from ``plant.cfg`` in ripple and sensor noise only.

    ``Plant`` reads ``cfg.ripple`` at every sensor update but caches the noise standard
    deviations (in volts) when it is built; those two are refreshed here with the
    conversions of ``Plant.__init__``.  (A plant setter would be the cleaner home.)
    """
    plant.cfg = cfg
    s = cfg.sensors
    plant._sig_torque_V = s.torque_noise_Nm / cfg.bridge.volt2Nm
    plant._sig_tacho_V = s.tacho_noise_radps / s.volt2radps


class DriveNode(CanNode):
    """Drive emulator node (CANopen node-ID 2): amplifier, harmonic drive, sensors."""

    def __init__(
        self,
        bus: can.BusABC,
        plant: PlantModel,
        config: DriveConfig | None = None,
        truth_bus: can.BusABC | None = None,
        faults: SensorFaultSource | None = None,
    ) -> None:
        """``faults`` is the run's fault injector, the one whose ``sensors()`` hook the
        plant has (if any): its seed and log serve the faults switched on through object
        0x2310.  Without one the drive keeps its own (seed 0; the plant's hook's log).

        ``plant`` is any :class:`hostsim.plant_model.PlantModel`; the emulator's extras
        (0x2300 and the sensor faults of 0x2310) need the emulator's own
        :class:`hostsim.plant.Plant` and are refused (SDO abort) for another model."""
        super().__init__(bus)
        self.truth_bus = truth_bus
        self.plant = plant
        self.config = cfg = config or DriveConfig()
        self.diagnostics = DriveDiagnostics()
        self._Ts = cfg.sample_period_s
        self._next_sync = cfg.actuation == "next-sync"
        #: The emulator's own plant: 0x2300 and the sensor faults of 0x2310 act on it.
        self._emulator = isinstance(plant, Plant)
        if isinstance(plant, Plant):  # its step map now, not in the middle of a cycle
            plant.prepare(cfg.sample_period_s)
        self._dac = plant.dac
        self._adc = plant.adc
        self._max_torque = plant.max_motor_torque_Nm
        self._current_limit_Nm = self._max_torque * (1 - 1e-12)  # at the limit from here on
        self._now = 0.0

        # Command path: latched by DRIVE_RPDO1, active from the activation point.
        self._active_V = 0.0
        self._latched_V = 0.0
        self._pending_cw: int | None = None
        self._dac_counts = 0  # the latest DAC command (kept when a remap leaves it out)
        self._step_V = 0.0  # amplifier input over the plant step in progress
        self._command_in_cycle = False
        self._silent_cycles = 0
        self._plant_started = False
        self._sample: tuple[int, int, int, int] = (0, 0, 0, 0)
        self._saturated: set[int] = set()
        self._at_current_limit = False

        # Frames.
        # Codecs are used by signal name: each layout is checked against the names this
        # node packs and unpacks (a DBC with reordered signals fails here, loudly).
        self._sync = codec("control", "SYNC").expect("sync_counter")
        self._sensor = codec("control", "DRIVE_TPDO1").expect(
            "ADC_torque", "ADC_tacho", "ADC_current", "ENC_count"
        )
        self._command = codec("control", "DRIVE_RPDO1").expect("DAC_cmd", "controlword", "cycle")
        self._status = codec("control", "DRIVE_TPDO2").expect("statusword")
        self._truth_codecs = (
            codec("truth", "TRUTH_TORQUE").expect("T_true", "T_ripple"),
            codec("truth", "TRUTH_MOTION").expect(
                "theta_motor", "theta_output", "omega_motor", "omega_output"
            ),
            codec("truth", "TRUTH_JOINT").expect("tau_ext", "tau_d", "tau_m", "tau_m_cmd"),
        )
        self._sensor_msg = self._message(self._sensor.frame_id, self._sensor.length)
        self._status_msg = self._message(self._status.frame_id, self._status.length)
        self._truth_msgs = tuple(
            can.Message(arbitration_id=c.frame_id, is_extended_id=True, dlc=c.length, check=False)
            for c in self._truth_codecs
        )

        # CiA 301 services on the drive's object dictionary.
        consumers = (
            {cfg.controller_node_id: cfg.controller_heartbeat_timeout_ms}
            if cfg.controller_heartbeat_timeout_ms
            else {}
        )
        self.services = CanopenServices(
            bus,
            cfg.node_id,
            eds_path("drive"),
            heartbeat_producer_ms=cfg.heartbeat_ms,
            heartbeat_consumers=consumers,
        )
        # Fault injection through object 0x2310 (reproducible by the injector's seed, every
        # fault in its log): sensor faults switched over the plant's configured ones, and
        # the drive's own silence on the control bus.
        hook = plant.faults if isinstance(plant, Plant) else None
        if faults is None:
            faults = SensorFaultInjector(
                hook.cfg if hook is not None else SensorFaults(),
                0,
                hook.log if hook is not None else FaultLog(keep=False),
            )
        self.faults = faults
        self._sensor_hook: SensorHook | None = hook
        # The configured sensor faults: the plant's hook's, else the source's (the hook
        # it would install; the same object later, when 0x2310 switches a fault on).
        if hook is None:
            hook = faults.sensors(always=True)
            assert hook is not None
        self._base_sensor_faults = hook.cfg
        self._mask_windows: dict[tuple[int, str], SensorWindow] = {}
        self._silence = TransmitSilence(bus, faults.log, "control", lambda: self._now)

        # 0x2300 and 0x2310: (index, sub) -> power-on value; writes wait for the next SYNC.
        self._power_on_knobs = self._knob_values_of(plant) | self._fault_power_on_values()
        self._fault_values = {
            sub: value for (index, sub), value in self._power_on_knobs.items() if index == OD_FAULTS
        }
        self._set_knob_power_on_values()
        self._pending_knobs: dict[tuple[int, int], float] = {}
        # CiA 402 objects found by name in the drive's EDS.
        self._od_controlword = index_of(self.services.od, CONTROLWORD_OBJECT)
        self._od_statusword = index_of(self.services.od, STATUSWORD_OBJECT)
        self._init_cst()
        self._register_od_callbacks()
        services = self.services
        services.on_state_change(self._on_nmt_state)
        services.on_reset(self._on_nmt_reset)
        services.on_heartbeat_lost(self._on_heartbeat_lost)
        services.on_heartbeat_resumed(self._on_heartbeat_resumed)
        # PDO defaults come from the object dictionary (RPDO1 0x1400, TPDO1/2 0x1800/1,
        # checked against the DBC layouts: the DBC describes the default mapping); the live
        # PDOs are read from the OD's present values (_load_pdos).
        od = services.od
        self.handle(self._sync.frame_id, self._on_sync)
        pdo_cob_id(od, 0x1400, self._command)
        pdo_cob_id(od, 0x1800, self._sensor)
        pdo_cob_id(od, 0x1801, self._status)
        services.on_boot(self._on_remote_boot)
        # RPDO1's transmission type is the actuation setting: synchronous (type 1, taken
        # over at the next SYNC) or event-driven (255, taken over on receipt).
        services.set_power_on_value(0x1400, 2, 1 if self._next_sync else 255)
        defaults = lambda index, sub: variable(od, index, sub).default  # noqa: E731
        self._default_layouts = {
            (kind, n): read_layout(od, defaults, kind, n)
            for kind in ("rpdo", "tpdo")
            for n in (1, 2)
        }
        self._tpdos: list[Tpdo] = []
        self._rpdo_handlers: dict[int, PdoLayout] = {}
        self._rpdo_deadlines: dict[int, float] = {}
        self._fast_sensor = True
        for index in [*range(0x1400, 0x1404), *range(0x1600, 0x1604),
                      *range(0x1800, 0x1804), *range(0x1A00, 0x1A04)]:  # fmt: skip
            obj = od.get(index)
            for sub in getattr(obj, "subindices", {}):
                if variable(od, index, sub) is not None and variable(od, index, sub).writable:
                    services.on_write(index, sub, self._pdo_changed)
        for index in (OD_SYNC_PERIOD, OD_SYNC_WINDOW):
            if variable(od, index, 0) is not None:
                services.on_write(index, 0, self._pdo_changed)

        self._machine = self._new_state_machine()
        self._sync_monitor = self._new_sync_monitor()
        self._last_sync_at: float | None = None
        self._sync_lost = False
        self._load_pdos()

    @staticmethod
    def _message(frame_id: int, length: int) -> can.Message:
        return can.Message(arbitration_id=frame_id, is_extended_id=False, dlc=length, check=False)

    # ------------------------------------------------------------------ public API

    def boot(self, now: float) -> None:
        """Power-on: boot-up message, NMT PRE-OPERATIONAL (CiA 301 §7.3.2.2), and the CiA 402
        self-initialisation (transition 1: NOT READY TO SWITCH ON -> SWITCH ON DISABLED)."""
        self._now = now
        self.services.boot(now)
        self._machine.complete_initialisation()
        self._step_V = self._machine.torque_output(self._active_V)

    def tick(self, now: float) -> None:
        """Advance the node's clock: heartbeat producer and consumer (CiA 301 §7.2.8.3.2),
        event-driven TPDOs held back by their inhibit time or due by their event timer,
        the RPDO event-timer deadlines and the SYNC timeout.  Call every cycle before
        polling."""
        self._now = now
        self.services.tick(now)
        if self.services.state is _OPERATIONAL:
            self._check_deadlines(now)
        self._flush_statusword()

    def on_message(self, msg: can.Message) -> None:
        """CANopen service frames to the services, SYNC and PDOs to this node."""
        if self.services.handle(msg):
            self._flush_statusword()
            return
        super().on_message(msg)

    @property
    def nmt_state(self) -> NmtState:
        return self.services.state

    @property
    def drive_state(self) -> State:
        """The CiA 402 PDS state."""
        return self._machine.state

    @property
    def state_machine(self) -> DriveStateMachine:
        return self._machine

    @property
    def statusword(self) -> int:
        """Object 0x6041 now (what the next DRIVE_TPDO2 carries)."""
        return self._machine.statusword

    @property
    def torque_enabled(self) -> bool:
        """True only in OPERATION ENABLED (the amplifier follows the command)."""
        return self._machine.torque_enabled

    @property
    def amplifier_input_V(self) -> float:
        """The amplifier input over the plant step in progress (0 V unless enabled)."""
        return self._step_V

    # ------------------------------------------------------------------ SYNC

    def _on_sync(self, msg: can.Message) -> None:
        d = self.diagnostics
        if msg.is_remote_frame:  # a remote request on 0x080 is not a SYNC (CiA 301)
            d.malformed_frames += 1
            return
        d.syncs += 1
        monitor = self._sync_monitor
        errors = monitor.length_errors
        missed = monitor.accept(msg, self._now)
        d.sync_errors += monitor.length_errors - errors
        if missed is None:
            # A duplicated or reordered SYNC (its counter repeats or lies behind the last
            # one): no time passed for it, so the plant does not move and nothing is sent.
            d.duplicate_syncs = monitor.duplicates
            d.stale_syncs = monitor.stale
            return
        d.missed_syncs += missed
        self._last_sync_at = self._now
        if self._sync_lost:
            self._sync_lost = False
            self.services.emcy_clear(EmcyCode.COMMUNICATION, _SYNC_TIMEOUT_INFO)

        if self._pending_knobs:
            self._apply_knobs()
        plant = self.plant
        if self._plant_started:
            dt = (1 + missed) * self._Ts
            plant.advance(self._step_V, dt)
            self._machine.step(dt)
        else:
            self._plant_started = True
        sample = self._sample = plant.sample()
        self._update_position(sample[3], (1 + missed) * self._Ts)
        if self.services.state is not _INITIALISING:
            truth = plant.truth()
            self._check_sensors(sample, truth)
        if self.services.state is _OPERATIONAL:
            if self._fast_sensor:  # TPDO1 as the DBC describes it: every SYNC
                self._sensor_msg.data = self._sensor.encode(*sample)
                self.bus.send(self._sensor_msg)
                d.sensor_frames += 1
            else:
                for tpdo in self._tpdos:
                    if tpdo.layout.synchronous:
                        tpdo.on_sync(self._now)
            if self.truth_bus is not None:
                self._publish_truth(truth)
        self._check_command_hold()
        if self._next_sync:
            self._active_V = self._latched_V
            if self._pending_cw is not None:
                self._machine.apply_controlword(self._pending_cw)
                self._pending_cw = None
        self._step_V = self._machine.torque_output(self._active_V)
        self._flush_statusword()

    def _check_command_hold(self) -> None:
        """Count SYNC cycles without a command while OPERATION ENABLED; fault at the limit."""
        had_command = self._command_in_cycle
        self._command_in_cycle = False
        limit = self.config.command_hold_cycles
        if had_command or not limit or self._machine.state is not _OPERATION_ENABLED:
            self._silent_cycles = 0
            return
        self._silent_cycles += 1
        if self._silent_cycles >= limit:
            self.diagnostics.command_timeouts += 1
            self._emcy(EmcyCode.RPDO_TIMEOUT, bytes((min(self._silent_cycles, 255),)))
            self._machine.fault(EmcyCode.RPDO_TIMEOUT)
            self._silent_cycles = 0

    def _check_sensors(self, sample: tuple[int, int, int, int], truth: Truth) -> None:
        """EMCY 0x7300 per saturated ADC channel, 0x2310 at the current limit (edges)."""
        saturated = self._adc.saturated
        active = self._saturated
        for channel, counts in zip(ADC_CHANNELS, sample, strict=False):
            if saturated(counts):
                if channel not in active:
                    active.add(channel)
                    self.diagnostics.adc_saturations += 1
                    self._emcy(EmcyCode.SENSOR, bytes((channel,)))
            elif channel in active:
                active.discard(channel)
                self.services.emcy_clear(EmcyCode.SENSOR, bytes((channel,)))
        self._machine.warning = bool(active)
        at_limit = abs(truth.tau_m_cmd_Nm) >= self._current_limit_Nm
        if at_limit != self._at_current_limit:
            self._at_current_limit = at_limit
            self._machine.internal_limit_active = at_limit
            if at_limit:
                self.diagnostics.overcurrents += 1
                self._emcy(EmcyCode.CONTINUOUS_OVER_CURRENT)
            else:
                self.services.emcy_clear(EmcyCode.CONTINUOUS_OVER_CURRENT)

    # ------------------------------------------------------------------ command

    def _on_rpdo(self, msg: can.Message) -> None:
        """An RPDO in a mapping other than the DBC's: each mapped object is decoded with
        its OD data type; the DAC object and the controlword act as in the default
        mapping, other objects are written into the OD (their write callbacks apply them)."""
        d = self.diagnostics
        layout = self._rpdo_handlers.get(msg.arbitration_id)
        if layout is None or self.services.state is not _OPERATIONAL:
            d.pdos_ignored += 1
            return
        if msg.is_remote_frame or len(msg.data) < layout.length:
            d.malformed_frames += 1
            return
        self._rpdo_received(layout)
        dac_counts: int | None = None
        controlword: int | None = None
        node = self.services.node
        for index, sub, data in decode_to_od(layout, msg.data):
            if index == OD_DAC_COMMAND:
                dac_counts = int.from_bytes(data, "little", signed=True)
            elif index == self._od_target_torque:
                dac_counts = self._torque_to_counts(int.from_bytes(data, "little", signed=True))
            elif index == self._od_controlword:
                controlword = int.from_bytes(data, "little")
            else:
                try:
                    node.set_data(index, sub, data)
                except Exception:
                    d.malformed_frames += 1
        if dac_counts is None:
            dac_counts = self._dac_counts
        if controlword is None:
            controlword = self._machine.controlword
        self._command_values(dac_counts, controlword)

    def _rpdo_received(self, layout: PdoLayout) -> None:
        if layout.event_s > 0:
            self._rpdo_deadlines[layout.number] = self._now + layout.event_s
        if self.services.error_active(_RPDO_TIMEOUT):
            self.services.emcy_clear(_RPDO_TIMEOUT)

    def _on_command(self, msg: can.Message) -> None:
        d = self.diagnostics
        if self.services.state is not _OPERATIONAL:
            d.pdos_ignored += 1
            return
        if msg.is_remote_frame or len(msg.data) != self._command.length:
            d.malformed_frames += 1
            return
        dac_counts, controlword, _cycle = self._command.decode(msg.data)
        if self._rpdo1_event_s:
            self._rpdo_received(self._rpdo_handlers[msg.arbitration_id])
        self._command_values(dac_counts, controlword)

    def _command_values(self, dac_counts: int, controlword: int) -> None:
        d = self.diagnostics
        window = self._sync_window_s
        if (
            window
            and self._last_sync_at is not None
            and self._now - self._last_sync_at > window + TIME_EPSILON
            and self._next_sync
        ):
            d.late_commands += 1  # CiA 301 §7.5.2.8: outside the synchronous window
            d.pdos_ignored += 1
            return
        self._dac_counts = int(dac_counts)
        d.commands += 1
        if not self._sync_monitor.on_command(self._now):
            d.late_commands += 1
        self._command_in_cycle = True
        self._silent_cycles = 0
        if self.services.error_active(_RPDO_TIMEOUT):
            self.services.emcy_clear(_RPDO_TIMEOUT)
        self._latched_V = self._dac.to_volts(dac_counts)
        if self._next_sync:
            self._pending_cw = int(controlword)
        else:
            self._active_V = self._latched_V
            self._machine.apply_controlword(int(controlword))
            self._step_V = self._machine.torque_output(self._active_V)
        self._flush_statusword()

    # ------------------------------------------------------------------ statusword

    def _flush_statusword(self) -> None:
        """Event-driven TPDOs (the statusword's DRIVE_TPDO2 by default): sent when their
        data changed (or once after entering OPERATIONAL) and the inhibit time since the
        last one has passed, and again when the event timer expires (CiA 301 §7.2.2.5)."""
        if self.services.state is not _OPERATIONAL:
            return
        now = self._now
        for tpdo in self._event_tpdos:
            tpdo.flush(now)

    # ------------------------------------------------------------------ PDO configuration

    def _pdo_changed(self, _: object) -> None:
        self._load_pdos()

    def _load_pdos(self) -> None:
        """(Re)build the PDOs from the OD's present communication and mapping parameters
        (at start, on every accepted write to them, after an NMT reset)."""
        services = self.services
        od, read = services.od, services.read
        for cob in self._rpdo_handlers:
            self._handlers.pop((cob, False), None)
        self._rpdo_handlers = {}
        self._rpdo_deadlines = {}
        self._rpdo1_event_s = 0.0
        for n in range(1, MAX_PDOS + 1):
            layout = read_layout(od, read, "rpdo", n)
            if layout is None or not layout.valid:
                continue
            if n == 1:
                self._next_sync = layout.synchronous
                self._rpdo1_event_s = layout.event_s
            self._rpdo_handlers[layout.cob_id] = layout
            fast = _same_mapping(layout, self._default_layouts[("rpdo", 1)])
            self.handle(layout.cob_id, self._on_command if fast else self._on_rpdo)
        tpdos = []
        for n in range(1, MAX_PDOS + 1):
            layout = read_layout(od, read, "tpdo", n)
            if layout is not None:
                tpdos.append(Tpdo(self.bus, layout, self._payload(layout), self._tpdo_sent))
        self._tpdos = tpdos
        self._event_tpdos = [t for t in tpdos if t.layout.valid and not t.layout.synchronous]
        default = self._default_layouts[("tpdo", 1)]
        first = tpdos[0].layout if tpdos else None
        self._fast_sensor = (
            first is not None
            and first.valid
            and first.trans_type == 1
            and first.cob_id == default.cob_id
            and _same_mapping(first, default)
        )
        self._sync_period_s = (
            read(OD_SYNC_PERIOD) * 1e-6 if variable(od, OD_SYNC_PERIOD, 0) is not None else 0.0
        )
        self._sync_window_s = (
            read(OD_SYNC_WINDOW) * 1e-6 if variable(od, OD_SYNC_WINDOW, 0) is not None else 0.0
        )

    def _payload(self, layout: PdoLayout) -> Callable[[], bytes]:
        """The data source of a TPDO: the DBC codecs for the default mappings, the OD's
        live values (read callbacks) for any other."""
        if _same_mapping(layout, self._default_layouts[("tpdo", 1)]):
            return lambda: self._sensor.encode(*self._sample)
        if _same_mapping(layout, self._default_layouts[("tpdo", 2)]):
            return lambda: self._status.encode(self._machine.statusword)
        get = self.services.node.get_data
        return lambda: encode_from_od(layout, get)

    def _tpdo_sent(self, layout: PdoLayout) -> None:
        d = self.diagnostics
        if _same_mapping(layout, self._default_layouts[("tpdo", 1)]):
            d.sensor_frames += 1
        elif _same_mapping(layout, self._default_layouts[("tpdo", 2)]):
            d.statusword_frames += 1

    def _check_deadlines(self, now: float) -> None:
        """RPDO event timers (0x14xx:5) and the SYNC timeout (1.5 x 0x1006, as CANopenNode
        does): EMCY 0x8250 / 0x8100 and the abort-connection reaction (0x6007)."""
        for number, deadline in list(self._rpdo_deadlines.items()):
            if now > deadline + TIME_EPSILON:
                del self._rpdo_deadlines[number]
                self.diagnostics.rpdo_timeouts += 1
                self._emcy(EmcyCode.RPDO_TIMEOUT, bytes((number,)))
                self._communication_reaction(EmcyCode.RPDO_TIMEOUT)
        period = self._sync_period_s
        if (
            period
            and not self._sync_lost
            and self._last_sync_at is not None
            and now - self._last_sync_at > 1.5 * period + TIME_EPSILON
        ):
            self._sync_lost = True
            self.diagnostics.sync_timeouts += 1
            self._emcy(EmcyCode.COMMUNICATION, _SYNC_TIMEOUT_INFO)
            self._communication_reaction(EmcyCode.COMMUNICATION)

    # ------------------------------------------------------------------ NMT

    def _on_nmt_state(self, old: NmtState, new: NmtState) -> None:
        if old is NmtState.OPERATIONAL:
            self._leave_operational()
        if new is NmtState.OPERATIONAL:
            for tpdo in self._tpdos:
                tpdo.restart()
            self._rpdo_deadlines = {}
            self._last_sync_at = None
            self._sync_lost = False
            self.services.emcy_clear(EmcyCode.COMMUNICATION)

    def _leave_operational(self) -> None:
        """PDOs stop: react as the abort connection option code 0x6007 says (CiA 402-2)."""
        self._communication_reaction(None)

    def _communication_reaction(self, emcy_sent: int | None) -> None:
        """The abort connection option code 0x6007 (CiA 402-2): 0 none, 1 fault, 2 disable
        voltage, 3 quick stop; for leaving OPERATIONAL, an RPDO deadline or a SYNC loss.
        ``emcy_sent`` is the EMCY already sent for the cause (None: leaving OPERATIONAL,
        option 1 sends 0x8100)."""
        option = self.services.read(OD_ABORT_CONNECTION)
        if option == 0:  # no action: the command hold still faults a drive left running
            return
        self._pending_cw = None
        self._latched_V = self._active_V = 0.0
        machine = self._machine
        if machine.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return
        if option == 1:
            if emcy_sent is None:
                self._emcy(EmcyCode.COMMUNICATION)
            machine.fault(emcy_sent or EmcyCode.COMMUNICATION)
        elif option == 3:
            machine.apply_controlword(CONTROLWORD[Command.QUICK_STOP])
        else:
            machine.apply_controlword(CONTROLWORD[Command.DISABLE_VOLTAGE])

    def _on_nmt_reset(self, kind: ResetKind) -> None:
        """CiA 301 §7.3.2.2.2: reset node restores the application to power-on."""
        self.diagnostics.nmt_resets += 1
        self._load_pdos()  # the OD's communication area is back to its power-on values
        self._sync_monitor = self._new_sync_monitor()
        if kind != "node":
            return
        self._machine = self._new_state_machine()
        self._machine.complete_initialisation()
        self._step_V = 0.0
        self._saturated.clear()
        self._at_current_limit = False
        self._silence.stop()  # the boot-up message goes out
        self._pending_knobs = dict(self._power_on_knobs)

    def _new_sync_monitor(self) -> SyncMonitor:
        # Counter only: the elapsed time is not trusted to count missed SYNCs, because
        # lockstep runs on a real interface pace SYNC by the host, not by the clock.
        return SyncMonitor(
            period_s=None,
            overflow=self.config.sync_overflow,
            command_deadline_s=self._Ts,
        )

    def _on_remote_boot(self, node_id: int) -> None:
        if node_id == self.config.controller_node_id:
            self._sync_monitor.last_counter = None  # its SYNC counter restarts at 1

    # ------------------------------------------------------------------ heartbeat

    def _on_heartbeat_lost(self, node_id: int) -> None:
        """Heartbeat consumer timeout (EMCY 0x8130 already sent by the services)."""
        d = self.diagnostics
        d.heartbeat_losses += 1
        d.emcy_sent += 1
        d.emcy_log.append(
            EmcyRecord(self._now, EmcyCode.HEARTBEAT, bytes((node_id,)).ljust(5, b"\0"),
                       self.services.emcy_allowed)
        )  # fmt: skip
        if node_id == self.config.controller_node_id:
            self._machine.fault(EmcyCode.HEARTBEAT, persists=True)

    def _on_heartbeat_resumed(self, node_id: int) -> None:
        if node_id == self.config.controller_node_id:
            self._machine.clear_fault_condition()

    # ------------------------------------------------------------------ EMCY

    def _emcy(self, code: int, manufacturer: bytes = b"") -> bool:
        sent = self.services.emcy(code, manufacturer=manufacturer)
        d = self.diagnostics
        d.emcy_sent += 1
        d.emcy_log.append(EmcyRecord(self._now, code, manufacturer.ljust(5, b"\0"), sent))
        return sent

    # ------------------------------------------------------------------ CiA 402 and OD

    def _new_state_machine(self) -> DriveStateMachine:
        read = self.services.read
        ramp = self.config.quick_stop_time_s
        return DriveStateMachine(
            quick_stop_option=read(OD_QUICK_STOP_OPTION),
            quick_stop_time_s=ramp,
            fault_reaction_time_s=ramp if read(OD_FAULT_REACTION_OPTION) else 0.0,
            mode=read(OD_MODES_OF_OPERATION),
        )

    def _register_od_callbacks(self) -> None:
        s = self.services
        s.add_validator(
            OD_MODES_OF_OPERATION,
            0,
            lambda mode: None if mode in SUPPORTED_MODES else ABORT_INVALID_VALUE,
        )
        s.on_write(OD_MODES_OF_OPERATION, 0, lambda mode: self._machine.set_mode(mode))
        s.on_write(OD_QUICK_STOP_OPTION, 0, self._set_quick_stop_option)
        s.on_write(OD_FAULT_REACTION_OPTION, 0, self._set_fault_reaction_option)
        s.on_write(self._od_controlword, 0, self._sdo_controlword)
        for sub in EMULATOR_KNOBS:
            s.on_write(OD_EMULATOR, sub, self._knob_writer(OD_EMULATOR, sub))
        for sub in (*FAULT_FIELDS, *FAULT_MASKS, FAULT_SILENCE_MS):
            s.on_write(OD_FAULTS, sub, self._knob_writer(OD_FAULTS, sub))
        if not self._emulator:  # another plant model: nothing to retune or fault
            extras = (
                (OD_EMULATOR, tuple(EMULATOR_KNOBS)),
                (OD_FAULTS, (*FAULT_FIELDS, *FAULT_MASKS)),
            )
            for index, subs in extras:
                for sub in subs:
                    s.add_validator(index, sub, lambda _value: ABORT_DEVICE_STATE)
        # A channel saturates at one end: refuse a mask overlapping the other end's.
        for sub, other in ((6, 7), (7, 6)):
            s.add_validator(
                OD_FAULTS,
                sub,
                lambda mask, other=other: (
                    ABORT_INVALID_VALUE if mask & s.read(OD_FAULTS, other) else None
                ),
            )
        live: dict[tuple[int, int], Callable[[], int]] = {
            (self._od_statusword, 0): lambda: self._machine.statusword,
            (self._od_controlword, 0): lambda: self._machine.controlword,
            (OD_MODES_DISPLAY, 0): lambda: self._machine.modes_of_operation_display,
            (OD_ERROR_CODE, 0): lambda: self._machine.error_code,
            (OD_ENCODER, 0): lambda: self._sample[3],
            (self._od_torque_actual, 0): self._torque_actual,
            (self._od_position, 0): lambda: self._position,
            (self._od_velocity, 0): lambda: self._velocity,
        }
        for i, channel in enumerate(ADC_CHANNELS):
            live[(OD_ADC_COUNTS, channel)] = lambda i=i: self._sample[i]

        def read_live(index: int, subindex: int, od: Any, **_: Any) -> int | None:
            getter = live.get((index, subindex))
            return None if getter is None else getter()

        s.node.add_read_callback(read_live)

    # ------------------------------------------------------------------ CiA 402 CST

    def _init_cst(self) -> None:
        """Cyclic synchronous torque objects (CiA 402-2): 0x6071 target torque and 0x6077
        torque actual in per mille of 0x6076 motor rated torque (mNm), limited by 0x6072
        max torque (per mille); 0x6064 position actual (encoder increments, unwrapped to
        32 bits) and 0x606C velocity actual (increments per second, from the encoder over
        the last SYNC period).  The rated torque's power-on value is the amplifier's
        full-scale command, ``torque_per_volt`` x the DAC's full scale."""
        od = self.services.od
        self._od_target_torque = index_of(od, TARGET_TORQUE_OBJECT)
        self._od_max_torque = index_of(od, MAX_TORQUE_OBJECT)
        self._od_rated_torque = index_of(od, RATED_TORQUE_OBJECT)
        self._od_torque_actual = index_of(od, TORQUE_ACTUAL_OBJECT)
        self._od_position = index_of(od, POSITION_ACTUAL_OBJECT)
        self._od_velocity = index_of(od, VELOCITY_ACTUAL_OBJECT)
        per_volt = getattr(getattr(self.plant, "cfg", None), "torque_per_volt", None)
        self._torque_per_volt: float | None = float(per_volt) if per_volt else None
        if self._torque_per_volt:
            rated_mNm = round(self._torque_per_volt * self._dac.full_scale_V * 1e3)
            self.services.set_power_on_value(self._od_rated_torque, 0, rated_mNm)
        self._position = 0
        self._velocity = 0
        self._last_encoder: int | None = None

    def _rated_Nm(self) -> float:
        return self.services.read(self._od_rated_torque) * 1e-3

    def _torque_to_counts(self, per_mille: int) -> int:
        """0x6071 (per mille of rated torque, within 0x6072) as the amplifier's DAC
        command: torque / torque_per_volt, quantised as the raw DAC object would be."""
        if not self._torque_per_volt:
            return 0
        rated = self._rated_Nm()
        limit = self.services.read(self._od_max_torque) * 1e-3 * rated
        torque = min(max(per_mille * 1e-3 * rated, -limit), limit)
        return self._dac.to_counts(torque / self._torque_per_volt)

    def _torque_actual(self) -> int:
        """0x6077: the motor torque the amplifier produces, per mille of rated torque."""
        rated = self._rated_Nm()
        value = round(self.plant.truth().tau_m_Nm / rated * 1e3) if rated else 0
        return min(max(value, -32768), 32767)

    def _update_position(self, encoder: int, dt: float) -> None:
        last = self._last_encoder
        self._last_encoder = encoder
        if last is None:
            return
        delta = (encoder - last + 0x8000) % 0x10000 - 0x8000
        self._position = (self._position + delta + 0x80000000) % 0x100000000 - 0x80000000
        self._velocity = round(delta / dt) if dt > 0 else 0

    def _set_quick_stop_option(self, value: int) -> None:
        self._machine.quick_stop_option = value

    def _set_fault_reaction_option(self, value: int) -> None:
        self._machine.fault_reaction_time_s = self.config.quick_stop_time_s if value else 0.0

    def _sdo_controlword(self, value: int) -> None:
        self._machine.apply_controlword(value)

    # ------------------------------------------------------------------ emulator knobs

    @staticmethod
    def _knob_values_of(plant: PlantModel) -> dict[tuple[int, int], float]:
        if not isinstance(plant, Plant):
            return dict.fromkeys(((OD_EMULATOR, sub) for sub in EMULATOR_KNOBS), 0.0)
        cfg = plant.cfg
        values = {}
        for sub, (section, name) in EMULATOR_KNOBS.items():
            # The held load torque starts at 0 in a new Plant (no public getter for it).
            value = 0.0 if section == "load" else float(getattr(getattr(cfg, section), name))
            values[(OD_EMULATOR, sub)] = value
        return values

    def _fault_power_on_values(self) -> dict[tuple[int, int], float]:
        """0x2310 at power-on: the configured sensor faults' rates and sizes, no channel
        masked, no silence."""
        base = self._base_sensor_faults
        values: dict[tuple[int, int], float] = {
            (OD_FAULTS, sub): getattr(base, name) for sub, name in FAULT_FIELDS.items()
        }
        for sub in (*FAULT_MASKS, FAULT_SILENCE_MS):
            values[(OD_FAULTS, sub)] = 0
        return values

    def _set_knob_power_on_values(self) -> None:
        """The plant's configuration becomes the default (power-on value) of 0x2300 and
        0x2310."""
        od = self.services.od
        for (index, sub), value in self._power_on_knobs.items():
            od[index][sub].default = value

    def _knob_writer(self, index: int, sub: int) -> Callable[[float], None]:
        def write(value: float) -> None:
            self._pending_knobs[(index, sub)] = float(value) if index == OD_EMULATOR else value

        return write

    def _apply_knobs(self) -> None:
        """Apply the 0x2300 and 0x2310 writes of the past cycle (before the plant's next
        step)."""
        pending, self._pending_knobs = self._pending_knobs, {}
        emulator = {sub: v for (index, sub), v in pending.items() if index == OD_EMULATOR}
        faults = {sub: v for (index, sub), v in pending.items() if index == OD_FAULTS}
        if emulator:
            self._apply_emulator_knobs(emulator)
        if faults:
            self._apply_fault_switches(faults)

    def _apply_emulator_knobs(self, pending: dict[int, float]) -> None:
        """0x2300: the plant's ripple, sensor noise and load torque."""
        plant = self.plant
        cfg = plant.cfg
        changes: dict[str, dict[str, float]] = {"ripple": {}, "sensors": {}}
        for sub, value in pending.items():
            section, name = EMULATOR_KNOBS[sub]
            if section == "load":
                plant.set_load_torque(value)
            else:
                changes[section][name] = value
        if changes["ripple"] or changes["sensors"]:
            new = dataclasses.replace(
                cfg,
                ripple=dataclasses.replace(cfg.ripple, **changes["ripple"]),
                sensors=dataclasses.replace(cfg.sensors, **changes["sensors"]),
            )
            _retune_plant(plant, new)

    # ------------------------------------------------------------------ fault injection

    def _apply_fault_switches(self, changes: dict[int, Any]) -> None:
        """0x2310: start or end a silence; switch the plant's sensor faults.  The faults
        act from the sample that ends the plant step starting now; the sensor hook is
        installed only while some sensor fault is configured (none: the plant's
        fault-free path)."""
        if FAULT_SILENCE_MS in changes:
            self._silence.start(changes.pop(FAULT_SILENCE_MS) * 1e-3)
        if not changes:
            return
        self._fault_values.update(changes)
        cfg = self._switched_sensor_faults()
        hook = self._sensor_hook
        if hook is None:
            if not cfg.enabled:
                return
            hook = self._sensor_hook = self.faults.sensors(always=True)
            assert hook is not None
        hook.reconfigure(cfg)
        self.plant.faults = hook if cfg.enabled else None

    def _switched_sensor_faults(self) -> SensorFaults:
        """The configured sensor faults with 0x2310's rates and sizes, plus one window per
        masked channel from now on (a channel that stays masked keeps its window, so a
        stuck channel keeps its count)."""
        values = self._fault_values
        start = self.plant.time
        windows: dict[tuple[int, str], SensorWindow] = {}
        for sub, (_, level) in FAULT_MASKS.items():
            for bit, channel in enumerate(MASK_CHANNELS):
                if int(values[sub]) >> bit & 1:
                    key = (sub, channel)
                    windows[key] = self._mask_windows.get(key) or SensorWindow(
                        channel,  # type: ignore[arg-type]
                        start_s=start,
                        level=level,  # type: ignore[arg-type]
                    )
        self._mask_windows = windows
        base = self._base_sensor_faults
        stuck = tuple(w for (sub, _), w in windows.items() if FAULT_MASKS[sub][0] == "stuck")
        saturated = tuple(w for (sub, _), w in windows.items() if FAULT_MASKS[sub][0] != "stuck")
        return dataclasses.replace(
            base,
            stuck=base.stuck + stuck,
            saturated=base.saturated + saturated,
            **{name: values[sub] for sub, name in FAULT_FIELDS.items()},
        )

    @property
    def silent(self) -> bool:
        """True while a silence written to 0x2310 sub 8 lasts (the drive sends nothing)."""
        return self._silence.active and self._now < self._silence.until

    # ------------------------------------------------------------------ truth

    def _publish_truth(self, t: Truth) -> None:
        torque, motion, joint = self._truth_codecs
        m_torque, m_motion, m_joint = self._truth_msgs
        m_torque.data = torque.encode(t.T_true_Nm, t.T_ripple_Nm)
        m_motion.data = motion.encode(
            t.theta_motor_rad % TWO_PI,
            t.theta_output_rad % TWO_PI,
            t.omega_motor_radps,
            t.omega_output_radps,
        )
        m_joint.data = joint.encode(t.tau_ext_Nm, t.tau_d_Nm, t.tau_m_Nm, t.tau_m_cmd_Nm)
        send = self.truth_bus.send
        send(m_torque)
        send(m_motion)
        send(m_joint)


def _same_mapping(a: PdoLayout | None, b: PdoLayout | None) -> bool:
    return a is not None and b is not None and a.entries == b.entries
