"""Evaluation against ground truth: the firmware's filter side by side with alternatives.

A :class:`Recording` is what was on the buses, one row per control cycle: the drive's raw
sensor frame, the controller's telemetry and the emulator's truth for the same instant,
built by :class:`RecordingListener` live during a run or from a trace, so both are
evaluated by the same code. :func:`evaluate` scores, over the firmware's samples from the
evaluation start, the raw measurement, the firmware's filtered torque, both Kalman modes
re-run offline through the firmware's own :class:`firmware.isr.TorqueFilterChain`, the
listing's Butterworth low-pass at several cut-offs and a 2x/4x notch bank. Metrics
against the true torque: RMS error (and its share of raw), the error's amplitude at each
ripple harmonic (2x, 4x motor angle; 1x output angle: the residual misalignment) by
demodulation with the true angle, and the lag that best aligns a candidate with the truth
and the gain (the share of the true torque's variation it passes at that lag), where the
true torque varies enough to define them (:class:`_AlignSums`). :func:`evaluation_notes`
says what the table shows: the best candidate, when a low-pass wins, why the firmware's
filter is worse than raw where it is.
"""

from __future__ import annotations

import contextlib
import dataclasses
import heapq
import math
import textwrap
from array import array
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from hdhil.dbc import SYNC_COB_ID, FrameCodec, codec, predefined_cob_id, truth_frame_id
from hdhil.firmware.baselines import ButterworthLowPass, TrackingNotchBank
from hdhil.firmware.config import FirmwareConfig, paper_config, recommended_config
from hdhil.firmware.interrupt import CstSample
from hdhil.firmware.isr import TorqueFilterChain
from hdhil.firmware.stages import CstSource, adc_read, calibrate

#: Recording columns, in order.
#: The truth columns, in the order of :attr:`RecordingListener._truth`.
_TRUTH_COLUMNS = ("T_true", "T_ripple", "theta_motor", "omega_motor", "theta_output")

COLUMNS = (
    "adc_torque", "adc_tacho", "adc_current", "encoder",
    "T_meas_tele", "T_filtered_tele", "velocity_tele",
    "T_true", "T_ripple", "theta_motor", "omega_motor", "theta_output", "missed",
    "torque_actual", "position_actual", "joint_torque_mV",
)  # fmt: skip
#: :attr:`RecordingListener._truth` position -> its column in a row (truth columns are
#: consecutive, in the same order).
_TRUTH_INDEX = {k: COLUMNS.index(name) for k, name in enumerate(_TRUTH_COLUMNS)}


def missed_cycles(previous_s: float | None, now_s: float, sample_period_s: float) -> int:
    """Sample periods without a sensor frame between two sensor frames stamped
    ``previous_s`` and ``now_s``: the cycles in which the firmware ran no interrupt and
    told its filter chain so (:meth:`firmware.isr.InterruptHandler.sample_missed`).  A
    frame is sent once per SYNC, so the gap in periods, rounded, less one; 0 for a
    duplicate (same period) or the first frame.  Rounding tolerates delivery jitter up to
    half a period."""
    if previous_s is None:
        return 0
    return max(0, round((now_s - previous_s) / sample_period_s) - 1)


#: Butterworth cut-offs (Hz) evaluated as baselines.
BUTTERWORTH_CUTOFFS_HZ = (5.0, 10.0, 20.0, 50.0, 100.0)
#: Harmonics scored: (label, source, multiple).
HARMONICS = (("2x motor", "motor", 2.0), ("4x motor", "motor", 4.0), ("1x output", "output", 1.0))
#: Below this motor speed (rad/s) a sample is not used for harmonic amplitudes.
MIN_SPEED_RADPS = 5.0
#: Largest delay searched for the lag (samples).
MAX_LAG_SAMPLES = 60


class Recording:
    """Per-cycle columns of a run (``array('d')``, 8 bytes per value)."""

    def __init__(self, sample_period_s: float) -> None:
        self.sample_period_s = sample_period_s
        self._cols = {name: array("d") for name in COLUMNS}
        #: "raw" (the seed's ADC counts and encoder in ``adc_*``/``encoder``), "cst"
        #: (CiA 402 torque actual and position actual in ``torque_actual`` /
        #: ``position_actual``, ``encoder`` their low 16 bits, the ADC columns NaN) or
        #: "cst-sensor" (those and the joint-torque sensor 0x2102 in ``joint_torque_mV``,
        #: NaN in the other mappings).
        self.sensor_mapping = "raw"
        #: The drive's motor rated torque 0x6076 (Nm) as read by the controller at boot
        #: (its SDO answer in the trace); None in the raw mapping or before it is seen.
        self.rated_torque_Nm: float | None = None

    def __len__(self) -> int:
        return len(self._cols["adc_torque"])

    def column(self, name: str) -> np.ndarray:
        return np.frombuffer(self._cols[name], dtype=np.float64)

    def append_row(self, values: tuple[float, ...]) -> None:
        for col, value in zip(self._cols.values(), values, strict=True):
            col.append(value)

    def drop_first(self, rows: int) -> None:
        """Forget the first ``rows`` rows (a live evaluation's rows already scored)."""
        if rows > 0:
            # New arrays rather than resizing in place: a view of the old ones may live on.
            self._cols = {name: col[rows:] for name, col in self._cols.items()}

    def last(self, column: int) -> float:
        """The last row's value in column number ``column`` (NaN without rows)."""
        col = self._cols[COLUMNS[column]]
        return col[-1] if col else math.nan

    def set_last(self, name: str, value: float) -> None:
        col = self._cols[name]
        if col:
            col[-1] = value

    def operation(self) -> Recording:
        """The samples the firmware ran its interrupt on: from the first to the last row
        its telemetry answered (the drive may be enabled a cycle before the firmware's
        loop starts, and stays enabled through the stop), so sample 0 is the firmware's
        first interrupt, as in ``hdhil run``'s cycle count and the tracking score. The
        whole recording when no row was answered (a trace of firmware without telemetry)."""
        answered = np.flatnonzero(np.isfinite(self.column("T_meas_tele")))
        if answered.size == 0 or (answered[0] == 0 and answered[-1] == len(self) - 1):
            return self
        first, last = int(answered[0]), int(answered[-1]) + 1
        out = Recording(self.sample_period_s)
        out.sensor_mapping = self.sensor_mapping
        out.rated_torque_Nm = self.rated_torque_Nm
        for name, col in self._cols.items():
            out._cols[name] = col[first:last]
        return out


class RecordingListener(can.Listener):
    """Builds a :class:`Recording` from control-bus and truth frames (live or from a trace).

    A row opens at each drive sensor frame (``DRIVE_TPDO1``, sampled at t(k)) with the latest
    truth (sent by the drive at the same SYNC, for the same instant); the controller's
    telemetry that follows fills the row's telemetry columns.  When the trace carries the
    drive's statusword (``DRIVE_TPDO2``), only samples taken while the drive was in CiA 402
    OPERATION ENABLED are recorded: the start-up walk and the stop are not part of the
    experiment.  The firmware's telemetry answering a sensor frame also shows operation
    (its interrupt runs only then), so a lost statusword frame does not delay the first
    sample the replay takes behind the firmware's.

    With ``firmware`` the rows are scored as they come, in chunks (:class:`LiveEvaluation`,
    :meth:`evaluation`), and without ``keep`` the rows scored are forgotten: memory stays
    flat however long the run.

    ``drive_pdos`` (what a trace's sidecar records for a run in a mapping from a DCF,
    :func:`hdhil.canopen.mapping.layouts_to_json`): the drive's PDOs; with the CiA 402
    CST mapping the sensor frame is decoded from the drive's EDS (torque actual 0x6077,
    position actual 0x6064) and the drive's rated torque 0x6076 is taken from the
    controller's SDO read of it at boot, as the firmware did.

    ``drive_node_id``: the drive's CANopen node-ID (its sensor frame, statusword and SDO
    answers at that node's identifiers: the pre-defined connection set, or the COB-IDs
    ``drive_pdos`` records); the controller's telemetry is at ``controller_node_id``'s.
    A joint of a rig (:func:`rig_recordings_from_trace`): ``telemetry_id`` the identifier
    of the controller's telemetry of the joint (its TPDO1 for the first joint a node
    serves, TPDO3 for the second), ``truth_joint_index`` the joint's truth identifiers
    (:func:`hdhil.dbc.truth_frame_id`).
    """

    def __init__(
        self,
        sample_period_s: float,
        drive_pdos: dict[str, Any] | None = None,
        *,
        firmware: FirmwareConfig | None = None,
        skip_s: float = 0.0,
        keep: bool = True,
        truth_after_sensor: bool = False,
        drive_node_id: int = 2,
        controller_node_id: int = 1,
        telemetry_id: int | None = None,
        truth_joint_index: int = 0,
    ) -> None:
        #: The rows recorded (all of them with ``keep``; without, those not yet scored).
        self.recording = Recording(sample_period_s)
        #: With ``firmware``: the run scored as it goes (:class:`LiveEvaluation`).
        self.live = (
            LiveEvaluation(self.recording, firmware, skip_s, keep=keep)
            if firmware is not None
            else None
        )
        self._next_check = self.live.next_check if self.live is not None else -1
        self._sensor = codec("control", "DRIVE_TPDO1").expect(
            "ADC_torque", "ADC_tacho", "ADC_current", "ENC_count"
        )
        self._cst: tuple[int, ...] | None = None
        if drive_pdos:
            self._use_mapping(drive_pdos)
        self._sdo = codec("control", "SDO_TX_DRIVE").expect(
            "sdo_cs", "sdo_index", "sdo_sub", "sdo_data"
        )
        self._tele = codec("control", "CTRL_TPDO1").expect(
            "T_meas", "T_filtered", "velocity", "current"
        )
        self._truth_torque = codec("truth", "TRUTH_TORQUE").expect("T_true", "T_ripple")
        self._truth_motion = codec("truth", "TRUTH_MOTION").expect(
            "theta_motor", "theta_output", "omega_motor", "omega_output"
        )
        self._truth = [math.nan] * 5  # T_true, T_ripple, theta_m, omega_m, theta_out
        #: Where a sample's truth frames stand: before its sensor frame (the lockstep tap
        #: stamps them at the sample instant) or after it (a logger in another process
        #: receives them as the drive sends them, the sensor frame first).
        self._truth_after = truth_after_sensor
        self._truth_t = -math.inf  # when the truth kept for the next sensor frame came
        self._status = codec("control", "DRIVE_TPDO2").expect("statusword")
        sensor_id, status_id, sdo_id, tele_id = layout_frame_ids(
            drive_pdos, drive_node_id, controller_node_id
        )
        self._sensor = self._sensor.at(sensor_id)
        self._status = self._status.at(status_id)
        self._sdo = self._sdo.at(sdo_id)
        self._tele = self._tele.at(tele_id if telemetry_id is None else telemetry_id)
        if truth_joint_index:
            self._truth_torque, self._truth_motion = (
                c.at(truth_frame_id(truth_joint_index, c.frame_id))
                for c in (self._truth_torque, self._truth_motion)
            )
        self._enabled: bool | None = None  # unknown until a statusword is seen
        self._t = 0.0  # timestamp of the frame being handled
        self._last_sensor_t: float | None = None
        self._missed = 0  # periods without a sensor frame since the last recorded sample
        #: The last sensor frame's row while the statusword says "not in operation".
        self._pending: tuple[float, ...] | None = None
        self._dispatch = {
            (self._sensor.frame_id, False): self._on_sensor,
            (self._tele.frame_id, False): self._on_telemetry,
            (self._truth_torque.frame_id, True): self._on_truth_torque,
            (self._truth_motion.frame_id, True): self._on_truth_motion,
            (self._status.frame_id, False): self._on_statusword,
        }
        if self._cst is not None:
            self._dispatch[(self._sdo.frame_id, False)] = self._on_sdo_answer

    def _use_mapping(self, drive_pdos: dict[str, Any]) -> None:
        from hdhil.canopen.mapping import control_database, layouts_from_json

        db = control_database(_at_node_2(layouts_from_json(drive_pdos)))
        sensor = FrameCodec(db.get_message_by_name("DRIVE_TPDO1"), "control")
        names = sensor.signal_names
        if {"torque_actual_value", "position_actual_value"} <= set(names):
            self._sensor = sensor
            self._cst = (names.index("torque_actual_value"), names.index("position_actual_value"))
            self.recording.sensor_mapping = "cst"
            if "joint_torque_sensor" in names:
                self._cst += (names.index("joint_torque_sensor"),)
                self.recording.sensor_mapping = "cst-sensor"
        elif set(names) != {"ADC_torque", "ADC_tacho", "ADC_current", "ENC_count"}:
            raise ValueError(
                f"the trace's sensor frame maps ({', '.join(names)}): neither the raw nor "
                "the CiA 402 CST mapping"
            )

    def _on_sdo_answer(self, data: bytes) -> None:
        """The drive's answer to the read of 0x6076 (expedited upload response, CiA 301
        §7.2.4.3.6: command specifier 0x4x with the expedited bit)."""
        cs, index, sub, value = self._sdo.decode(data)
        if (int(cs) & 0xE2) == 0x42 and int(index) == 0x6076 and int(sub) == 0 and value > 0:
            self.recording.rated_torque_Nm = float(value) * 1e-3

    def on_message_received(self, msg: can.Message) -> None:
        handler = self._dispatch.get((msg.arbitration_id, msg.is_extended_id))
        if handler is not None and not msg.is_remote_frame and not msg.is_error_frame:
            self._t = msg.timestamp
            with contextlib.suppress(ValueError):  # wrong length: malformed, not a sample
                handler(msg.data)
            if 0 <= self._next_check <= len(self.recording):
                assert self.live is not None
                self._next_check = self.live.advance()

    def on_frames(self, frames: list[can.Message]) -> None:
        """:meth:`on_message_received` for each frame, in one call (the run's tap hands
        on every frame of the run: the per-frame work is kept to a lookup)."""
        get = self._dispatch.get
        recording = self.recording
        for msg in frames:
            handler = get((msg.arbitration_id, msg.is_extended_id))
            if handler is None or msg.is_remote_frame or msg.is_error_frame:
                continue
            self._t = msg.timestamp
            # contextlib.suppress, as on_message_received, is a context manager per frame
            try:  # noqa: SIM105
                handler(msg.data)
            except ValueError:  # wrong length: malformed, not a sample
                pass
            if 0 <= self._next_check <= len(recording):
                assert self.live is not None
                self._next_check = self.live.advance()

    def result(self) -> dict[str, Any]:
        """The evaluation of what was recorded, for a listener with ``firmware`` (run in
        the trace writer's process, :class:`LiveEvaluationFactory`)."""
        if self.live is None:
            raise ValueError("a RecordingListener without firmware scores nothing")
        return self.live.finish()

    def _on_statusword(self, data: bytes) -> None:
        (statusword,) = self._status.decode(data)
        # CiA 402 statusword bits 0-3, 5, 6: 0b0100111 = OPERATION ENABLED.
        self._enabled = (statusword & 0x6F) == 0x27

    def _on_sensor(self, data: bytes) -> None:
        nan = math.nan
        gauge = nan
        if self._cst is None:
            torque, tacho, current, encoder = self._sensor.decode(data)
            actual = position = nan
        else:
            values = self._sensor.decode(data)
            picks = self._cst
            actual, position = values[picks[0]], values[picks[1]]
            if len(picks) > 2:
                gauge = values[picks[2]]
            torque = tacho = current = nan
            encoder = int(position) & 0xFFFF
        Ts = self.recording.sample_period_s
        last = self._last_sensor_t
        if last is not None and round((self._t - last) / Ts) <= 0:
            return  # a second sensor frame in one period: the firmware ignores it too
        self._missed += missed_cycles(last, self._t, Ts)
        self._last_sensor_t = self._t
        t = self._truth
        if self._truth_after and self._t - self._truth_t >= 0.5 * Ts:
            t = [math.nan] * 5  # kept from an earlier SYNC whose sensor frame was lost
        row = (torque, tacho, current, encoder, math.nan, math.nan, math.nan,
               t[0], t[1], t[2], t[3], t[4], float(self._missed), actual, position,
               gauge)  # fmt: skip
        # The truth of one SYNC belongs to one sample: a sample whose truth frames never
        # came (truth faults) has none, rather than the previous or the next sample's.
        self._truth = [math.nan] * 5
        if self._enabled is False:
            self._pending = row  # recorded if the firmware's telemetry answers it
            return
        self._append(row)
        self._pending = None  # an older row waiting for telemetry is not the firmware's
        self._missed = 0

    def _append(self, row: tuple[float, ...]) -> None:
        self.recording.append_row(row)

    def _on_telemetry(self, data: bytes) -> None:
        if self._enabled is False:
            # The firmware runs its interrupt, and sends this, only in operation: the
            # statusword saying so was lost (it is sent on change, then every 100 ms).
            if self._pending is None:
                return
            self._enabled = True
            self._append(self._pending)
            self._missed = 0
        self._pending = None
        T_meas, T_filtered, velocity, _current = self._tele.decode(data)
        rec = self.recording
        rec.set_last("T_meas_tele", T_meas)
        rec.set_last("T_filtered_tele", T_filtered)
        rec.set_last("velocity_tele", velocity)

    def _on_truth_torque(self, data: bytes) -> None:
        T_true, T_ripple = self._truth_torque.decode(data)
        self._take_truth(0, (T_true, T_ripple))

    def _on_truth_motion(self, data: bytes) -> None:
        theta_m, theta_o, omega_m, _omega_o = self._truth_motion.decode(data)
        self._take_truth(2, (theta_m, omega_m, theta_o))

    def _take_truth(self, first: int, values: tuple[float, ...]) -> None:
        """Truth values from position ``first`` of :attr:`_truth`: for the next sensor
        frame, or with ``truth_after_sensor`` for the last one while its row has none of
        them yet (the drive sends them after its sensor frame; a logger reading two
        sockets may stamp them late, past the next SYNC, or early, before their sensor
        frame: those are kept for it)."""
        column = _TRUTH_INDEX[first]
        if self._truth_after and self._last_sensor_t is not None:
            pending = self._pending
            has = pending[column] if pending is not None else self.recording.last(column)
            if math.isnan(has):  # the last row has none of these yet: they are its own
                if pending is not None:
                    row = list(pending)
                    row[column : column + len(values)] = values
                    self._pending = tuple(row)
                else:
                    for name, value in zip(_TRUTH_COLUMNS[first:], values, strict=False):
                        self.recording.set_last(name, value)
                return
        self._truth[first : first + len(values)] = values
        self._truth_t = self._t


def _at_node_2(layouts: dict[Any, Any]) -> dict[Any, Any]:
    """``layouts`` with each PDO of the pre-defined connection set at its COB-ID for node-ID
    2, where ``control.dbc`` has its message (the layout by name; the identifier of a
    drive at another node-ID comes from :func:`layout_frame_ids`)."""
    return {
        key: dataclasses.replace(lay, cob_id=predefined_cob_id(*key, 2))
        if 1 <= key[1] <= 4
        and lay.cob_id & 0x7F
        and lay.cob_id == predefined_cob_id(*key, lay.cob_id & 0x7F)
        else lay
        for key, lay in layouts.items()
    }


def layout_frame_ids(
    drive_pdos: dict[str, Any] | None, drive_node_id: int = 2, controller_node_id: int = 1
) -> tuple[int, int, int, int]:
    """The identifiers of the drive's sensor frame (TPDO1), statusword (TPDO2) and SDO
    answers, and of the controller's telemetry (its TPDO1), for a drive at
    ``drive_node_id`` and the controller at ``controller_node_id``: the CiA 301
    pre-defined connection set (:func:`hdhil.dbc.predefined_cob_id`), or the
    COB-IDs ``drive_pdos`` (a sidecar's, :func:`hdhil.canopen.mapping.layouts_to_json`)
    records for the drive's PDOs."""
    from hdhil.canopen.mapping import layouts_from_json
    from hdhil.canopen.sdo import SDO_TX_BASE

    pdos = layouts_from_json(drive_pdos) if drive_pdos else {}

    def cob(kind: str, number: int) -> int:
        layout = pdos.get((kind, number))
        return (
            layout.cob_id if layout is not None else predefined_cob_id(kind, number, drive_node_id)
        )

    return (cob("tpdo", 1), cob("tpdo", 2), SDO_TX_BASE + drive_node_id,
            predefined_cob_id("tpdo", 1, controller_node_id))  # fmt: skip


@dataclass(frozen=True)
class LiveEvaluationFactory:
    """A :class:`RecordingListener` scoring as it goes and keeping no rows, made where it
    is called: the trace writer's child process (``child_listener`` of
    :class:`hdhil.can.traces.writer.WriterProcess`), which feeds it the frames it writes
    and hands its ``result()`` (the evaluation) back. Picklable for the ``spawn`` start
    method."""

    sample_period_s: float
    drive_pdos: dict[str, Any] | None
    firmware: FirmwareConfig
    skip_s: float
    drive_node_id: int = 2
    controller_node_id: int = 1

    def __call__(self) -> RecordingListener:
        return RecordingListener(
            self.sample_period_s,
            self.drive_pdos,
            firmware=self.firmware,
            skip_s=self.skip_s,
            keep=False,
            drive_node_id=self.drive_node_id,
            controller_node_id=self.controller_node_id,
        )


def recording_from_trace(path: Path, sample_period_s: float = 1e-3) -> tuple[Recording, str]:
    """Read a trace into a recording; returns it and a damage description ('' if clean).
    The drive's PDO mapping comes from the trace's sidecar JSON (the default mapping
    without one)."""
    from hdhil.can.traces.reader import read_trace
    from hdhil.can.traces.sidecar import read_metadata
    from hdhil.canopen.mapping import trace_node_ids

    meta = read_metadata(path) or {}
    # `hdhil log` records the drive's frames as it sends them, each sample's sensor frame
    # before its truth frames; `hdhil run`'s tap stamps the truth at the sample instant.
    after = meta.get("recorded_by") == "hdhil log"
    drive_id, controller_id = trace_node_ids(meta)  # a drive at its node-ID's identifiers
    listener = RecordingListener(
        sample_period_s,
        meta.get("drive_pdos"),
        truth_after_sensor=after,
        drive_node_id=drive_id,
        controller_node_id=controller_id,
    )
    with read_trace(path) as trace:
        for msg in trace:
            listener.on_message_received(msg)
        damage = "; ".join(d.describe(str(path)) for d in trace.damage)
    return listener.recording, damage


#: How far (s) a rig trace's frames may stand out of time order: the run's tap hands the
#: trace writer each channel's frames in turns, every :data:`hdhil.rig.rigrun.
#: TAP_EVERY_CYCLES` cycles (16 ms at 1 kHz), so a truth frame may follow sensor frames
#: sent after it.
REORDER_S = 0.1


def in_time_order(
    frames: Iterable[can.Message], slack_s: float = REORDER_S
) -> Iterator[can.Message]:
    """``frames`` by timestamp (stable), for frames at most ``slack_s`` out of order:
    a frame is handed on once a frame ``slack_s`` later has been read."""
    heap: list[tuple[float, int, can.Message]] = []
    for seq, msg in enumerate(frames):
        heapq.heappush(heap, (msg.timestamp, seq, msg))
        while heap[0][0] < msg.timestamp - slack_s:
            yield heapq.heappop(heap)[2]
    while heap:
        yield heapq.heappop(heap)[2]


class _BusFrames:
    """A rig bus's joints (:class:`RecordingListener`) fed from its channel and the truth,
    each sample with the truth of its SYNC: the truth a drive sends for a sample is
    stamped before the bus's SYNC of that sample, and a SYNC sent early in the cycle
    (a loaded bus) can have the next sample's truth stamped between it and the sensor
    frames. So truth frames are handed on at the bus's next SYNC (at once on a bus whose
    trace shows no SYNC)."""

    def __init__(self) -> None:
        self.listeners: list[RecordingListener] = []
        self._held: list[can.Message] = []
        self._synced = False

    def on_truth(self, msg: can.Message) -> None:
        if self._synced:
            self._held.append(msg)
        else:
            self._deliver(msg)

    def on_frame(self, msg: can.Message) -> None:
        if msg.arbitration_id == SYNC_COB_ID and not msg.is_extended_id:
            self._synced = True
            for held in self._held:
                self._deliver(held)
            self._held.clear()
        self._deliver(msg)

    def _deliver(self, msg: can.Message) -> None:
        for lis in self.listeners:
            lis.on_message_received(msg)


@dataclass(frozen=True)
class JointRecording:
    """One joint of a rig's trace (:func:`rig_recordings_from_trace`): where it sits in
    the layout and its :class:`Recording`."""

    name: str
    bus: str
    node_id: int
    joint_index: int
    recording: Recording


def rig_recordings_from_trace(
    path: Path, rig: dict[str, Any], sample_period_s: float = 1e-3
) -> tuple[list[JointRecording], str]:
    """Read a rig's trace (``hdhil run --trace`` of a scenario with ``[joints]``) into a
    recording per joint, in the layout's order, in one pass; returns them and a damage
    description ('' if clean). ``rig``: the sidecar's ``rig`` entry (buses with their
    channels, joints). Each joint takes the frames of its bus's channel at the
    identifiers the rig's database gives its messages by name (as ``hdhil dump`` decodes
    them: ``J1_DRIVE_TPDO1``, ``J1_CTRL_TPDO1``, :func:`hdhil.canopen.rigdb.
    rig_databases`) and its own truth on the truth channel. ``ValueError`` for a ``rig``
    entry that does not describe a layout."""
    from hdhil.can.traces.reader import read_trace
    from hdhil.canopen.mapping import rig_sidecar_layout
    from hdhil.canopen.rigdb import rig_databases
    from hdhil.core.errors import UserError
    from hdhil.dbc import CHANNEL_NUMBER

    buses, channels, drives, indices = rig_sidecar_layout(rig)
    joints = [(d.joint, d.bus, d.node_id, d.controller_node_id, index)
              for d, index in zip(drives, indices, strict=True)]  # fmt: skip
    try:
        databases = rig_databases(drives, buses)
        listeners = []
        for name, bus, node, cid, index in joints:
            tele = databases[bus].get_message_by_name(f"{name}_CTRL_TPDO1").frame_id
            listener = RecordingListener(sample_period_s, drive_node_id=node,
                                         controller_node_id=cid, telemetry_id=tele,
                                         truth_joint_index=index)  # fmt: skip
            listeners.append((channels[bus], listener))
    except (KeyError, TypeError, ValueError, UserError) as exc:
        raise ValueError(f"the sidecar's rig layout cannot be read ({exc})") from None
    buses_of: dict[int, _BusFrames] = {}
    for channel, lis in listeners:
        buses_of.setdefault(channel, _BusFrames()).listeners.append(lis)
    every = list(buses_of.values())
    truth = CHANNEL_NUMBER["truth"]
    with read_trace(path) as trace:
        for msg in in_time_order(trace):
            if msg.channel == truth:
                for bus_frames in every:
                    bus_frames.on_truth(msg)
            elif (bus_frames := buses_of.get(msg.channel)) is not None:  # type: ignore[arg-type]
                bus_frames.on_frame(msg)
        damage = "; ".join(d.describe(str(path)) for d in trace.damage)
    out = [
        JointRecording(name, bus, node, index, lis.recording)
        for (name, bus, node, _, index), (_, lis) in zip(joints, listeners, strict=True)
    ]
    return out, damage


@dataclass(frozen=True)
class CandidateScore:
    name: str
    rms_error: float
    rms_ratio: float
    harmonics: dict[str, float]  # amplitude of the error at each harmonic (Nm)
    reduction_dB: dict[str, float]  # vs raw
    misalignment_pp: float
    #: Delay (ms) that best aligns the candidate with the true torque, and the share of
    #: the true torque's variation it passes at that delay (:class:`_AlignSums`); None
    #: where the true torque varies too little to tell (:data:`MIN_TRUE_STD_NM`).
    lag_ms: float | None
    gain: float | None


def harmonic_amplitude(
    error: np.ndarray, angle: np.ndarray, multiple: float, mask: np.ndarray
) -> float:
    """Amplitude of the component of ``error`` at ``multiple`` × ``angle`` (demodulation)."""
    return _demodulated_amplitude(error, np.exp(-1j * multiple * angle), mask)


def _demodulated_amplitude(error: np.ndarray, phasor: np.ndarray, mask: np.ndarray) -> float:
    """:func:`harmonic_amplitude` with the phasor exp(−j·multiple·angle) given, so that
    one phasor per harmonic serves every candidate: 2 |mean((e − ē) · phasor)| over
    ``mask``."""
    if not mask.any():
        return math.nan
    e = error[mask] - error[mask].mean()
    return float(2.0 * abs(np.mean(e * phasor[mask])))


#: A raw error harmonic below this (Nm) has nothing to reduce: no dB figure (e.g. the CiA
#: 402 CST mapping, whose torque actual value carries no gauge ripple).
MIN_RAW_HARMONIC_NM = 1e-6


def _reduction_dB(raw: float, amplitude: float) -> float:
    """20 log10(raw / amplitude): the reduction of one error harmonic against raw; NaN
    when raw has none to reduce, infinite when none is left."""
    if not raw >= MIN_RAW_HARMONIC_NM:
        return math.nan
    return 20 * math.log10(raw / amplitude) if amplitude > 0 else math.inf


def _lag_ms(costs: np.ndarray, sample_period_s: float) -> float:
    """The delay (ms) at the minimum of ``costs`` (one per delay of 0 … MAX_LAG_SAMPLES
    samples), refined by a parabola through the minimum and its neighbours."""
    i = int(np.argmin(costs))
    shift = 0.0
    if 0 < i < len(costs) - 1:
        c0, c1, c2 = costs[i - 1], costs[i], costs[i + 1]
        denom = c0 - 2 * c1 + c2
        if denom > 0:
            shift = 0.5 * (c0 - c2) / denom
    return float((i + shift) * sample_period_s * 1e3)


@dataclass(frozen=True)
class Alignment:
    """How a candidate follows the true torque: its delay behind it and the share of the
    true torque's variation it passes at that delay (:class:`_AlignSums`); both None
    when the true torque varies too little (or the run is too short) to tell."""

    lag_ms: float | None
    gain: float | None


def estimate_alignment(x: np.ndarray, truth: np.ndarray, sample_period_s: float) -> Alignment:
    """Lag and gain of ``x`` against ``truth`` (:class:`_AlignSums`)."""
    sums = _AlignSums()
    sums.add(np.asarray(x, dtype=np.float64), np.asarray(truth, dtype=np.float64))
    return sums.result(sample_period_s)


def estimate_lag(x: np.ndarray, truth: np.ndarray, sample_period_s: float) -> float | None:
    """Delay (ms) of ``x`` behind ``truth``: argmin over d of mean (x(k) − truth(k−d))²."""
    return estimate_alignment(x, truth, sample_period_s).lag_ms


class _Sums:
    """Running sums of float vectors, compensated (Neumaier): chunk by chunk they add up
    to what one sum over everything gives, to the last bits."""

    def __init__(self, size: int) -> None:
        self._s = np.zeros(size)
        self._c = np.zeros(size)

    def add(self, x: np.ndarray) -> None:
        s = self._s
        t = s + x
        self._c += np.where(np.abs(s) >= np.abs(x), (s - t) + x, (x - t) + s)
        self._s = t

    @property
    def total(self) -> np.ndarray:
        s = self._s
        return np.where(np.isfinite(s), s + self._c, s)


#: Below this standard deviation of the true torque (Nm) no gain or lag is given: the
#: torque varies too little against the sensor noise and the filters' residuals to
#: measure how a candidate follows it (free motion: a few mNm).
MIN_TRUE_STD_NM = 0.1


class _LagSums:
    """:func:`estimate_lag` over a signal that comes in chunks: per delay d the sum of
    (x(k) − truth(k−d))² over k ≥ MAX_LAG_SAMPLES, with the last MAX_LAG_SAMPLES truth
    samples carried from chunk to chunk, and the sums for the truth's variance."""

    def __init__(self) -> None:
        self.n = 0
        self._history = np.zeros(0)  # the last (up to) M truth samples
        self._shift: float | None = None  # subtracted before the variance's sums
        self._sums = _Sums(MAX_LAG_SAMPLES + 3)  # costs for d = 0 … M, Σ(t − c), Σ(t − c)²

    def add(self, x: np.ndarray, truth: np.ndarray) -> None:
        M = MAX_LAG_SAMPLES
        size = len(x)
        if size == 0:
            return
        if self._shift is None:
            self._shift = float(truth.mean())
        dt = truth - self._shift
        contrib = np.zeros(M + 3)
        contrib[M + 1] = dt.sum()
        contrib[M + 2] = (dt * dt).sum()
        ext = np.concatenate((self._history, truth))
        first = max(M, self.n)  # the first k scored in this chunk
        count = self.n + size - first
        if count > 0:
            at = first - self.n + len(self._history)  # ext index of truth(first)
            window = np.lib.stride_tricks.sliding_window_view(ext[at - M : at + count], count)
            # row i: x(k) − truth(k − (M − i)); each row summed on its own (pairwise)
            sq = x[first - self.n :] - window
            np.square(sq, out=sq)
            contrib[: M + 1] = sq.sum(axis=1)[::-1]
        self._sums.add(contrib)
        self._history = ext[-M:].copy()
        self.n += size

    def result(self, sample_period_s: float) -> float | None:
        M, n = MAX_LAG_SAMPLES, self.n
        if n < 4 * M:
            return None
        total = self._sums.total
        mean = total[M + 1] / n
        if not total[M + 2] / n - mean * mean >= MIN_TRUE_STD_NM**2:  # the truth's variance
            return None
        return _lag_ms(total[: M + 1] / (n - M), sample_period_s)


class _AlignSums:
    """Lag and gain of a candidate x against the true torque t, over a signal that comes
    in chunks.

    The **lag** is :class:`_LagSums`'s: the delay d (0 … :data:`MAX_LAG_SAMPLES`
    samples, refined between samples by a parabola) that minimises the mean of
    (x(k) − t(k − d))², which is where the cross-correlation of x with t peaks. The
    **gain** is the least-squares slope of x(k) on t(k − d) at that delay (the nearest
    whole sample), means removed: cov(x(k), t(k − d)) / var(t(k − d)), the share of the
    true torque's variation the candidate passes once aligned (1: in full; a filter
    that absorbs 64 % of a torque change gives 0.36). Kept for the gain are, per d, the
    sums of t, t² and x·t over k ≥ MAX_LAG_SAMPLES (the last MAX_LAG_SAMPLES truth
    samples carried from chunk to chunk). A sample without a value (NaN: telemetry or
    truth lost) counts as 0 in both, so that the chunks add up to the whole."""

    def __init__(self) -> None:
        self.n = 0
        self.lag = _LagSums()
        self._history = np.zeros(0)  # the last (up to) M truth samples
        M = MAX_LAG_SAMPLES
        self._sums = _Sums(3 * (M + 1) + 1)  # per d: Σt(k−d), Σt(k−d)², Σx(k)t(k−d); Σx

    def add(self, x: np.ndarray, truth: np.ndarray) -> None:
        M = MAX_LAG_SAMPLES
        size = len(x)
        if size == 0:
            return
        xc = np.nan_to_num(x, nan=0.0)
        tc = np.nan_to_num(truth, nan=0.0)
        self.lag.add(xc, tc)
        contrib = np.zeros(3 * (M + 1) + 1)
        ext = np.concatenate((self._history, tc))
        first = max(M, self.n)  # the first k scored in this chunk
        count = self.n + size - first
        if count > 0:
            at = first - self.n + len(self._history)  # ext index of truth(first)
            seg = ext[at - M : at + count]  # t(k − d) for d = M … 0 and the k scored
            # Σ t(k − d) and Σ t(k − d)² from running sums, Σ x(k) t(k − d) as one product
            # with the window whose row i is t(k − (M − i))
            for j, values in enumerate((seg, np.square(seg))):
                run = np.concatenate(([0.0], np.cumsum(values)))
                contrib[j * (M + 1) : (j + 1) * (M + 1)] = (run[count:] - run[: M + 1])[::-1]
            window = np.lib.stride_tricks.sliding_window_view(seg, count)
            xk = xc[first - self.n :]
            contrib[2 * M + 2 : 3 * M + 3] = (window @ xk)[::-1]
            contrib[3 * M + 3] = xk.sum()
        self._sums.add(contrib)
        self._history = ext[-M:].copy()
        self.n += size

    def result(self, sample_period_s: float) -> Alignment:
        lag = self.lag.result(sample_period_s)  # None: too short, or too little variation
        if lag is None:
            return Alignment(None, None)
        M = MAX_LAG_SAMPLES
        d = min(M, round(lag * 1e-3 / sample_period_s))
        total = self._sums.total / (self.n - M)
        mean_t, mean_tt, mean_xt = total[d], total[M + 1 + d], total[2 * M + 2 + d]
        mean_x = total[3 * M + 3]
        var_t = mean_tt - mean_t * mean_t
        gain = (mean_xt - mean_x * mean_t) / var_t if var_t > 0 else math.nan
        return Alignment(lag, float(gain))


class ChainReplay:
    """The firmware's own filter chain (:class:`firmware.isr.TorqueFilterChain`) over
    recorded samples, continuing from one call to the next (:func:`offline_chain`)."""

    def __init__(self, cfg: FirmwareConfig) -> None:
        self._chain = TorqueFilterChain(cfg)

    def __call__(
        self,
        T_meas: np.ndarray,
        velocity: np.ndarray,
        encoder: np.ndarray,
        missed: np.ndarray | None = None,
    ) -> np.ndarray:
        chain = self._chain
        step = chain.step
        out: list[float] = []
        append = out.append
        gaps = [0] * len(T_meas) if missed is None else missed.astype(np.int64).tolist()
        for T, v, e, gap in zip(
            T_meas.tolist(), velocity.tolist(), encoder.astype(np.int64).tolist(), gaps,
            strict=True,
        ):  # fmt: skip
            if gap:
                for _ in range(gap):
                    chain.sample_missed()
            append(step(T, v, e)[3])
        return np.array(out, dtype=np.float64)


def offline_chain(
    cfg: FirmwareConfig,
    T_meas: np.ndarray,
    velocity: np.ndarray,
    encoder: np.ndarray,
    missed: np.ndarray | None = None,
) -> np.ndarray:
    """The firmware's own filter chain over recorded samples; returns T_filtered.

    ``missed[k]``: sample periods without a sample before sample k (the recording's
    ``missed`` column); the chain is told of each, as the firmware's was, so a lossy
    trace is replayed with the same skipped updates the firmware made."""
    return ChainReplay(cfg)(T_meas, velocity, encoder, missed)


class _Calibration:
    """T_meas and motor velocity from recorded counts, chunk by chunk, through the
    firmware's stages (in the CST mappings its :class:`firmware.stages.CstSource`, with
    the torque sensor's calibration when the joint-torque sensor 0x2102 is mapped).

    In the raw mapping each channel is calibrated on its own (:func:`firmware.stages.
    calibrate`: T_meas from the torque count, the velocity from the tacho count), so
    each distinct count goes through ``adc_read`` and ``calibrate`` once and the
    samples take their values from that table: the same numbers as sample by sample."""

    def __init__(
        self, cfg: FirmwareConfig, sensor_mapping: str, rated_torque_Nm: float | None
    ) -> None:
        self._cst: CstSource | None = None
        if sensor_mapping in ("cst", "cst-sensor"):
            if rated_torque_Nm is None:
                raise ValueError(
                    "the trace holds no answer to the controller's read of the drive's rated "
                    "torque 0x6076: the CST torque actual values cannot be scaled"
                )
            self._cst = CstSource(
                rated_torque_Nm, cfg.calibration.encoder_counts_per_rev, cfg.diff_tau_s,
                cfg.sample_period_s,
                cfg.calibration if sensor_mapping == "cst-sensor" else None,
            )  # fmt: skip
        adc, cal = cfg.adc, cfg.calibration
        self._torque = _PerCount(lambda q: calibrate(*adc_read(q, 0, 0, adc), cal)[0])
        self._velocity = _PerCount(lambda tq: calibrate(*adc_read(0, tq, 0, adc), cal)[1])

    def __call__(self, cols: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        if self._cst is None:
            return self._torque(cols["adc_torque"]), self._velocity(cols["adc_tacho"])
        source = self._cst
        n = len(cols["torque_actual"])
        T_meas = np.empty(n)
        vel = np.empty(n)
        gauge: list[int] | list[None] = (
            cols["joint_torque_mV"].astype(np.int64).tolist()
            if source.calibration is not None
            else [None] * n
        )
        for k, (q, pos, mV) in enumerate(
            zip(
                cols["torque_actual"].astype(np.int64).tolist(),
                cols["position_actual"].astype(np.int64).tolist(),
                gauge,
                strict=True,
            )
        ):
            T_meas[k], vel[k] = source(CstSample(q, pos, mV))[:2]
        return T_meas, vel


class _PerCount:
    """``convert(count)`` for every sample, computed once per distinct count."""

    def __init__(self, convert: Callable[[int], float]) -> None:
        self._convert = convert
        self._table: dict[int, float] = {}

    def __call__(self, counts: np.ndarray) -> np.ndarray:
        distinct, where = np.unique(counts.astype(np.int64), return_inverse=True)
        table, convert = self._table, self._convert
        values = []
        for c in distinct.tolist():
            v = table.get(c)
            if v is None:
                v = table[c] = convert(c)
            values.append(v)
        return np.array(values, dtype=np.float64)[where.reshape(-1)]


def _columns(rec: Recording) -> dict[str, np.ndarray]:
    return {name: rec.column(name) for name in COLUMNS}


def calibrated_signals(rec: Recording, cfg: FirmwareConfig) -> tuple[np.ndarray, np.ndarray]:
    """T_meas and motor velocity from the recorded counts, through the firmware's stages
    (:class:`_Calibration`)."""
    return _Calibration(cfg, rec.sensor_mapping, rec.rated_torque_Nm)(_columns(rec))


class _Candidates:
    """Every candidate's torque estimate, chunk by chunk: the filters keep their state
    from one chunk to the next, so the chunks give what the whole recording gives."""

    def __init__(
        self, cfg: FirmwareConfig, sensor_mapping: str, rated_torque_Nm: float | None
    ) -> None:
        self._calibration = _Calibration(cfg, sensor_mapping, rated_torque_Nm)
        Ts = cfg.sample_period_s
        paper = paper_config(cfg)
        recommended = recommended_config(cfg)
        # With a law the telemetry's torque is the law's estimate τ̂s (the regulator's
        # observer fed by the ripple filter), not the ripple filter's output.
        self._firmware = (
            f"firmware (LQG on {cfg.ripple.mode})"
            if cfg.control.active
            else f"firmware ({cfg.ripple.mode})"
        )
        self._chains = {
            f"kalman paper ({paper.ripple.order}th order)": ChainReplay(paper),
            f"kalman recommended ({len(recommended.ripple.oscillators)} harmonics)": (
                ChainReplay(recommended)
            ),
        }
        self._lowpass = {
            f"butterworth {fc:g} Hz": ButterworthLowPass(fc, Ts)
            for fc in BUTTERWORTH_CUTOFFS_HZ
            if fc < 0.5 / Ts
        }
        self._notch = TrackingNotchBank((2.0, 4.0), Ts)

    def __call__(self, cols: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        T_meas, vel = self._calibration(cols)
        encoder, missed = cols["encoder"], cols["missed"]
        signals = {"raw": T_meas, self._firmware: cols["T_filtered_tele"]}
        for name, replay in self._chains.items():
            signals[name] = replay(T_meas, vel, encoder, missed)
        for name, lowpass in self._lowpass.items():
            signals[name] = lowpass.filter(T_meas)
        signals["notch bank 2x/4x"] = self._notch.filter(T_meas, vel)
        return signals


def candidate_signals(rec: Recording, cfg: FirmwareConfig) -> dict[str, np.ndarray]:
    """Every candidate's torque estimate over the recording, keyed by display name."""
    return _Candidates(cfg, rec.sensor_mapping, rec.rated_torque_Nm)(_columns(rec))


class _Unwrap:
    """``np.unwrap`` of an angle that comes in chunks: the same operations, with the last
    angle and the correction summed so far carried from chunk to chunk."""

    def __init__(self) -> None:
        self._last: float | None = None
        self._correction = 0.0

    def __call__(self, p: np.ndarray) -> np.ndarray:
        if len(p) == 0:
            return p.copy()
        finite = np.isfinite(p)
        if not finite.all():  # a sample without truth: NaN there, the others unwrapped
            out = np.full(len(p), math.nan)
            if finite.any():
                out[finite] = self(p[finite])
            return out
        first = p[:1] if self._last is None else np.array([self._last])
        dd = np.diff(p, prepend=first)
        ddmod = np.mod(dd + math.pi, 2 * math.pi) - math.pi
        np.copyto(ddmod, math.pi, where=(ddmod == -math.pi) & (dd > 0))
        correct = ddmod - dd
        np.copyto(correct, 0, where=abs(dd) < math.pi)
        correct[0] += self._correction  # the running sum continues where it stopped
        summed = correct.cumsum()
        self._last = float(p[-1])
        self._correction = float(summed[-1])
        return p + summed


class _Demodulation:
    """:func:`_demodulated_amplitude` of a signal that comes in chunks, at every
    harmonic: 2 |S_ep/n − (S_e/n)(S_p/n)| from running sums of e (less its first chunk's
    mean, against cancellation), of the phasor p and of e·p."""

    def __init__(self) -> None:
        self.n = 0
        self._shift: float | None = None
        self._sums = _Sums(1 + 4 * len(HARMONICS))  # Σe, then (Σp, Σep) re/im per harmonic

    def add(self, e: np.ndarray, phasors: list[np.ndarray]) -> None:
        if len(e) == 0:
            return
        if self._shift is None:
            self._shift = float(e.mean())
        d = e - self._shift
        contrib = [d.sum()]
        for p in phasors:
            sp, sep = p.sum(), (d * p).sum()
            contrib += [sp.real, sp.imag, sep.real, sep.imag]
        self._sums.add(np.array(contrib))
        self.n += len(e)

    def amplitudes(self) -> dict[str, float]:
        if self.n == 0:
            return {label: math.nan for label, _, _ in HARMONICS}
        t = self._sums.total / self.n
        mean_e = t[0]
        out = {}
        for i, (label, _, _) in enumerate(HARMONICS):
            p = complex(t[1 + 4 * i], t[2 + 4 * i])
            ep = complex(t[3 + 4 * i], t[4 + 4 * i])
            out[label] = float(2.0 * abs(ep - mean_e * p))
        return out


class _CandidateStats:
    """One candidate's running scores: its squared error, the error's harmonics and
    the sums for its lag and gain."""

    def __init__(self) -> None:
        self.ok = 0
        self.squares = _Sums(1)
        self.harmonics = _Demodulation()
        self.alignment = _AlignSums()


class StreamingEvaluation:
    """:func:`evaluate` over the firmware's samples fed in chunks (:meth:`feed`, rows in
    order from the firmware's first sample), keeping only bounded state: the filters'
    states, running sums and the last :data:`MAX_LAG_SAMPLES` truth samples per
    candidate. One chunk of everything is :func:`evaluate` itself."""

    def __init__(
        self,
        cfg: FirmwareConfig,
        skip_s: float = 0.0,
        sensor_mapping: str = "raw",
        rated_torque_Nm: float | None = None,
    ) -> None:
        self.cfg = cfg
        self.skip_s = skip_s
        self._sensor = (sensor_mapping, rated_torque_Nm)
        self._k0 = round(skip_s / cfg.sample_period_s)  # first sample of the window
        self.n = 0
        self._any_truth = False
        self._samples = 0  # in the window, with truth
        self._without_truth = 0  # in the window, without
        self._true_squares = _Sums(1)
        self._true_shift: float | None = None  # subtracted before the variance's sums
        self._true_moments = _Sums(2)  # Σ(t − shift), Σ(t − shift)²
        self._true_ripple = _Demodulation()
        self._angles = {"motor": _Unwrap(), "output": _Unwrap()}
        self._candidates: _Candidates | None = None
        self._error: ValueError | None = None  # from the candidates, raised by result()
        self._stats: dict[str, _CandidateStats] = {}

    def feed(self, cols: dict[str, np.ndarray]) -> None:
        """Score the next rows (``cols``: :data:`COLUMNS` arrays of equal length)."""
        size = len(cols["T_true"])
        if size == 0:
            return
        start = self.n
        self.n += size
        T_true = cols["T_true"]
        valid = np.isfinite(T_true)
        self._any_truth = self._any_truth or bool(valid.any())
        angles = {src: unwrap(cols[f"theta_{src}"]) for src, unwrap in self._angles.items()}
        signals = self._signals(cols)
        j0 = min(size, max(0, self._k0 - start))  # the first row in the window
        window = np.zeros(size, dtype=bool)
        window[j0:] = valid[j0:]
        in_window = int(window.sum())
        self._samples += in_window
        self._without_truth += size - j0 - in_window
        if signals is None or j0 == size:
            return
        in_truth = T_true[window]
        self._true_squares.add(np.array([(in_truth**2).sum()]))
        if self._true_shift is None and in_truth.size:
            self._true_shift = float(in_truth.mean())
        centred = in_truth - (self._true_shift or 0.0)
        self._true_moments.add(np.array([centred.sum(), (centred**2).sum()]))
        turning = window & (np.abs(cols["omega_motor"]) > MIN_SPEED_RADPS)
        at = np.flatnonzero(turning)
        phasors = [np.exp(-1j * mult * angles[src][at]) for _, src, mult in HARMONICS]
        self._true_ripple.add(cols["T_ripple"][at], phasors)
        T_true_at = T_true[at]
        for name, x in signals.items():
            stats = self._stats.setdefault(name, _CandidateStats())
            ok = window & np.isfinite(x)
            err = x - T_true
            err_ok = err[ok]
            stats.ok += len(err_ok)
            stats.squares.add(np.array([(err_ok**2).sum()]))
            m = ok[at]
            stats.harmonics.add(x[at][m] - T_true_at[m], [p[m] for p in phasors])
            stats.alignment.add(np.where(ok, x, math.nan)[j0:], np.where(ok, T_true, math.nan)[j0:])

    def _signals(self, cols: dict[str, np.ndarray]) -> dict[str, np.ndarray] | None:
        if self._error is not None:
            return None
        try:
            if self._candidates is None:
                self._candidates = _Candidates(self.cfg, *self._sensor)
            return self._candidates(cols)
        except ValueError as exc:  # e.g. a CST trace without the rated torque
            self._error = exc
            return None

    def _true_std(self) -> float:
        """The true torque's standard deviation over the samples scored (Nm)."""
        s, ss = self._true_moments.total / self._samples
        return math.sqrt(max(0.0, ss - s * s))

    def result(self) -> dict[str, Any]:
        """The scores of every row fed: what :func:`evaluate` returns (JSON-ready)."""
        n, skip_s = self.n, self.skip_s
        if n == 0:
            return {"samples": 0, "candidates": []}
        if not self._any_truth:
            # No ground truth at all (a trace without the truth channel, or truth silenced)
            return {"samples": 0, "skip_s": skip_s, "candidates": [], "samples_without_truth": n}
        if self._error is not None:
            raise self._error
        # Samples in the window without ground truth (truth frames lost or silenced): left
        # out of every score, and reported.
        without_truth = self._without_truth
        missing = {"samples_without_truth": without_truth} if without_truth else {}
        if self._samples == 0:
            return {"samples": 0, "skip_s": skip_s, "candidates": [], **missing}
        scores = []
        raw_rms = raw_harm = None
        for name, stats in self._stats.items():
            rms = math.sqrt(stats.squares.total[0] / stats.ok) if stats.ok else math.nan
            harm = stats.harmonics.amplitudes()
            alignment = stats.alignment.result(self.cfg.sample_period_s)
            if raw_rms is None:
                raw_rms, raw_harm = rms, harm
            assert raw_harm is not None
            reduction = {label: _reduction_dB(raw_harm[label], a) for label, a in harm.items()}
            scores.append(CandidateScore(
                name=name, rms_error=rms, rms_ratio=rms / raw_rms if raw_rms else math.nan,
                harmonics=harm, reduction_dB=reduction,
                misalignment_pp=2.0 * harm["1x output"],
                lag_ms=alignment.lag_ms, gain=alignment.gain,
            ))  # fmt: skip
        return {
            "samples": self._samples,
            "skip_s": skip_s,
            "rms_true": math.sqrt(self._true_squares.total[0] / self._samples),
            "std_true": self._true_std(),
            "true_ripple": self._true_ripple.amplitudes(),
            "candidates": [dataclasses.asdict(s) for s in scores],
            **missing,
        }


#: Rows a live evaluation scores at a time (:class:`LiveEvaluation`).
CHUNK_ROWS = 4096
#: The columns a :class:`StreamingEvaluation` reads.
_SCORED = tuple(name for name in COLUMNS if name not in ("adc_current", "T_meas_tele",
                                                         "velocity_tele"))  # fmt: skip


class LiveEvaluation:
    """A :class:`StreamingEvaluation` of a :class:`Recording` that is still growing.

    Only the firmware's samples are scored (:meth:`Recording.operation`): the rows from
    the first to the last its telemetry answered. Rows are handed on once a later
    answered row confirms them; unanswered rows (the start, the stop) wait, and those
    after the last answered row are never scored. Should the telemetry never answer,
    every row is (as :meth:`Recording.operation` does), which the rows waiting at the
    start are scored for on the side, in case. The last row may still get its telemetry:
    it waits for the next. Without ``keep`` the recording forgets the rows handed on."""

    def __init__(
        self,
        rec: Recording,
        cfg: FirmwareConfig,
        skip_s: float = 0.0,
        *,
        keep: bool = True,
        chunk_rows: int = CHUNK_ROWS,
    ) -> None:
        self.rec = rec
        self.cfg = cfg
        self.skip_s = skip_s
        self.keep = keep
        self.chunk_rows = max(1, chunk_rows)
        self._cursor = 0  # the first row of ``rec`` not handed on
        #: Hand on views of the recording, not copies: only when it no longer grows.
        self.views = False
        self._started = False  # a row was answered
        self._main: StreamingEvaluation | None = None
        self._none_answered: StreamingEvaluation | None = None  # if none ever is
        self.next_check = self.chunk_rows + 1

    def _evaluation(self) -> StreamingEvaluation:
        return StreamingEvaluation(
            self.cfg, self.skip_s, self.rec.sensor_mapping, self.rec.rated_torque_Nm
        )

    def _hand_on(self, to: StreamingEvaluation, end: int) -> None:
        a, b = self._cursor, end
        if b > a:
            # A copy: a live view would keep the recording's arrays from growing.
            cols = {name: self.rec.column(name)[a:b] for name in _SCORED}
            to.feed(cols if self.views else {name: c.copy() for name, c in cols.items()})
            del cols
        self._cursor = b

    def advance(self, final: bool = False) -> int:
        """Hand on the rows confirmed so far (all with ``final``); returns the length of
        the recording at which to call again."""
        rec = self.rec
        end = len(rec) if final else len(rec) - 1
        if end > self._cursor:
            tele = rec.column("T_meas_tele")[self._cursor : end]
            answered = np.flatnonzero(np.isfinite(tele))
            del tele
            if not self._started and answered.size:
                self._started = True
                self._none_answered = None  # the rows before are not the firmware's
                self._cursor += int(answered[0])
                answered -= answered[0]
            if self._started:
                if answered.size:
                    if self._main is None:
                        self._main = self._evaluation()
                    self._hand_on(self._main, self._cursor + int(answered[-1]) + 1)
                if final:
                    self._cursor = end  # after the last answered row: the stop
            elif final or end - self._cursor >= self.chunk_rows:
                if self._none_answered is None:
                    self._none_answered = self._evaluation()
                self._hand_on(self._none_answered, end)
        if not self.keep:
            rec.drop_first(self._cursor)
            self._cursor = 0
        return len(rec) + self.chunk_rows

    def finish(self) -> dict[str, Any]:
        """The evaluation of every row recorded (:func:`evaluate`)."""
        self.advance(final=True)
        ev = self._main if self._started else self._none_answered
        return (ev or self._evaluation()).result()


def evaluate(rec: Recording, cfg: FirmwareConfig, skip_s: float = 0.0) -> dict[str, Any]:
    """Score every candidate against truth over the firmware's samples
    (:meth:`Recording.operation`) from ``skip_s``; returns a JSON-ready dict."""
    live = LiveEvaluation(rec, cfg, skip_s, chunk_rows=len(rec) + 1)
    live.views = True
    return live.finish()


def evaluate_listener(
    listener: RecordingListener, cfg: FirmwareConfig, skip_s: float = 0.0
) -> dict[str, Any]:
    """The evaluation of what ``listener`` recorded: its live evaluation's, finished, or
    :func:`evaluate` of its recording."""
    if listener.live is not None:
        return listener.live.finish()
    return evaluate(listener.recording, cfg, skip_s)


def _fmt(v: float | None, spec: str) -> str:
    """``v`` formatted by ``spec``; "—" for none, "∞" for infinity, right-aligned to the
    width ``spec`` gives."""
    width = spec.split(".")[0]
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return format("—", f">{width}") if width else "—"
    if isinstance(v, float) and math.isinf(v):
        return format("∞", f">{width}") if width else "∞"
    return format(v, spec)


#: Below this true ripple amplitude (Nm) at every harmonic the plant carries no ripple.
NO_RIPPLE_NM = 1e-3


#: Width (characters) the notes under the evaluation table are wrapped to.
NOTE_WIDTH = 99


def _is_low_pass(name: str) -> bool:
    return name.startswith("butterworth")


def evaluation_notes(ev: dict[str, Any]) -> list[str]:
    """What the table says, in words: the best candidate by RMS error against the true
    torque, when a low-pass wins, why the firmware's filter is worse than raw where it
    is, and why gain and lag are missing where they are."""
    rows = [c for c in ev.get("candidates") or () if not math.isnan(c["rms_error"])]
    if not rows:
        return []
    best = min(rows, key=lambda c: c["rms_error"])
    firmware = next((c for c in rows if c["name"].startswith("firmware")), None)
    notes = [f"best by RMS error: {best['name']}, "
             f"{best['rms_error']:.4f} Nm"]  # fmt: skip
    if firmware is not None and firmware is not best:
        same = f"{firmware['rms_error']:.4f}" == f"{best['rms_error']:.4f}"
        notes[0] += (
            ", as the firmware's filter"
            if same
            else f"; the firmware's filter {firmware['rms_error']:.4f} Nm"
        )
    if firmware is not None and firmware["name"].startswith("firmware (LQG"):
        notes.append(
            "firmware (LQG on ...): the torque the firmware reports is the regulator's "
            "estimate τ̂s, its observer fed by the ripple filter's output"
        )
    std = ev.get("std_true", math.nan)
    if _is_low_pass(best["name"]):
        notes.append(
            f"a low-pass wins here: the true torque hardly varies (std {std:.4f} Nm), so "
            "its lag costs nothing and it removes the sensor noise with the ripple; on a "
            "varying torque it lags (and at low cut-offs loses gain) where the Kalman "
            "filter passes the torque in full with no lag (scenarios torque-steps, "
            "sine-load)"
        )
    else:
        notes.append(
            "a low-pass wins only on a near-constant load (it also removes sensor noise, "
            "and its lag does not show); on a varying torque the Kalman filter passes it in "
            "full with no lag"
        )
    if firmware is not None and firmware["rms_ratio"] > 1.0:
        ripple = ev.get("true_ripple") or {}
        red = firmware["reduction_dB"]
        worst = max(("2x motor", "4x motor"), key=lambda h: -red.get(h, math.nan)
                    if not math.isnan(red.get(h, math.nan)) else -math.inf)  # fmt: skip
        up = -red.get(worst, math.nan)
        plant = (
            "the plant carries no ripple here, so all the filter can subtract is true torque"
            if ripple and max(ripple.values()) < NO_RIPPLE_NM
            else "it subtracts true torque along with the ripple"
        )
        where = (
            f": its error at {worst} angle is {up:.0f} dB above raw's, the true torque's "
            "variation at the ripple frequencies taken for ripple"
            if up > 0
            else ""
        )
        notes.append(
            f"the firmware's filter makes the torque worse than raw "
            f"({firmware['rms_ratio']:.1f}x raw's RMS error): {plant}{where}"
        )
    if any(c["gain"] is None for c in rows):
        if not std >= MIN_TRUE_STD_NM:
            why = (f"the true torque varies too little to measure them (std {std:.4f} Nm, "
                   f"below {MIN_TRUE_STD_NM:g} Nm)")  # fmt: skip
        else:
            why = f"too few samples (fewer than {4 * MAX_LAG_SAMPLES})"
        notes.append(f"gain, lag —: {why}")
    return notes


def format_evaluation(ev: dict[str, Any]) -> str:
    without = ev.get("samples_without_truth", 0)
    if not ev.get("samples"):
        start = f" after {ev['skip_s']:g} s" if ev.get("skip_s") else ""
        if without:
            return (f"  evaluation: no samples with ground truth{start}: the truth frames of "
                    f"all {without} samples are missing (truth faults?)")  # fmt: skip
        return f"  evaluation: no samples with ground truth{start} (run longer or use --skip)"
    lines = [
        f"  evaluation vs truth ({ev['samples']} samples after {ev['skip_s']:g} s; "
        f"RMS true torque {ev['rms_true']:.4f} Nm, std {_fmt(ev.get('std_true'), '.4f')} Nm)",
    ]
    if without:
        lines.append(
            f"    {without} samples without ground truth (truth frames missing) are left out"
        )
    lines += [
        f"    {'candidate':<34} {'RMS err/Nm':>10} {'% raw':>7} {'gain':>6} {'lag/ms':>7} "
        f"{'2x dB':>7} {'4x dB':>7} {'mis p-p/Nm':>10}",
    ]
    for c in ev["candidates"]:
        red = c["reduction_dB"]
        lines.append(
            f"    {c['name']:<34} {_fmt(c['rms_error'], '10.4f')} "
            f"{_fmt(100 * c['rms_ratio'], '7.1f')} {_fmt(c.get('gain'), '6.3f')} "
            f"{_fmt(c['lag_ms'], '7.2f')} {_fmt(red['2x motor'], '7.1f')} "
            f"{_fmt(red['4x motor'], '7.1f')} {_fmt(c['misalignment_pp'], '10.3f')}"
        )
    lines.append(
        "    (gain: slope on the true torque at the lag, 1 = in full; lag: delay aligning best; "
        "dB: vs raw)"
    )
    for note in evaluation_notes(ev):
        lines += textwrap.wrap(note, NOTE_WIDTH, initial_indent="    ", subsequent_indent="      ")
    return "\n".join(lines)
