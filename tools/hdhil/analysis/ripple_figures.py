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
from hdhil.core.plotlabels import NM, axis_label
from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.isr import TorqueFilterChain

__all__ = [
    "FORMATS",
    "SPECTRUM_WINDOW_S",
    "JointRow",
    "PlotData",
    "configs_have_misalignment",
    "flat_velocity_window",
    "has_misalignment",
    "make_figure",
    "make_rig_figure",
    "plot_data",
    "ripple_peaks",
    "spectrum_peaks",
    "steady_start",
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
_EXP_LABEL = r"expected $J_\mathrm{load}\,\dot{\omega}_m/N$"
_TIME = axis_label("time", "s")
_TORQUE = axis_label("torque", NM)


def has_misalignment(scenario: Any) -> bool:
    """Whether a scenario (:class:`hdhil.rig.scenario.Scenario`) contains misalignment:
    the plant's misalignment torque or a firmware oscillator at the output angle.  Figs.
    10-11 are drawn only then."""
    return configs_have_misalignment(scenario.plant, scenario.firmware)


def configs_have_misalignment(plant: Any, firmware: FirmwareConfig) -> bool:
    """:func:`has_misalignment` of one joint's plant and firmware configuration (a
    joint of a rig: :attr:`hdhil.rig.scenario.Scenario.joint_configs`)."""
    if plant.ripple.misalignment_pp_Nm > 0.0:
        return True
    return any(o.source == "output" for o in firmware.ripple.oscillators)


def steady_start(data: PlotData, steady_from_s: float | None = None) -> float:
    """Where Fig. 11's steady part starts (s): ``steady_from_s`` when given (the
    scenario's ``evaluate_from_s``), else one output revolution after the motor starts
    turning (the filter's output oscillator learns the misalignment over a revolution);
    0 when the output never turns a whole revolution."""
    if steady_from_s is not None:
        return max(0.0, float(steady_from_s))
    turning = np.flatnonzero(np.abs(data.velocity) >= TURNING_RADPS)
    if turning.size == 0:
        return 0.0
    k0 = int(turning[0])
    turned = np.abs(data.output_angle[k0:] - data.output_angle[k0])
    done = np.flatnonzero(turned >= 2.0 * math.pi)
    return float(data.t[k0 + int(done[0])]) if done.size else 0.0


def make_figure(
    data: PlotData,
    title: str,
    window: tuple[float, float] | None = None,
    *,
    misalignment: bool | None = None,
    steady_from_s: float | None = None,
) -> Figure:
    """The figure; ``window`` = (T0, T1) in s for the spectrum, else auto-detected
    (:func:`flat_velocity_window`).  Time is the sample index times the firmware's sample
    period.  Every axis holds one quantity; legends sit below the axes, outside the data.

    - **Fig. 8, top** (§4): the measured torque and the motor velocity against time.
    - **Fig. 8, bottom** (§4): the power spectrum of the measured torque over a window
      where the velocity is nearly flat ("the power spectrum of the measured torque
      plotted for the time interval 0.8 to 1.1 sec when the velocity is almost flat and
      about 156 rad/sec shows two peaks at 312, and 624 rad/sec"), on a rad/s axis, with
      markers at 2x and 4x the mean motor velocity and the peaks found
      (:func:`ripple_peaks`).
    - **Fig. 9** (§4): the measured torque against the Kalman-filtered torque, plus the
      true torque when the trace carries ground truth, over the whole run; and a 0.1 s
      close-up in the spectrum window so that single ripple periods show, in two panels
      on one time axis: the measured torque above, the filtered (and true) torque below,
      each scaled to its own curves.
    - **Figs. 10-11** (§5), only when the scenario contains misalignment
      (``misalignment``: :func:`has_misalignment`; None, no scenario known: drawn):
      misalignment before / after filtering, against the output angle in revolutions,
      over the samples where the motor turns.  Fig. 10: the measured and expected torque
      (J_load·acc/N, Fig. 10's solid line).  Fig. 11: the filtered, expected and true
      torque, scaled to the steady part (from :func:`steady_start`), with the start-up
      before it in a panel of its own.  The output angle comes from the truth channel
      when present, else from the firmware's encoder count (motor angle / gear ratio).
    """
    with_mis = misalignment is None or misalignment
    fig = Figure(figsize=(14, 16 if with_mis else 8.5), layout="constrained")
    fig.suptitle(title, fontsize=13)
    grid = fig.add_gridspec(4 if with_mis else 2, 2)
    ax_tv = fig.add_subplot(grid[0, 0])
    ax_sp = fig.add_subplot(grid[0, 1])
    ax_f9 = fig.add_subplot(grid[1, 0])
    close = grid[1, 1].subgridspec(2, 1, hspace=0.0)
    ax_zm = fig.add_subplot(close[0])
    ax_zo = fig.add_subplot(close[1], sharex=ax_zm)
    span = _window_samples(data, window)

    _draw_panels(ax_tv, ax_sp, ax_f9, ax_zm, ax_zo, data, span)

    # Figs. 10-11: misalignment vs output angle, before and after filtering.
    if with_mis:
        ax_m10 = fig.add_subplot(grid[2, :])
        after = grid[3, :].subgridspec(1, 2, width_ratios=(1, 3))
        _draw_misalignment(
            ax_m10,
            fig.add_subplot(after[0]),
            fig.add_subplot(after[1]),
            data,
            steady_start(data, steady_from_s),
        )
    return fig


@dataclass
class JointRow:
    """One joint's row of :func:`make_rig_figure`: its heading (the joint's name and
    where it sits), its signals, whether its scenario contains misalignment
    (:func:`has_misalignment` of the joint's configuration) and where its steady part
    starts (s; None: :func:`steady_start` finds it)."""

    heading: str
    data: PlotData
    misalignment: bool = False
    steady_from_s: float | None = None


#: Height (in) of one joint's row of :func:`make_rig_figure` (twice that with the
#: misalignment panels) and the figure's width.
ROW_HEIGHT_IN = 4.4
RIG_WIDTH_IN = 24.0


def make_rig_figure(
    rows: list[JointRow], title: str, window: tuple[float, float] | None = None
) -> Figure:
    """The figure of a rig of several joints: one row per joint, headed by the joint's
    name, with the panels :func:`make_figure` draws for one joint side by side (Fig. 8's
    measured torque and velocity and its spectrum, Fig. 9 and its close-up) and, for a
    joint whose configuration contains misalignment, Figs. 10 and 11 in a second line of
    its row. ``window`` (T0, T1) in s: every joint's spectrum window, else each joint's
    own flattest window (:func:`flat_velocity_window`)."""
    if not rows:
        raise UserError("no joint to plot")
    spans = [_window_samples(row.data, window) for row in rows]  # checked before drawing
    heights = [2 if row.misalignment else 1 for row in rows]
    fig = Figure(figsize=(RIG_WIDTH_IN, ROW_HEIGHT_IN * sum(heights) + 0.9),
                 layout="constrained")  # fmt: skip
    fig.suptitle(title, fontsize=14)
    subs = fig.subfigures(len(rows), 1, squeeze=False, height_ratios=heights)[:, 0]
    for sub, row, span in zip(subs, rows, spans, strict=True):
        sub.suptitle(row.heading, fontsize=13, fontweight="bold", x=0.01, ha="left")
        grid = sub.add_gridspec(2 if row.misalignment else 1, 4,
                                width_ratios=(1.1, 1.0, 1.1, 1.15))  # fmt: skip
        close = grid[0, 3].subgridspec(2, 1, hspace=0.0)
        ax_zm = sub.add_subplot(close[0])
        ax_zo = sub.add_subplot(close[1], sharex=ax_zm)
        axes = [sub.add_subplot(grid[0, k]) for k in range(3)]
        _draw_panels(*axes, ax_zm, ax_zo, row.data, span, close_up_cols=1)
        if row.misalignment:
            after = grid[1, 2:].subgridspec(1, 2, width_ratios=(1, 3))
            _draw_misalignment(sub.add_subplot(grid[1, :2]), sub.add_subplot(after[0]),
                               sub.add_subplot(after[1]), row.data,
                               steady_start(row.data, row.steady_from_s))  # fmt: skip
    return fig


def _draw_panels(
    ax_tv: Any, ax_sp: Any, ax_f9: Any, ax_zm: Any, ax_zo: Any,
    data: PlotData, span: tuple[int, int] | None, close_up_cols: int = 3,
) -> None:  # fmt: skip
    """Figs. 8 and 9 (:func:`make_figure`) on their axes: the torque and velocity, the
    spectrum, the measured against the filtered torque and its close-up (its legend in
    ``close_up_cols`` columns)."""
    t = data.t

    # Fig. 8 top: measured torque and velocity, each on its own axis.
    ax_tv.plot(t, data.T_meas, label="measured torque (left axis)", **_FILT)
    ax_tv.set(xlabel=_TIME, ylabel=_TORQUE, title="Fig. 8: measured torque, velocity")
    ax_v = ax_tv.twinx()
    ax_v.plot(t, data.velocity, color="tab:red", lw=1.0, label="motor velocity (right axis)")
    ax_v.set_ylabel(axis_label("motor velocity", "rad/s"), color="tab:red")
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

    # Fig. 9: measured vs filtered (+ true) over the whole run.
    true = data.T_true
    ax_f9.plot(t, data.T_meas, label="measured", **_MEAS)
    ax_f9.plot(t, data.T_filtered, label=data.filtered_label, **_FILT)
    if true is not None:
        ax_f9.plot(t, true, label="true (truth channel)", **_TRUE)
    ax_f9.set(xlabel=_TIME, ylabel=_TORQUE, title="Fig. 9: measured vs Kalman-filtered torque")
    ax_f9.grid(alpha=0.3)
    _fit_ylim(ax_f9, [data.T_meas, data.T_filtered, true])
    _legend_below(ax_f9)

    # Fig. 9 close-up: measured above, filtered and true below (one axis each).
    zoom = _close_up(data, span)
    tz = t[zoom]
    ax_zm.plot(tz, data.T_meas[zoom], label="measured", **_MEAS)
    _fit_ylim(ax_zm, [data.T_meas[zoom]])
    ax_zm.set_ylabel(axis_label("measured", NM))
    ax_zm.tick_params(axis="x", labelbottom=False)
    ax_zm.set_title(
        f"Fig. 9 close-up: {tz[0]:.2f}-{tz[-1]:.2f} s "
        f"(mean velocity {np.mean(data.velocity[zoom]):.0f} rad/s)"
    )
    ax_zo.plot(tz, data.T_filtered[zoom], label=data.filtered_label, **_FILT)
    zoom_true = true[zoom] if true is not None else None
    if zoom_true is not None:
        ax_zo.plot(tz, zoom_true, label="true (truth channel)", **_TRUE)
    _fit_ylim(ax_zo, [data.T_filtered[zoom], zoom_true])
    ax_zo.set(
        xlabel=_TIME, ylabel=axis_label("filtered" if zoom_true is None else "filtered, true", NM)
    )
    h, lab = ax_zm.get_legend_handles_labels()
    h2, lab2 = ax_zo.get_legend_handles_labels()
    _legend_below(ax_zo, h + h2, lab + lab2, below=-0.34, ncols=close_up_cols)  # half height
    for ax in (ax_zm, ax_zo):
        ax.grid(alpha=0.3)


def _legend_below(
    ax: Any, handles: Any = None, labels: Any = None, below: float = -0.16, ncols: int = 3
) -> None:
    """The axes' legend under it, outside the data (the constrained layout makes room);
    ``below``: its top in axes heights under the axes' bottom edge (clear of the x label);
    at most ``ncols`` columns."""
    if handles is None:
        handles, labels = ax.get_legend_handles_labels()
    if handles:
        ax.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, below),
                  ncols=min(ncols, len(handles)), fontsize=8, frameon=False)  # fmt: skip


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
    ax.set(
        xlabel=axis_label("angular frequency", "rad/s"),
        ylabel=axis_label("PSD of measured torque", "N²·m²·s/rad"),
    )
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


def _draw_misalignment(
    ax10: Any, ax_start: Any, ax11: Any, data: PlotData, steady_s: float
) -> None:
    """Fig. 10 (before: measured and expected torque) and Fig. 11 (after: filtered,
    expected and true torque), each scaled to its own curves: on one axis the measured
    torque's misalignment swing flattens the filtered and true curves.  Fig. 11 is drawn
    from ``steady_s`` on, scaled to that steady part; the start-up before it (where the
    filter is still learning) has a panel of its own."""
    turning = np.abs(data.velocity) >= TURNING_RADPS
    rev_label = axis_label(f"output angle from {data.output_angle_source}", "rev")
    for ax in (ax10, ax_start, ax11):
        ax.set(ylabel=_TORQUE, xlabel=rev_label)
        ax.grid(alpha=0.3)
    if not turning.any():
        ax10.set_title("Fig. 10: misalignment (motor not turning: nothing to show)")
        ax11.set_title("Fig. 11: misalignment after filtering (motor not turning)")
        ax_start.set_title("start-up")
        return
    rev = (data.output_angle - data.output_angle[turning][0]) / (2.0 * math.pi)
    # Keep gaps where the motor stops: mask instead of dropping samples.
    x = np.where(turning, rev, np.nan)
    meas = np.where(turning, data.T_meas, np.nan)
    expected = np.where(turning, data.T_expected, np.nan)
    ax10.plot(x, meas, label="measured", **_MEAS)
    ax10.plot(x, expected, label=f"{_EXP_LABEL} (the seed's solid line)", zorder=3, **_EXP)
    _fit_ylim(ax10, [meas, expected])
    extent = np.nanmax(np.abs(x[turning]))
    ax10.set_title(
        f"Fig. 10: misalignment before filtering, {extent:.2f} output revolutions with "
        f"|motor velocity| >= {TURNING_RADPS:g} rad/s"
    )
    steady = data.t >= steady_s
    if not (turning & steady).any():  # no steady part: all of it is start-up
        steady = np.zeros_like(turning)
    for ax, part, what in (
        (ax_start, ~steady, f"start-up, t < {steady_s:g} s"),
        (ax11, steady, f"t >= {steady_s:g} s" if steady_s > 0 else "whole run"),
    ):
        keep = turning & part
        xs = np.where(keep, rev, np.nan)
        filtered = np.where(keep, data.T_filtered, np.nan)
        exp = np.where(keep, data.T_expected, np.nan)
        true = np.where(keep, data.T_true, np.nan) if data.T_true is not None else None
        ax.plot(xs, filtered, label=data.filtered_label, **_FILT)
        ax.plot(xs, exp, label=_EXP_LABEL, zorder=3, **_EXP)
        if true is not None:  # on top: the reference the filtered torque is read against
            ax.plot(xs, true, label="true (truth channel)", zorder=4, **_TRUE)
        _fit_ylim(ax, [filtered, true, exp])
        if keep.any():
            ax.set_xlim(np.nanmin(xs), np.nanmax(xs))
        if ax is ax11:
            ax.set_title(f"Fig. 11: misalignment after filtering, {what} (steady part)")
        else:
            ax.set_title(what if keep.any() else f"{what}: none", fontsize=10)
    _legend_below(ax10)
    _legend_below(ax11, below=-0.2)  # the figure's last row: clear of its x label
