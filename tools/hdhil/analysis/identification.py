"""Natural frequency and damping of the flexible joint from an open-loop chirp
([Vertechy] §II, Fig. 5): the half-power bandwidth method, cross-checked by the
logarithmic decrement.

With the link free, [Vertechy] Eq. 2 makes the sensor torque's response to the motor
torque a second-order system (plant sign, ``T = -tau_s``)::

    T / tau_m = K wn² / (s² + 2 zeta wn s + wn²),   K = J / J_m = J_l / (J_m + J_l),
    wn² = k / J,   2 zeta wn = c / J,   J = J_m J_l / (J_m + J_l)

The steps, each a function: :func:`chirp_data_from_trace` (one command/sensor pair per
control cycle), :func:`frequency_response` (Welch H1 over the excited band),
:func:`half_power` and :func:`log_decrement` (the two readings), :func:`identify` (all
of them, with ``c = 2 zeta wn J`` and ``k = J wn²``), :func:`format_identification`
and :func:`make_figure` (the report and the Bode plot).  ``hdhil identify`` is the
command line over them; Python code calls them directly.  Input mistakes (no command
frames, too short, no resonance in the band) raise :class:`hdhil.core.errors.UserError`.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import signal

from hdhil.core.errors import UserError
from hdhil.dbc import codec, predefined_cob_id
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.stages import adc_read, calibrate
from hdhil.hostsim.plant import PlantConfig

__all__ = [
    "DEFAULT_SEGMENT_S",
    "ChirpData",
    "FrequencyResponse",
    "HalfPower",
    "Identification",
    "LogDecrement",
    "chirp_data_from_trace",
    "format_identification",
    "frequency_response",
    "half_power",
    "identify",
    "log_decrement",
    "make_figure",
    "model_values",
]

#: Welch segment length (s): 4.1 s at 1 kHz (4096 samples) resolves 0.24 Hz, a
#: fourteenth of the seed joint's 3.4 Hz half-power bandwidth.
DEFAULT_SEGMENT_S = 4.096
#: Welch segment overlap (fraction of a segment).
OVERLAP = 0.75
#: The excited band: bins where the command's spectrum is at least this fraction of its peak.
BAND_FRACTION = 0.05
#: Band-pass for the impulse response: Gaussian std in multiples of the half-power bandwidth.
BANDPASS_WIDTHS = 1.0
#: Log decrement: peaks start this many Gaussian time constants after the envelope's peak.
SETTLE_SIGMAS = 3.0
#: Log decrement: peaks down to this fraction of the largest envelope value, at most MAX_PEAKS.
PEAK_FLOOR = 0.03
MAX_PEAKS = 10
#: CiA 402 controlword bits that enable the drive (as hostsim.drive).
_ENABLE_MASK = 0x000F


# ----------------------------------------------------------------------------- signals


@dataclass(frozen=True)
class ChirpData:
    """Per-cycle signals of a trace: motor torque command ``u`` and sensor torque ``y``
    (Nm at the output), sampled every ``sample_period_s``."""

    u: np.ndarray
    y: np.ndarray
    sample_period_s: float
    torque_saturated: int = 0  #: torque samples at the ADC's end codes
    damage: str = ""  #: description of trace damage ('' if clean)

    def __len__(self) -> int:
        return len(self.y)


def chirp_data_from_trace(
    path: Path, firmware: FirmwareConfig, torque_per_volt: float
) -> ChirpData:
    """Read a trace into (command, sensor torque) pairs, one per control cycle.

    Sensor torque: ``DRIVE_TPDO1.ADC_torque`` -> volts (firmware ADC) -> Nm (firmware
    calibration, ``[firmware.calibration] volt2Nm``).  Command: ``DRIVE_RPDO1.DAC_cmd``
    of the same cycle -> volts (firmware DAC) x ``torque_per_volt`` (the actuator's output
    torque per volt, :attr:`hostsim.plant.PlantConfig.torque_per_volt`); 0 while the
    controlword does not enable the drive.  The command of cycle k is paired with the
    sample of cycle k: the actuation delay (one or two samples) changes the phase of H,
    not its magnitude.  Cycles without a command (the trace's last, typically) are
    dropped.
    """
    from hdhil.can.traces.reader import read_trace

    sensor = codec("control", "DRIVE_TPDO1").expect(
        "ADC_torque", "ADC_tacho", "ADC_current", "ENC_count"
    )
    command = codec("control", "DRIVE_RPDO1").expect("DAC_cmd", "controlword", "cycle")
    # a drive at another node-ID (the trace's sidecar layout): its frames at its identifiers
    from hdhil.can.traces.sidecar import read_metadata
    from hdhil.canopen.mapping import trace_node_ids

    drive_id, _ = trace_node_ids(read_metadata(path) if Path(path).is_file() else None)
    sensor = sensor.at(predefined_cob_id("tpdo", 1, drive_id))
    command = command.at(predefined_cob_id("rpdo", 1, drive_id))
    adc, dac, cal = firmware.adc, firmware.dac, firmware.calibration
    ys: list[float] = []
    us: list[float] = []
    saturated = 0
    commands = 0
    with read_trace(path) as trace:
        for msg in trace:
            if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
                continue
            if msg.arbitration_id == sensor.frame_id:
                with contextlib.suppress(ValueError):
                    counts = sensor.decode(msg.data)[0]
                    torque_V = adc_read(counts, 0, 0, adc)[0]
                    ys.append(calibrate(torque_V, 0.0, 0.0, cal)[0])
                    us.append(math.nan)
                    saturated += adc.saturated(counts)
            elif msg.arbitration_id == command.frame_id and us:
                with contextlib.suppress(ValueError):
                    counts, controlword, _cycle = command.decode(msg.data)
                    enabled = (controlword & _ENABLE_MASK) == _ENABLE_MASK
                    us[-1] = dac.to_volts(counts) * torque_per_volt if enabled else 0.0
                    commands += 1
        damage = "; ".join(d.describe(str(path)) for d in trace.damage)
    if not ys:
        raise UserError(f"{path}: no DRIVE_TPDO1 frames (drive sensor frames): nothing to identify")
    if not commands:
        raise UserError(
            f"{path}: no DRIVE_RPDO1 frames (motor commands): the input of the frequency "
            "response is missing"
        )
    u = np.asarray(us)
    keep = np.isfinite(u)
    return ChirpData(
        u=u[keep],
        y=np.asarray(ys)[keep],
        sample_period_s=firmware.sample_period_s,
        torque_saturated=saturated,
        damage=damage,
    )


# ----------------------------------------------------------------------------- analysis


@dataclass(frozen=True)
class FrequencyResponse:
    """Welch H1 estimate: frequencies (Hz), ``H = Pxy / Pxx``, ``Pxx`` and the coherence;
    ``band`` is the (first, last) index of the excited band."""

    f: np.ndarray
    H: np.ndarray
    pxx: np.ndarray
    coherence: np.ndarray
    band: tuple[int, int]
    nperseg: int
    fs: float

    @property
    def magnitude(self) -> np.ndarray:
        return np.abs(self.H)


def frequency_response(
    u: np.ndarray, y: np.ndarray, fs: float, segment_s: float = DEFAULT_SEGMENT_S
) -> FrequencyResponse:
    """``H1 = Pxy / Pxx`` of ``y`` against ``u`` (Welch: :func:`scipy.signal.csd` /
    :func:`scipy.signal.welch`, Hann segments of ``segment_s``, 75 % overlap).

    The overlap matters for a single sweep: each frequency is then excited in several
    segments, so the segment boundaries do not bias H (with 50 % the peak moved by up to
    3 %).  Only the excited band (Pxx at least :data:`BAND_FRACTION` of its maximum) is
    used by the readings.
    """
    nperseg = round(segment_s * fs)
    if nperseg < 16:
        raise UserError(f"--segment {segment_s:g} s is {nperseg} samples: too short")
    if len(u) < nperseg:
        raise UserError(
            f"trace too short: {len(u)} samples ({len(u) / fs:.3g} s), a {segment_s:g} s "
            f"segment needs {nperseg} (a shorter --segment gives a coarser resolution)"
        )
    if not np.ptp(u) > 0.0:
        raise UserError("the motor torque command does not vary: nothing to identify")
    kw = {"fs": fs, "window": "hann", "nperseg": nperseg, "noverlap": round(OVERLAP * nperseg)}
    f, pxx = signal.welch(u, **kw)
    _, pxy = signal.csd(u, y, **kw)
    _, coh = signal.coherence(u, y, **kw)
    excited = np.flatnonzero(pxx >= BAND_FRACTION * pxx.max())
    lo, hi = int(excited[0]), int(excited[-1])
    with np.errstate(divide="ignore", invalid="ignore"):
        H = np.where(pxx > 0.0, pxy / pxx, np.nan)
    return FrequencyResponse(f, H, pxx, coh, (lo, hi), nperseg, fs)


@dataclass(frozen=True)
class HalfPower:
    """Half-power bandwidth results (Hz, dimensionless).

    ``fn_Hz``/``zeta``: the classic reading (fn = peak frequency, zeta = (f2 − f1) / 2 fn);
    ``fn_exact_Hz``/``zeta_exact``: exact for a second-order system (module docstring).
    """

    f_peak_Hz: float
    peak_gain: float
    f1_Hz: float
    f2_Hz: float
    fn_Hz: float
    zeta: float
    fn_exact_Hz: float
    zeta_exact: float

    @property
    def bandwidth_Hz(self) -> float:
        return self.f2_Hz - self.f1_Hz


def _crossing(f: np.ndarray, mag: np.ndarray, j: int, level: float) -> float:
    """Frequency between bins j and j+1 where ``mag`` crosses ``level`` (linear)."""
    m0, m1 = mag[j], mag[j + 1]
    return float(f[j] + (level - m0) * (f[j + 1] - f[j]) / (m1 - m0))


def half_power(fr: FrequencyResponse) -> HalfPower:
    """The seed's half-power bandwidth method on ``fr`` ([Vertechy] §II).

    Peak |H| (parabola through the three highest bins of log |H|), the frequencies
    f1 < f2 where |H| falls to peak / sqrt(2) (linear interpolation between bins), then

    - as the seed uses it: ``fn = f_peak``, ``zeta = (f2 - f1) / (2 fn)``;
    - exact for the second-order system (recommended; the classic form reads the peak of
      |H|, which lies at ``wn sqrt(1 - 2 zeta²)``, about 1 % below fn at zeta = 0.1, and
      overestimates zeta by about 2 %): with ``R = (f2² - f1²) / (f2² + f1²)``,
      ``s = R / sqrt(1 + R²) = 2 zeta sqrt(1 - zeta²)``, ``zeta² = (1 - sqrt(1 - s²)) /
      2`` and ``fn² = (f1² + f2²) / (2 (1 - 2 zeta²))``.
    """
    f, mag = fr.f, fr.magnitude
    lo, hi = fr.band
    i = lo + int(np.nanargmax(mag[lo : hi + 1]))
    if not lo < i < hi:
        raise UserError(
            f"no resonance peak inside the excited band {f[lo]:.3g}-{f[hi]:.3g} Hz "
            f"(|H| is largest at its edge, {f[i]:.3g} Hz)"
        )
    a, b, c = np.log(mag[i - 1 : i + 2])
    curvature = a - 2.0 * b + c
    offset = 0.5 * (a - c) / curvature if curvature < 0 else 0.0
    f_peak = float(f[i] + offset * (f[1] - f[0]))
    peak = float(math.exp(b - 0.25 * (a - c) * offset))
    level = peak / math.sqrt(2.0)
    j = i
    while j > lo and mag[j] >= level:
        j -= 1
    k = i
    while k < hi and mag[k] >= level:
        k += 1
    if mag[j] >= level or mag[k] >= level:
        raise UserError(
            f"the resonance at {f_peak:.3g} Hz does not fall to half power inside the "
            f"excited band {f[lo]:.3g}-{f[hi]:.3g} Hz: sweep a wider band"
        )
    f1 = _crossing(f, mag, j, level)
    f2 = _crossing(f, mag, k - 1, level)
    zeta = (f2 - f1) / (2.0 * f_peak)
    # exact for K wn² / (s² + 2 zeta wn s + wn²): R = 2 zeta sqrt(1 - zeta²) / (1 - 2 zeta²)
    r = (f2 * f2 - f1 * f1) / (f2 * f2 + f1 * f1)
    s2 = r * r / (1.0 + r * r)
    zeta_exact = math.sqrt(0.5 * (1.0 - math.sqrt(1.0 - s2)))
    fn_exact = math.sqrt((f1 * f1 + f2 * f2) / (2.0 * (1.0 - 2.0 * zeta_exact**2)))
    return HalfPower(f_peak, peak, f1, f2, f_peak, zeta, fn_exact, zeta_exact)


@dataclass(frozen=True)
class LogDecrement:
    """Logarithmic decrement of the band-passed impulse response.

    ``t``/``h``: the analytic impulse response (normalised, envelope peak 1) for plots;
    ``peak_t``/``peak_x``: the positive peaks of its real part that were used.
    """

    delta: float
    zeta: float
    fd_Hz: float
    fn_Hz: float
    peaks: int
    t: np.ndarray = field(repr=False)
    h: np.ndarray = field(repr=False)
    peak_t: np.ndarray = field(repr=False)
    peak_x: np.ndarray = field(repr=False)


def log_decrement(fr: FrequencyResponse, hp: HalfPower) -> LogDecrement:
    """The seed's logarithmic-decrement cross-check, on the impulse response from H.

    The impulse response is the inverse FFT of H, band-passed by a Gaussian window
    centred on the peak (standard deviation :data:`BANDPASS_WIDTHS` half-power
    bandwidths), taken one-sided so the result is the analytic signal.  A band-pass is
    needed because H is only known in the excited band; the window's own time response
    is a Gaussian pulse, so :data:`SETTLE_SIGMAS` of its standard deviations after the
    envelope's peak the response is the mode's free decay.  Its successive positive
    peaks (down to :data:`PEAK_FLOOR` of the largest) give ``delta`` (least-squares slope
    of ln(peak) against the peak index), ``zeta = delta / sqrt(4 pi² + delta²)``, the
    damped frequency ``fd`` from the peak spacing and ``fn = fd / sqrt(1 - zeta²)``:
    independent of the half-power figures.  On the exact H of the seed joint this returns
    zeta to 0.1 % for widths of 0.75 to 1.5 bandwidths; on a Welch estimate it reads
    about 2 % high (the segment window smooths H, which shortens the decay).
    """
    f, n, fs = fr.f, fr.nperseg, fr.fs
    lo, hi = fr.band
    width = BANDPASS_WIDTHS * hp.bandwidth_Hz
    window = np.exp(-0.5 * ((f - hp.f_peak_Hz) / width) ** 2)
    window[:lo] = 0.0
    window[hi + 1 :] = 0.0
    spectrum = np.zeros(n, dtype=complex)
    spectrum[: len(f)] = np.nan_to_num(fr.H) * window
    analytic = np.fft.ifft(spectrum)[: n // 2]
    envelope = np.abs(analytic)
    scale = float(envelope.max())
    if not scale > 0.0:
        raise UserError("the impulse response is zero: no log decrement")
    h = analytic / scale
    t = np.arange(len(h)) / fs
    start = t[int(np.argmax(envelope))] + SETTLE_SIGMAS / (2.0 * math.pi * width)
    x = h.real
    found, _ = signal.find_peaks(x)
    used = [p for p in found if t[p] >= start]
    peaks: list[int] = []
    for p in used:
        if x[p] < PEAK_FLOOR or len(peaks) == MAX_PEAKS:
            break
        peaks.append(p)
    if len(peaks) < 3:
        raise UserError(
            f"only {len(peaks)} decay peaks above {PEAK_FLOOR:.0%} in the impulse response: "
            "the resonance is too damped (or too noisy) for a logarithmic decrement"
        )
    idx = np.arange(len(peaks))
    peak_x = x[peaks]
    peak_t = t[peaks]
    delta = float(-np.polyfit(idx, np.log(peak_x), 1)[0])
    period = float(np.polyfit(idx, peak_t, 1)[0])
    zeta = delta / math.hypot(2.0 * math.pi, delta)
    fd = 1.0 / period
    fn = fd / math.sqrt(1.0 - zeta * zeta)
    return LogDecrement(delta, zeta, fd, fn, len(peaks), t, h, peak_t, peak_x)


@dataclass(frozen=True)
class Identification:
    """Everything ``hdhil identify`` finds, plus the model values when known."""

    samples: int
    sample_period_s: float
    band_Hz: tuple[float, float]
    resolution_Hz: float
    J_motor: float
    J_load: float
    half_power: HalfPower
    log_decrement: LogDecrement
    coherence_at_peak: float
    response: FrequencyResponse = field(repr=False)
    torque_saturated: int = 0
    model: dict[str, float] | None = None  #: the scenario's fn_Hz, zeta, c, k, gain

    @property
    def J(self) -> float:
        """``J = J_m J_l / (J_m + J_l)`` ([Vertechy], below Eq. 2)."""
        return self.J_motor * self.J_load / (self.J_motor + self.J_load)

    def damping(self, fn_Hz: float, zeta: float) -> float:
        """``c = 2 zeta wn J`` (Nm s/rad)."""
        return 2.0 * zeta * 2.0 * math.pi * fn_Hz * self.J

    def stiffness(self, fn_Hz: float) -> float:
        """``k = J wn²`` (Nm/rad)."""
        return self.J * (2.0 * math.pi * fn_Hz) ** 2

    @property
    def static_gain(self) -> float:
        """``K = peak |H| x 2 zeta sqrt(1 - zeta²)`` (exact half-power zeta)."""
        z = self.half_power.zeta_exact
        return self.half_power.peak_gain * 2.0 * z * math.sqrt(1.0 - z * z)

    def methods(self) -> dict[str, dict[str, float]]:
        """fn, zeta, c and k by method: ``half_power`` (the seed's reading),
        ``half_power_exact`` (recommended) and ``log_decrement``."""
        hp, ld = self.half_power, self.log_decrement
        out = {}
        for name, fn, zeta in (
            ("half_power", hp.fn_Hz, hp.zeta),
            ("half_power_exact", hp.fn_exact_Hz, hp.zeta_exact),
            ("log_decrement", ld.fn_Hz, ld.zeta),
        ):
            out[name] = {
                "fn_Hz": fn,
                "zeta": zeta,
                "c_Nms_per_rad": self.damping(fn, zeta),
                "k_Nm_per_rad": self.stiffness(fn),
            }
        return out

    def as_dict(self) -> dict[str, Any]:
        hp = asdict(self.half_power)
        ld = self.log_decrement
        return {
            "samples": self.samples,
            "duration_s": self.samples * self.sample_period_s,
            "band_Hz": list(self.band_Hz),
            "resolution_Hz": self.resolution_Hz,
            "J_motor": self.J_motor,
            "J_load": self.J_load,
            "J": self.J,
            "half_power_points": {
                key: hp[key] for key in ("f_peak_Hz", "peak_gain", "f1_Hz", "f2_Hz")
            },
            "log_decrement_detail": {
                "delta": ld.delta,
                "fd_Hz": ld.fd_Hz,
                "peaks": ld.peaks,
            },
            "methods": self.methods(),
            "static_gain": self.static_gain,
            "coherence_at_peak": self.coherence_at_peak,
            "torque_saturated": self.torque_saturated,
            "model": self.model,
        }


def identify(
    data: ChirpData,
    J_motor: float,
    J_load: float,
    segment_s: float = DEFAULT_SEGMENT_S,
    model: dict[str, float] | None = None,
) -> Identification:
    """Frequency response, half-power bandwidth and log decrement of ``data``; the
    inertias ``J_motor``/``J_load`` (kg m², reduced to the output) give ``J`` and with it
    the damping coefficient ``c = 2 zeta wn J`` and the stiffness ``k = J wn²``
    (:class:`Identification`).  The static gain ``K = peak |H| x 2 zeta sqrt(1 -
    zeta²)`` should be ``J_l / (J_m + J_l)`` if both calibrations (sensor and actuator)
    are right.  ``model``: the scenario's values (:func:`model_values`), printed beside
    the identified ones (a real drive's trace has no such truth)."""
    if not (J_motor > 0 and J_load > 0):
        raise UserError(f"inertias must be > 0, got J_m = {J_motor!r}, J_l = {J_load!r}")
    fs = 1.0 / data.sample_period_s
    fr = frequency_response(data.u, data.y, fs, segment_s)
    hp = half_power(fr)
    ld = log_decrement(fr, hp)
    i_peak = int(np.argmin(np.abs(fr.f - hp.f_peak_Hz)))
    lo, hi = fr.band
    return Identification(
        samples=len(data),
        sample_period_s=data.sample_period_s,
        band_Hz=(float(fr.f[lo]), float(fr.f[hi])),
        resolution_Hz=float(fr.f[1] - fr.f[0]),
        J_motor=J_motor,
        J_load=J_load,
        half_power=hp,
        log_decrement=ld,
        coherence_at_peak=float(fr.coherence[i_peak]),
        response=fr,
        torque_saturated=data.torque_saturated,
        model=model,
    )


def model_values(plant: PlantConfig) -> dict[str, float]:
    """The scenario's joint: fn (Hz), zeta, c, k and the static gain J_l / (J_m + J_l)."""
    d = plant.drivetrain
    return {
        "fn_Hz": d.natural_frequency_Hz,
        "zeta": d.damping_ratio,
        "c_Nms_per_rad": d.c_flex,
        "k_Nm_per_rad": d.k_flex,
        "static_gain": d.J_load / (d.J_motor + d.J_load),
    }


# ----------------------------------------------------------------------------- output


def format_identification(ident: Identification, source: str = "") -> str:
    """The human-readable summary."""
    hp = ident.half_power
    ld = ident.log_decrement
    lines = [
        f"identify {source}".rstrip(),
        f"  samples            {ident.samples} ({ident.samples * ident.sample_period_s:.3g} s), "
        f"excited band {ident.band_Hz[0]:.2f}-{ident.band_Hz[1]:.2f} Hz, "
        f"resolution {ident.resolution_Hz:.3f} Hz",
        f"  peak               {hp.peak_gain:.4g} at {hp.f_peak_Hz:.3f} Hz "
        f"(coherence {ident.coherence_at_peak:.3f})",
        f"  half-power points  f1 {hp.f1_Hz:.3f} Hz, f2 {hp.f2_Hz:.3f} Hz "
        f"(bandwidth {hp.bandwidth_Hz:.3f} Hz)",
        f"  log decrement      delta {ld.delta:.4f} over {ld.peaks} peaks, fd {ld.fd_Hz:.3f} Hz",
        f"  J = Jm Jl/(Jm+Jl)  {ident.J:.4f} kg m² (Jm {ident.J_motor:g}, Jl {ident.J_load:g})",
        "",
        f"  {'method':<28} {'fn [Hz]':>9} {'zeta':>8} {'c [Nms/rad]':>12} {'k [Nm/rad]':>11}",
    ]
    labels = {
        "half_power": "half-power (fn = peak)",
        "half_power_exact": "half-power, exact 2nd order",
        "log_decrement": "logarithmic decrement",
    }
    model = ident.model
    for name, v in ident.methods().items():
        lines.append(
            f"  {labels[name]:<28} {v['fn_Hz']:>9.3f} {v['zeta']:>8.4f} "
            f"{v['c_Nms_per_rad']:>12.2f} {v['k_Nm_per_rad']:>11.0f}"
        )
    if model is not None:
        lines.append(
            f"  {'scenario model':<28} {model['fn_Hz']:>9.3f} {model['zeta']:>8.4f} "
            f"{model['c_Nms_per_rad']:>12.2f} {model['k_Nm_per_rad']:>11.0f}"
        )
        lines.append("")
        for name, v in ident.methods().items():
            lines.append(
                f"  {labels[name]:<28} error fn {_pct(v['fn_Hz'], model['fn_Hz'])}, "
                f"c {_pct(v['c_Nms_per_rad'], model['c_Nms_per_rad'])}"
            )
    lines.append("")
    static = f"  static gain K      {ident.static_gain:.4f}"
    if model is not None:
        static += f" (model J_l/(J_m+J_l) = {model['static_gain']:.4f})"
    lines.append(static)
    ratio = ld.zeta / hp.zeta_exact
    lines.append(f"  cross-check        log decrement / half-power (exact) zeta = {ratio:.3f}")
    if ident.torque_saturated:
        lines.append(
            f"  warning            {ident.torque_saturated} torque samples at the ADC's "
            "end codes: the response was clipped"
        )
    return "\n".join(lines)


def _pct(value: float, reference: float) -> str:
    return f"{100.0 * (value / reference - 1.0):+6.2f} %"


def make_figure(ident: Identification, title: str = "") -> Any:
    """Bode magnitude ([Vertechy] Fig. 5) with the peak and half-power points, the phase
    and the coherence of the estimate over the excited band, and the band-passed impulse
    response with the peaks of the logarithmic decrement; legends beside the axes."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter

    from hdhil.core.plotlabels import axis_label

    hp, ld, fr = ident.half_power, ident.log_decrement, ident.response
    lo, hi = fr.band
    f = fr.f[lo : hi + 1]
    mag_dB = 20.0 * np.log10(fr.magnitude[lo : hi + 1])
    fig = Figure(figsize=(9, 12), layout="constrained")
    ax, ax_ph, ax_coh, ax2 = fig.subplots(4, 1, height_ratios=(3, 2, 1.3, 2))
    for axis in (ax_ph, ax_coh):
        axis.sharex(ax)
    ax.semilogx(f, mag_dB, color="C0", lw=1.2, label="|H1| = |Pxy / Pxx| (Welch)")
    fn, zeta = hp.fn_exact_Hz, hp.zeta_exact
    r = f / fn
    fit = ident.static_gain / np.abs(1.0 - r * r + 2j * zeta * r)
    ax.semilogx(f, 20.0 * np.log10(fit), "--", color="C7", lw=1.0, label="2nd-order fit")
    peak_dB = 20.0 * math.log10(hp.peak_gain)
    ax.plot([hp.f_peak_Hz], [peak_dB], "o", color="C3", label=f"peak {hp.f_peak_Hz:.2f} Hz")
    ax.axhline(peak_dB - 10.0 * math.log10(2.0), color="C1", lw=0.8, ls=":")
    ax.plot(
        [hp.f1_Hz, hp.f2_Hz],
        [peak_dB - 10.0 * math.log10(2.0)] * 2,
        "s",
        color="C1",
        label=f"half power {hp.f1_Hz:.2f} / {hp.f2_Hz:.2f} Hz",
    )
    c = ident.damping(fn, zeta)
    ax.set_title(
        title
        or f"sensor torque / motor torque command: fn {fn:.2f} Hz, zeta {zeta:.4f}, "
        f"c {c:.2f} N·m·s/rad"
    )
    ax.set_xlabel(axis_label("frequency", "Hz"))
    ax.set_ylabel(axis_label("magnitude", "dB"))
    plain = FuncFormatter(lambda v, _pos: f"{v:g}")
    ax.xaxis.set_major_formatter(plain)
    ax.xaxis.set_minor_formatter(plain)
    ax.tick_params(axis="x", which="minor", labelsize=7)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)

    # Phase: the measured H1's and the fit's, unwrapped over the band ([Vertechy] Fig. 5
    # shows the magnitude only; the phase crossing -90 deg at fn checks the reading).
    phase = np.degrees(np.unwrap(np.angle(fr.H[lo : hi + 1])))
    fit_phase = np.degrees(np.unwrap(np.angle(1.0 / (1.0 - r * r + 2j * zeta * r))))
    phase += 360.0 * round((fit_phase[0] - phase[0]) / 360.0)  # same branch as the fit
    ax_ph.semilogx(f, phase, color="C0", lw=1.2, label="arg H1")
    ax_ph.semilogx(f, fit_phase, "--", color="C7", lw=1.0, label="2nd-order fit")
    ax_ph.axvline(fn, color="C3", lw=0.8, ls=":", label=f"fn {fn:.2f} Hz")
    ax_ph.axhline(-90.0, color="0.5", lw=0.6)
    ax_ph.set_ylabel(axis_label("phase", "deg"))
    ax_ph.set_xlabel(axis_label("frequency", "Hz"))
    ax_ph.grid(True, which="both", alpha=0.3)
    ax_ph.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)

    # Coherence: where H1 can be trusted (near 1: the response is linear in the command
    # and noise is small).
    ax_coh.semilogx(f, fr.coherence[lo : hi + 1], color="C2", lw=1.2, label="coherence")
    ax_coh.set_ylim(0.0, 1.05)
    ax_coh.set_ylabel("coherence")
    ax_coh.set_xlabel(axis_label("frequency", "Hz"))
    ax_coh.grid(True, which="both", alpha=0.3)
    ax_coh.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    for axis in (ax_ph, ax_coh):
        axis.xaxis.set_major_formatter(plain)
        axis.xaxis.set_minor_formatter(plain)
        axis.tick_params(axis="x", which="minor", labelsize=7)
    shown = ld.t <= min(ld.t[-1], (ld.peak_t[-1] if len(ld.peak_t) else 0.5) * 1.5 + 0.05)
    ax2.plot(
        ld.t[shown], ld.h.real[shown], color="C0", lw=1.0, label="impulse response (band-passed)"
    )
    ax2.plot(ld.t[shown], np.abs(ld.h[shown]), color="C7", lw=0.8, ls="--", label="envelope")
    ax2.plot(ld.peak_t, ld.peak_x, "o", color="C3", label=f"log decrement {ld.delta:.3f}")
    ax2.set_title(f"logarithmic decrement: zeta {ld.zeta:.4f}, fd {ld.fd_Hz:.2f} Hz")
    ax2.set_xlabel(axis_label("time", "s"))
    ax2.set_ylabel("normalised amplitude")
    ax2.grid(True, alpha=0.3)
    ax2.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    return fig
