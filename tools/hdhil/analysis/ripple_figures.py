"""[Taghirad97]'s torque figures (Figs. 8-11) drawn from any hdhil trace (or a real
drive's): the ripple spectrum at constant speed, measured against Kalman-filtered
torque, and the misalignment against the output angle.

:func:`plot_data` turns a :class:`hdhil.rig.evaluate.Recording` into the signals drawn
(:class:`PlotData`: the drive's ``DRIVE_TPDO1`` counts through the firmware
calibration, the firmware's ``T_filtered`` telemetry or, without telemetry, the
firmware's own filter chain re-run offline); :func:`make_figure` draws the 3 x 2 grid.
The analysis behind the spectrum panel (:func:`flat_velocity_window`,
:func:`torque_spectrum`, :func:`spectrum_peaks`, :func:`ripple_peaks`) is usable on
its own.  ``hdhil plot`` is the command line over these.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from scipy.ndimage import maximum_filter1d, minimum_filter1d, uniform_filter1d
from scipy.signal import find_peaks, periodogram

from hdhil.core.errors import UserError
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.isr import TorqueFilterChain

__all__ = [
    "FORMATS",
    "SPECTRUM_WINDOW_S",
    "PlotData",
    "flat_velocity_window",
    "make_figure",
    "plot_data",
    "ripple_peaks",
    "spectrum_peaks",
    "torque_spectrum",
]

#: Output formats (``savefig`` picks the backend from the extension).
FORMATS = (".png", ".pdf", ".svg")
#: Length of the auto-detected spectrum window (s): the seed's 0.8-1.1 s (Fig. 8).
SPECTRUM_WINDOW_S = 0.3
#: Fewest samples for a spectrum (and for a trace to be plotted at all).
MIN_SPECTRUM_SAMPLES = 64
#: A spectrum window must have a mean |motor velocity| of at least this (rad/s).
MIN_FLAT_SPEED_RADPS = 10.0
#: Velocity smoothing before the flatness test (s): averages out tachometer noise.
VELOCITY_SMOOTHING_S = 0.025
#: Samples with |motor velocity| below this are left out of the misalignment panel (rad/s).
TURNING_RADPS = 5.0
#: Length of the Fig. 9 close-up (s).
CLOSE_UP_S = 0.1
#: Zero-padding factor of the periodogram (smooth peaks, finer peak positions).
OVERSAMPLE = 8


# ---------------------------------------------------------------------------- analysis
def flat_velocity_window(
    velocity: np.ndarray, sample_period_s: float, length_s: float = SPECTRUM_WINDOW_S
) -> tuple[int, int] | None:
    """The ``length_s`` window (sample indices ``k0:k1``) where the motor velocity is
    flattest: smallest (max − min) / mean |v| of the velocity smoothed over 25 ms, among
    windows with mean |v| >= :data:`MIN_FLAT_SPEED_RADPS`.  A trace shorter than the
    window gives its whole length.  None if the motor never turns fast enough."""
    n = len(velocity)
    L = min(n, max(MIN_SPECTRUM_SAMPLES, round(length_s / sample_period_s)))
    if n < MIN_SPECTRUM_SAMPLES:
        return None
    smooth = uniform_filter1d(
        np.asarray(velocity, dtype=np.float64),
        max(1, round(VELOCITY_SMOOTHING_S / sample_period_s)),
        mode="nearest",
    )
    # Centred running max / min / mean over L samples, then take the windows' starts.
    half = L // 2
    starts = np.arange(0, n - L + 1)
    centre = starts + half
    spread = (maximum_filter1d(smooth, L) - minimum_filter1d(smooth, L))[centre]
    mean = uniform_filter1d(np.abs(smooth), L)[centre]
    ok = mean >= MIN_FLAT_SPEED_RADPS
    if not ok.any():
        return None
    score = np.where(ok, spread / np.where(ok, mean, 1.0), np.inf)
    k0 = int(starts[np.argmin(score)])
    return k0, k0 + L


def torque_spectrum(
    torque: np.ndarray, sample_period_s: float, oversample: int = OVERSAMPLE
) -> tuple[np.ndarray, np.ndarray]:
    """Power spectral density of ``torque`` (Hann window, linear trend removed, zero-padded
    ``oversample`` times): angular frequencies (rad/s) and PSD (Nm² per rad/s)."""
    x = np.asarray(torque, dtype=np.float64)
    nfft = oversample * (1 << max(0, (len(x) - 1).bit_length()))
    f, pxx = periodogram(
        x, fs=1.0 / sample_period_s, window="hann", nfft=nfft, detrend="linear", scaling="density"
    )
    return 2.0 * math.pi * f, pxx / (2.0 * math.pi)


def spectrum_peaks(
    omega: np.ndarray, power: np.ndarray, count: int = 2, min_omega: float = 0.0
) -> np.ndarray:
    """The ``count`` strongest local maxima of ``power`` at ``omega >= min_omega``, as
    angular frequencies (same unit as ``omega``), in increasing order.  Each is refined by
    a parabola through log-power at the maximum and its two neighbours.  [Taghirad97] Fig. 8:
    for a 156 rad/s motor these are the ripple peaks at 312 and 624 rad/s."""
    omega = np.asarray(omega, dtype=np.float64)
    power = np.asarray(power, dtype=np.float64)
    idx, _ = find_peaks(power)
    idx = idx[omega[idx] >= min_omega]
    if len(idx) == 0:
        return np.empty(0)
    best = idx[np.argsort(power[idx])[::-1][:count]]
    log_p = np.log(np.maximum(power, np.finfo(float).tiny))
    peaks = []
    for i in best:
        a, b, c = log_p[i - 1], log_p[i], log_p[i + 1]
        denom = a - 2.0 * b + c
        shift = 0.5 * (a - c) / denom if denom < 0 else 0.0
        peaks.append(omega[i] + shift * (omega[i + 1] - omega[i]))
    return np.sort(np.array(peaks))


def ripple_peaks(
    torque: np.ndarray, sample_period_s: float, count: int = 2
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Spectrum and its ``count`` strongest peaks, ignoring the lowest three frequency
    resolutions 2π/(N Ts) (the leakage of the slow torque and the window's DC lobe).
    Returns ``(omega, power, peaks)`` in rad/s."""
    omega, power = torque_spectrum(torque, sample_period_s)
    resolution = 2.0 * math.pi / (len(torque) * sample_period_s)
    return omega, power, spectrum_peaks(omega, power, count, min_omega=3.0 * resolution)


# -------------------------------------------------------------------------------- data
@dataclass
class PlotData:
    """The signals drawn, one value per control cycle.  ``T_true`` is None without
    ground truth; ``output_angle`` is in rad, from ``output_angle_source``."""

    sample_period_s: float
    t: np.ndarray
    T_meas: np.ndarray
    velocity: np.ndarray
    T_filtered: np.ndarray
    filtered_label: str
    T_expected: np.ndarray
    T_true: np.ndarray | None
    output_angle: np.ndarray
    output_angle_source: str
    mode: str

    def __len__(self) -> int:
        return len(self.t)


def plot_data(rec: Any, cfg: FirmwareConfig) -> PlotData:
    """The :class:`PlotData` of a :class:`hdhil.rig.evaluate.Recording`."""
    from hdhil.rig.evaluate import calibrated_signals

    n = len(rec)
    if n == 0:
        raise UserError("no DRIVE_TPDO1 frames (drive sensor frames) in the trace: nothing to plot")
    if n < MIN_SPECTRUM_SAMPLES:
        raise UserError(f"too few samples to plot: {n} (need at least {MIN_SPECTRUM_SAMPLES})")
    Ts = cfg.sample_period_s
    T_meas, velocity = calibrated_signals(rec, cfg)
    encoder = rec.column("encoder")

    # The firmware's chain, offline: T_exp (Fig. 10's expected torque) and, for a trace
    # without telemetry, the filtered torque.
    chain = TorqueFilterChain(cfg)
    T_expected = np.empty(n)
    T_offline = np.empty(n)
    for k, (T, v, count) in enumerate(
        zip(T_meas.tolist(), velocity.tolist(), encoder.astype(np.int64).tolist(), strict=True)
    ):
        _, T_expected[k], _, T_offline[k], _ = chain.step(T, v, count)
    T_tele = rec.column("T_filtered_tele")
    if np.isfinite(T_tele).any():
        T_filtered, label = T_tele.copy(), f"filtered (firmware telemetry, {cfg.ripple.mode})"
    else:
        T_filtered, label = T_offline, f"filtered (offline firmware chain, {cfg.ripple.mode})"

    T_true = rec.column("T_true")
    theta_out = rec.column("theta_output")
    if np.isfinite(theta_out).all():
        output_angle, source = np.unwrap(theta_out), "truth"
    else:
        counts = np.unwrap(encoder, period=65536.0)
        output_angle = counts * (2.0 * math.pi / cfg.calibration.encoder_counts_per_rev)
        output_angle /= cfg.gear_ratio
        source = "encoder / gear ratio"
    return PlotData(
        sample_period_s=Ts,
        t=np.arange(n) * Ts,
        T_meas=T_meas,
        velocity=velocity,
        T_filtered=T_filtered,
        filtered_label=label,
        T_expected=T_expected,
        T_true=T_true.copy() if np.isfinite(T_true).any() else None,
        output_angle=output_angle,
        output_angle_source=source,
        mode=cfg.ripple.mode,
    )


def _window_samples(data: PlotData, window: tuple[float, float] | None) -> tuple[int, int] | None:
    """``--window T0 T1`` as sample indices (checked), or the auto-detected window."""
    Ts = data.sample_period_s
    n = len(data)
    if window is None:
        return flat_velocity_window(data.velocity, Ts)
    t0, t1 = window
    if not (math.isfinite(t0) and math.isfinite(t1) and t0 < t1):
        raise UserError(f"--window {t0:g} {t1:g}: need T0 < T1")
    k0, k1 = max(0, math.ceil(t0 / Ts - 1e-9)), min(n, math.floor(t1 / Ts + 1e-9) + 1)
    if k1 - k0 < MIN_SPECTRUM_SAMPLES:
        raise UserError(
            f"--window {t0:g} {t1:g}: {max(0, k1 - k0)} samples within the trace "
            f"(0-{(n - 1) * Ts:g} s); need at least {MIN_SPECTRUM_SAMPLES}"
        )
    return k0, k1


# ------------------------------------------------------------------------------ figure
_MEAS = {"color": "0.6", "lw": 0.6}
_FILT = {"color": "tab:blue", "lw": 1.0}
_TRUE = {"color": "black", "lw": 1.0, "ls": "--"}
_EXP = {"color": "tab:orange", "lw": 1.4, "ls": "-."}


def make_figure(data: PlotData, title: str, window: tuple[float, float] | None = None) -> Figure:
    """The 3 x 2 figure; ``window`` = (T0, T1) in s for the spectrum, else
    auto-detected (:func:`flat_velocity_window`).  Time is the sample index times the
    firmware's sample period.

    - **Fig. 8, top** (§4): the measured torque and the motor velocity against time.
    - **Fig. 8, bottom** (§4): the power spectrum of the measured torque over a window
      where the velocity is nearly flat ("the power spectrum of the measured torque
      plotted for the time interval 0.8 to 1.1 sec when the velocity is almost flat and
      about 156 rad/sec shows two peaks at 312, and 624 rad/sec"), on a rad/s axis, with
      markers at 2x and 4x the mean motor velocity and the peaks found
      (:func:`ripple_peaks`).
    - **Fig. 9** (§4): the measured torque against the Kalman-filtered torque, plus the
      true torque when the trace carries ground truth; the whole run, and a 0.1 s
      close-up in the spectrum window so that single ripple periods show.
    - **Figs. 10-11** (§5): misalignment before / after filtering: the measured and
      filtered torque (and the expected torque J_load·acc/N, Fig. 10's solid line, and
      the true torque if known) against the output angle in revolutions, over the
      samples where the motor turns.  The output angle comes from the truth channel when
      present, else from the firmware's encoder count (motor angle / gear ratio).
    """
    fig = Figure(figsize=(14, 16), layout="constrained")
    fig.suptitle(title, fontsize=13)
    grid = fig.add_gridspec(4, 2)
    ax_tv = fig.add_subplot(grid[0, 0])
    ax_sp = fig.add_subplot(grid[0, 1])
    ax_f9 = fig.add_subplot(grid[1, 0])
    ax_zo = fig.add_subplot(grid[1, 1])
    ax_m10 = fig.add_subplot(grid[2, :])
    ax_m11 = fig.add_subplot(grid[3, :], sharex=ax_m10)
    t = data.t
    span = _window_samples(data, window)

    # Fig. 8 top: measured torque and velocity.
    ax_tv.plot(t, data.T_meas, label="measured torque", **_FILT)
    ax_tv.set(xlabel="time (s)", ylabel="torque (Nm)", title="Fig. 8: measured torque, velocity")
    ax_v = ax_tv.twinx()
    ax_v.plot(t, data.velocity, color="tab:red", lw=1.0, label="motor velocity")
    ax_v.set_ylabel("motor velocity (rad/s)", color="tab:red")
    ax_v.tick_params(axis="y", colors="tab:red")
    if span is not None:
        ax_tv.axvspan(t[span[0]], t[span[1] - 1], color="tab:green", alpha=0.15,
                      label="spectrum window")  # fmt: skip
    lines = ax_tv.get_legend_handles_labels()
    more = ax_v.get_legend_handles_labels()
    _legend_below(ax_tv, lines[0] + more[0], lines[1] + more[1])
    ax_tv.grid(alpha=0.3)

    # Fig. 8 bottom: spectrum over the flat-velocity window.
    _draw_spectrum(ax_sp, data, span)

    # Fig. 9: measured vs filtered (+ true), whole run and a close-up.
    for ax, sl in ((ax_f9, slice(None)), (ax_zo, _close_up(data, span))):
        true = data.T_true[sl] if data.T_true is not None else None
        if ax is ax_zo:
            # The close-up: the measured torque on its own (right) axis, so that an
            # offset of the measurement (misalignment, ripple) does not flatten the
            # filtered and true curves, whose ripple-free detail is the point here.
            ax_m = ax.twinx()
            ax_m.plot(t[sl], data.T_meas[sl], label="measured (right axis)", **_MEAS)
            ax_m.set_ylabel("measured torque (Nm)", color="0.45")
            ax_m.tick_params(axis="y", colors="0.45")
            _fit_ylim(ax_m, [data.T_meas[sl]])
            ax.set_zorder(ax_m.get_zorder() + 1)
            ax.patch.set_visible(False)
        else:
            ax.plot(t[sl], data.T_meas[sl], label="measured", **_MEAS)
        ax.plot(t[sl], data.T_filtered[sl], label=data.filtered_label, **_FILT)
        if true is not None:
            ax.plot(t[sl], true, label="true (truth channel)", **_TRUE)
        ax.set(xlabel="time (s)", ylabel="torque (Nm)")
        ax.grid(alpha=0.3)
        if ax is ax_zo:
            _fit_ylim(ax, [data.T_filtered[sl], true])
            h, lab = ax.get_legend_handles_labels()
            hm, labm = ax_m.get_legend_handles_labels()
            _legend_below(ax, hm + h, labm + lab)
        else:
            _fit_ylim(ax, [data.T_meas[sl], data.T_filtered[sl], true])
            _legend_below(ax)
    ax_f9.set_title("Fig. 9: measured vs Kalman-filtered torque")
    zoom = _close_up(data, span)
    ax_zo.set_title(
        f"Fig. 9 close-up: {t[zoom][0]:.2f}-{t[zoom][-1]:.2f} s "
        f"(mean velocity {np.mean(data.velocity[zoom]):.0f} rad/s)"
    )

    # Figs. 10-11: misalignment vs output angle, before and after filtering.
    _draw_misalignment(ax_m10, ax_m11, data)
    return fig


def _legend_below(ax: Any, handles: Any = None, labels: Any = None) -> None:
    """The axes' legend under it, outside the data (the constrained layout makes room)."""
    if handles is None:
        handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, -0.16),
                  ncols=min(3, len(handles)), fontsize=8, frameon=False)  # fmt: skip


def _fit_ylim(ax: Any, curves: list[np.ndarray | None], margin: float = 0.06) -> None:
    """y limits showing every curve whole (robust to NaN), with a small margin."""
    values = [np.asarray(c)[np.isfinite(c)] for c in curves if c is not None]
    values = [v for v in values if v.size]
    if not values:
        return
    lo = min(float(v.min()) for v in values)
    hi = max(float(v.max()) for v in values)
    pad = (hi - lo) * margin or max(abs(hi), 1e-3) * margin
    ax.set_ylim(lo - pad, hi + pad)


def _close_up(data: PlotData, span: tuple[int, int] | None) -> slice:
    """:data:`CLOSE_UP_S` in the middle of the spectrum window (at the end of the trace
    without one)."""
    n = len(data)
    L = min(n, max(2, round(CLOSE_UP_S / data.sample_period_s)))
    centre = (span[0] + span[1]) // 2 if span is not None else n - L // 2
    start = min(max(0, centre - L // 2), n - L)
    return slice(start, start + L)


def _draw_spectrum(ax: Any, data: PlotData, span: tuple[int, int] | None) -> None:
    Ts = data.sample_period_s
    ax.set(xlabel="angular frequency (rad/s)", ylabel="PSD of measured torque (Nm²/(rad/s))")
    if span is None:
        ax.set_title("Fig. 8: power spectrum (no window with the motor turning at constant speed)")
        ax.text(0.5, 0.5, "motor never at a steady speed >= "
                f"{MIN_FLAT_SPEED_RADPS:g} rad/s", ha="center", transform=ax.transAxes)  # fmt: skip
        return
    k0, k1 = span
    omega, power, peaks = ripple_peaks(data.T_meas[k0:k1], Ts)
    v = float(np.mean(np.abs(data.velocity[k0:k1])))
    top = min(math.pi / Ts, max(7.0 * v, 10.0 * 2.0 * math.pi / ((k1 - k0) * Ts)))
    shown = omega <= top
    ax.semilogy(omega[shown], power[shown], color="tab:blue", lw=1.0, label="measured torque")
    for mult, style in ((2, "--"), (4, ":")):
        if v > 0:
            ax.axvline(mult * v, color="tab:red", ls=style, lw=1.0,
                       label=f"{mult}x velocity = {mult * v:.0f} rad/s")  # fmt: skip
    if v < MIN_FLAT_SPEED_RADPS:  # no velocity-locked ripple to look for
        peaks = peaks[:0]
    if len(peaks):
        peak_power = np.interp(peaks, omega, power)
        ax.plot(peaks, peak_power, "v", color="black", ms=7, label="peaks found")
        for w, p in zip(peaks, peak_power, strict=True):
            ax.annotate(f"{w:.0f}", (w, p), textcoords="offset points", xytext=(4, 6), fontsize=9)
    ax.set_xlim(0, top)
    low, high = np.min(power[shown]), np.max(power[shown])
    ax.set_ylim(max(low, high * 1e-9) / 2.0, high * 10.0)  # room for the peak labels
    ax.set_title(
        f"Fig. 8: power spectrum, {k0 * Ts:.2f}-{(k1 - 1) * Ts:.2f} s, mean velocity {v:.1f} rad/s"
    )
    ax.grid(alpha=0.3)
    _legend_below(ax)


def _draw_misalignment(ax10: Any, ax11: Any, data: PlotData) -> None:
    """Fig. 10 (before: measured and expected torque) and Fig. 11 (after: filtered and
    true torque) in two panels, each scaled to its own curves: on one axis the measured
    torque's misalignment swing flattens the filtered and true curves."""
    turning = np.abs(data.velocity) >= TURNING_RADPS
    for ax in (ax10, ax11):
        ax.set(ylabel="torque (Nm)")
        ax.set_xlabel(f"output angle (revolutions, from {data.output_angle_source})")
        ax.grid(alpha=0.3)
    if not turning.any():
        ax10.set_title("Fig. 10: misalignment (motor not turning: nothing to show)")
        ax11.set_title("Fig. 11: misalignment after filtering (motor not turning)")
        return
    rev = (data.output_angle - data.output_angle[turning][0]) / (2.0 * math.pi)
    # Keep gaps where the motor stops: mask instead of dropping samples.
    x = np.where(turning, rev, np.nan)
    meas = np.where(turning, data.T_meas, np.nan)
    expected = np.where(turning, data.T_expected, np.nan)
    filtered = np.where(turning, data.T_filtered, np.nan)
    true = np.where(turning, data.T_true, np.nan) if data.T_true is not None else None
    ax10.plot(x, meas, label="measured", **_MEAS)
    ax10.plot(x, expected, label="expected J_load·acc/N (the seed's solid line)", zorder=3,
              **_EXP)  # fmt: skip
    _fit_ylim(ax10, [meas, expected])
    extent = np.nanmax(np.abs(x[turning]))
    ax10.set_title(
        f"Fig. 10: misalignment before filtering, {extent:.2f} output revolutions with "
        f"|motor velocity| >= {TURNING_RADPS:g} rad/s"
    )
    if true is not None:
        ax11.plot(x, true, label="true (truth channel)", **_TRUE)
    ax11.plot(x, filtered, label=data.filtered_label, **_FILT)
    ax11.plot(x, expected, label="expected J_load·acc/N", zorder=3, **_EXP)
    _fit_ylim(ax11, [filtered, true, expected])
    ax11.set_title("Fig. 11: misalignment after filtering (scaled to the filtered torque)")
    for ax in (ax10, ax11):
        _legend_below(ax)
