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
(where the true torque varies enough to define one).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from hdhil.dbc import FrameCodec, codec
from hdhil.firmware.baselines import ButterworthLowPass, TrackingNotchBank
from hdhil.firmware.config import FirmwareConfig, paper_config, recommended_config
from hdhil.firmware.interrupt import CstSample
from hdhil.firmware.isr import TorqueFilterChain
from hdhil.firmware.stages import CstSource, adc_read, calibrate

#: Recording columns, in order.
COLUMNS = (
    "adc_torque", "adc_tacho", "adc_current", "encoder",
    "T_meas_tele", "T_filtered_tele", "velocity_tele",
    "T_true", "T_ripple", "theta_motor", "omega_motor", "theta_output", "missed",
    "torque_actual", "position_actual",
)  # fmt: skip


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
BUTTERWORTH_CUTOFFS_HZ = (10.0, 20.0, 50.0, 100.0)
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
        #: "raw" (the seed's ADC counts and encoder in ``adc_*``/``encoder``) or "cst"
        #: (CiA 402 torque actual and position actual in ``torque_actual`` /
        #: ``position_actual``, ``encoder`` their low 16 bits, the ADC columns NaN).
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

    ``drive_pdos`` (what a trace's sidecar records for a run in a mapping from a DCF,
    :func:`hdhil.canopen.mapping.layouts_to_json`): the drive's PDOs; with the CiA 402
    CST mapping the sensor frame is decoded from the drive's EDS (torque actual 0x6077,
    position actual 0x6064) and the drive's rated torque 0x6076 is taken from the
    controller's SDO read of it at boot, as the firmware did.
    """

    def __init__(self, sample_period_s: float, drive_pdos: dict[str, Any] | None = None) -> None:
        self.recording = Recording(sample_period_s)
        self._sensor = codec("control", "DRIVE_TPDO1").expect(
            "ADC_torque", "ADC_tacho", "ADC_current", "ENC_count"
        )
        self._cst: tuple[int, int] | None = None
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
        self._status = codec("control", "DRIVE_TPDO2").expect("statusword")
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

        db = control_database(layouts_from_json(drive_pdos))
        sensor = FrameCodec(db.get_message_by_name("DRIVE_TPDO1"), "control")
        names = sensor.signal_names
        if {"torque_actual_value", "position_actual_value"} <= set(names):
            self._sensor = sensor
            self._cst = (names.index("torque_actual_value"), names.index("position_actual_value"))
            self.recording.sensor_mapping = "cst"
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

    def _on_statusword(self, data: bytes) -> None:
        (statusword,) = self._status.decode(data)
        # CiA 402 statusword bits 0-3, 5, 6: 0b0100111 = OPERATION ENABLED.
        self._enabled = (statusword & 0x6F) == 0x27

    def _on_sensor(self, data: bytes) -> None:
        nan = math.nan
        if self._cst is None:
            torque, tacho, current, encoder = self._sensor.decode(data)
            actual = position = nan
        else:
            values = self._sensor.decode(data)
            actual, position = values[self._cst[0]], values[self._cst[1]]
            torque = tacho = current = nan
            encoder = int(position) & 0xFFFF
        Ts = self.recording.sample_period_s
        last = self._last_sensor_t
        if last is not None and round((self._t - last) / Ts) <= 0:
            return  # a second sensor frame in one period: the firmware ignores it too
        self._missed += missed_cycles(last, self._t, Ts)
        self._last_sensor_t = self._t
        t = self._truth
        row = (torque, tacho, current, encoder, math.nan, math.nan, math.nan,
               t[0], t[1], t[2], t[3], t[4], float(self._missed), actual, position)  # fmt: skip
        # The truth of one SYNC belongs to one sample: a sample whose truth frames never
        # came (truth faults) has none, rather than the previous sample's.
        self._truth = [math.nan] * 5
        if self._enabled is False:
            self._pending = row  # recorded if the firmware's telemetry answers it
            return
        self.recording.append_row(row)
        self._missed = 0

    def _on_telemetry(self, data: bytes) -> None:
        if self._enabled is False:
            # The firmware runs its interrupt, and sends this, only in operation: the
            # statusword saying so was lost (it is sent on change, then every 100 ms).
            if self._pending is None:
                return
            self._enabled = True
            self.recording.append_row(self._pending)
            self._missed = 0
        self._pending = None
        T_meas, T_filtered, velocity, _current = self._tele.decode(data)
        rec = self.recording
        rec.set_last("T_meas_tele", T_meas)
        rec.set_last("T_filtered_tele", T_filtered)
        rec.set_last("velocity_tele", velocity)

    def _on_truth_torque(self, data: bytes) -> None:
        self._truth[0], self._truth[1] = self._truth_torque.decode(data)

    def _on_truth_motion(self, data: bytes) -> None:
        theta_m, theta_o, omega_m, _omega_o = self._truth_motion.decode(data)
        self._truth[2], self._truth[3], self._truth[4] = theta_m, omega_m, theta_o


def recording_from_trace(path: Path, sample_period_s: float = 1e-3) -> tuple[Recording, str]:
    """Read a trace into a recording; returns it and a damage description ('' if clean).
    The drive's PDO mapping comes from the trace's sidecar JSON (the default mapping
    without one)."""
    from hdhil.can.traces.reader import read_trace
    from hdhil.can.traces.sidecar import read_metadata

    meta = read_metadata(path) or {}
    listener = RecordingListener(sample_period_s, meta.get("drive_pdos"))
    with read_trace(path) as trace:
        for msg in trace:
            listener.on_message_received(msg)
        damage = "; ".join(d.describe(str(path)) for d in trace.damage)
    return listener.recording, damage


@dataclass(frozen=True)
class CandidateScore:
    name: str
    rms_error: float
    rms_ratio: float
    harmonics: dict[str, float]  # amplitude of the error at each harmonic (Nm)
    reduction_dB: dict[str, float]  # vs raw
    misalignment_pp: float
    lag_ms: float | None


def _unwrap_angle(wrapped: np.ndarray) -> np.ndarray:
    return np.unwrap(wrapped)


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


def estimate_lag(x: np.ndarray, truth: np.ndarray, sample_period_s: float) -> float | None:
    """Delay (ms) of ``x`` behind ``truth``: argmin over d of mean (x(k) − truth(k−d))²."""
    n = len(x)
    if n < 4 * MAX_LAG_SAMPLES or np.var(truth) < 1e-2:
        return None
    lags = np.arange(0, MAX_LAG_SAMPLES + 1)
    costs = np.array([np.mean((x[MAX_LAG_SAMPLES:] - truth[MAX_LAG_SAMPLES - d : n - d]) ** 2)
                      for d in lags])  # fmt: skip
    i = int(np.argmin(costs))
    shift = 0.0
    if 0 < i < len(lags) - 1:
        c0, c1, c2 = costs[i - 1], costs[i], costs[i + 1]
        denom = c0 - 2 * c1 + c2
        if denom > 0:
            shift = 0.5 * (c0 - c2) / denom
    return float((lags[i] + shift) * sample_period_s * 1e3)


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
    chain = TorqueFilterChain(cfg)
    step = chain.step
    out: list[float] = []
    append = out.append
    gaps = [0] * len(T_meas) if missed is None else missed.astype(np.int64).tolist()
    for T, v, e, gap in zip(
        T_meas.tolist(), velocity.tolist(), encoder.astype(np.int64).tolist(), gaps, strict=True
    ):
        if gap:
            for _ in range(gap):
                chain.sample_missed()
        append(step(T, v, e)[3])
    return np.array(out, dtype=np.float64)


def calibrated_signals(rec: Recording, cfg: FirmwareConfig) -> tuple[np.ndarray, np.ndarray]:
    """T_meas and motor velocity from the recorded counts, through the firmware's stages
    (in the CST mapping its :class:`firmware.stages.CstSource`).

    In the raw mapping each channel is calibrated on its own (:func:`firmware.stages.
    calibrate`: T_meas from the torque count, the velocity from the tacho count), so
    each distinct count goes through ``adc_read`` and ``calibrate`` once and the
    samples take their values from that table: the same numbers as sample by sample."""
    if rec.sensor_mapping == "cst":
        return _cst_signals(rec, cfg)
    adc, cal = cfg.adc, cfg.calibration
    T_meas = _per_count(
        rec.column("adc_torque"), lambda q: calibrate(*adc_read(q, 0, 0, adc), cal)[0]
    )
    vel = _per_count(
        rec.column("adc_tacho"), lambda tq: calibrate(*adc_read(0, tq, 0, adc), cal)[1]
    )
    return T_meas, vel


def _per_count(counts: np.ndarray, convert: Callable[[int], float]) -> np.ndarray:
    """``convert(count)`` for every sample, computed once per distinct count."""
    distinct, where = np.unique(counts.astype(np.int64), return_inverse=True)
    table = np.array([convert(c) for c in distinct.tolist()], dtype=np.float64)
    return table[where.reshape(-1)]


def _cst_signals(rec: Recording, cfg: FirmwareConfig) -> tuple[np.ndarray, np.ndarray]:
    rated = rec.rated_torque_Nm
    if rated is None:
        raise ValueError(
            "the trace holds no answer to the controller's read of the drive's rated "
            "torque 0x6076: the CST torque actual values cannot be scaled"
        )
    source = CstSource(
        rated, cfg.calibration.encoder_counts_per_rev, cfg.diff_tau_s, cfg.sample_period_s
    )
    n = len(rec)
    T_meas = np.empty(n)
    vel = np.empty(n)
    for k, (q, pos) in enumerate(
        zip(
            rec.column("torque_actual").astype(np.int64).tolist(),
            rec.column("position_actual").astype(np.int64).tolist(),
            strict=True,
        )
    ):
        T_meas[k], vel[k] = source(CstSample(q, pos))[:2]
    return T_meas, vel


def candidate_signals(rec: Recording, cfg: FirmwareConfig) -> dict[str, np.ndarray]:
    """Every candidate's torque estimate over the recording, keyed by display name."""
    T_meas, vel = calibrated_signals(rec, cfg)
    encoder = rec.column("encoder")
    Ts = cfg.sample_period_s
    mode = cfg.ripple.mode
    signals = {"raw": T_meas, f"firmware ({mode})": rec.column("T_filtered_tele")}
    paper = paper_config(cfg)
    recommended = recommended_config(cfg)
    missed = rec.column("missed")
    signals[f"kalman paper ({paper.ripple.order}th order)"] = offline_chain(
        paper, T_meas, vel, encoder, missed
    )
    signals[f"kalman recommended ({len(recommended.ripple.oscillators)} harmonics)"] = (
        offline_chain(recommended, T_meas, vel, encoder, missed)
    )
    for fc in BUTTERWORTH_CUTOFFS_HZ:
        if fc < 0.5 / Ts:
            signals[f"butterworth {fc:g} Hz"] = ButterworthLowPass(fc, Ts).filter(T_meas)
    signals["notch bank 2x/4x"] = TrackingNotchBank((2.0, 4.0), Ts).filter(T_meas, vel)
    return signals


def evaluate(rec: Recording, cfg: FirmwareConfig, skip_s: float = 0.0) -> dict[str, Any]:
    """Score every candidate against truth over the firmware's samples
    (:meth:`Recording.operation`) from ``skip_s``; returns a JSON-ready dict."""
    rec = rec.operation()
    n = len(rec)
    T_true = rec.column("T_true")
    valid = np.isfinite(T_true)
    if n == 0:
        return {"samples": 0, "candidates": []}
    if not valid.any():
        # No ground truth at all (a trace without the truth channel, or truth silenced)
        return {"samples": 0, "skip_s": skip_s, "candidates": [], "samples_without_truth": n}
    signals = candidate_signals(rec, cfg)
    k0 = min(n, round(skip_s / cfg.sample_period_s))
    window = np.zeros(n, dtype=bool)
    window[k0:] = True
    window &= valid
    # Samples in the window without ground truth (truth frames lost or silenced): left
    # out of every score, and reported.
    without_truth = int(n - k0 - window[k0:].sum())
    missing = {"samples_without_truth": without_truth} if without_truth else {}
    if not window.any():
        return {"samples": 0, "skip_s": skip_s, "candidates": [], **missing}
    theta_m = _unwrap_angle(rec.column("theta_motor"))
    theta_o = _unwrap_angle(rec.column("theta_output"))
    turning = window & (np.abs(rec.column("omega_motor")) > MIN_SPEED_RADPS)
    angles = {"motor": theta_m, "output": theta_o}
    phasors = {label: np.exp(-1j * mult * angles[src]) for label, src, mult in HARMONICS}

    scores = []
    raw_rms = raw_harm = None
    for name, x in signals.items():
        ok = window & np.isfinite(x)
        err = x - T_true
        rms = float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else math.nan
        harm = {label: _demodulated_amplitude(err, phasors[label], turning & ok)
                for label, _, _ in HARMONICS}  # fmt: skip
        if raw_rms is None:
            raw_rms, raw_harm = rms, harm
        reduction = {label: _reduction_dB(raw_harm[label], a) for label, a in harm.items()}
        lag = estimate_lag(
            np.where(ok, x, 0.0)[k0:], np.where(ok, T_true, 0.0)[k0:], cfg.sample_period_s
        )
        scores.append(CandidateScore(
            name=name, rms_error=rms, rms_ratio=rms / raw_rms if raw_rms else math.nan,
            harmonics=harm, reduction_dB=reduction,
            misalignment_pp=2.0 * harm["1x output"], lag_ms=lag,
        ))  # fmt: skip
    return {
        "samples": int(window.sum()),
        "skip_s": skip_s,
        "rms_true": float(np.sqrt(np.mean(T_true[window] ** 2))),
        "true_ripple": {
            label: _demodulated_amplitude(rec.column("T_ripple"), phasors[label], turning)
            for label, _, _ in HARMONICS
        },
        "candidates": [dataclasses.asdict(s) for s in scores],
        **missing,
    }


def _fmt(v: float | None, spec: str) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    if isinstance(v, float) and math.isinf(v):
        return "∞"
    return format(v, spec)


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
        f"RMS true torque {ev['rms_true']:.4f} Nm)",
    ]
    if without:
        lines.append(
            f"    {without} samples without ground truth (truth frames missing) are left out"
        )
    lines += [
        f"    {'candidate':<34} {'RMS err/Nm':>10} {'% raw':>7} {'2x dB':>7} {'4x dB':>7} "
        f"{'mis p-p/Nm':>10} {'lag/ms':>7}",
    ]
    for c in ev["candidates"]:
        red = c["reduction_dB"]
        lines.append(
            f"    {c['name']:<34} {_fmt(c['rms_error'], '10.4f')} "
            f"{_fmt(100 * c['rms_ratio'], '7.1f')} {_fmt(red['2x motor'], '7.1f')} "
            f"{_fmt(red['4x motor'], '7.1f')} {_fmt(c['misalignment_pp'], '10.3f')} "
            f"{_fmt(c['lag_ms'], '7.2f')}"
        )
    lines.append(
        "    (dB: reduction of the error's harmonic amplitude against raw; "
        "mis p-p: residual at 1x output angle)"
    )
    return "\n".join(lines)
