"""The controller node: the ported interrupt handler behind a CANopen link.

On the seed's DSP a hardware timer fired ``c_int10`` every sample period ([Taghirad97],
listing A.1, ``t1_schedule_intr(c_int10, sample_period)``).  Over CAN the timer becomes
the SYNC the controller produces, and the ADC read becomes the drive's synchronous TPDO:

1. ``send_sync()``: SYNC k (CiA 301, with counter) starts cycle k.
2. The drive samples its sensors at t(k) and answers with ``DRIVE_TPDO1``.
3. ``_on_sensor_frame``: the interrupt body runs on those counts
   (:class:`firmware.isr.InterruptHandler`), then the DAC command goes out in
   ``DRIVE_RPDO1`` and the logged variables in the telemetry ``CTRL_TPDO1``, both before
   SYNC k+1.

With a torque-control law active ([Vertechy], :class:`firmware.config.ControlConfig`)
``CTRL_TPDO1.T_filtered`` carries the LQG estimate ``τ̂s`` instead of the ripple
filter's torque, and a second telemetry frame ``CTRL_TPDO2`` (0x281) follows with
``τ̂s'``, ``τ̂lgd``, ``τsD`` and the estimated error ``e``.  Without a law ``CTRL_TPDO2`` is
not sent at all: the PDO is not valid, as CANopen marks it with bit 31 of its COB-ID
(``dbc/controller.eds`` object 0x1801 defaults to 0x80000281, and the node keeps that bit
in step with the law), and the bus carries exactly the [Taghirad97] schedule.  Worst-case
control-bus load: 44 % without, 57.5 % with a law.

CANopen roles (CiA 301, :mod:`hdhil.canopen.services`)
------------------------------------------------------
The controller is node-ID 1: an NMT slave itself (boot-up 0x701, heartbeat producer 0x701
every 100 ms, SDO server on 0x601/0x581, EMCY producer 0x081) and the NMT master, SYNC
producer and CiA 402 controlling device of the drive (node-ID 2, heartbeat consumer with
250 ms).  The runner drives it without threads::

    controller.boot(now)                   # boot-up 0x701, wait for the drive's boot-up
    every cycle k (now = k * Ts):
        controller.tick(now)               # heartbeats, timeouts, sequencer, new parameters
        if controller.boot_error: fail with it (one line)
        if controller.phase in ("stopped", "safe"): end the run
        controller.send_sync()             # False when no SYNC went out
        poll the nodes until the cycle's frames are handled

Phases (:class:`Phase`, the ``phase`` property) and what goes on the bus:

============  ==================================================  ======  ============
phase         what happens                                        SYNC    DRIVE_RPDO1
============  ==================================================  ======  ============
wait-boot     PRE-OPERATIONAL, waiting for the drive's boot-up    yes     no
starting      drive NMT-started, CiA 402 walk (controlword)       yes     DAC 0 + cw
operational   the interrupt handler runs on every sensor frame    yes     DAC + 0x000F
stopping      CiA 402 walk back (0x0007, then 0x0006)             yes     DAC 0 + cw
stopped       drive sent to PRE-OPERATIONAL, controller too       no      no
safe          fault: the drive is no longer commanded             no      no
============  ==================================================  ======  ============

On entering "safe" from a commanding phase the controller stops commanding at once (no
further RPDO, no SYNC) and sends NMT "enter pre-operational" for the drive: a CiA 402
drive reacts to leaving OPERATIONAL with its abort-connection option (0x6007: fault,
disable voltage or quick stop), which is the one torque-off path that works whether the
drive takes its RPDO over on receipt or at the next SYNC (none follows).  A last
"disable voltage" RPDO would not help: sent at the same instant, the NMT frame (identifier
0) wins arbitration and the drive, already pre-operational, drops the PDO.  The controller
goes PRE-OPERATIONAL itself, so its heartbeat reports it.  SDO and heartbeat keep running
in "stopped" and "safe"; both are final: **recovery is a restart** (a new node and
``boot``).  Heartbeats and the SDO server run in every phase.

Start-up (CiA 301 §7.3.2 NMT, CiA 402 PDS state machine): on the drive's boot-up (or its
heartbeat, if it booted before the controller) the controller sends NMT "start remote
node" (0x000: 01 02), enters OPERATIONAL itself and walks the drive's state machine with
the controlword of ``DRIVE_RPDO1`` (sent on every sensor frame, DAC 0); the walk's
decisions (which controlword for which state, one fault reset per node) are
:class:`hdhil.firmware.walk.Cia402Walk`'s, its table is in :mod:`hdhil.firmware.walk`.

The statusword comes in ``DRIVE_TPDO2`` (0x282, event-driven; RPDO2 of the controller,
object 0x2011).  An event-driven PDO is sent on change only, so right after NMT start the
controller also reads the drive's statusword once by SDO (expedited upload on 0x602/0x582,
:class:`hdhil.canopen.sdo.SdoClient`; the index is looked up by name in ``drive.eds``):
a drive that comes up in FAULT is fault-reset from the first command on.  A walk step
that sees no statusword for ``STATUSWORD_TIMEOUT_S`` (20 ms) counts as a missed
statusword: the controller re-sends NMT start (start-up only) and reads 0x6041 by SDO
again, which recovers a lost event-driven PDO.  The whole walk must finish within
``WALK_TIMEOUT_S`` (1 s): a start-up that does not ends in "safe", a stop that does not
ends in "stopped" anyway (counted in ``stop_timeouts``).

Timing in lockstep (boot-ups at t = 0; ``diagnostics.startup_cycles`` counts the SYNCs
from NMT start to OPERATION ENABLED).  The drive's boot-up is handled in cycle 0 (NMT
start, SDO read of the statusword).  A drive that applies the controlword on receipt
(``hostsim.drive`` with ``actuation = "immediate"``) answers each step in the same cycle:
the walk takes the SYNCs of cycles 1, 2, 3 (0x0006, 0x0007, 0x000F), and the first
operational sample, ``samplecount = 0``, is cycle 4.  A drive that takes the whole RPDO
over at the next SYNC (``"next-sync"``, the default: CiA 301 synchronous RPDO) changes
state at SYNC k+1 and its statusword follows its sensor frame, so each step takes two
cycles: 6 SYNCs, first sample in cycle 7.  The stop takes 2 (immediate) or 3 (next-sync)
cycles.

Stop (``request_stop()``, or automatically once ``num_samples`` interrupts have run, as the
listing's ``main`` leaves its loop and writes DAC 0): controlword 0x0007 "disable
operation" (transition 5), then 0x0006 "shutdown" (transition 6), then NMT "enter
pre-operational" (0x80) for the drive (it keeps its heartbeat and SDO server, so it can
still be inspected, but takes no PDOs), and the controller goes PRE-OPERATIONAL: "stopped".

Faults: the drive's heartbeat times out (250 ms, monitored from its first heartbeat; the
check runs in ``tick``, so it is detected within one tick): EMCY 0x8130 with the drive's
node-ID in manufacturer byte 0, phase "safe".  In "operational", ``sensor_hold_cycles``
SYNCs in a row without a sensor frame: the drive holds the last command until then (the
controller sends nothing without a sensor frame), then EMCY 0x8250 "RPDO timeout"
(manufacturer bytes: the drive's node-ID and the number of SYNCs) and "safe".  A boot-up
of the drive while it is commanded (it was reset) and NMT commands from another master
that take the controller out of OPERATIONAL (or reset it) also lead to "safe".

Sensor plausibility (:class:`firmware.stages.SensorPlausibility`) does not stop the
controller: replaced tacho samples and encoder increments are counted in the
diagnostics, and when a channel is replaced ``max_rejections`` times in a row the next
``tick`` sends EMCY 0x7301 "tacho fault" or 0x7305 "incremental sensor 1 fault"
(CiA 402), once; EMCY 0x0000 follows when the channel is plausible again.  A cycle
without a sensor frame widens the next sample's bounds by one period.

Live parameters (SDO)
---------------------
The controller's object dictionary holds the firmware parameters (objects 0x2400-0x2430,
:data:`hdhil.firmware.parameters.PARAMETERS`), checked and staged by
:class:`hdhil.firmware.parameters.LiveParameters`.  Accepted writes are applied at the
next cycle boundary (``tick`` or ``send_sync``, whichever comes first) by
:func:`hdhil.firmware.parameters.apply_config`:

- reference generator (0x2400): rebuilt; the wave continues at the present sample index;
- ``num_samples`` (0x2401:1): the new limit counts from the first operational sample;
- ripple filter (0x2410): the filter chain is rebuilt, **the ripple Kalman filter
  restarts** from P0 (its learned ripple is lost); the differentiator and the encoder
  unwrapping carry over.  Writing ``mode`` gives the mode's default tuning for the same
  harmonics (:func:`hdhil.firmware.config.paper_config` / ``recommended_config``), and
  the OD's r, residual_q and q_i are updated to it;
- control law (0x2420:1): the LQG stage is rebuilt (observer from rest); ``CTRL_TPDO2``
  is sent only while a law is active and 0x1801:1 bit 31 follows; the desired torque's
  amplitude/frequency only swap the desired-torque generator;
- calibration (0x2430): used from the next sample on.

0x1006 (communication cycle period) holds the running period and 0x1019 the SYNC counter
overflow; neither can be changed over SDO (abort 0x08000022): the runner paces the
cycle and the drive's SYNC consumer expects the overflow.  PDO-mapped process data (ADC
counts, telemetry) is not mirrored into the OD; the
controlword (0x6040) and the drive's statusword (0x2011) are, when they change.

The drive's mapping (``drive_dcf``)
----------------------------------
Without a DCF the frames are the seed's raw ADC/DAC mapping, encoded with
``control.dbc``'s compiled codecs.  With one, the controller configures the drive from it
at boot (:mod:`hdhil.canopen.dcf`) and gives its own PDOs the matching mapping
(:func:`hdhil.canopen.mapping.peer_pdo_writes`: the drive's TPDO is this node's RPDO with
the same COB-ID, objects matched by name), written into its OD through the CiA 301
checks; the frames are then encoded and decoded from that live mapping.  In the CiA 402
cyclic synchronous torque mapping (``dbc/drive-cst.dcf``: 0x6040 + 0x6071 in, 0x6077 +
0x6064 out) the controller reads the drive's rated torque 0x6076 by SDO before NMT
start, the interrupt handler's sensor source becomes
:class:`firmware.stages.CstSource` and the command goes out as 0x6071 in per mille
(:func:`firmware.stages.torque_command_per_mille`); the [Vertechy] control laws, which
regulate the sensor torque, are refused there.

This module only moves frames and sequences the link: every computation is in
:mod:`firmware.isr` and its stages.  It uses nothing but a python-can bus, so the same
node drives the emulator on ``simbus`` or a real drive on SocketCAN/PCAN/Kvaser.  It never
subscribes to ground truth.  PDO COB-IDs come from ``control.dbc`` (pre-defined connection
set of nodes 1 and 2); other node-IDs move only the CiA 301 service frames.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, cast

import can

from hdhil.can.node import CanNode, pdo_cob_id
from hdhil.canopen.cia402 import CONTROLWORD_OBJECT, STATUSWORD_OBJECT, State
from hdhil.canopen.dcf import DcfConfigurator, configuration_writes
from hdhil.canopen.mapping import dcf_layouts, layout_codec, od_layouts, peer_pdo_writes
from hdhil.canopen.od import eds_index, index_of
from hdhil.canopen.pdo import PdoLayout
from hdhil.canopen.sdo import ABORT_DEVICE_STATE, SdoClient, abort_text
from hdhil.canopen.services import (
    CanopenServices,
    EmcyCode,
    NmtCommand,
    NmtState,
    ResetKind,
)
from hdhil.dbc import FrameCodec, codec, eds_path
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.interrupt import AdcSample, CstSample, InterruptHandlerModel
from hdhil.firmware.isr import InterruptHandler
from hdhil.firmware.odlimits import check_od_limits
from hdhil.firmware.parameters import (
    PARAMETERS,
    LiveParameters,
    Parameter,
    apply_config,
    store_value,
)
from hdhil.firmware.stages import torque_command_per_mille
from hdhil.firmware.walk import CONTROLWORD_ENABLE_OPERATION, Cia402Walk, WalkStep

__all__ = [
    "CONTROLWORD_ENABLE_OPERATION",
    "PARAMETERS",
    "ControllerDiagnostics",
    "ControllerNode",
    "Parameter",
    "Phase",
    "PhaseChange",
]


class Phase(str, enum.Enum):
    """The controller's link phase (module docstring, table "Phases")."""

    WAIT_BOOT = "wait-boot"
    STARTING = "starting"
    OPERATIONAL = "operational"
    STOPPING = "stopping"
    STOPPED = "stopped"
    SAFE = "safe"

    def __str__(self) -> str:
        return self.value


#: Phases in which the controller commands the drive (sends DRIVE_RPDO1).
_COMMANDING = frozenset({Phase.STARTING, Phase.OPERATIONAL, Phase.STOPPING})
#: Final phases: no SYNC, no PDO; only a restart leaves them.
_FINAL = frozenset({Phase.STOPPED, Phase.SAFE})
# The phases the per-cycle code tests for, as module globals: an attribute of an Enum class
# (``Phase.OPERATIONAL``) is looked up through ``EnumType.__getattr__``'s slow path in
# Python 3.11, several times slower than a global.
_WAIT_BOOT = Phase.WAIT_BOOT
_OPERATIONAL = Phase.OPERATIONAL


class PhaseChange(NamedTuple):
    """One entry of the phase history: when (the latest ``tick``/``boot`` time, s), the
    new phase and why."""

    time_s: float
    phase: Phase
    reason: str


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


def _seconds(t: float) -> str:
    """2.0 -> "2.0", 0.25 -> "0.25" (as a user would write the timeout)."""
    return f"{t:.1f}" if round(t, 1) == t else f"{t:g}"


# ------------------------------------------------------------------------- the node


class ControllerNode(CanNode):
    """SYNC producer, NMT master, CiA 402 controlling device and torque-sensing firmware
    (CANopen node-ID 1).  See the module docstring for the phases and timings.

    The jobs are split: :class:`hdhil.firmware.walk.Cia402Walk` decides the CiA 402
    walk, :class:`hdhil.firmware.parameters.LiveParameters` owns the parameter objects,
    :class:`hdhil.canopen.sdo.SdoClient` reads the drive's statusword, and this class
    moves the frames and sequences the link phases.

    Args:
        bus: the control bus (any python-can bus).
        config: the firmware configuration (the scenario's); written into the OD.
        sync_overflow: SYNC counter overflow, object 0x1019 (CiA 301: 2..240 here).
        node_id: this node's CANopen node-ID.
        drive_node_id: the drive's node-ID (NMT, heartbeat consumer, SDO client).
        heartbeat_ms: heartbeat producer time (0x1017).
        drive_heartbeat_timeout_ms: heartbeat consumer time for the drive (0x1016:1).
        boot_timeout_s: how long ``boot`` waits for the drive's boot-up.
        sensor_hold_cycles: SYNCs without a sensor frame tolerated in "operational".
    """

    #: A walk step without statusword for this long reads the statusword by SDO.
    STATUSWORD_TIMEOUT_S = 0.02
    #: A start-up or stop walk must be done within this time.
    WALK_TIMEOUT_S = 1.0
    #: Automatic fault resets per node lifetime (CiA 402 transition 15).
    MAX_FAULT_RESETS = Cia402Walk.MAX_FAULT_RESETS

    def __init__(
        self,
        bus: can.BusABC,
        config: FirmwareConfig,
        sync_overflow: int = 240,
        *,
        node_id: int = 1,
        drive_node_id: int = 2,
        heartbeat_ms: int = 100,
        drive_heartbeat_timeout_ms: int = 250,
        boot_timeout_s: float = 2.0,
        sensor_hold_cycles: int = 10,
        isr: InterruptHandlerModel | None = None,
        drive_dcf: str | Path | None = None,
    ) -> None:
        if not 2 <= sync_overflow <= 240:
            raise ValueError(f"SYNC counter overflow must be 2..240 (CiA 301), got {sync_overflow}")
        if not 1 <= drive_node_id <= 127 or drive_node_id == node_id:
            raise ValueError(f"drive node-ID must be 1..127 and not {node_id}, got {drive_node_id}")
        if not (math.isfinite(boot_timeout_s) and boot_timeout_s > 0):
            raise ValueError(f"boot timeout must be > 0 s, got {boot_timeout_s}")
        if isinstance(sensor_hold_cycles, bool) or not (
            isinstance(sensor_hold_cycles, int) and sensor_hold_cycles >= 1
        ):
            raise ValueError(
                f"sensor_hold_cycles must be an integer >= 1, got {sensor_hold_cycles}"
            )
        super().__init__(bus)
        check_od_limits(config)  # every OD parameter representable in its entry
        self.config = config
        #: The interrupt handler (:class:`firmware.interrupt.InterruptHandlerModel`): the
        #: firmware's own unless ``isr`` is given; the plausibility EMCYs and the SDO
        #: parameters that retune stages need the firmware's own.
        self.isr: InterruptHandlerModel = InterruptHandler(config) if isr is None else isr
        self._own_isr = isinstance(self.isr, InterruptHandler)
        self._settle_left = 0  # start-up pause cycles left (listing main(), _set_phase)
        self.diagnostics = ControllerDiagnostics()
        self.sync_overflow = sync_overflow
        self.node_id = node_id
        self.drive_node_id = drive_node_id
        self.boot_timeout_s = boot_timeout_s
        self.sensor_hold_cycles = sensor_hold_cycles
        #: Why the drive never booted (one line for the user); None otherwise.
        self.boot_error: str | None = None

        self.services = CanopenServices(
            bus,
            node_id,
            eds_path("controller"),
            heartbeat_producer_ms=heartbeat_ms,
            heartbeat_consumers={drive_node_id: drive_heartbeat_timeout_ms},
        )
        od = self.services.od
        # CiA 402 objects by name: the controller's own controlword mirror, and the
        # drive's statusword in the drive's EDS (what the SDO client reads).
        self._controlword_index = index_of(od, CONTROLWORD_OBJECT)
        self._drive_statusword_index = eds_index(str(eds_path("drive")), STATUSWORD_OBJECT)
        self._period_us = round(config.sample_period_s * 1e6)
        self._store_comm_values()
        self._sync = self.services.make_sync_producer()
        self.parameters = LiveParameters(self.services, lambda: self.config, self._on_parameter)
        self.parameters.store(config)
        self.parameters.enabled = self._own_isr
        self.services.add_validator(0x1006, 0, self._check_cycle_period)
        self.services.on_boot(self._on_boot)
        self.services.on_heartbeat_lost(self._on_heartbeat_lost)
        self.services.on_state_change(self._on_nmt_state)
        self.services.on_reset(self._on_reset)
        self.sdo = SdoClient(bus, drive_node_id)
        #: Boot-time configuration of the drive from its DCF (CiA 306), by SDO, after its
        #: boot-up and before NMT start; None without a DCF.
        self.configurator = (
            DcfConfigurator(self.sdo, configuration_writes(drive_dcf, drive_node_id))
            if drive_dcf is not None
            else None
        )
        #: The drive's PDOs as its DCF leaves them (empty without a DCF), and the writes
        #: that gave this node's own PDOs the matching mapping (empty: the default
        #: mapping).  Raises ``ValueError`` for a mapping the firmware cannot run.
        self.drive_layouts: dict[tuple[str, int], PdoLayout] = {}
        self.pdo_writes: list[tuple[int, int, int]] = []
        if drive_dcf is not None:
            drive_od, self.drive_layouts = dcf_layouts(drive_dcf, drive_node_id)
            self.pdo_writes = peer_pdo_writes(od, self.services.read, drive_od, self.drive_layouts)
        for index, sub, value in self.pdo_writes:
            try:
                self.services.write(index, sub, value)
            except Exception as exc:
                raise ValueError(
                    f"the controller cannot take 0x{index:04X}:{sub:02X} = 0x{value:X} "
                    f"for the drive's mapping: {exc}"
                ) from None
        # 0x6076, looked up by name in the drive's EDS when a mapping may need it
        self._rated_index = (
            eds_index(str(eds_path("drive")), "motor_rated_torque") if self.pdo_writes else 0
        )
        #: The drive's motor rated torque 0x6076 (Nm), read by SDO at boot in the CiA 402
        #: CST mapping; None in the raw mapping (or before the read).
        self.rated_torque_Nm: float | None = None
        self._rated_requested = False
        self.walk = Cia402Walk(drive_node_id, self._on_controlword)

        self._phase = Phase.WAIT_BOOT
        self._now = 0.0
        self._configure_deadline = 0.0
        self._phase_cycles = 0
        self._quiet_cycles = 0  # walk cycles since the last statusword
        self._nmt_start_syncs = 0
        self._sensor_seen = True
        self._isr_ran = False  # the interrupt ran in this cycle (once per SYNC)
        self._missing_sensor = 0
        self._own_nmt = False
        self._plausibility_revision = 0
        self._stuck_revision = 0
        self._plausibility_emcy: set[int] = set()  # EMCY codes of active sensor errors
        self._cycle = 0
        Ts = config.sample_period_s
        self._statusword_timeout_cycles = max(1, math.ceil(self.STATUSWORD_TIMEOUT_S / Ts - 1e-9))
        self._walk_timeout_cycles = max(1, math.ceil(self.WALK_TIMEOUT_S / Ts - 1e-9))

        # Codecs are used by signal name: each layout is checked against the names this
        # node packs and unpacks (a DBC with reordered signals fails here, loudly).  In
        # the default mapping they are control.dbc's; a mapping taken from the drive's DCF
        # is encoded and decoded from this node's object dictionary (_mapped_codecs).
        self._sensor = codec("control", "DRIVE_TPDO1").expect(
            "ADC_torque", "ADC_tacho", "ADC_current", "ENC_count"
        )
        self._command = codec("control", "DRIVE_RPDO1").expect("DAC_cmd", "controlword", "cycle")
        self._telemetry = codec("control", "CTRL_TPDO1").expect(
            "T_meas", "T_filtered", "velocity", "current"
        )
        self._control_telemetry = codec("control", "CTRL_TPDO2").expect(
            "dtau_s_hat", "tau_lgd_hat", "tau_sD", "e_hat"
        )
        self._status = codec("control", "DRIVE_TPDO2").expect("statusword")
        #: Which sensor objects the drive sends: "raw" (the seed's ADC counts and encoder)
        #: or "cst" (CiA 402 torque actual 0x6077 and position actual 0x6064).
        self.sensor_mapping = "raw"
        self._sensor_picks: tuple[int, ...] = (0, 1, 2, 3)
        self._command_picks: tuple[int, ...] = (0, 1, 2)
        self._torque_per_volt = config.control.torque_per_volt
        self._dbc_command = not self.pdo_writes
        if self.pdo_writes:
            self._mapped_codecs(od)
        self._command_msg = self._message(self._command.frame_id, self._command.length)
        self._telemetry_msg = self._message(self._telemetry.frame_id, self._telemetry.length)
        self._control_msg = self._message(
            self._control_telemetry.frame_id, self._control_telemetry.length
        )
        #: CTRL_TPDO2 is valid (sent) only while a control law runs (COB-ID bit 31 clear).
        self.control_pdo_valid = config.control.active
        self._store_control_pdo_validity()
        # PDO identifiers come from the object dictionary (RPDO1 0x1400, RPDO2 0x1401; the
        # TPDOs 0x1800-0x1802), each checked against the DBC layout the node encodes with.
        self.handle(pdo_cob_id(od, 0x1400, self._sensor), self._on_sensor_frame)
        self.handle(pdo_cob_id(od, 0x1401, self._status), self._on_statusword_frame)
        for comm_index, frame in ((0x1800, self._telemetry), (0x1802, self._command),
                                  (0x1801, self._control_telemetry)):  # fmt: skip
            pdo_cob_id(od, comm_index, frame)
        self.handle(self.sdo.response_id, self._on_sdo_response)

    def _mapped_codecs(self, od: Any) -> None:
        """Codecs of a mapping taken from the drive's DCF, from this node's live PDOs
        (RPDO1 the sensor frame, RPDO2 the statusword, TPDO3 the command), with the
        objects picked by name: the sensor frame must carry the seed's ADC channels and
        encoder or the CiA 402 torque and position actual values, the command the
        controlword and the DAC command or the target torque."""
        layouts = od_layouts(od, self.services.read)

        def live(kind: str, number: int, name: str) -> FrameCodec:
            layout: PdoLayout = layouts[(kind, number)]
            if not layout.valid:
                raise ValueError(f"the controller's {kind.upper()}{number} ({name}) is not valid")
            return layout_codec(od, layout, name)

        def picks(frame: FrameCodec, names: tuple[str, ...]) -> tuple[int, ...] | None:
            have = frame.signal_names
            return tuple(have.index(n) for n in names) if set(names) <= set(have) else None

        sensor = live("rpdo", 1, "DRIVE_TPDO1")
        raw = picks(sensor, ("ADC_torque", "ADC_tacho", "ADC_current", "ENC_count"))
        cst = picks(sensor, ("torque_actual_value", "position_actual_value"))
        if raw is None and cst is None:
            raise ValueError(
                f"the drive's sensor PDO maps ({', '.join(sensor.signal_names)}); the firmware "
                "needs ADC_torque, ADC_tacho, ADC_current and ENC_count (raw mapping) or "
                "torque_actual_value and position_actual_value (CiA 402 CST mapping)"
            )
        command = live("tpdo", 3, "DRIVE_RPDO1")
        target = "DAC_cmd" if raw is not None else "target_torque"
        order = picks(command, (target, "controlword"))
        if order is None:
            raise ValueError(
                f"the drive's command PDO maps ({', '.join(command.signal_names)}); with the "
                f"{'raw' if raw is not None else 'CST'} sensor objects it must map {target} "
                "and controlword"
            )
        cycle = picks(command, ("cycle",))
        self._command_picks = (*order, *(cycle or ()))
        self._sensor = sensor
        self._sensor_picks = raw if raw is not None else cst  # type: ignore[assignment]
        self._command = command
        self._status = live("rpdo", 2, "DRIVE_TPDO2").expect("statusword")
        if raw is None:
            self.sensor_mapping = "cst"
            # [Vertechy]'s laws regulate the sensor torque tau_s = k (theta_l - theta_m)
            # (Eq. 2, 8); 0x6077 is the amplifier's motor torque, a different quantity,
            # so no law runs on it (at start-up or by a later SDO write of 0x2420:1).
            if self.config.control.active:
                raise ValueError(
                    "the torque-control laws ([Vertechy]) regulate the strain-gauge sensor "
                    "torque; the CiA 402 CST mapping carries the amplifier's torque 0x6077 "
                    "only: run them in the raw mapping"
                )
            self.services.add_validator(0x2420, 1, lambda law: ABORT_DEVICE_STATE if law else None)

    @staticmethod
    def _message(frame_id: int, length: int) -> can.Message:
        return can.Message(arbitration_id=frame_id, is_extended_id=False, dlc=length, check=False)

    # ------------------------------------------------------------------ public API

    @property
    def phase(self) -> Phase:
        """The link phase: "wait-boot", "starting", "operational", "stopping", "stopped"
        or "safe" (a ``str`` enum, so ``node.phase == "operational"`` works)."""
        return self._phase

    @property
    def done(self) -> bool:
        """True once ``num_samples`` interrupts have run (listing: ``samplecount < numsamples``)."""
        return self.isr.done

    @property
    def drive_state(self) -> State | None:
        """The drive's CiA 402 state from its latest statusword (None before the first)."""
        return self.walk.drive_state

    @property
    def controlword(self) -> int:
        """The controlword the next DRIVE_RPDO1 carries."""
        return self.walk.controlword

    def boot(self, now: float) -> None:
        """Power-on (CiA 301 §7.3.2.2): boot-up message 0x701, PRE-OPERATIONAL, and, as NMT
        master, start waiting ``boot_timeout_s`` for the drive's boot-up."""
        self._now = now
        self.services.boot(now)
        self.services.nmt.expect_boot(self.drive_node_id, now, self.boot_timeout_s)
        self._set_phase(Phase.WAIT_BOOT, "power on: waiting for the drive's boot-up")

    def tick(self, now: float) -> None:
        """Once per cycle, before polling: heartbeat producer and consumer (may enter
        "safe"), parameters written last cycle, the drive's boot-up wait and its timeout."""
        self._now = now
        self.services.tick(now)
        self._apply_pending()
        if self._phase is _WAIT_BOOT and self.services.state is not NmtState.INITIALISING:
            drive = self.drive_node_id
            if (
                self.services.nmt.boot_seen(drive)
                or self.services.nmt.remote_states.get(drive) is not None
            ):
                self._drive_seen()
            elif drive in self.services.nmt.boot_timed_out(now):
                self.boot_error = (
                    f"drive (node {drive}) sent no boot-up within "
                    f"{_seconds(self.boot_timeout_s)} s: check power, node-ID and bit rate"
                )
                self._enter_safe(self.boot_error)
        if self._own_isr:  # our InterruptHandler: its plausibility and stuck-channel flags
            isr = self.isr
            if isr.chain.plausibility.revision != self._plausibility_revision:
                self._report_plausibility()
            stuck = isr.stuck
            if stuck is not None and stuck.revision != self._stuck_revision:
                self._report_stuck(stuck)
        counters = self.services.counters
        self.diagnostics.emcy_sent = self.services.emcy.sent
        self.diagnostics.emcy_received = counters.emcy_received

    def send_sync(self) -> bool:
        """Start a cycle: SYNC with the CiA 301 counter (1..overflow, then 1 again).

        Sent in every phase but "stopped" and "safe", and only in an NMT state that allows
        it (not before ``boot``).  At this cycle boundary the node also applies new
        parameters, checks the sensor hold ("operational") and the walk's statusword
        timeouts ("starting"/"stopping").  Returns True if a SYNC went out.
        """
        self._apply_pending()
        phase = self._phase
        if phase is _OPERATIONAL:
            if not self._sensor_hold_ok():
                return False
        elif phase is Phase.STARTING or phase is Phase.STOPPING:
            self._walk_watchdog()
            if self._phase in _FINAL:
                return False
        elif phase in _FINAL:
            return False
        if not self.services.send_sync():
            return False
        self._sensor_seen = False
        self._isr_ran = False
        self.diagnostics.syncs_sent += 1
        return True

    def request_stop(self, reason: str = "stop requested") -> None:
        """Walk the drive back (controlword 0x0007, then 0x0006), then NMT pre-operational
        for the drive: phase "stopping", then "stopped".  No effect once stopping."""
        phase = self._phase
        if phase is Phase.WAIT_BOOT:
            self._set_phase(Phase.STOPPED, f"{reason} before the drive booted")
        elif phase is Phase.STARTING or phase is Phase.OPERATIONAL:
            self._set_phase(Phase.STOPPING, reason)
            self._sequence()

    # ------------------------------------------------------------------- frames

    def on_message(self, msg: can.Message) -> None:
        """CiA 301 service frames go to the services first; SYNC/PDOs to the handlers."""
        if not self.services.handle(msg):
            super().on_message(msg)

    def _on_sensor_frame(self, msg: can.Message) -> None:
        if msg.is_remote_frame or len(msg.data) != self._sensor.length:
            self.diagnostics.malformed_frames += 1
            return
        phase = self._phase
        if phase not in _COMMANDING or not self.services.pdo_allowed:
            self.diagnostics.pdos_ignored += 1
            return
        if phase is _OPERATIONAL and self._isr_ran:
            # A second sensor frame in one cycle (duplicated on the bus): the interrupt
            # runs once per SYNC, as the seed's timer interrupt does.
            self.diagnostics.extra_sensor_frames += 1
            return
        self._sensor_seen = True
        self.diagnostics.sensor_frames += 1
        if phase is not _OPERATIONAL:
            self._send_command(self.isr.shutdown_dac_counts, self.walk.controlword)
            return
        self._isr_ran = True
        if self._settle_left:
            # listing main(): write_dac0( Vbias ); then the settling pause before the
            # first interrupt (FirmwareConfig.startup_settle_s)
            self._settle_left -= 1
            own = cast(InterruptHandler, self.isr)
            self._send_command(own.startup_dac_counts, CONTROLWORD_ENABLE_OPERATION)
            return
        values = self._sensor.decode(msg.data)
        if self.sensor_mapping == "raw":
            a, b, c, d = self._sensor_picks
            out = self.isr(AdcSample(values[a], values[b], values[c], values[d]))
        else:
            a, b = self._sensor_picks
            out = self.isr(CstSample(values[a], values[b]))
        self._send_command(out.dac_counts, CONTROLWORD_ENABLE_OPERATION, out.reference_V)
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
        if self.isr.done:
            self.request_stop(f"num_samples = {self.config.num_samples} reached")

    def _report_stuck(self, stuck: Any) -> None:
        """An EMCY when a channel gets stuck, cleared when it reads again; the diagnostic
        counters follow.  Codes (CiA 402 / IEC 61800-7-201, "sensor" family 0x73xx), with
        the channel in manufacturer byte 0: torque 0x7300 "sensor error" with 1 (no more
        specific code exists for a torque bridge), tacho 0x7301 "tacho fault" with 2."""
        self._stuck_revision = stuck.revision
        self.diagnostics.stuck_sensor_events = stuck.events
        self.diagnostics.stuck_tacho_events = getattr(stuck, "tacho_events", 0)
        for code, channel, flag in (
            (EmcyCode.SENSOR, 1, stuck.torque_stuck),
            (EmcyCode.TACHO_FAULT, 2, stuck.tacho_stuck),
        ):
            if flag:
                self.services.emcy.raise_error(code, manufacturer=bytes((channel,)))
            else:
                self.services.emcy.clear(code, bytes((channel,)))

    def _report_plausibility(self) -> None:
        """The plausibility stage's counters into the diagnostics, and its error flags on
        the bus (CiA 301 §7.2.7: an EMCY when an error occurs, EMCY 0x0000 "error reset
        or no error" when it goes away; not one per replaced sample).

        Codes (CiA 402 / IEC 61800-7-201 table of error codes, "sensor" family 0x73xx):
        0x7301 "tacho fault" for the velocity and 0x7305 "incremental sensor 1 fault" for
        the encoder.  Both are more specific than 0x7300 "sensor", which the drive
        already sends for a saturated ADC channel, so a host can tell the two apart.
        """
        check = self.isr.chain.plausibility
        self._plausibility_revision = check.revision
        d = self.diagnostics
        d.tacho_rejections = check.tacho_rejections
        d.encoder_rejections = check.encoder_rejections
        d.tacho_reseeds = check.tacho_reseeds
        d.encoder_reseeds = check.encoder_reseeds
        d.plausibility_errors = check.errors_raised
        active = self._plausibility_emcy
        for code, error in (
            (EmcyCode.TACHO_FAULT, check.tacho_error),
            (EmcyCode.INCREMENTAL_SENSOR_1, check.encoder_error),
        ):
            if error and code not in active:
                active.add(code)
                self.services.emcy.raise_error(code)
            elif not error and code in active:
                active.discard(code)
                self.services.emcy.clear(code, b"")  # not the stuck tacho's 0x7301

    def _send_command(self, dac_counts: int, controlword: int, volts: float | None = None) -> None:
        if self._dbc_command:
            data = self._command.encode(dac_counts, controlword, self._cycle & 0xFF)
        else:
            data = self._encode_mapped_command(dac_counts, controlword, volts)
        self._command_msg.data = data
        self.bus.send(self._command_msg)
        self.diagnostics.commands_sent += 1
        self.walk.cw_sends += 1
        self._cycle += 1

    def _encode_mapped_command(
        self, dac_counts: int, controlword: int, volts: float | None
    ) -> bytes:
        """The command PDO of a mapping from the DCF: the DAC code, or in the CST mapping
        the target torque 0x6071 in per mille of the drive's rated torque (from the
        handler's amplifier voltage, else the DAC code's), then the controlword and the
        cycle counter if mapped."""
        command: int = dac_counts
        if self.sensor_mapping == "cst":
            rated = self.rated_torque_Nm
            if volts is None:
                volts = self.config.dac.to_volts(dac_counts)
            command = torque_command_per_mille(volts, self._torque_per_volt, rated) if rated else 0
        values = [0] * len(self._command.signal_names)
        for position, value in zip(
            self._command_picks, (command, controlword, self._cycle & 0xFF), strict=False
        ):
            values[position] = value
        return self._command.encode(*values)

    def _on_statusword_frame(self, msg: can.Message) -> None:
        if msg.is_remote_frame or len(msg.data) != self._status.length:
            self.diagnostics.malformed_frames += 1
            return
        if self._phase not in _COMMANDING or not self.services.pdo_allowed:
            self.diagnostics.pdos_ignored += 1
            return
        self.diagnostics.statusword_frames += 1
        (statusword,) = self._status.decode(msg.data)
        self._on_statusword(int(statusword))

    def _on_sdo_response(self, msg: can.Message) -> None:
        """Answer to the statusword read (expedited upload, CiA 301 §7.2.4.3.6)."""
        result = self.sdo.on_response(msg)
        if result is None:
            return
        conf = self.configurator
        if conf is not None and conf.busy and self._phase is _WAIT_BOOT:
            conf.on_result(result)
            if conf.error is not None:
                self.boot_error = conf.error
                self._enter_safe(conf.error)
            elif conf.done:
                self.diagnostics.dcf_writes = len(conf.writes)
                self._after_configuration()
            return
        if self._rated_requested and self.rated_torque_Nm is None and self._phase is _WAIT_BOOT:
            self._on_rated_torque(result)
            return
        if not result.ok:
            self.diagnostics.sdo_aborts += 1
        elif len(result.data) >= 2:
            self.diagnostics.statusword_sdo_answers += 1
            if self._phase in _COMMANDING:
                self._on_statusword(int.from_bytes(result.data[:2], "little"))

    def _on_statusword(self, statusword: int) -> None:
        self._quiet_cycles = 0
        store_value(self.services, 0x2011, 0, statusword)
        if not self.walk.on_statusword(statusword):
            self.diagnostics.invalid_statuswords += 1
            return
        self._sequence()

    # ---------------------------------------------------------------- sequencer

    def _on_controlword(self, controlword: int) -> None:
        store_value(self.services, self._controlword_index, 0, controlword)

    def _sequence(self) -> None:
        """The CiA 402 walk: the next controlword (or phase) for the drive's state."""
        phase = self._phase
        walk = self.walk
        if phase is Phase.OPERATIONAL:
            step = walk.in_operation()
        elif phase is Phase.STARTING:
            step = walk.up()
        elif phase is Phase.STOPPING:
            step = walk.down()
        else:
            return
        self.diagnostics.fault_resets = walk.fault_resets
        self._take(step)

    def _take(self, step: WalkStep) -> None:
        action = step.action
        if action == "walk":
            return
        if action == "operational":
            self._enter_operational()
        elif action == "restart":
            self._set_phase(Phase.STARTING, step.reason)
            self._sequence()
        elif action == "stopped":
            self._finish_stop(step.reason)
        else:
            self._enter_safe(step.reason)

    def _drive_seen(self) -> None:
        """The drive is up: configure it from its DCF first (if any), then start it."""
        conf = self.configurator
        if conf is None or conf.done:
            self._after_configuration()
        elif not conf.started:
            self._configure_deadline = self._now + self.WALK_TIMEOUT_S
            conf.start()
            if conf.done:  # an empty DCF
                self._after_configuration()
        elif conf.busy and self._now > self._configure_deadline:
            self._enter_safe(
                f"drive (node {self.drive_node_id}) did not answer the DCF configuration "
                f"within {_seconds(self.WALK_TIMEOUT_S)} s "
                f"({conf.position} of {len(conf.writes)} writes done)"
            )

    def _after_configuration(self) -> None:
        """In the CiA 402 CST mapping, read the drive's motor rated torque 0x6076 by SDO
        first (0x6071 and 0x6077 are per mille of it); then start the drive."""
        if self.sensor_mapping != "cst" or self.rated_torque_Nm is not None:
            self._start_drive()
        elif not self._rated_requested:
            self._rated_requested = True
            self._configure_deadline = self._now + self.WALK_TIMEOUT_S
            self.sdo.upload(self._rated_index, 0)
        elif self._now > self._configure_deadline:
            self.boot_error = (
                f"drive (node {self.drive_node_id}) did not answer the read of its motor "
                f"rated torque 0x{self._rated_index:04X} within {_seconds(self.WALK_TIMEOUT_S)} s"
            )
            self._enter_safe(self.boot_error)

    def _on_rated_torque(self, result: Any) -> None:
        """The answer to the 0x6076 read: the CST sensor source and command scale."""
        what = f"drive (node {self.drive_node_id}) motor rated torque 0x{self._rated_index:04X}"
        value = int.from_bytes(bytes(result.data[:4]).ljust(4, b"\0"), "little") if result.ok else 0
        if not result.ok or value <= 0:
            code = result.abort or 0
            self.boot_error = (
                f"{what}: read aborted 0x{code:08X} ({abort_text(code)})"
                if not result.ok
                else f"{what} is {value} mNm: the CST mapping needs a rated torque > 0"
            )
            self._enter_safe(self.boot_error)
            return
        self.rated_torque_Nm = value * 1e-3
        if self._own_isr:
            cast(InterruptHandler, self.isr).use_cst_source(self.rated_torque_Nm)
        self._start_drive()

    def _start_drive(self) -> None:
        """NMT start of the drive, controller OPERATIONAL, walk from "shutdown"."""
        drive = self.drive_node_id
        boot = self.services.nmt.boot_times.get(drive)
        self.diagnostics.boot_time_s = self._now if boot is None else boot
        how = "boot-up" if boot is not None else "heartbeat (booted earlier)"
        self.services.nmt.command(NmtCommand.START, drive)
        self._enter_nmt(NmtState.OPERATIONAL)
        self.walk.restart()
        self._nmt_start_syncs = self.diagnostics.syncs_sent
        self._set_phase(Phase.STARTING, f"{how} of drive (node {drive}): NMT start")
        # Event-driven PDOs are sent on change only: read the present state once.
        self._read_statusword()

    def _enter_operational(self) -> None:
        d = self.diagnostics
        self.walk.set_controlword(CONTROLWORD_ENABLE_OPERATION)
        if d.operational_at_s is None:
            d.operational_at_s = self._now
            d.startup_cycles = d.syncs_sent - self._nmt_start_syncs
        self._sensor_seen = True
        self._missing_sensor = 0
        self._set_phase(Phase.OPERATIONAL, "drive reports OPERATION ENABLED")

    def _finish_stop(self, reason: str) -> None:
        self.services.nmt.command(NmtCommand.ENTER_PRE_OPERATIONAL, self.drive_node_id)
        self._set_phase(Phase.STOPPED, f"{reason}; drive NMT pre-operational")
        self._enter_nmt(NmtState.PRE_OPERATIONAL)

    def _walk_watchdog(self) -> None:
        """At each SYNC of a walk: SDO read of a missing statusword, walk timeout."""
        self._phase_cycles += 1
        self._quiet_cycles += 1
        if self._phase_cycles >= self._walk_timeout_cycles:
            what = f"within {_seconds(self.WALK_TIMEOUT_S)} s ({self.walk.state_text()})"
            if self._phase is Phase.STARTING:
                self._enter_safe(
                    f"drive (node {self.drive_node_id}) did not reach OPERATION ENABLED {what}"
                )
            else:
                self.diagnostics.stop_timeouts += 1
                self._finish_stop(f"drive did not confirm the stop {what}")
            return
        if self._quiet_cycles >= self._statusword_timeout_cycles:
            self._quiet_cycles = 0
            self.diagnostics.statusword_timeouts += 1
            if self._phase is Phase.STARTING:
                self.services.nmt.command(NmtCommand.START, self.drive_node_id)
            self._read_statusword()

    def _read_statusword(self) -> None:
        """SDO upload of the drive's statusword (CiA 301 §7.2.4.3.5), answered later."""
        self.sdo.upload(self._drive_statusword_index, 0)
        self.diagnostics.statusword_sdo_reads += 1

    def _sensor_hold_ok(self) -> bool:
        """Sensor hold in "operational": False (and "safe") after ``sensor_hold_cycles``
        SYNCs in a row without a sensor frame."""
        if self._sensor_seen:
            self._missing_sensor = 0
            return True
        self._missing_sensor += 1
        self.isr.sample_missed()
        d = self.diagnostics
        d.sensor_frames_missed += 1
        d.sensor_hold_longest = max(d.sensor_hold_longest, self._missing_sensor)
        if self._missing_sensor < self.sensor_hold_cycles:
            return True
        n = self._missing_sensor
        self._enter_safe(
            f"no sensor frame from drive (node {self.drive_node_id}) for {n} SYNCs",
            EmcyCode.RPDO_TIMEOUT,
            bytes((self.drive_node_id, min(n, 255))),
        )
        return False

    # ------------------------------------------------------------ phases, faults

    def _set_phase(self, phase: Phase, reason: str) -> None:
        if phase is _OPERATIONAL:
            # the listing's start-up pause belongs to the firmware's own handler
            self._settle_left = self.config.startup_settle_cycles if self._own_isr else 0
        self._phase = phase
        self._phase_cycles = 0
        self._quiet_cycles = 0
        self.diagnostics.phase_history.append(PhaseChange(self._now, phase, reason))

    def _enter_nmt(self, state: NmtState) -> None:
        """The controller changes its own NMT state (not a command from another master)."""
        if self.services.state is NmtState.INITIALISING or self.services.state is state:
            return
        self._own_nmt = True
        try:
            self.services.enter_state(state)
        finally:
            self._own_nmt = False

    def _enter_safe(self, reason: str, emcy: int | None = None, manufacturer: bytes = b"") -> None:
        """Stop commanding the drive for good (module docstring, phase "safe")."""
        if self._phase is Phase.SAFE:
            return
        if emcy is not None:
            self.services.emcy.raise_error(emcy, manufacturer=manufacturer)
        if self._phase in _COMMANDING and self.services.state is NmtState.OPERATIONAL:
            self.services.nmt.command(NmtCommand.ENTER_PRE_OPERATIONAL, self.drive_node_id)
        self.diagnostics.safe_reason = reason
        self._set_phase(Phase.SAFE, reason)
        if self.services.state is NmtState.OPERATIONAL:
            self._enter_nmt(NmtState.PRE_OPERATIONAL)
        self.diagnostics.emcy_sent = self.services.emcy.sent

    def _on_boot(self, node_id: int) -> None:
        if node_id != self.drive_node_id:
            return
        if self._phase is Phase.WAIT_BOOT and self.services.state is not NmtState.INITIALISING:
            self._drive_seen()
        elif self._phase in _COMMANDING:
            self._enter_safe(
                f"drive (node {node_id}) sent a boot-up while {self._phase}: it was reset"
            )

    def _on_heartbeat_lost(self, node_id: int) -> None:
        if node_id != self.drive_node_id:
            return
        monitor = self.services.heartbeat_consumer.monitored[node_id]
        d = self.diagnostics
        d.heartbeat_losses += 1
        d.heartbeat_lost_at_s = monitor.lost_at
        if self._phase not in _FINAL:
            self._enter_safe(
                f"heartbeat of drive (node {node_id}) lost: none for "
                f"{monitor.timeout_s * 1e3:g} ms, detected at {monitor.lost_at:.3f} s"
            )

    def _on_nmt_state(self, old: NmtState, new: NmtState) -> None:
        """NMT commands from another master that take the controller out of service."""
        if self._own_nmt or self._phase in _FINAL or new is NmtState.INITIALISING:
            return
        monitor = self.services.heartbeat_consumer.monitored.get(self.drive_node_id)
        if monitor is not None and monitor.status == "lost" and monitor.lost_at == self._now:
            return  # 0x1029 error behaviour on heartbeat loss: _on_heartbeat_lost follows
        if new is NmtState.STOPPED or (old is NmtState.OPERATIONAL and self._phase in _COMMANDING):
            self._enter_safe(f"NMT {new.name} commanded by another master")

    def _on_reset(self, kind: ResetKind) -> None:
        """NMT reset of the controller by another master: OD values back to what the node
        runs (the EDS defaults would not be), then "safe"."""
        self._store_comm_values()
        self._sync.configure(overflow=self.sync_overflow, cob_id=self._sync.cob_id)
        if kind == "node":
            self.parameters.store(self.parameters.pending or self.config)
        self._store_control_pdo_validity()
        if self._phase not in _FINAL:
            self._enter_safe(f"NMT reset ({kind}) of the controller by another master")

    # ---------------------------------------------------------------- OD values

    # ---------------------------------------------------------------- OD values

    def _store_comm_values(self) -> None:
        """0x1006 = the sample period (µs) and 0x1019 = the SYNC counter overflow."""
        store_value(self.services, 0x1006, 0, self._period_us)
        store_value(self.services, 0x1019, 0, self.sync_overflow)

    def _store_control_pdo_validity(self) -> None:
        cob = self.services.read(0x1801, 1)
        cob = cob & ~0x80000000 if self.control_pdo_valid else cob | 0x80000000
        store_value(self.services, 0x1801, 1, cob)

    def _check_cycle_period(self, value: int) -> int | None:
        """0x1006 holds the running period: the runner paces the cycle.  Refusing 0 also
        keeps 0x1019 fixed (CiA 301: writable only while 0x1006 is 0), which the drive's
        SYNC consumer is configured with."""
        return None if value == self._period_us else ABORT_DEVICE_STATE

    # ---------------------------------------------------------- live parameters

    def _on_parameter(self, _: Parameter) -> None:
        self.diagnostics.parameter_writes += 1

    def _apply_pending(self) -> None:
        """Swap the changed stages in at the cycle boundary (module docstring)."""
        params = self.parameters
        new = params.take_pending()
        if new is None:
            return
        old = self.config
        prebuilt = None
        if new.control != old.control:
            prebuilt, params.prebuilt_control = params.prebuilt_control, None
        self.config = new
        done = apply_config(self.isr, old, new, prebuilt)
        d = self.diagnostics
        if done.filter_restarted:
            d.filter_restarts += 1
        if done.control_rebuilt:
            d.control_rebuilds += 1
        if done.control_changed:
            self.control_pdo_valid = new.control.active
            self._store_control_pdo_validity()
        d.parameter_updates_applied += 1
