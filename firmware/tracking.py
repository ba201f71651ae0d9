"""[Vertechy] §VI tracking simulation without the bus: the figures of the control laws.

§VI, Fig. 7: the regulator tracks ``τsD = 20 sin(0.4 π t)`` Nm while the output link is
moved as ``θl = 20 sin(2 π t)`` deg, with ``τd = τg = W = 0``.  :func:`simulate_tracking`
closes the firmware's own torque-control stage (:class:`firmware.isr.TorqueControl`:
design, observer Eq. 8, law Eq. 4, sign mapping, torque limit, DAC quantisation, the
applied torque fed back) around the motor side of [Vertechy] Eq. 1 with the link on its
prescribed trajectory (:class:`TrackingPlant`), in the 1 ms loop with one sample of
transport delay.  The plant is linear, so one matrix exponential per sample integrates
it exactly.  No CAN and no emulator: the figures come out in a few hundred milliseconds,
and the test suite checks them against the emulator's plant closed around the interrupt
handler.

It reproduces the paper's ranking (JTF1 < JTF3 < JTF2), not its "|e| <= 0.3 Nm" for
JTF1: the Wiener-process observer of ``τlgd`` lags the moving link (max |e| about 1.2 Nm
at 1 Hz).  :data:`firmware.config.JTF1_FF_TRACKING` (the §IV feedforward, zero-static-
error gains, V = 1e7) reaches 0.21 Nm, a tuning for noise-free conditions.  The numbers
and the reasons are in docs/papers.md.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hdhil.core.dataconf import check_fields
from hdhil.core.expm import expm
from hdhil.firmware.config import ControlConfig, FirmwareConfig, Law
from hdhil.firmware.isr import IsrOutput, TorqueControl
from hdhil.firmware.lqg_design import JointParams

__all__ = ["TrackingPlant", "simulate_tracking", "tracking_table"]


@dataclass(frozen=True)
class TrackingPlant:
    """The [Vertechy] §VI simulation plant: motor side of Eq. 1, link on a prescribed sine.

    ``Jm θm'' = τm + k (θl − θm) + c (θl' − θm')`` with ``θl = A sin(2 π f t)``
    (``A = link_amplitude_deg``, ``f = link_frequency_Hz``), everything reduced to the
    output; ``τd = τg = 0``.  The motor starts where a rigid joint would (no twist,
    moving with the link), like :class:`hostsim.plant.LinkMotionConfig`.  The sensor
    reads the spring torque ``τs = k (θl − θm)`` (reported in the product sign ``T =
    -τs``), plus white noise of standard deviation ``noise_Nm`` per sample ([Vertechy]
    §I: W = 0.12 Nm; 0 in the paper's simulation), rounded to ``adc_lsb_Nm`` (0: not quantised).
    The motor torque follows the command through a first-order lag ``current_lag_s``
    (0: at once).

    Attributes:
        joint: the true joint (default: [Vertechy] §I-II, as the design assumes).
        link_amplitude_deg, link_frequency_Hz: the link trajectory ([Vertechy]: 20°, 1 Hz).
        noise_Nm: torque-measurement noise standard deviation per sample (Nm).
        adc_lsb_Nm: torque-measurement quantisation step (Nm).
        current_lag_s: amplifier current-loop time constant (s).
        seed: noise generator seed.
    """

    joint: JointParams = dataclasses.field(default_factory=JointParams)
    link_amplitude_deg: float = 20.0
    link_frequency_Hz: float = 1.0
    noise_Nm: float = 0.0
    adc_lsb_Nm: float = 0.0
    current_lag_s: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        check_fields(
            self,
            {
                "link_amplitude_deg": "finite",
                "link_frequency_Hz": ">0",
                "noise_Nm": ">=0",
                "adc_lsb_Nm": ">=0",
                "current_lag_s": ">=0",
            },
        )

    def discrete(self, Ts: float) -> tuple[np.ndarray, np.ndarray]:
        """Exact ZOH over ``Ts`` of the state ``[θm, θm', τa, s, co]`` (``τa`` the acting
        motor torque, ``s = sin ωt``, ``co = cos ωt``) for the held command ``u``:
        ``x(k+1) = Ad x(k) + bd u``."""
        p = self.joint
        A = math.radians(self.link_amplitude_deg)
        w = 2.0 * math.pi * self.link_frequency_Hz
        a = np.zeros((6, 6))  # last column: the input u
        a[0, 1] = 1.0
        a[1, 0], a[1, 1] = -p.k / p.Jm, -p.c / p.Jm
        a[1, 3], a[1, 4] = p.k * A / p.Jm, p.c * A * w / p.Jm
        if self.current_lag_s > 0.0:
            a[1, 2] = 1.0 / p.Jm
            a[2, 2], a[2, 5] = -1.0 / self.current_lag_s, 1.0 / self.current_lag_s
        else:
            a[1, 5] = 1.0 / p.Jm
        a[3, 4], a[4, 3] = w, -w
        F = expm(a * Ts)
        Ad, bd = F[:5, :5], F[:5, 5]
        if self.current_lag_s == 0.0:
            Ad[2, :], bd[2] = 0.0, 1.0  # τa is the held command
        return Ad, bd

    def initial_state(self) -> np.ndarray:
        """Rigid start: ``θm = θl(0) = 0``, ``θm' = θl'(0) = A ω``, no torque."""
        A = math.radians(self.link_amplitude_deg)
        w = 2.0 * math.pi * self.link_frequency_Hz
        return np.array([0.0, A * w, 0.0, 0.0, 1.0])


def simulate_tracking(
    control: ControlConfig | FirmwareConfig,
    duration_s: float = 5.0,
    plant: TrackingPlant | None = None,
    *,
    law: Law | None = None,
    evaluate_from_s: float = 1.0,
    record: bool = False,
) -> dict[str, Any]:
    """Close the firmware's torque-control stage around :class:`TrackingPlant`.

    Args:
        control: the control configuration (a :class:`FirmwareConfig` to take its
            sample period and DAC too; otherwise 1 ms and the default 12-bit, ±10 V
            DAC).  Its ``torque_per_volt`` is taken to be the drive's (the command acts
            exactly as ``DAC volts × torque_per_volt``).
        duration_s: simulated time (s).
        plant: the plant (default: [Vertechy] §VI, no noise).
        law: override ``control.law`` (for tables).
        evaluate_from_s: the figures ignore the start-up transient before this time.
        record: also return the time series (``t``, ``T``, ``T_D``, ``T_hat``,
            ``tau_lgd_hat``, ``tau_m``, arrays).

    Returns:
        ``law`` (name), ``max_abs_e`` and ``rms_e`` (true tracking error ``e = T − T_D``,
        Nm; [Vertechy]'s ``τs − τsD`` up to the sign), ``max_abs_e_hat`` / ``rms_e_hat``
        (the firmware's estimate ``T̂ − T_D``), ``max_abs_tau_m`` (Nm),
        ``saturations`` (samples clipped), ``samples`` (evaluated), ``sample_period_s``.
    """
    fw = control if isinstance(control, FirmwareConfig) else FirmwareConfig(control=control)
    c = fw.control
    if law is not None:
        c = dataclasses.replace(c, law=Law(law))
    if not c.active:
        raise ValueError("simulate_tracking needs a control law (law 'none' controls nothing)")
    fw = dataclasses.replace(fw, control=c)
    plant = plant or TrackingPlant()
    Ts = fw.sample_period_s
    n = round(duration_s / Ts)
    k0 = round(evaluate_from_s / Ts)
    if not 0 <= k0 < n:
        raise ValueError(f"evaluate_from_s must lie in [0, duration_s), got {evaluate_from_s!r}")

    stage = TorqueControl(fw)
    out = IsrOutput()
    Ad, bd = plant.discrete(Ts)
    rows = [tuple(float(v) for v in Ad[i]) for i in range(5)]
    b = tuple(float(v) for v in bd)
    x = list(plant.initial_state())
    k_s = plant.joint.k
    A_l = math.radians(plant.link_amplitude_deg)
    rng = np.random.default_rng(plant.seed)
    sigma = plant.noise_Nm
    noise = rng.standard_normal(n) * sigma if sigma > 0 else np.zeros(n)
    lsb = plant.adc_lsb_Nm
    delayed = c.delay_samples == 1
    applied = 0.0
    rec = np.zeros((n, 6))
    for k in range(n):
        T = -k_s * (A_l * x[3] - x[0])  # product sign of τs = k (θl − θm)
        y = T + noise[k]
        if lsb > 0.0:
            y = round(y / lsb) * lsb
        stage(k, y, out)
        if not delayed:
            applied = out.tau_m_cmd
        rec[k] = (T, out.tau_sD, out.tau_s_hat, out.tau_lgd_hat, out.tau_m_cmd, out.e_hat)
        x = [
            sum(r[j] * x[j] for j in range(5)) + r_b * applied
            for r, r_b in zip(rows, b, strict=True)
        ]
        if delayed:
            applied = out.tau_m_cmd
    e = rec[k0:, 0] - rec[k0:, 1]
    e_hat = rec[k0:, 5]
    result: dict[str, Any] = {
        "law": c.law.name.lower(),
        "max_abs_e": float(np.max(np.abs(e))),
        "rms_e": float(np.sqrt(np.mean(e * e))),
        "max_abs_e_hat": float(np.max(np.abs(e_hat))),
        "rms_e_hat": float(np.sqrt(np.mean(e_hat * e_hat))),
        "max_abs_tau_m": float(np.max(np.abs(rec[k0:, 4]))),
        "saturations": stage.saturations,
        "samples": int(n - k0),
        "sample_period_s": Ts,
    }
    if record:
        result.update(
            t=np.arange(n) * Ts,
            T=rec[:, 0],
            T_D=rec[:, 1],
            T_hat=rec[:, 2],
            tau_lgd_hat=rec[:, 3],
            tau_m=rec[:, 4],
        )
    return result


def tracking_table(
    control: ControlConfig | None = None,
    ff_control: ControlConfig | None = None,
    plant: TrackingPlant | None = None,
    duration_s: float = 5.0,
    evaluate_from_s: float = 1.0,
) -> list[dict[str, Any]]:
    """[Vertechy]'s Fig. 7 comparison plus the feedforward configuration, one row per law.

    Rows: JTF1, JTF2, JTF3 with ``control``'s design (default: the paper's, 20 Nm/V),
    then ``ff_control`` (default :data:`firmware.config.JTF1_FF_TRACKING` with the same
    actuator calibration) labelled ``jtf1_ff (tuned)``.
    """
    from hdhil.firmware.config import JTF1_FF_TRACKING

    base = control or ControlConfig(law=Law.JTF1, torque_per_volt=20.0, torque_limit_Nm=150.0)
    ff = ff_control or dataclasses.replace(
        JTF1_FF_TRACKING,
        torque_per_volt=base.torque_per_volt,
        torque_limit_Nm=base.torque_limit_Nm,
    )
    rows = []
    for law in (Law.JTF1, Law.JTF2, Law.JTF3):
        rows.append(
            simulate_tracking(base, duration_s, plant, law=law, evaluate_from_s=evaluate_from_s)
        )
    row = simulate_tracking(ff, duration_s, plant, evaluate_from_s=evaluate_from_s)
    row["law"] = "jtf1_ff (tuned)"
    rows.append(row)
    return rows
