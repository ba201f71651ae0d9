"""``hdhil filter INPUT --out OUT.csv``: run the firmware's torque filter offline.

The filtering is the firmware's own code, not a copy, so the output is what the
controller computes on the same samples. Inputs: a signal CSV (``time``, ``T_meas`` in
Nm, ``velocity`` in rad/s, optionally the 16-bit ``encoder``; or the unit-suffixed
columns ``hdhil dump --csv`` writes), which goes through
:class:`firmware.isr.TorqueFilterChain`; or a trace written by ``hdhil run``, whose
``DRIVE_TPDO1`` ADC counts go through the whole interrupt handler
(:class:`firmware.isr.InterruptHandler`: ADC read, calibration, the same chain).
Without an encoder the recommended filter takes its phase from the integrated velocity.
Non-finite values reach the filter, which skips and counts them; anything else that is
not a number is an error naming the line.

Output: a CSV ``time_s,T_meas_Nm,acceleration_radps2,T_expected_Nm,ripple_Nm,
T_filtered_Nm``, written atomically. Configuration: the firmware defaults, ``--config``
(a scenario file or firmware tables) or ``--paper`` ([Taghirad97] listing A.1).
Exit codes: 0 done; 1 the trace is damaged (what was readable is filtered); 2 a user
error.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import gzip
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

from hdhil.can.traces.formats import SUPPORTED_SUFFIXES as TRACE_EXTENSIONS
from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.core.errors import UserError
from hdhil.core.files import MAX_LINE_CHARS, AtomicOutput, bounded_lines, check_input, load_toml
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.isr import AdcSample, InterruptHandler, TorqueFilterChain
from hdhil.rig.evaluate import missed_cycles

#: Output columns, in order.
OUTPUT_COLUMNS = (
    "time_s", "T_meas_Nm", "acceleration_radps2", "T_expected_Nm", "ripple_Nm", "T_filtered_Nm"
)  # fmt: skip
#: Required columns of a signal CSV.
REQUIRED_COLUMNS = ("time", "T_meas", "velocity")
#: The names each input column may have: bare, or with its unit as ``hdhil dump --csv``
#: writes it (so a per-cycle export filters directly).
COLUMN_ALIASES = {
    "time": ("time", "time_s"),
    "T_meas": ("T_meas", "T_meas_Nm"),
    "velocity": ("velocity", "velocity_radps"),
    "encoder": ("encoder", "ENC_count"),
}


def _column(names: list[str], column: str) -> int | None:
    """Index of ``column`` (under any of its aliases) in ``names``, or ``None``."""
    for alias in COLUMN_ALIASES[column]:
        if alias in names:
            return names.index(alias)
    return None


_CAN_CSV_HEADER = "timestamp,arbitration_id"

__all__ = [
    "OUTPUT_COLUMNS",
    "REQUIRED_COLUMNS",
    "FilterSummary",
    "filter_signal_csv",
    "filter_trace",
    "load_firmware_config",
]


# ------------------------------------------------------------------------ configuration
def load_firmware_config(path: str | os.PathLike[str] | None) -> FirmwareConfig:
    """The firmware configuration from a TOML file (``None``: the defaults).

    A file with a ``firmware`` table (a scenario file) contributes that table; any other
    file is read as the firmware tables themselves.
    """
    if path is None:
        return FirmwareConfig()
    p = Path(path)
    data = load_toml(p, "--config")
    table: Any = data.get("firmware", data)
    if not isinstance(table, dict):
        raise UserError(f"--config {p}: [firmware] must be a table")
    try:
        return from_dict(FirmwareConfig, table, "firmware")
    except ConfigError as exc:
        raise ConfigError(f"--config {p}: {exc}") from None


# ------------------------------------------------------------------------------ output
class _CsvTarget:
    """The output CSV through :class:`hdhil.core.files.AtomicOutput`: a regular file (or
    ``-``, stdout) only, replaced by :meth:`commit` once complete; :meth:`abort` removes
    the temporary file and leaves the old one as it was."""

    def __init__(self, target: str, source: Path) -> None:
        self._out = AtomicOutput(target, "--out")
        self.label = "stdout" if target == "-" else target
        out = self._out.target
        if out is not None:
            with contextlib.suppress(OSError):
                if out.exists() and out.resolve() == source.resolve():
                    raise UserError(f"--out {target}: would overwrite the input")
        file = self._out.__enter__().file
        assert file is not None
        self.file: TextIO = file
        self.writer = csv.writer(self.file, lineterminator="\n")
        self.writer.writerow(OUTPUT_COLUMNS)

    def commit(self) -> None:
        try:
            self._out.__exit__(None, None, None)
        except OSError as exc:
            self.abort()
            raise UserError(f"--out {self.label}: cannot write ({exc.strerror or exc})") from None

    def abort(self) -> None:
        with contextlib.suppress(OSError):
            self._out.__exit__(RuntimeError, None, None)


# ------------------------------------------------------------------------------- input
def _split_suffix(path: Path) -> tuple[str, bool]:
    suffixes = [s.lower() for s in path.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        return (suffixes[-2] if len(suffixes) >= 2 else ""), True
    return (suffixes[-1] if suffixes else ""), False


def _open_text(path: Path, compressed: bool) -> TextIO:
    if compressed:
        return gzip.open(path, "rt", encoding="utf-8", errors="replace", newline="")
    return open(path, encoding="utf-8", errors="replace", newline="")


def _check_input(path: Path) -> tuple[str, bool]:
    """``(format, compressed)`` of an existing, readable, supported input."""
    check_input(path)  # a regular file (a FIFO or a device would block or never end)
    fmt, compressed = _split_suffix(path)
    if fmt not in TRACE_EXTENSIONS:
        raise UserError(
            f"{path}: unsupported input format {fmt or '(no extension)'!r}; use a .csv with "
            f"columns {','.join(REQUIRED_COLUMNS)}[,encoder] or a trace "
            f"({', '.join(TRACE_EXTENSIONS)}, optionally .gz)"
        )
    if not os.access(path, os.R_OK):
        raise UserError(f"{path}: permission denied")
    return fmt, compressed


def _is_can_csv(path: Path, compressed: bool) -> bool:
    """A ``.csv`` whose first line is python-can's trace header."""
    try:
        with _open_text(path, compressed) as fh:
            first = fh.readline(MAX_LINE_CHARS)
    except (OSError, EOFError) as exc:
        raise UserError(f"{path}: cannot read ({exc})") from None
    return first.lstrip("\ufeff").strip().replace(" ", "").startswith(_CAN_CSV_HEADER)


class FilterSummary:
    """What a filter run did (for the summary line and for library callers)."""

    def __init__(self, cfg: FirmwareConfig, phase: str, source: str) -> None:
        self.cfg = cfg
        self.phase = phase
        self.source = source
        self.samples = 0
        self.skipped = 0
        self.covariance_resets = 0
        self.malformed_frames = 0
        #: Sensor frames before the firmware's first interrupt (start-up, settling pause),
        #: left out as the firmware left them.
        self.before_first_interrupt = 0
        self.damage: list[str] = []

    def line(self, out_label: str) -> str:
        ripple = self.cfg.ripple
        what = f"{ripple.mode} filter, {len(ripple.oscillators)} harmonics"
        if ripple.mode == "recommended":
            what += f", phase from {self.phase}"
        parts = [
            f"{self.samples} samples from {self.source}",
            f"{self.skipped} skipped (non-finite)",
        ]
        if ripple.mode == "recommended":
            parts.append(f"{self.covariance_resets} covariance resets")
        if self.malformed_frames:
            parts.append(f"{self.malformed_frames} malformed DRIVE_TPDO1 frames ignored")
        if self.before_first_interrupt:
            parts.append(
                f"{self.before_first_interrupt} sensor frames before the firmware's first "
                "interrupt left out"
            )
        return f"hdhil filter: {', '.join(parts)} ({what}); wrote {out_label}"


def _number(text: str, column: str, where: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise UserError(f"{where}: column {column!r}: not a number: {text.strip()!r}") from None


def _count(text: str, where: str) -> int:
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not value.is_integer():
        raise UserError(f"{where}: column 'encoder': not an integer count: {text.strip()!r}")
    return int(value)


def _cell(text: str) -> float:
    """A signal cell: a number, or NaN where it is empty (a cycle whose frame is missing
    in a per-cycle export; the filter skips and counts it like any non-finite sample)."""
    return float(text) if text.strip() else math.nan


def filter_signal_csv(
    path: Path, compressed: bool, cfg: FirmwareConfig, writer: Any
) -> FilterSummary:
    """Filter a signal CSV through :class:`TorqueFilterChain`, writing output rows."""
    label = str(path)
    with _open_text(path, compressed) as fh:
        reader = csv.reader(bounded_lines(fh, label))
        try:
            header = next(reader)
        except StopIteration:
            raise UserError(f"{label}: empty file (expected a header line)") from None
        except csv.Error as exc:
            raise UserError(f"{label}:1: {exc}") from None
        names = [h.strip().lstrip("\ufeff") for h in header]
        missing = [c for c in REQUIRED_COLUMNS if _column(names, c) is None]
        if missing:
            raise UserError(
                f"{label}: missing column(s) {', '.join(missing)} "
                f"(header: {','.join(names) or '(empty)'})"
            )
        i_time, i_T, i_vel = (_column(names, c) for c in REQUIRED_COLUMNS)
        assert i_time is not None and i_T is not None and i_vel is not None
        i_enc = _column(names, "encoder")
        phase = cfg.ripple.phase_source
        if i_enc is None and cfg.ripple.mode == "recommended" and phase == "encoder":
            cfg = _with_tacho_phase(cfg)
            phase = "tacho (no encoder column)"
        width = len(names)
        chain = TorqueFilterChain(cfg)
        step = chain.step
        writerow = writer.writerow
        summary = FilterSummary(cfg, phase, "signal CSV")
        n = 0
        line = 1
        try:
            for row in reader:
                line = reader.line_num
                if not row or (len(row) == 1 and not row[0].strip()):
                    continue  # blank line
                if len(row) != width:
                    raise UserError(f"{label}:{line}: expected {width} fields, got {len(row)}")
                try:
                    t = float(row[i_time])
                    T = _cell(row[i_T])
                    v = _cell(row[i_vel])
                except ValueError:
                    where = f"{label}:{line}"
                    for i, name in ((i_time, "time"), (i_T, "T_meas"), (i_vel, "velocity")):
                        _number(row[i], name, where)
                    raise  # pragma: no cover - one of the three raised
                enc = None if i_enc is None else _count(row[i_enc], f"{label}:{line}")
                acc, T_exp, _dT, T_f, ripple = step(T, v, enc)
                writerow((t, T, acc, T_exp, ripple, T_f))
                n += 1
        except csv.Error as exc:
            raise UserError(f"{label}:{line}: {exc}") from None
    if n == 0:
        raise UserError(f"{label}: no samples (only a header line)")
    summary.samples = n
    _collect(summary, chain)
    return summary


def _with_tacho_phase(cfg: FirmwareConfig) -> FirmwareConfig:
    return dataclasses.replace(cfg, ripple=dataclasses.replace(cfg.ripple, phase_source="tacho"))


def _collect(summary: FilterSummary, chain: TorqueFilterChain) -> None:
    summary.skipped = chain.kalman.skipped
    summary.covariance_resets = getattr(chain.kalman, "covariance_resets", 0)


def _trace_ids(path: Path) -> tuple[int, int]:
    """The identifiers of the drive's sensor frame and of the controller's telemetry in
    the trace at ``path``: at the node-IDs its sidecar's layout records (the
    single-joint rig's, 0x182 and 0x181, without one)."""
    from hdhil.can.traces.sidecar import read_metadata
    from hdhil.canopen.mapping import trace_node_ids
    from hdhil.rig.evaluate import layout_frame_ids

    drive, controller = trace_node_ids(read_metadata(path) if path.is_file() else None)
    sensor, _status, _sdo, telemetry = layout_frame_ids(None, drive, controller)
    return sensor, telemetry


def _sensor_frames(path: Path, summary: FilterSummary) -> Iterator[tuple[float, tuple[int, ...]]]:
    """``(timestamp, (torque, tacho, current, encoder))`` of every DRIVE_TPDO1 frame."""
    from hdhil.can.traces.reader import read_trace
    from hdhil.dbc import codec

    sensor = codec("control", "DRIVE_TPDO1").expect(
        "ADC_torque", "ADC_tacho", "ADC_current", "ENC_count"
    )
    frame_id = _trace_ids(Path(path))[0]
    length = sensor.length
    decode = sensor.decode
    trace = read_trace(path)
    with trace:
        t0 = trace.first_time or 0.0
        for msg in trace:
            if msg.arbitration_id != frame_id or msg.is_extended_id:
                continue
            if msg.is_remote_frame or msg.is_error_frame or len(msg.data) != length:
                summary.malformed_frames += 1
                continue
            yield msg.timestamp - t0, decode(msg.data)  # type: ignore[misc]
    summary.damage = [d.describe(trace.path) for d in trace.damage]


def _first_interrupt_time(path: Path) -> float | None:
    """The time (from the trace's first frame) of the controller's first telemetry frame
    (``CTRL_TPDO1``), or None when the trace has none (a logger of another firmware).

    hdhil's firmware sends it from every interrupt it runs and from nothing else, so the
    sensor frame of its first interrupt is the last DRIVE_TPDO1 before it: those before
    came while the controller was starting the drive or held the start-up output
    (``FirmwareConfig.startup_settle_s``, [Taghirad97] listing ``main()``)."""
    from hdhil.can.traces.reader import read_trace

    telemetry_id = _trace_ids(Path(path))[1]
    trace = read_trace(path)
    with trace:
        t0 = trace.first_time or 0.0
        for msg in trace:
            if msg.arbitration_id == telemetry_id and not msg.is_extended_id:
                return float(msg.timestamp - t0)
    return None


def _control_frames(
    path: Path, summary: FilterSummary
) -> Iterator[tuple[str, float, bytes | tuple[int, ...]]]:
    """The control-bus frames the replay needs, in the trace's order: ``("sensor", t,
    (torque, tacho, current, encoder))`` for DRIVE_TPDO1, ``("sync", t, data)`` and
    ``("telemetry", t, data)`` for the controller's SYNC and CTRL_TPDO1.

    Only the sensor frames' channel is read: a logger joined to two buses that both carry
    the control frames (two multicast groups on one port) records each frame twice."""
    from hdhil.can.traces.reader import read_trace
    from hdhil.dbc import codec

    sensor = codec("control", "DRIVE_TPDO1").expect(
        "ADC_torque", "ADC_tacho", "ADC_current", "ENC_count"
    )
    sensor_id, telemetry_id = _trace_ids(Path(path))
    length = sensor.length
    decode = sensor.decode
    sync_id = codec("control", "SYNC").frame_id
    channel: object = _UNSET
    trace = read_trace(path)
    with trace:
        t0 = trace.first_time or 0.0
        for msg in trace:
            fid = msg.arbitration_id
            if msg.is_extended_id or fid not in (sensor_id, sync_id, telemetry_id):
                continue
            if fid == sensor_id:
                if msg.is_remote_frame or msg.is_error_frame or len(msg.data) != length:
                    summary.malformed_frames += 1
                    continue
                if channel is _UNSET:
                    channel = msg.channel
                elif msg.channel != channel:
                    continue
                yield "sensor", msg.timestamp - t0, decode(msg.data)  # type: ignore[misc]
            elif msg.is_remote_frame or msg.is_error_frame:
                continue
            elif channel is _UNSET or msg.channel == channel:
                kind = "sync" if fid == sync_id else "telemetry"
                yield kind, msg.timestamp - t0, bytes(msg.data)
    summary.damage = [d.describe(trace.path) for d in trace.damage]


_UNSET = object()


def _by_timestamp(
    frames: Iterator[tuple[float, tuple[int, ...]]], sample_period_s: float
) -> Iterator[tuple[int, float, tuple[int, ...]]]:
    """``(missed, t, counts)`` of a trace without hdhil's telemetry: a sample per period
    from the frames' timestamps (a second frame in one period left out, as the firmware
    leaves it), the periods without a frame counted as missed."""
    previous: float | None = None
    for t, counts in frames:
        if previous is not None and round((t - previous) / sample_period_s) <= 0:
            continue
        missed = missed_cycles(previous, t, sample_period_s)
        previous = t
        yield missed, t, counts


class _FirmwareView:
    """Which sensor frames the firmware ran its interrupt on, and the periods it skipped,
    from the order of the control-bus frames (the frames of :func:`_control_frames`).

    The firmware runs its interrupt once per SYNC, on the first sensor frame it reads
    after that SYNC, and answers it with its telemetry (``CTRL_TPDO1``); a frame it reads
    later in the same cycle is ignored, and a frame that reaches it after its answer waits
    for the next SYNC.  In lockstep the trace's order is the firmware's; in real time a
    late frame (the drive's process held up) is answered a cycle later and a burst of
    frames loses all but one, which the frames' timestamps do not tell.  The telemetry
    does: it carries the sample's ``T_meas``, velocity and current, which name the sensor
    frame among those not yet answered.  The periods the firmware skipped are the SYNCs
    between two telemetry frames, less one.  A sensor frame alone in a period without
    telemetry (its telemetry lost, or the drive's stop) counts as a sample, as does one
    whose telemetry names none of the frames waiting (another firmware, another
    calibration): the last one waiting, as a lockstep trace has it.

    Yields ``(missed, t, counts)``: the periods skipped before the sample, its frame's
    time and counts."""

    def __init__(self, cfg: FirmwareConfig, summary: FilterSummary) -> None:
        from hdhil.dbc import codec
        from hdhil.firmware.stages.sources import AdcSource

        self._source = AdcSource(cfg.adc, cfg.calibration)
        self._telemetry = codec("control", "CTRL_TPDO1")
        self._summary = summary
        self._period_s = cfg.sample_period_s

    def _key(self, counts: tuple[int, ...]) -> bytes:
        T_meas, velocity, current, *_ = self._source(AdcSample(*counts))
        data = self._telemetry.encode(T_meas, 0.0, velocity, current)
        return data[:2] + data[4:]

    def samples(
        self, frames: Iterator[tuple[str, float, Any]]
    ) -> Iterator[tuple[int, float, tuple[int, ...]]]:
        summary = self._summary
        # Sensor frames not yet answered: (period index, first in its period, t, counts).
        waiting: list[tuple[int, bool, float, tuple[int, ...]]] = []
        period = 0  # SYNCs seen
        last_sync: bytes | None = None
        last_sync_t = 0.0
        sensor_in_period = False
        answered: int | None = None  # the period of the last sample (None: none yet)
        for kind, t, value in frames:
            if kind == "sync":
                if value and value == last_sync:
                    continue  # a duplicated SYNC (its counter repeats)
                period += self._periods(last_sync, last_sync_t, value, t)
                last_sync, last_sync_t = value, t
                sensor_in_period = False
            elif kind == "sensor":
                waiting.append((period, not sensor_in_period, t, value))
                sensor_in_period = True
            elif waiting:  # telemetry answering one of the waiting frames
                want = value[:2] + value[4:]
                # Before the first interrupt every frame was answered in its period (the
                # drive's start-up, the start-up pause): its frame came in this period or
                # late in the previous one.
                start = 0
                if answered is None:
                    start = next(
                        (i for i, w in enumerate(waiting) if w[0] >= period - 1),
                        len(waiting) - 1,
                    )
                matches = [
                    i for i in range(start, len(waiting)) if self._key(waiting[i][3]) == want
                ]
                # Equal counts (the encoder aside) in several frames: the first frame of
                # this period, as in lockstep, else the oldest.
                index = next(
                    (i for i in matches if waiting[i][0] == period and waiting[i][1]),
                    matches[0] if matches else len(waiting) - 1,
                )
                if answered is None:
                    summary.before_first_interrupt += index
                else:
                    for sample in self._unanswered(waiting[:index], answered, period):
                        answered += sample[0] + 1
                        yield sample
                missed = 0 if answered is None else max(0, period - answered - 1)
                _, _, ts, counts = waiting[index]
                answered = period
                del waiting[: index + 1]
                yield missed, ts, counts
        if answered is not None:
            yield from self._unanswered(waiting, answered, period + 1)

    def _periods(self, last: bytes | None, last_t: float, sync: bytes, t: float) -> int:
        """Periods from the SYNC ``last`` (at ``last_t``) to ``sync`` (at ``t``): by the
        CiA 301 counter, or where it wrapped or is not sent, by the time (a SYNC lost on
        the bus is a period all the same)."""
        if last is None:
            return 1
        if sync and last and sync[0] > last[0]:
            return sync[0] - last[0]
        return max(1, round((t - last_t) / self._period_s))

    def _unanswered(
        self, waiting: list[tuple[int, bool, float, tuple[int, ...]]], after: int, before: int
    ) -> Iterator[tuple[int, float, tuple[int, ...]]]:
        """The frames of ``waiting`` the firmware ran its interrupt on without telemetry:
        the first frame of each period between ``after`` and ``before`` (exclusive) that
        has no telemetry; the others were ignored."""
        last = after
        for p, first, ts, counts in waiting:
            if first and last < p < before:
                yield p - last - 1, ts, counts
                last = p


def filter_trace(path: Path, cfg: FirmwareConfig, writer: Any) -> FilterSummary:
    """Filter the DRIVE_TPDO1 frames of a trace through the firmware's interrupt
    handler (ADC read, calibration, :class:`TorqueFilterChain`), writing output rows.

    The samples are those the firmware ran its interrupt on, in its cycles
    (:class:`_FirmwareView`): a trace of hdhil's firmware (its telemetry tells) is
    replayed from its first interrupt's sensor frame, with the frames it ignored left out
    and the periods it skipped told to the handler; any other trace from its first sensor
    frame, one frame per period."""
    isr = InterruptHandler(cfg)
    summary = FilterSummary(cfg, cfg.ripple.phase_source, "DRIVE_TPDO1 frames")
    writerow = writer.writerow
    n = 0
    samples = (
        _FirmwareView(cfg, summary).samples(_control_frames(path, summary))
        if _first_interrupt_time(path) is not None
        else _by_timestamp(_sensor_frames(path, summary), cfg.sample_period_s)
    )
    for missed, t, (torque, tacho, current, encoder) in samples:
        for _ in range(missed):
            isr.sample_missed()
        out = isr(AdcSample(torque, tacho, current, encoder))
        writerow((t, out.T_meas, out.acceleration, out.T_expected, out.ripple, out.T_filtered))
        n += 1
    if n == 0:
        raise UserError(f"{path}: no DRIVE_TPDO1 frames (drive sensor frames) in the trace")
    summary.samples = n
    _collect(summary, isr.chain)
    return summary
