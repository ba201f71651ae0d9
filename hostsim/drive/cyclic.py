"""The drive's process data: PDOs configured from the object dictionary, commands in,
sensors out, the plant stepped once per SYNC.

This is the drive's 1 kHz path, kept apart from the node's slower CANopen duties (NMT,
heartbeat, SDO) so that what happens in a cycle reads in one place: on SYNC k, step the
plant, sample it, send, activate the command latched in cycle k-1. It also keeps the
deadlines of the process data (RPDO event timers, the SYNC timeout, the command hold),
whose expiry the node answers (:meth:`DriveNode.react_to_connection_loss`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import can

from hdhil.can.node import pdo_cob_id
from hdhil.canopen.cia402 import CONTROLWORD_OBJECT, State
from hdhil.canopen.od import index_of, variable
from hdhil.canopen.pdo import (
    MAX_PDOS,
    PdoLayout,
    Tpdo,
    decode_to_od,
    encode_from_od,
    read_layout,
)
from hdhil.canopen.services import TIME_EPSILON, EmcyCode, NmtState, SyncMonitor
from hdhil.dbc import codec
from hdhil.hostsim.plant_model import SensorCounts, Truth

if TYPE_CHECKING:
    from hdhil.canopen.cia402 import DriveStateMachine
    from hdhil.hostsim.drive.node import DriveNode

__all__ = [
    "ADC_CHANNELS",
    "OD_ADC_COUNTS",
    "OD_DAC_COMMAND",
    "OD_ENCODER",
    "OD_JOINT_TORQUE_SENSOR",
    "OD_SYNC_PERIOD",
    "OD_SYNC_WINDOW",
    "CyclicIO",
]

OD_ADC_COUNTS = 0x2100
OD_ENCODER = 0x2101
#: The joint-torque sensor: the torque channel's analog input in mV (drive.eds, 0x2102).
OD_JOINT_TORQUE_SENSOR = 0x2102
OD_DAC_COMMAND = 0x2200
OD_SYNC_PERIOD = 0x1006
OD_SYNC_WINDOW = 0x1007
#: ADC channels in DRIVE_TPDO1 order; the number is the 0x2100 sub-index and the EMCY
#: 0x7300 manufacturer byte 0.
ADC_CHANNELS = (1, 2, 3)
#: EMCY 0x8100 manufacturer byte 0 for a SYNC timeout (CANopenNode's "SYNC time out").
SYNC_TIMEOUT_INFO = b"\x01"

# What the per-cycle code tests for, as module globals: an attribute of an Enum class
# (``NmtState.OPERATIONAL``) is looked up through ``EnumType.__getattr__``'s slow path in
# Python 3.11, several times slower than a global.
_INITIALISING = NmtState.INITIALISING
_OPERATIONAL = NmtState.OPERATIONAL
_OPERATION_ENABLED = State.OPERATION_ENABLED
_RPDO_TIMEOUT = EmcyCode.RPDO_TIMEOUT


class CyclicIO:
    """The drive's PDOs and its SYNC cycle.

    **Timing** (docs/design.md, "Timing semantics"): on SYNC k the drive integrates the
    plant from t(k-1) to t(k) holding the amplifier input set at SYNC k-1 (zero-order
    hold), samples its sensors at t(k), sends the sensor TPDO and the ground-truth frames,
    then activates the command latched during cycle k-1 (CiA 301 synchronous RPDO,
    "actuate at next SYNC").  With ``actuation="immediate"`` a command is active as soon
    as it is received instead.  For a command computed from the sample at t(k):
    ``next-sync`` (default, transmission type 1) applies it from t(k+1), one full period
    of transport delay plus the zero-order hold; ``immediate`` from t(k), the [Taghirad97]
    DSP case (``write_dac0`` at the end of the interrupt) with the compute and bus
    latency neglected.

    The plant is physics: it advances on **every** SYNC in every NMT state (the network
    being pre-operational does not stop the motor), with the amplifier input that the CiA
    402 state allows (0 V unless OPERATION ENABLED), and the sensors are sampled every
    SYNC too (the noise sequence of a seed does not depend on the NMT history).  Only
    publishing is gated by NMT.  The plant clock is the SYNC counter: a SYNC that follows
    a counter jump (missed SYNCs, CiA 301 SYNC counter 1..overflow) advances the plant by
    the missed periods as well, so it stays in step with the SYNC producer; a counter
    that restarts at 1 (the producer restarted) is not a jump.  The very first SYNC only
    marks t(0).

    When the amplifier input changes: at each SYNC, after the plant step and the sample,
    the drive sets the input for the step that starts there from the CiA 402 state at
    that moment.  A state change between two SYNCs (a tick that detects a heartbeat loss,
    an NMT command, an SDO write) therefore takes effect at the next SYNC, at most one
    period later; in lockstep, where the tick at t(k) runs just before SYNC k, a fault
    detected by that tick removes the torque from exactly t(k).  With immediate actuation
    a received command sets the input of the running step at once (controlword and DAC
    alike).

    **Statusword** (0x6041) goes out in ``DRIVE_TPDO2`` (COB-ID 0x282, TPDO2
    0x1801/0x1A01), event-driven (transmission type 255): when it differs from the last
    one sent, and once on entering OPERATIONAL, at most once per inhibit time (0x1801 sub
    3, 10 x 100 us = 1 ms): a change inside the inhibit time is sent at the first tick or
    frame after it.  Bits 7 (warning: a sensor ADC channel saturated) and 11 (internal
    limit active: the amplifier at its current limit) are set by this node.  Any other
    mapping written to 0x1400-0x1A03 is read back from the object dictionary
    (:meth:`load_pdos`), its objects decoded with their OD data types.

    **Command hold**: while OPERATION ENABLED, a SYNC cycle in which no DRIVE_RPDO1
    arrived keeps the previous command (zero-order hold).  At the SYNC that ends the
    ``command_hold_cycles``-th consecutive cycle without one, the drive faults with EMCY
    0x8250 "RPDO timeout" (manufacturer byte 0 = the number of cycles) and 0x603F =
    0x8250, in place of activating that cycle's command: with synchronous actuation the
    last command stays active for ``command_hold_cycles`` periods in all.  A fault rather
    than a quick stop, because a lost command stream is a communication error the
    controller must acknowledge (fault reset), as for a lost heartbeat.  The next
    DRIVE_RPDO1 clears the EMCY (0x0000).  SYNC counter jumps are counted as missed SYNCs,
    commands arriving more than one period after their SYNC as late commands
    (:class:`hdhil.canopen.services.SyncMonitor`).  RPDO event timers (0x14xx:5) and the
    SYNC timeout (1.5 x 0x1006, as CANopenNode does) raise EMCY 0x8250 / 0x8100 and the
    abort-connection reaction (0x6007).

    **Sensor EMCY** (once on the rising edge, EMCY 0x0000 when the condition goes away):
    0x7300 "sensor error" when an ADC channel sits at a code limit (manufacturer byte 0 =
    the channel: 1 torque, 2 tacho, 3 current, the sub-indices of 0x2100); 0x2310
    "continuous over current" when the amplifier's current command sits at its current
    limit.
    """

    def __init__(self, node: DriveNode) -> None:
        self.node = node
        self.bus = node.bus
        # The node's parts that live as long as it does, held here for the 1 kHz path.
        self._diagnostics = node.diagnostics
        self._emulator = node.emulator
        self._cst = node.cst
        self._truth = node.truth_publisher
        self.plant = plant = node.plant
        cfg = node.config
        services = self.services = node.services
        self._emcy = services.emcy
        self._Ts = cfg.sample_period_s
        self.next_sync = cfg.actuation == "next-sync"
        self._dac = plant.dac
        self._adc = adc = plant.adc
        self._adc_min, self._adc_max = adc.code_min, adc.code_max
        self._hold_limit = cfg.command_hold_cycles
        # at the limit from here on
        self._current_limit_Nm = plant.max_motor_torque_Nm * (1 - 1e-12)

        # Command path: latched by DRIVE_RPDO1, active from the activation point.
        self.active_V = 0.0
        self._latched_V = 0.0
        self._pending_cw: int | None = None
        self._dac_counts = 0  # the latest DAC command (kept when a remap leaves it out)
        #: The amplifier input over the plant step in progress.
        self.step_V = 0.0
        self._command_in_cycle = False
        self._silent_cycles = 0
        self._plant_started = False
        #: The latest sample, as DRIVE_TPDO1 carries it.
        self.sample: SensorCounts = (0, 0, 0, 0)
        self._saturated: set[int] = set()
        self._at_current_limit = False

        # Codecs are used by signal name: each layout is checked against the names this
        # node packs and unpacks (a DBC with reordered signals fails here, loudly).
        self._sync = codec("control", "SYNC").expect("sync_counter")
        self._sensor = codec("control", "DRIVE_TPDO1").expect(
            "ADC_torque", "ADC_tacho", "ADC_current", "ENC_count"
        )
        self._command = codec("control", "DRIVE_RPDO1").expect("DAC_cmd", "controlword", "cycle")
        self._status = codec("control", "DRIVE_TPDO2").expect("statusword")
        # PDO defaults come from the object dictionary (RPDO1 0x1400, TPDO1/2 0x1800/1):
        # their COB-IDs (from the node-ID, $NODEID+0x180 etc. in the EDS), their layouts
        # checked against the DBC's (the DBC describes the default mapping); the live
        # PDOs are read from the OD's present values (load_pdos).
        od = services.od
        self._command = self._command.at(pdo_cob_id(od, 0x1400, self._command))
        self._sensor = self._sensor.at(pdo_cob_id(od, 0x1800, self._sensor))
        self._status = self._status.at(pdo_cob_id(od, 0x1801, self._status))
        self._sensor_msg = _message(self._sensor.frame_id, self._sensor.length)
        self._od_controlword = index_of(services.od, CONTROLWORD_OBJECT)
        node.handle(self._sync.frame_id, self.on_sync)
        services.on_boot(self._on_remote_boot)
        # RPDO1's transmission type is the actuation setting: synchronous (type 1, taken
        # over at the next SYNC) or event-driven (255, taken over on receipt).
        services.set_power_on_value(0x1400, 2, 1 if self.next_sync else 255)
        defaults = lambda index, sub: variable(od, index, sub).default  # noqa: E731
        self._default_layouts = {
            (kind, n): read_layout(od, defaults, kind, n)
            for kind in ("rpdo", "tpdo")
            for n in (1, 2)
        }
        self._tpdos: list[Tpdo] = []
        self._event_tpdos: list[Tpdo] = []
        self._rpdo_handlers: dict[int, PdoLayout] = {}
        self._rpdo_deadlines: dict[int, float] = {}
        self._fast_sensor = True
        #: The synchronous TPDOs besides TPDO1 (sent on SYNC on the fast path too).
        self._other_sync_tpdos: list[Tpdo] = []
        for index in [*range(0x1400, 0x1404), *range(0x1600, 0x1604),
                      *range(0x1800, 0x1804), *range(0x1A00, 0x1A04)]:  # fmt: skip
            obj = od.get(index)
            for sub in getattr(obj, "subindices", {}):
                if variable(od, index, sub) is not None and variable(od, index, sub).writable:
                    services.on_write(index, sub, self._pdo_changed)
        for index in (OD_SYNC_PERIOD, OD_SYNC_WINDOW):
            if variable(od, index, 0) is not None:
                services.on_write(index, 0, self._pdo_changed)
        self._statusword: int | None = None  # the one _statusword_data encodes
        self._statusword_data = b""
        self._sync_monitor = self._new_sync_monitor()
        self._last_sync_at: float | None = None
        self._sync_lost = False

    def live_values(self) -> dict[tuple[int, int], Callable[[], int]]:
        """0x2100 ADC counts and 0x2101 encoder count of the latest sample, and 0x2102 the
        joint-torque sensor (:meth:`joint_torque_sensor_mV`)."""
        live: dict[tuple[int, int], Callable[[], int]] = {(OD_ENCODER, 0): lambda: self.sample[3]}
        for i, channel in enumerate(ADC_CHANNELS):
            live[(OD_ADC_COUNTS, channel)] = lambda i=i: self.sample[i]
        live[(OD_JOINT_TORQUE_SENSOR, 0)] = self.joint_torque_sensor_mV
        return live

    def joint_torque_sensor_mV(self) -> int:
        """0x2102: the strain-gauge bridge's amplified output as the torque channel of the
        latest sample reads it (0x2100 sub 1, the same ADC code), in mV (INTEGER16).  The
        joint torque is the sensor's calibration of it (drive.eds: volt2Nm x (mV / 1000 -
        offset)); the drive applies none, as a drive's analog input does not."""
        value = round(self.sample[0] * self._adc.lsb_V * 1e3)
        return min(max(value, -32768), 32767)

    # ------------------------------------------------------------------ SYNC

    def on_sync(self, msg: can.Message) -> None:
        """SYNC k: step the plant to t(k), sample, send, activate the latched command."""
        node = self.node
        d = self._diagnostics
        if msg.is_remote_frame:  # a remote request on 0x080 is not a SYNC (CiA 301)
            d.malformed_frames += 1
            return
        d.syncs += 1
        now = node.now
        monitor = self._sync_monitor
        errors = monitor.length_errors
        missed = monitor.accept(msg, now)
        d.sync_errors += monitor.length_errors - errors
        if missed is None:
            # A duplicated or reordered SYNC (its counter repeats or lies behind the last
            # one): no time passed for it, so the plant does not move and nothing is sent.
            d.duplicate_syncs = monitor.duplicates
            d.stale_syncs = monitor.stale
            return
        d.missed_syncs += missed
        self._last_sync_at = now
        services = self.services
        if self._sync_lost:
            self._sync_lost = False
            services.emcy.clear(EmcyCode.COMMUNICATION, SYNC_TIMEOUT_INFO)

        emulator = self._emulator
        if emulator.pending:
            emulator.apply()
        plant = self.plant
        machine = node.machine
        dt = (1 + missed) * self._Ts
        if self._plant_started:
            try:
                plant.advance(self.step_V, dt)
            except ArithmeticError as exc:  # NonFiniteStateError, or a plug-in's overflow
                self._plant_failed(exc)
            machine.step(dt)
        else:
            self._plant_started = True
        sample = self.sample = plant.sample()
        self._cst.update_position(sample[3], dt)
        if services.state is not _INITIALISING:
            truth = plant.truth()
            self._check_sensors(sample, truth)
        if services.state is _OPERATIONAL:
            if self._fast_sensor:  # TPDO1 as the DBC describes it: every SYNC
                msg = self._sensor_msg
                msg.data = self._sensor.encode(*sample)
                self.bus.send(msg)
                d.sensor_frames += 1
                for tpdo in self._other_sync_tpdos:  # TPDO2-4 mapped synchronous
                    tpdo.on_sync(now)
            else:
                for tpdo in self._tpdos:
                    if tpdo.layout.synchronous:
                        tpdo.on_sync(now)
            publisher = self._truth
            if publisher.bus is not None:
                publisher.publish(truth)
        # Command hold: count SYNC cycles without a command while OPERATION ENABLED
        # (inline: it runs every SYNC).
        if self._command_in_cycle:
            self._command_in_cycle = False
            self._silent_cycles = 0
        elif machine.state is not _OPERATION_ENABLED or not self._hold_limit:
            self._silent_cycles = 0
        else:
            self._command_hold_missed(machine)
        if self.next_sync:
            self.active_V = self._latched_V
            if self._pending_cw is not None:
                machine.apply_controlword(self._pending_cw)
                self._pending_cw = None
        self.step_V = machine.torque_output(self.active_V)
        if services.state is _OPERATIONAL:  # flush_statusword, inline
            for tpdo in self._event_tpdos:
                tpdo.flush(now)

    def _plant_failed(self, exc: ArithmeticError) -> None:
        """The plant could not be advanced (its state went non-finite): the emulated
        drive's own software failed, so it faults (EMCY 0x6100, a fault that persists:
        no fault reset brings the plant back) and keeps the plant at its last finite
        state.  The first failure is kept in :attr:`DriveDiagnostics.plant_failure`."""
        node = self.node
        d = self._diagnostics
        if d.plant_failure is None:
            d.plant_failure = str(exc) or type(exc).__name__
            node.emcy(EmcyCode.INTERNAL_SOFTWARE)
        node.machine.fault(EmcyCode.INTERNAL_SOFTWARE, persists=True)

    def _command_hold_missed(self, machine: DriveStateMachine) -> None:
        """A SYNC cycle without a command while OPERATION ENABLED: fault at the limit."""
        self._silent_cycles += 1
        if self._silent_cycles >= self._hold_limit:
            node = self.node
            node.diagnostics.command_timeouts += 1
            node.emcy(EmcyCode.RPDO_TIMEOUT, bytes((min(self._silent_cycles, 255),)))
            machine.fault(EmcyCode.RPDO_TIMEOUT)
            self._silent_cycles = 0

    def _check_sensors(self, sample: SensorCounts, truth: Truth) -> None:
        """EMCY 0x7300 per saturated ADC channel, 0x2310 at the current limit (edges)."""
        machine = self.node.machine
        active = self._saturated
        lo, hi = self._adc_min, self._adc_max
        # The usual cycle, no channel at a limit before or now, tested in one expression.
        if active or not (lo < sample[0] < hi and lo < sample[1] < hi and lo < sample[2] < hi):
            self._check_saturation(sample)
        machine.warning = bool(active)
        at_limit = abs(truth.tau_m_cmd_Nm) >= self._current_limit_Nm
        if at_limit != self._at_current_limit:
            node = self.node
            self._at_current_limit = at_limit
            machine.internal_limit_active = at_limit
            if at_limit:
                node.diagnostics.overcurrents += 1
                node.emcy(EmcyCode.CONTINUOUS_OVER_CURRENT)
            else:
                self.services.emcy.clear(EmcyCode.CONTINUOUS_OVER_CURRENT)

    def _check_saturation(self, sample: SensorCounts) -> None:
        node = self.node
        saturated = self._adc.saturated
        active = self._saturated
        for channel, counts in zip(ADC_CHANNELS, sample, strict=False):
            if saturated(counts):
                if channel not in active:
                    active.add(channel)
                    node.diagnostics.adc_saturations += 1
                    node.emcy(EmcyCode.SENSOR, bytes((channel,)))
            elif channel in active:
                active.discard(channel)
                self.services.emcy.clear(EmcyCode.SENSOR, bytes((channel,)))

    # ------------------------------------------------------------------ command

    def _on_rpdo(self, msg: can.Message) -> None:
        """An RPDO in a mapping other than the DBC's: each mapped object is decoded with
        its OD data type; the DAC object and the controlword act as in the default
        mapping, other objects are written into the OD (their write callbacks apply them)."""
        d = self.node.diagnostics
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
        od_node = self.services.node
        cst = self.node.cst
        for index, sub, data in decode_to_od(layout, msg.data):
            if index == OD_DAC_COMMAND:
                dac_counts = int.from_bytes(data, "little", signed=True)
            elif index == cst.od_target_torque:
                dac_counts = cst.torque_to_counts(int.from_bytes(data, "little", signed=True))
            elif index == self._od_controlword:
                controlword = int.from_bytes(data, "little")
            else:
                try:
                    od_node.set_data(index, sub, data)
                except Exception:
                    d.malformed_frames += 1
        if dac_counts is None:
            dac_counts = self._dac_counts
        if controlword is None:
            controlword = self.node.machine.controlword
        self._command_values(dac_counts, controlword)
        self.flush_statusword()  # the objects written above may be in an event TPDO

    def _rpdo_received(self, layout: PdoLayout) -> None:
        if layout.event_s > 0:
            self._rpdo_deadlines[layout.number] = self.node.now + layout.event_s
        if self.services.emcy.error_active(_RPDO_TIMEOUT):
            self.services.emcy.clear(_RPDO_TIMEOUT)

    def _on_command(self, msg: can.Message) -> None:
        if self.services.state is not _OPERATIONAL:
            self.node.diagnostics.pdos_ignored += 1
            return
        if msg.is_remote_frame or len(msg.data) != self._command.length:
            self.node.diagnostics.malformed_frames += 1
            return
        dac_counts, controlword, _cycle = self._command.decode(msg.data)
        if self._rpdo1_event_s:
            self._rpdo_received(self._rpdo_handlers[msg.arbitration_id])
        self._command_values(dac_counts, controlword)

    def _command_values(self, dac_counts: int, controlword: int) -> None:
        node = self.node
        d = node.diagnostics
        now = node.now
        window = self._sync_window_s
        if (
            window
            and self._last_sync_at is not None
            and now - self._last_sync_at > window + TIME_EPSILON
            and self.next_sync
        ):
            d.late_commands += 1  # CiA 301 §7.5.2.8: outside the synchronous window
            d.pdos_ignored += 1
            return
        self._dac_counts = int(dac_counts)
        d.commands += 1
        if not self._sync_monitor.on_command(now):
            d.late_commands += 1
        self._command_in_cycle = True
        self._silent_cycles = 0
        emcy = self._emcy
        if emcy.active and emcy.error_active(_RPDO_TIMEOUT):  # no call while none is active
            emcy.clear(_RPDO_TIMEOUT)
        self._latched_V = self._dac.to_volts(dac_counts)
        if self.next_sync:
            # Latched only: nothing an event TPDO carries changed, and the last flush was
            # at this same ``now`` (the node's tick or a frame's handling), so none is due.
            self._pending_cw = int(controlword)
        else:
            machine = node.machine
            self.active_V = self._latched_V
            machine.apply_controlword(int(controlword))
            self.step_V = machine.torque_output(self.active_V)
            self.flush_statusword()

    def drop_command(self) -> None:
        """Forget the latched and the active command (a lost connection)."""
        self._pending_cw = None
        self._latched_V = self.active_V = 0.0

    # ------------------------------------------------------------------ event TPDOs

    def flush_statusword(self) -> None:
        """Event-driven TPDOs (the statusword's DRIVE_TPDO2 by default): sent when their
        data changed (or once after entering OPERATIONAL) and the inhibit time since the
        last one has passed, and again when the event timer expires (CiA 301 §7.2.2.5)."""
        if self.services.state is not _OPERATIONAL:
            return
        now = self.node.now
        for tpdo in self._event_tpdos:
            tpdo.flush(now)

    # ------------------------------------------------------------------ PDO configuration

    def _pdo_changed(self, _: object) -> None:
        self.load_pdos()

    def load_pdos(self) -> None:
        """(Re)build the PDOs from the OD's present communication and mapping parameters
        (at start, on every accepted write to them, after an NMT reset)."""
        services = self.services
        node = self.node
        od, read = services.od, services.read
        for cob in self._rpdo_handlers:
            node.unhandle(cob)
        self._rpdo_handlers = {}
        self._rpdo_deadlines = {}
        self._rpdo1_event_s = 0.0
        for n in range(1, MAX_PDOS + 1):
            layout = read_layout(od, read, "rpdo", n)
            if layout is None or not layout.valid:
                continue
            if n == 1:
                self.next_sync = layout.synchronous
                self._rpdo1_event_s = layout.event_s
            self._rpdo_handlers[layout.cob_id] = layout
            fast = _same_mapping(layout, self._default_layouts[("rpdo", 1)])
            node.handle(layout.cob_id, self._on_command if fast else self._on_rpdo)
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
        self._other_sync_tpdos = [t for t in tpdos[1:] if t.layout.valid and t.layout.synchronous]
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
            return lambda: self._sensor.encode(*self.sample)
        if _same_mapping(layout, self._default_layouts[("tpdo", 2)]):
            return self._statusword_payload
        get = self.services.node.get_data
        return lambda: encode_from_od(layout, get)

    def _statusword_payload(self) -> bytes:
        """DRIVE_TPDO2's data: the statusword, encoded again only when it changed (the
        event TPDO asks for it several times a cycle)."""
        statusword = self.node.machine.statusword
        if statusword != self._statusword:
            self._statusword = statusword
            self._statusword_data = self._status.encode(statusword)
        return self._statusword_data

    def _tpdo_sent(self, layout: PdoLayout) -> None:
        d = self.node.diagnostics
        if _same_mapping(layout, self._default_layouts[("tpdo", 1)]):
            d.sensor_frames += 1
        elif _same_mapping(layout, self._default_layouts[("tpdo", 2)]):
            d.statusword_frames += 1

    # ------------------------------------------------------------------ deadlines and NMT

    def check_deadlines(self, now: float) -> None:
        """RPDO event timers (0x14xx:5) and the SYNC timeout (1.5 x 0x1006, as CANopenNode
        does): EMCY 0x8250 / 0x8100 and the abort-connection reaction (0x6007)."""
        node = self.node
        deadlines = self._rpdo_deadlines
        for number, deadline in list(deadlines.items()) if deadlines else ():
            if now > deadline + TIME_EPSILON:
                del self._rpdo_deadlines[number]
                node.diagnostics.rpdo_timeouts += 1
                node.emcy(EmcyCode.RPDO_TIMEOUT, bytes((number,)))
                node.react_to_connection_loss(EmcyCode.RPDO_TIMEOUT)
        period = self._sync_period_s
        if (
            period
            and not self._sync_lost
            and self._last_sync_at is not None
            and now - self._last_sync_at > 1.5 * period + TIME_EPSILON
        ):
            self._sync_lost = True
            node.diagnostics.sync_timeouts += 1
            node.emcy(EmcyCode.COMMUNICATION, SYNC_TIMEOUT_INFO)
            node.react_to_connection_loss(EmcyCode.COMMUNICATION)

    def enter_operational(self) -> None:
        """OPERATIONAL entered: event TPDOs go out once, the deadlines start afresh."""
        for tpdo in self._tpdos:
            tpdo.restart()
        self._rpdo_deadlines = {}
        self._last_sync_at = None
        self._sync_lost = False

    def reset_communication(self) -> None:
        """NMT reset (node or communication): the PDOs as the OD now says, a new SYNC
        monitor."""
        self.load_pdos()  # the OD's communication area is back to its power-on values
        self._sync_monitor = self._new_sync_monitor()

    def reset_application(self) -> None:
        """NMT reset node: no amplifier input, no sensor condition raised."""
        self.step_V = 0.0
        self._saturated.clear()
        self._at_current_limit = False

    def _new_sync_monitor(self) -> SyncMonitor:
        # Counter only: the elapsed time is not trusted to count missed SYNCs, because
        # lockstep runs on a real interface pace SYNC by the host, not by the clock.
        return SyncMonitor(
            period_s=None,
            overflow=self.node.config.sync_overflow,
            command_deadline_s=self._Ts,
        )

    def _on_remote_boot(self, node_id: int) -> None:
        if node_id == self.node.config.controller_node_id:
            self._sync_monitor.last_counter = None  # its SYNC counter restarts at 1


def _message(frame_id: int, length: int) -> can.Message:
    return can.Message(arbitration_id=frame_id, is_extended_id=False, dlc=length, check=False)


def _same_mapping(a: PdoLayout | None, b: PdoLayout | None) -> bool:
    return a is not None and b is not None and a.entries == b.entries
