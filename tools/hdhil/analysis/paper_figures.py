"""Two more of the papers' figures, redrawn from this project's data (``hdhil plot
--figure fig8`` and ``hdhil calibrate --plot``):

- :func:`fig8_data` / :func:`make_fig8`: [Vertechy] Fig. 8, "Performance of the
  proposed LQG torque regulator (experimental results)", from a trace of a torque-control
  run;
- :func:`make_calibration_figure`: [Taghirad97] Figs. 6-7, "Torque sensor calibration
  results for low-range loading" / "... full-range loading", from a calibration result.

Torques of Fig. 8 are in the seed's sign (``τs = -T``, :mod:`hdhil.firmware.isr`), so
the desired torque is ``+20 sin(0.4 π t)`` as printed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.figure import Figure

from hdhil.core.errors import UserError
from hdhil.core.plotlabels import NM, axis_label

if TYPE_CHECKING:
    from hdhil.hostsim.plant import LinkMotionConfig

__all__ = [
    "Fig8Data",
    "Fig8Stats",
    "fig8_data",
    "fig8_stats",
    "fig8_window",
    "make_calibration_figure",
    "make_fig8",
]


@dataclass
class Fig8Data:
    """Time series of [Vertechy] Fig. 8, one row per control telemetry sample, in the
    seed's sign convention (Nm, deg, rad/s)."""

    t: np.ndarray
    tau_s_meas: np.ndarray  #: τs^m, the calibrated measured torque
    tau_s_hat: np.ndarray  #: τ̂s, the observer's estimate
    tau_sD: np.ndarray  #: τsD, the desired torque from telemetry
    tau_s_true: np.ndarray  #: τs, truth (NaN without a truth channel)
    tau_l_hat: np.ndarray  #: the observer's exogenous-torque estimate (τ̂lg with Eq. 5)
    #: τl^m (+ τg): what the handle's sensor measures, true (``TRUTH_JOINT.tau_ext`` less
    #: the output bearings' friction, ``LinkMotionConfig.handle_torque``)
    tau_l_meas: np.ndarray
    theta_l_deg: np.ndarray
    omega_l: np.ndarray
    tau_m: np.ndarray  #: commanded motor torque (output-referred)

    def __len__(self) -> int:
        return len(self.t)


def fig8_data(trace: Path, handle: LinkMotionConfig | None = None) -> tuple[Fig8Data, str]:
    """Read a trace of a torque-control run into :class:`Fig8Data` (and a damage note).
    ``handle``: the run's link (``[plant.link]``), whose bearing friction separates the
    handle torque τl^m from ``TRUTH_JOINT.tau_ext``; None: τl^m is ``tau_ext``."""
    from hdhil.can.traces.reader import read_trace
    from hdhil.dbc import codec

    t1 = codec("control", "CTRL_TPDO1").expect("T_meas", "T_filtered", "velocity", "current")
    t2 = codec("control", "CTRL_TPDO2").expect("dtau_s_hat", "tau_lgd_hat", "tau_sD", "e_hat")
    tt = codec("truth", "TRUTH_TORQUE").expect("T_true", "T_ripple")
    tm = codec("truth", "TRUTH_MOTION").expect(
        "theta_motor", "theta_output", "omega_motor", "omega_output"
    )
    tj = codec("truth", "TRUTH_JOINT").expect("tau_ext", "tau_d", "tau_m", "tau_m_cmd")
    keys = {
        (t1.frame_id, False): "t1",
        (t2.frame_id, False): "t2",
        (tt.frame_id, True): "tt",
        (tm.frame_id, True): "tm",
        (tj.frame_id, True): "tj",
    }
    from hdhil.rig.score import trace_time_offset

    last: dict[str, tuple[Any, ...]] = {}
    rows: list[tuple[float, ...]] = []
    nan = math.nan
    t0 = trace_time_offset(trace)  # simulated time 0 (None: the first frame's time)
    with read_trace(trace) as frames:
        for msg in frames:
            if t0 is None:
                t0 = msg.timestamp
            key = keys.get((msg.arbitration_id, msg.is_extended_id))
            if key is None or len(msg.data) != 8:
                continue
            if key != "t2":
                last[key] = {"t1": t1, "tt": tt, "tm": tm, "tj": tj}[key].decode(msg.data)
                continue
            if "t1" not in last:
                continue
            _dtau, tau_lgd_hat, tau_sD, _e = t2.decode(msg.data)
            T_meas, T_filtered, _vel, _cur = last["t1"]
            T_true = last["tt"][0] if "tt" in last else nan
            th, om = (last["tm"][1], last["tm"][3]) if "tm" in last else (nan, nan)
            tau_ext, _tau_d, _tau_m, tau_m_cmd = last.get("tj", (nan,) * 4)
            rows.append((msg.timestamp - t0, T_meas, T_filtered, tau_sD, T_true, tau_lgd_hat,
                         tau_ext, th, om, tau_m_cmd))  # fmt: skip
        damage = "; ".join(d.describe(str(trace)) for d in frames.damage)
    if len(rows) < 2:
        raise UserError(
            f"{trace}: no torque-control telemetry (CTRL_TPDO2) to draw [Vertechy] Fig. 8 from; "
            "record a run with a control law (e.g. hdhil run --scenario lqg-experiment --trace)"
        )
    a = np.array(rows, dtype=float)
    theta = np.degrees((a[:, 7] + math.pi) % (2.0 * math.pi) - math.pi)  # link within ±180°
    if handle is not None and handle.bearing_coulomb_Nm:
        a[:, 6] = [handle.handle_torque(x, w) for x, w in zip(a[:, 6], a[:, 8], strict=True)]
    return (
        Fig8Data(
            t=a[:, 0],
            tau_s_meas=-a[:, 1],
            tau_s_hat=-a[:, 2],
            tau_sD=-a[:, 3],
            tau_s_true=-a[:, 4],
            tau_l_hat=a[:, 5],
            tau_l_meas=a[:, 6],
            theta_l_deg=theta,
            omega_l=a[:, 8],
            tau_m=a[:, 9],
        ),
        damage,
    )


#: Legends beside the axes, outside the data (the constrained layout makes room).
_BESIDE = {"loc": "upper left", "bbox_to_anchor": (1.01, 1.0), "fontsize": 8, "frameon": False}


@dataclass(frozen=True)
class Fig8Stats:
    """The figures quoted in Fig. 8's legends, over exactly the samples drawn."""

    max_abs_e: float  #: max |e|, e = τs − τsD (N·m)
    max_abs_dl: float  #: max |τ̂l − τl^m| (N·m)
    max_abs_tau_m: float  #: max |τm| (N·m)


def fig8_window(d: Fig8Data, skip_s: float) -> np.ndarray:
    """The samples Fig. 8 draws (and computes its legend figures over): ``t >= skip_s``."""
    return d.t >= skip_s


def fig8_stats(d: Fig8Data, skip_s: float) -> Fig8Stats:
    """:class:`Fig8Stats` over :func:`fig8_window`."""
    w = fig8_window(d, skip_s)

    def peak(x: np.ndarray) -> float:
        x = x[w & np.isfinite(x)]
        return float(np.max(np.abs(x))) if x.size else math.nan

    return Fig8Stats(
        max_abs_e=peak(d.tau_s_true - d.tau_sD),
        max_abs_dl=peak(d.tau_l_hat - d.tau_l_meas),
        max_abs_tau_m=peak(d.tau_m),
    )


def make_fig8(d: Fig8Data, title: str, skip_s: float = 0.0) -> Figure:
    """[Vertechy] Fig. 8 over ``t >= skip_s`` (the start-up before it is not drawn; the
    figures in the legends, :func:`fig8_stats`, are over the same samples).  One axis
    per quantity, from top to bottom:

    1. the raw sensor torque τs^m, the Kalman estimate τ̂s and the desired torque τsD;
    2. the external-torque estimate τ̂l and the handle's measurement τl^m (here the
       emulator's true handle torque, :attr:`Fig8Data.tau_l_meas`), dashed on top so
       that both show where they agree;
    3. the tracking error e and the difference τ̂l − τl^m ("the proposed controller is
       able to keep the torque sensor tracking error e within ±0.5 Nm"; "the
       significant difference (roughly ±3 Nm) between τ̂l and τl^m");
    4. the commanded motor torque τm ("τm is rather smooth and remains within ±40 Nm");
    5. the link position θl, and its velocity on its own (right) axis (no legend: the
       axes' coloured labels name them).

    Everything comes from the trace: the controller's telemetry (``CTRL_TPDO1``,
    ``CTRL_TPDO2``: τ̂s, τ̂lgd, τsD), the drive's command (``TRUTH_JOINT.tau_m_cmd``)
    and the truth channel.  Legends sit beside the axes, outside the data.
    """
    fig = Figure(figsize=(12, 14), layout="constrained")
    axes = fig.subplots(5, 1, sharex=True, height_ratios=(3, 3, 2.5, 2.5, 2.5))
    w = fig8_window(d, skip_s)
    if not w.any():
        raise UserError(f"the trace ends before t = {skip_s:g} s: nothing to draw from there")
    stats = fig8_stats(d, skip_s)
    t = d.t[w]
    e = (d.tau_s_true - d.tau_sD)[w]
    dl = (d.tau_l_hat - d.tau_l_meas)[w]

    ax = axes[0]
    ax.plot(t, d.tau_s_meas[w], color="0.6", lw=2.0, label=r"$\tau_s^m$ (measured)")
    ax.plot(t, d.tau_s_hat[w], color="C0", lw=0.8, label=r"$\hat{\tau}_s$ (Kalman estimate)")
    ax.plot(t, d.tau_sD[w], "k--", lw=0.8, label=r"$\tau_{sD}$ (desired)")
    ax.set_ylabel(axis_label("sensor torque", NM))
    ax = axes[1]
    ax.plot(t, d.tau_l_hat[w], color="C1", lw=1.6, label=r"$\hat{\tau}_l$ (observer)")
    ax.plot(t, d.tau_l_meas[w], color="k", lw=0.9, ls=(0, (4, 2)), zorder=3,
            label=r"$\tau_l^m$ (handle torque, true)")  # fmt: skip
    ax.set_ylabel(axis_label("external torque", NM))
    ax = axes[2]
    e_label = rf"$e = \tau_s - \tau_{{sD}}$ (max $|e|$ {stats.max_abs_e:.2f} {NM})"
    dl_label = rf"$\hat{{\tau}}_l - \tau_l^m$ (max $|\cdot|$ {stats.max_abs_dl:.2f} {NM})"
    ax.plot(t, e, color="C3", lw=0.8, label=e_label)
    ax.plot(t, dl, color="C2", lw=0.8, label=dl_label)
    for y in (-0.5, 0.5):
        ax.axhline(y, color="k", lw=0.5, ls=":")
    ax.set_ylabel(axis_label("error", NM))
    ax = axes[3]
    ax.plot(t, d.tau_m[w], color="C3", lw=0.8,
            label=rf"$\tau_m$ (max $|\tau_m|$ {stats.max_abs_tau_m:.1f} {NM})")  # fmt: skip
    for y in (-40.0, 40.0):
        ax.axhline(y, color="k", lw=0.5, ls=":", label="±40 N·m" if y > 0 else None)
    ax.set_ylabel(axis_label("motor torque", NM))
    ax = axes[4]
    ax.plot(t, d.theta_l_deg[w], color="C0", lw=1.0)
    ax.set_ylabel(axis_label(r"link angle $\theta_l$", "deg"), color="C0")
    ax.tick_params(axis="y", colors="C0")
    ax_v = ax.twinx()
    ax_v.plot(t, np.degrees(d.omega_l[w]), color="C4", lw=0.8)
    ax_v.set_ylabel(axis_label(r"link velocity $\dot{\theta}_l$", "deg/s"), color="C4")
    ax_v.tick_params(axis="y", colors="C4")
    ax.set_xlabel(axis_label("time", "s"))
    ax.set_xlim(t[0], t[-1])
    for ax in axes:
        ax.grid(True, lw=0.3)
        if ax.get_legend_handles_labels()[0]:  # the last panel: its axes' labels say it
            ax.legend(**_BESIDE)
    fig.suptitle(title, fontsize=9)
    return fig


def make_calibration_figure(result: Any, title: str) -> Figure:
    """[Taghirad97] Figs. 6-7: torque against bridge voltage per experiment, fitted lines,
    one panel per load range (``result`` a :class:`hdhil.hostsim.calibration.CalibrationResult`);
    legends below the axes, outside the data."""
    ranges = sorted({e.range_Nm for e in result.experiments})
    fig = Figure(figsize=(6.0 * len(ranges), 5.5), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(ranges)))
    for ax, rng, fig_no in zip(axes, ranges, range(6, 6 + len(ranges)), strict=False):
        for e in (x for x in result.experiments if x.range_Nm == rng):
            v = np.asarray(e.volts)
            (pts,) = ax.plot(
                v, e.torques_Nm, "o", ms=3, label=f"exp. {e.index}: {e.gain_Nm_per_V:.3f} {NM}/V"
            )
            line = np.array([v.min(), v.max()])
            ax.plot(line, e.gain_Nm_per_V * (line - e.offset_V), lw=0.7, color=pts.get_color())
        kind = "low-range" if rng == ranges[0] and len(ranges) > 1 else "full-range"
        ax.set_title(f"[Taghirad97] Fig. {fig_no}: {kind} loading (±{rng:g} {NM})", fontsize=9)
        ax.set_xlabel(axis_label("bridge amplifier output", "V"))
        ax.set_ylabel(axis_label("applied torque", NM))
        ax.grid(True, lw=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncols=2,
                  frameon=False)  # fmt: skip
    fig.suptitle(title, fontsize=9)
    return fig
