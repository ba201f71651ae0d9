"""Configuration of [Vertechy]'s joint-torque control in the interrupt handler.

:class:`ControlConfig` selects the law (:class:`Law`: JTF1 with or without the
desired-torque feedforward, JTF2, JTF3; Eq. 4, or Eq. 5 with the friction model of
:class:`FrictionModelConfig`), the desired torque wave (:class:`DesiredTorqueConfig`),
where the law takes its estimates from (the observer, Eq. 8, or the literature's
filters) and the design inputs :func:`firmware.lqg_design.design_lqg` computes the gains
from; no gain is hard-coded.  Off by default (``law = none``): then the handler is the
[Taghirad97] port unchanged.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Literal

from hdhil.core.dataconf import check_fields
from hdhil.firmware.config.reference import ReferenceConfig, Wave
from hdhil.firmware.lqg_design import (
    ControlLaw,
    Feedforward,
    JointParams,
    LqgWeights,
    ObserverMethod,
)

__all__ = [
    "JTF1_FF_TRACKING",
    "JTF_DERIVATIVE_HZ",
    "JTF_LOWPASS_HZ",
    "SEED_FRICTION_MODEL",
    "ControlConfig",
    "ControlFeedback",
    "DesiredTorqueConfig",
    "Estimates",
    "FrictionForm",
    "FrictionModelConfig",
    "Law",
]


class Law(enum.IntEnum):
    """Which torque-control law the interrupt runs ([Vertechy] §IV, Fig. 7).

    A plain integer code, so that a later SDO write (UNSIGNED8) can select it; in a
    scenario file it is written by name (``law = "jtf1"``).

    - ``NONE`` (0, the default): no torque control; the handler generates the
      reference voltage of [Taghirad97] (``reference_generation`` → ``write_dac0``), exactly
      as before.
    - ``JTF1`` (1): [Vertechy] Eq. 4, the LQG regulator (k1..k4 from the LQ design).
    - ``JTF1_FF`` (2): Eq. 4 with the desired-torque-derivative feedforward of §IV
      ("more demanding applications": ``e2 = τs' − τsD'`` and the gain k5 on ``τsD'``).
    - ``JTF2`` (3): PD JTF of refs. [17, 18], ``k3 = 0``, ``k4 = 1 + Jm/Jl``.
    - ``JTF3`` (4): PD JTF of refs. [19, 20], ``k3 = 0``, ``k4 = 1``.
    """

    NONE = 0
    JTF1 = 1
    JTF1_FF = 2
    JTF2 = 3
    JTF3 = 4

    @property
    def control_law(self) -> ControlLaw | None:
        """The :class:`firmware.lqg_design.ControlLaw` this code selects (None for ``NONE``)."""
        return None if self is Law.NONE else ControlLaw(self.name.lower())


@dataclass(frozen=True)
class DesiredTorqueConfig:
    """The desired sensor torque ``τsD`` as a waveform ([Vertechy] §VI: ``τsD = 20
    sin(0.4 π t)`` Nm, the default).

    The default amplitude is **-20 Nm**: the configuration is in the product sign (see
    below) and [Vertechy]'s ``τs`` is ``-T``, so ``T_D = -20 sin(0.4 π t)`` is its
    ``τsD = +20 sin(0.4 π t)``.  The sign matters relative to the link motion of the §VI
    scenario (``θl = 20° sin 2πt``, angles have the same sign in both conventions): the
    two error components add differently (JTF2: 5.4 Nm max |e| as in the paper, 5.8 Nm with
    the sign flipped; :mod:`firmware.tracking`).

    The waves are the reference generator's (:class:`firmware.stages.ReferenceGenerator`,
    :class:`Wave`) with the same parameters, in Nm instead of volts: ``bias_Nm`` b,
    ``amplitude_Nm`` A, ``frequency_Hz`` f, ``duty``, ``step_time_s``, and for a chirp
    ``chirp_end_Hz``, ``chirp_duration_s`` (e.g. a closed-loop sweep).  Torques are in the
    product convention (positive when the motor drives the load, like ``T_meas``; see
    :mod:`firmware.isr` for the mapping to [Vertechy]'s ``τs``).  The derivative ``τsD'``
    (feedforward of ``JTF1_FF`` and the one-sample prediction) is the central difference
    of the wave over ±1 sample, exact to 2.6e-7 relative for the default sine; for the
    discontinuous waves (square, step) it is an impulse of 2 samples.
    """

    wave: Wave = Wave.SINE
    bias_Nm: float = 0.0
    amplitude_Nm: float = -20.0
    frequency_Hz: float = 0.2
    duty: float = 0.5
    step_time_s: float = 0.0
    chirp_end_Hz: float = 10.0
    chirp_duration_s: float = 10.0

    def __post_init__(self) -> None:
        if not isinstance(self.wave, Wave):
            raise ValueError(f"desired.wave must be one of {[w.name.lower() for w in Wave]}")
        self.reference()  # same ranges as the reference generator's

    def reference(self) -> ReferenceConfig:
        """The same wave as a :class:`ReferenceConfig` (numbers in Nm, not V)."""
        return ReferenceConfig(
            wave=self.wave,
            bias_V=self.bias_Nm,
            amplitude_V=self.amplitude_Nm,
            frequency_Hz=self.frequency_Hz,
            duty=self.duty,
            step_time_s=self.step_time_s,
            chirp_end_Hz=self.chirp_end_Hz,
            chirp_duration_s=self.chirp_duration_s,
        )


#: The two readings of [Vertechy]'s garbled Eq. 5 friction model
#: (:class:`FrictionModelConfig`): ``"tanh"``, ``-C tanh(ω/s)``, or ``"fade-in"``,
#: ``-C sgn(ω) (1 + tanh(|ω|/s - o)) / 2``.
FrictionForm = Literal["tanh", "fade-in"]


@dataclass(frozen=True)
class FrictionModelConfig:
    """The motor-disturbance model ``τ̂d`` of [Vertechy] Eq. 5 (JTF1 with friction
    compensation, ``τm,2 = -[k1 (τ̂s - τsD) + k2 τ̂s' + k3 τ̂lg + k4 τsD] - τ̂d``).

    [Vertechy] §VI: "the experimentally determined motor
    friction torque model ``τ̂d = [-13.7 sign(ϑ̇m)(1 + tanh(|ϑ̇m|/2) - 4)]/2`` Nm, the
    controller implements (5) instead of (4)".  Printed garbled; both readings below top
    out at 13.7 Nm and oppose the motion, as the paper's ``max(τsD + τ̂d) ≈ 33.7`` Nm with
    ``τsD`` ≤ 20 Nm needs (``docs/papers.md``, "the experiment of §VI"):

    - the tanh reading, ``model = "tanh"`` (the default): a friction that is smooth
      through rest and saturates at a few ``velocity_scale_radps``::

          τ̂d = -coulomb_Nm · tanh(ω / velocity_scale_radps)

    - the fade-in reading, ``model = "fade-in"``: the printed formula with one bracket
      moved, a smooth step centred at ``|ω| = fade_in_offset · velocity_scale_radps``
      (8 rad/s) that vanishes near rest, so that the compensation is faded in once
      the motor turns (it is not applied where the sign of a slow velocity is
      uncertain)::

          τ̂d = -coulomb_Nm · sgn(ω) · (1 + tanh(|ω| / s - fade_in_offset)) / 2

      with ``s = velocity_scale_radps``.  Against a plant whose friction is the tanh
      one, its rise between about 4 and 12 rad/s is a negative damping at the motor
      and the joint mode oscillates while the motor turns that slowly
      (``docs/papers.md``).

    ``ω`` is the motor-shaft velocity the firmware measures (tachometer, rad/s at the
    motor shaft, not reduced to the output) and ``velocity_scale_radps`` the ``2`` of
    ``|ϑ̇m|/2``; the torque is output-referred, the same sign in the product
    convention and [Vertechy]'s (``firmware.isr``).

    ``coulomb_Nm = 0`` (the default) switches the compensation off: the law is Eq. 4 and
    the observer's third state is ``τlgd``; with a model it is ``τlg`` ([Vertechy] §V: "the
    substitution in (8) of τm,1 with (τm,2 + τ̂d) enables to find τ̂lg instead of
    τ̂lgd"), on a vertical joint (τg = 0) the external torque ``τl``.
    """

    #: Nm (output-referred) the model tops out at; 0 switches Eq. 5 off.
    coulomb_Nm: float = 0.0
    #: rad/s of the motor shaft: the ``2`` of ``|ϑ̇m|/2``.
    velocity_scale_radps: float = 2.0
    #: The reading of the garbled Eq. 5: ``"tanh"``, ``-C tanh(ω/s)``, or ``"fade-in"``,
    #: ``-C sgn(ω) (1 + tanh(|ω|/s - o)) / 2`` (ω the motor-shaft speed).
    model: FrictionForm = "tanh"
    #: ``o`` of the fade-in reading (the ``4``): the step is centred at ``o s`` rad/s.
    fade_in_offset: float = 4.0

    def __post_init__(self) -> None:
        if self.model not in ("tanh", "fade-in"):
            raise ValueError(
                f"control.friction.model must be 'tanh' or 'fade-in', got {self.model!r}"
            )
        check_fields(
            self, {"coulomb_Nm": ">=0", "velocity_scale_radps": ">0", "fade_in_offset": ">=0"}
        )

    @property
    def active(self) -> bool:
        """True when the law compensates the friction (Eq. 5)."""
        return self.coulomb_Nm > 0.0

    def torque(self, velocity_radps: float) -> float:
        """``τ̂d`` (Nm, output) at the motor velocity ``velocity_radps`` (rad/s, motor)."""
        x = velocity_radps / self.velocity_scale_radps
        if self.model == "tanh":
            return -self.coulomb_Nm * math.tanh(x)
        if x == 0.0:
            return 0.0
        step = 0.5 * (1.0 + math.tanh(abs(x) - self.fade_in_offset))
        return -math.copysign(self.coulomb_Nm * step, x)


#: [Vertechy] §VI: the experiment's motor friction model (13.7 Nm, 2 rad/s at the motor).
SEED_FRICTION_MODEL = FrictionModelConfig(coulomb_Nm=13.7, velocity_scale_radps=2.0)

#: [Vertechy] §V: the estimates JTF2 and JTF3 take in the literature ("the estimates τ̂s
#: and τ̂s' are obtained by simply feeding the torque sensor measurement y through basic
#: low-pass and derivative filters"): ``"filters"``; ``"observer"`` takes them from the
#: LQG observer (Eq. 8), as JTF1 does.
Estimates = Literal["observer", "filters"]

#: Cut-off (Hz) of the first-order low-pass giving τ̂s for the ``filters`` estimates.
#: [Vertechy] gives none.  It must pass the 17 Hz joint mode the PD law damps with little
#: phase lag (18.8° at 17 Hz) while cutting the sensor noise (W = 0.12 Nm rms per
#: sample) to ~0.05 Nm rms (the noise bandwidth of a 50 Hz first-order low-pass is
#: 78.5 Hz of the 500 Hz Nyquist band).  20-100 Hz change the noise-free §VI figure by
#: less than 0.15 Nm.
JTF_LOWPASS_HZ = 50.0
#: Cut-off (Hz) of the band-limited differentiator ``s / (s/ωd + 1)`` giving τ̂s' for the
#: ``filters`` estimates.  [Vertechy] gives none; the loop decides it.  With its k1,
#: k2 (q1 = 500, q2 = 0.1: the derivative term alone closes a loop near 130 Hz) and one
#: sample of actuation delay, the §VI tracking loop (``firmware.tracking``, noise-free)
#: runs into the torque limit for any derivative cut-off up to 300 Hz (max |e| of
#: JTF3 at 50 Hz low-pass: 7.9 Nm at 50 Hz, 3.0 Nm at 200 Hz, 2.24 Nm at 300 Hz, all
#: saturating) and is stable from 350 Hz on (2.13 Nm, no saturation).  400 Hz keeps a
#: margin; it leaves the sensor noise almost unfiltered in τ̂s', which is [Vertechy] §V's
#: point ("this may degrade JTF control performance since built-in joint-torque
#: sensors are usually affected by noise w having significant variance").  (The [Taghirad97]
#: listing's ``Diff_filter``, H(s) = s / (0.005 s + 1), has 31.8 Hz.)
JTF_DERIVATIVE_HZ = 400.0


ControlFeedback = Literal["T_meas", "T_filtered"]


@dataclass(frozen=True)
class ControlConfig:
    """Joint-torque control of [Vertechy] in the interrupt handler (:mod:`firmware.isr`).

    With ``law = NONE`` (the default) nothing here is used and the firmware behaves as
    the [Taghirad97] port always did.  With a law, the handler's "reference generation"
    stage runs the LQG regulator of [Vertechy] (observer Eq. 8 + law Eq. 4) on the
    measured torque and writes the motor torque command to the DAC.  The design (LQ
    gains, Kalman gain, discrete observer) is computed once, when the handler is built,
    by :func:`firmware.lqg_design.design_lqg` from the fields below; no gain is hard-coded.

    - ``law``: :class:`Law` (plain integer code, SDO-writable later).
    - ``joint``: Jm, Jl, k, c for the design ([Vertechy] §I-II: 2.5, 0.7, 6300, 11.8).
    - ``weights``: q1, q2, W, V ([Vertechy] §VI: 500, 0.1, 0.12, 1e4).
    - ``feedforward``: how k3, k4, k5 are chosen, ``lq`` (Friedland's LQ gains, the
      paper's numbers) or ``exact`` (zero static error, ``G0 = B⁺E``).
    - ``observer``: discretisation of Eq. 8 (``zoh-kalman`` or ``zoh-observer``).
    - ``delay_samples`` / ``predict``: the command computed at sample k acts from
      t(k + delay_samples): 1 for the synchronous RPDO (``--actuation next-sync``), 0
      for ``immediate``; ``predict`` applies Eq. 4 to the one-step prediction
      (:class:`firmware.lqg.LqgController`).
    - ``feedback``: the torque the regulator measures: ``T_meas`` (default, [Vertechy]:
      the LQG's own Kalman filter does the filtering) or ``T_filtered`` (after the
      [Taghirad97] ripple filter, for a joint with angle-locked torque ripple).
    - ``desired``: ``τsD`` (:class:`DesiredTorqueConfig`).
    - ``torque_per_volt``: the actuator calibration, output-referred motor torque per
      DAC volt (Nm/V).  It **must match the drive** (``hostsim``:
      ``PlantConfig.torque_per_volt = gear_ratio · Kt · gain_A_per_V``); the default 6.0
      is the default plant's 100 · 0.06 Nm/A · 1 A/V.  Negative for an inverted drive.
    - ``torque_limit_Nm``: motor torque limit (output-referred); the command is clipped
      to it and to the DAC range (±10 V · ``torque_per_volt``).  Default 36 Nm, the
      default plant's current limit (6 A · 0.06 Nm/A · 100).
    - ``friction``: the motor-friction model of Eq. 5 (:class:`FrictionModelConfig`);
      off by default (Eq. 4).  :data:`SEED_FRICTION_MODEL` is [Vertechy]'s experiment.
    - ``estimates``: where the law takes ``τ̂s`` and ``τ̂s'`` from: ``observer`` (Eq. 8,
      the default, for every law) or ``filters`` ([Vertechy] §V: JTF2 and JTF3 as the
      literature builds them, a first-order low-pass at ``lowpass_Hz`` and a
      band-limited differentiator at ``derivative_Hz`` on the measured torque, no
      prediction; :data:`JTF_LOWPASS_HZ`, :data:`JTF_DERIVATIVE_HZ`).  With
      ``filters`` the observer still runs, on the applied command, for the telemetry
      of ``τ̂lgd``; JTF1 with ``filters`` is refused (its k3 needs ``τ̂lgd``).
    """

    law: Law = Law.NONE
    joint: JointParams = field(default_factory=JointParams)
    weights: LqgWeights = field(default_factory=LqgWeights)
    feedforward: Feedforward = Feedforward.LQ
    observer: ObserverMethod = ObserverMethod.ZOH_KALMAN
    delay_samples: int = 1
    predict: bool = True
    feedback: ControlFeedback = "T_meas"
    desired: DesiredTorqueConfig = field(default_factory=DesiredTorqueConfig)
    torque_per_volt: float = 6.0
    torque_limit_Nm: float = 36.0
    friction: FrictionModelConfig = field(default_factory=FrictionModelConfig)
    estimates: Estimates = "observer"
    lowpass_Hz: float = JTF_LOWPASS_HZ
    derivative_Hz: float = JTF_DERIVATIVE_HZ

    def __post_init__(self) -> None:
        if self.estimates not in ("observer", "filters"):
            raise ValueError(
                f"control.estimates must be 'observer' or 'filters', got {self.estimates!r}"
            )
        if self.estimates == "filters" and self.law in (Law.JTF1, Law.JTF1_FF):
            raise ValueError(
                "control.estimates = 'filters' is for jtf2 and jtf3 ([Vertechy] §V); JTF1 "
                "needs the observer's exogenous-torque estimate"
            )
        check_fields(self, {"lowpass_Hz": ">0", "derivative_Hz": ">0"})
        for name, expected in (
            ("friction", FrictionModelConfig),
            ("law", Law),
            ("joint", JointParams),
            ("weights", LqgWeights),
            ("feedforward", Feedforward),
            ("observer", ObserverMethod),
            ("desired", DesiredTorqueConfig),
        ):
            if not isinstance(getattr(self, name), expected):
                raise ValueError(f"control.{name} must be a {expected.__name__}")
        d = self.delay_samples
        if isinstance(d, bool) or d not in (0, 1):
            raise ValueError(f"control.delay_samples must be 0 or 1, got {d!r}")
        if not isinstance(self.predict, bool):
            raise ValueError(f"control.predict must be true or false, got {self.predict!r}")
        if self.feedback not in ("T_meas", "T_filtered"):
            raise ValueError(
                f"control.feedback must be 'T_meas' or 'T_filtered', got {self.feedback!r}"
            )
        check_fields(self, {"torque_per_volt": "!=0", "torque_limit_Nm": ">0"})

    @property
    def active(self) -> bool:
        """True when a control law runs (``law`` is not ``NONE``)."""
        return self.law is not Law.NONE

    @property
    def ripple_filter_in_loop(self) -> bool:
        """True when the torque-ripple filter's output is used: without a law it is the
        torque the telemetry reports (``CTRL_TPDO1.T_filtered``), with one only if the
        regulator feeds back on it (``feedback = "T_filtered"``); otherwise the filter
        has nothing to act on and the telemetry carries the law's estimate τ̂s."""
        return not self.active or self.feedback == "T_filtered"


#: JTF1 + feedforward tuned for the [Vertechy] §VI tracking scenario (link moved as
#: ``θl = 20° sin 2πt``, ``τsD = 20 sin 0.4πt``), max |e| <= 0.3 Nm
#: (docs/papers.md has the numbers and the reasons).  [Vertechy]'s LQ
#: loop gains k1, k2 (q1 = 500, q2 = 0.1) are kept; three things change, and each is
#: needed:
#:
#: - ``JTF1_FF``: the paper's own ``τsD'`` feedforward (§IV, "more demanding
#:   applications");
#: - ``feedforward = exact``: zero-static-error gains on the exogenous inputs (k3 =
#:   -Jm/Jl, k4 = 1 + Jm/Jl, k5 = Jm c/(J k)) instead of the LQ compromise, which
#:   leaves -4 % of τsD and +3 % of τlgd as a static error;
#: - ``V = 1e7`` (paper: 1e4): a faster observer of the exogenous torque τlgd, whose
#:   Wiener-process model lags a moving link by ~17 ms x τlgd' at V = 1e4.
#:
#: The price is precision ([Vertechy] §V: larger V/W is "more accurate but less precise"):
#: with the paper's sensor noise (W = 0.12 Nm per sample) the noise part of e is
#: about twice the paper design's and the command noise reaches a 150 Nm torque limit.
#: A tuning for the noise-free §VI scenario (the paper's simulation), not for a noisy
#: joint.  ``torque_per_volt`` and ``torque_limit_Nm`` are the defaults; set them to
#: the drive's.
JTF1_FF_TRACKING = ControlConfig(
    law=Law.JTF1_FF,
    weights=LqgWeights(V=1e7),
    feedforward=Feedforward.EXACT,
)
