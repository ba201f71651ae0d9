"""Typed configuration of the ported firmware (the 1 kHz interrupt handler of [Taghirad97]).

Every value the C listing of [Taghirad97] (Appendix A.1 ``free_kalman.c``, and A.2) keeps
in a global variable, a host mailbox or a literal inside a function is a field here, with
the listing's value as the default; the torque control of [Vertechy] is
:class:`ControlConfig`.  All classes are frozen dataclasses that check their ranges in
``__post_init__``, so ``hdhil.core.dataconf.from_dict`` turns a bad scenario value into a
one-line ``ConfigError`` naming the key (docs/reference/scenario-keys.md lists them).

The ripple filter has two modes (:class:`RippleFilterConfig`): ``"paper"`` is the
prediction-type Kalman filter of [Taghirad97] exactly as listings A.1 / A.2 implement it
(:class:`firmware.ripple.RippleKalman`; presets :data:`LISTING_A1_RIPPLE`,
:data:`LISTING_A2_RIPPLE`, :data:`SECTION5_RIPPLE`); ``"recommended"`` (the default) is
our angle-locked harmonic regression filter (:class:`firmware.ripple.HarmonicKalman`),
which keeps the low-frequency torque the paper filter absorbs.  :func:`paper_config` /
:func:`recommended_config` switch a whole :class:`FirmwareConfig` between the modes.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass, field
from typing import Literal

from hdhil.core.converter import Converter
from hdhil.core.dataconf import check_fields
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
    "LISTING_A1_RIPPLE",
    "LISTING_A2_RIPPLE",
    "LISTING_SETTLE_S",
    "PAPER_P0",
    "PAPER_Q_MOTOR",
    "PAPER_Q_OUTPUT",
    "PAPER_R",
    "PLAUSIBLE_ACCELERATION_RADPS2",
    "PLAUSIBLE_ENCODER_COUNTS",
    "PLAUSIBLE_REJECTIONS",
    "PLAUSIBLE_TACHO_NOISE_RADPS",
    "RECOMMENDED_P0",
    "RECOMMENDED_P0_OUTPUT",
    "RECOMMENDED_Q_HARMONIC",
    "RECOMMENDED_Q_OUTPUT",
    "RECOMMENDED_Q_RESIDUAL",
    "RECOMMENDED_R",
    "RECOMMENDED_RIPPLE",
    "RECOMMENDED_SECTION5_RIPPLE",
    "RECOMMENDED_STANDSTILL_RADPS",
    "SECTION5_RIPPLE",
    "SEED_FRICTION_MODEL",
    "Calibration",
    "ControlConfig",
    "DesiredTorqueConfig",
    "Estimates",
    "FilterMode",
    "FirmwareConfig",
    "FrictionModelConfig",
    "Law",
    "Oscillator",
    "PhaseSource",
    "PlausibilityConfig",
    "ReferenceConfig",
    "RippleFilterConfig",
    "Wave",
    "paper_config",
    "recommended_config",
]

FilterMode = Literal["paper", "recommended"]
PhaseSource = Literal["encoder", "tacho"]


class Wave(enum.IntEnum):
    """Reference wave types ([Taghirad97], listing A.1: ``int wavetype = 0; /* no wave
    generation by default */`` and ``ref_fl = reference_generation(wavetype)``).

    The listing includes ``servo_refgen.h`` but does not print ``reference_generation``;
    only ``0`` = "no wave" is given.  The numbering of the other types is ours;
    their definitions are in :class:`firmware.stages.ReferenceGenerator`.
    """

    NONE = 0  # constant output: bias only (the listing's default)
    SINE = 1
    SQUARE = 2
    TRIANGLE = 3
    STEP = 4
    SAWTOOTH = 5
    CHIRP = 6  # linear frequency sweep ([Vertechy] Fig. 5: identification by a chirp)


@dataclass(frozen=True)
class ReferenceConfig:
    """The reference generator's host mailboxes ([Taghirad97], listing A.1 ``main()``:
    ``copy(parm_ptr, &Nbias ...)``, ``Namplitude``, ``wavetype``, ``freq``, ``duty``).

    The listing receives ``Nbias`` / ``Namplitude`` as host numbers and converts them
    with ``PC2V_linear_conv``; here they are given directly in volts at the DAC.  Any
    finite value is accepted: the 12-bit, +/-10 V DAC saturates what lies outside.
    The listing's global default ``duty = 1.0`` makes a square wave constant; we use
    0.5 (a symmetric square wave) as default.  The listing's ``freq = 0`` default is
    replaced by 1 Hz because the frequency must be > 0 here.

    Units: ``frequency_Hz`` is in hertz (cycles per second).  The listing declares
    ``float theta = 0, freq = 0; /* Angle and angular frequency of function */``, so its
    ``freq`` mailbox (``parm_ptr+6``) held an angular frequency; its unit is not printed
    (rad/s or rad per sample).  A value ω in rad/s from such a host is ``frequency_Hz =
    ω / 2π``.

    Left out, with the reason: the listing's globals ``theta``, ``rise`` and ``fall``
    (listing A.1, ``float theta = 0 ...; float rise = 0.0; float fall = 0.0;``).  They
    belong to ``reference_generation`` (``servo_refgen.h``), whose body [Taghirad97] does
    not print, and ``main()`` never writes them from the host (it copies ``Nbias``,
    ``sample_period``, ``numsamples``, ``Namplitude``, ``wavetype``, ``freq``, ``duty``
    only), so they keep their initial 0 for every run the listing makes.  ``theta`` is
    the generator's running angle: here the phase ``2π f k Ts`` computed from the sample
    index (no accumulated state to drift).  ``rise = fall = 0`` are zero edge times:
    here every edge (square, step) is instantaneous, which is what those zeros give.

    ``chirp_end_Hz`` and ``chirp_duration_s`` (not in the papers) are for ``wave =
    "chirp"`` only: a linear sweep from ``frequency_Hz`` to ``chirp_end_Hz`` over
    ``chirp_duration_s``, repeated ([Vertechy] Fig. 5: "obtained experimentally by
    commanding tau_m with a chirp function").
    """

    wave: Wave = Wave.NONE
    bias_V: float = 0.0
    amplitude_V: float = 0.0
    frequency_Hz: float = 1.0
    duty: float = 0.5
    step_time_s: float = 0.0
    chirp_end_Hz: float = 10.0
    chirp_duration_s: float = 10.0

    def __post_init__(self) -> None:
        if not isinstance(self.wave, Wave):
            raise ValueError(f"reference.wave must be one of {[w.name.lower() for w in Wave]}")
        check_fields(self, {"bias_V": "finite", "amplitude_V": "finite", "frequency_Hz": ">0"})
        check_fields(self, {"chirp_end_Hz": ">0", "chirp_duration_s": ">0"})
        if not (math.isfinite(self.duty) and 0.0 <= self.duty <= 1.0):
            raise ValueError(f"reference.duty must be within [0, 1], got {self.duty!r}")
        if not (math.isfinite(self.step_time_s) and self.step_time_s >= 0.0):
            raise ValueError(
                f"reference.step_time_s must be a finite number >= 0, got {self.step_time_s!r}"
            )


@dataclass(frozen=True)
class Calibration:
    """Sensor gains, volts to physical units, and the encoder resolution.

    - ``volt2Nm = 6.6``: torque sensor gain, [Taghirad97], Table 1 (6.60 Nm/V, 2 %
      consistency over 8 experiments) and listing A.1 ``float volt2Nm = 6.6``.
    - ``volt2radps = 56.2565``: tachometer gain, [Taghirad97], listing A.1
      ``float volt2radps = 56.2565``.
    - ``volt2amp``: the servo amplifier's current-monitor scaling (A per V).  Not in
      the papers: the listing stores ``MotorCurrOut`` in volts, uncalibrated; 1.0 keeps
      that behaviour.
    - ``torque_offset_V``: bridge offset subtracted before scaling (not in the papers;
      the listing assumes a zeroed bridge amplifier).
    - ``encoder_counts_per_rev = 8000``: quadrature counts per motor revolution of the
      encoder behind the listing's 16-bit ``pcsample``.  [Taghirad97] does not give it; 8000
      (2000 lines x 4) is the drive emulator's default
      (``hostsim.plant.SensorConfig.encoder_counts_per_rev``).  It **must match the
      drive**: the recommended ripple filter takes its harmonic phase from
      ``count * 2 pi / encoder_counts_per_rev`` (a wrong value makes the harmonics
      slide against the true ripple).  Unused in paper mode.

    The gains may be negative (a sensor wired with the opposite sign convention) but
    must be finite and non-zero.
    """

    volt2Nm: float = 6.6
    volt2radps: float = 56.2565
    volt2amp: float = 1.0
    torque_offset_V: float = 0.0
    encoder_counts_per_rev: int = 8000

    def __post_init__(self) -> None:
        check_fields(
            self,
            {"volt2Nm": "!=0", "volt2radps": "!=0", "volt2amp": "!=0", "torque_offset_V": "finite"},
        )
        cpr = self.encoder_counts_per_rev
        if isinstance(cpr, bool) or not isinstance(cpr, int) or cpr <= 0:
            raise ValueError(
                f"Calibration.encoder_counts_per_rev must be an integer > 0, got {cpr!r}"
            )


#: Paper mode: process-noise variance of a motor-locked oscillator block ([Taghirad97] §4 and
#: listing A.1, ``Q = 1e3 I``).
PAPER_Q_MOTOR = 1e3
#: Paper mode: process-noise variance of the misalignment block (listing A.2,
#: ``Q[2][2] = Q[3][3] = 5e-2``).
PAPER_Q_OUTPUT = 5e-2
#: Paper mode: measurement-noise variance R ([Taghirad97] §4 and listing A.1, ``R = 1.0``).
PAPER_R = 1.0
#: Paper mode: initial covariance P = p0·I (listing A.1, ``P[i][i] = 1.0``).
PAPER_P0 = 1.0

#: Recommended mode: random-walk variance of each harmonic coefficient per step (Nm²).
#: The ripple amplitude of a harmonic drive changes with load (and slowly with
#: temperature and wear); in the emulated free-motion run the 2x amplitude drifts by
#: about 0.15 Nm within a second.  The ratio to ``residual_q`` sets the width of the
#: notches the filter puts at the harmonics, as a fixed fraction of the harmonic
#: frequency (:func:`firmware.response.torque_transfer`).  With ``residual_q`` = 1e-3:
#: 3e-6 keeps the true-torque gain within 1 % of 1 up to 0.8 x the harmonic frequency
#: (0.990 at 5 Hz for a 6.4 Hz ripple at 20 rad/s; 1e-5 gives 0.967 there) and scores
#: 5.8 / 6.6 / 0.8 / 5.7 % of the raw error on free-motion / torque-steps /
#: misalignment / speed-chirp (1e-6: 6.8 / 7.2 / 0.9 / 6.8 %, tracks the drift worse).
RECOMMENDED_Q_HARMONIC = 3e-6
#: Recommended mode: random-walk variance per step of an output-angle harmonic's
#: coefficients (misalignment, [Taghirad97] §5).  Its frequency is 1/gear_ratio of the motor
#: harmonics', so what it learns wrongly (e.g. a start-up transient taken for
#: misalignment while P is still wide) is unlearned only over output revolutions: with
#: 1e-5 a wrong 0.9 Nm start took over 100 s to fall below 0.02 Nm at 120 rad/s, with
#: 1e-4 about 40 s.  The cost (156 rad/s, :func:`firmware.response.torque_transfer`):
#: true torque gain 0.96 at 0.8 x the output frequency and 0.994 at 1-5 Hz (1e-5: 0.996
#: and 0.999), since a slow harmonic is almost a second random walk beside r.
RECOMMENDED_Q_OUTPUT = 1e-4
#: Recommended mode: initial variance P(0) = p0·I (Nm²) without an output-angle harmonic:
#: the meshing ripple and the residual torque's start value are known to within ~1 Nm.
RECOMMENDED_P0 = 1.0
#: Recommended mode: P(0) = p0·I (Nm²) when an output-angle harmonic is configured.  [Taghirad97]
#: §5 reports a misalignment of 10 Nm peak to peak before re-assembly (< 2 Nm after),
#: i.e. up to 5 Nm amplitude: a prior of (5 Nm)².  It must hold for the residual too,
#: whose start value r = y(0) contains the misalignment at the start angle.  Measured on
#: the emulated 10 Nm p-p misalignment at 156 rad/s (15 s, 3.7 output revolutions):
#: 2.4 % of the raw error left in the last 2.5 s, against 23 % with 1 Nm² (9.4 % with
#: 25 Nm² for the output harmonic alone); the price is a worse first 0.1 s after
#: start-up, so 1 Nm² stays the default without an output harmonic.
RECOMMENDED_P0_OUTPUT = 25.0
#: Recommended mode: random-walk variance of the residual torque per step (Nm²), i.e. of
#: the true torque minus the inertia-only expected torque (friction, contact, load).
#: The filtered torque is T_meas minus the ripple columns only, so this value does not
#: delay the output; it decides how an innovation is shared between "the torque changed"
#: and "the ripple map is off".  Too large and the residual soaks up slow ripple (at low
#: speed, and the 1x-output misalignment at 0.25 Hz) before the harmonics learn it; too
#: small and a torque step is partly taken for ripple.  Measured with ``hdhil evaluate``
#: on the emulated scenarios (error as % of the raw error, after start-up):
#: q_r = 1e-2 / 1e-3 / 1e-4 gives free-motion 6.7 / 5.4 / 5.4 %, torque-steps 7.2 / 7.0 /
#: 8.8 % (lag 0 ms throughout), misalignment residual 0.48 / 0.025 / 0.001 Nm p-p after
#: one output revolution (10 Nm p-p raw).  1e-3 (0.03 Nm per step as a standard
#: deviation) is best or near best on all three; ``hdhil tune`` fits it to a trace.
RECOMMENDED_Q_RESIDUAL = 1e-3
#: Recommended mode: measurement-noise variance R (Nm²), what the firmware itself knows of
#: its measurement: the quantisation of the 12-bit, +/-10 V torque channel at 6.6 Nm/V
#: (LSB 0.0322 Nm, LSB²/12 = 8.7e-5 Nm²) plus the bridge amplifier noise (about 0.02 Nm
#: rms, 4e-4 Nm²): 4.9e-4, rounded to 5e-4.
RECOMMENDED_R = 5e-4
#: Recommended mode: below this motor speed (rad/s) the harmonic coefficients are frozen.
RECOMMENDED_STANDSTILL_RADPS = 2.0


@dataclass(frozen=True)
class Oscillator:
    """One harmonic of the ripple model: a frequency locked to the motor or output angle.

    Its angular frequency is ``multiple * velocity`` (``source = "motor"``: the meshing
    ripple, [Taghirad97] §4, ω1 = 2θ̇, ω2 = 4θ̇) or ``multiple * velocity / gear_ratio``
    (``source = "output"``: the misalignment block, [Taghirad97] §5, ω3 = vel / Gear Ratio;
    listing A.2 ``om2 = velocity * sample_period / 100.0``), where ``velocity`` is the
    motor velocity in rad/s.  Equivalently, its phase is ``multiple * φ`` with φ the
    motor angle, resp. the output angle φ / gear_ratio.

    ``q`` depends on the filter mode (:class:`RippleFilterConfig`):

    - paper mode: the process-noise variance of both states of the second-order
      oscillator block of [Taghirad97] Eq. 6 (the diagonal of Q: 1e3 in §4 and listing A.1,
      5e-2 for the misalignment block of listing A.2 ``Q[2][2] = Q[3][3] = 5e-2``);
    - recommended mode: the random-walk variance per step of the harmonic's two
      coefficients (a, b) of ``a cos(m φ) + b sin(m φ)``, in Nm².

    ``q = None`` (the default) takes the mode's default when the oscillator is placed
    in a :class:`RippleFilterConfig`: paper 1e3 (motor) / 5e-2 (output), recommended
    3e-6 (motor, :data:`RECOMMENDED_Q_HARMONIC`) / 1e-4 (output,
    :data:`RECOMMENDED_Q_OUTPUT`).  A built :class:`RippleFilterConfig` never holds None.
    """

    source: Literal["motor", "output"] = "motor"
    multiple: float = 2.0
    q: float | None = None

    def __post_init__(self) -> None:
        if self.source not in ("motor", "output"):
            raise ValueError(f"oscillator.source must be 'motor' or 'output', got {self.source!r}")
        check_fields(self, {"multiple": ">0"})
        if self.q is not None and (
            isinstance(self.q, bool)
            or not isinstance(self.q, (int, float))
            or not (math.isfinite(self.q) and self.q >= 0.0)
        ):
            raise ValueError(f"oscillator.q must be a finite number >= 0, got {self.q!r}")


def _default_q(mode: str, source: str) -> float:
    if mode == "paper":
        return PAPER_Q_OUTPUT if source == "output" else PAPER_Q_MOTOR
    return RECOMMENDED_Q_OUTPUT if source == "output" else RECOMMENDED_Q_HARMONIC


@dataclass(frozen=True)
class RippleFilterConfig:
    """The torque-ripple filter: the harmonics it models, its mode and its tuning.

    ``mode = "paper"``: the prediction-type Kalman filter of [Taghirad97] (Eqs. 5-10,
    listing A.1 / A.2 ``Kalman``), :class:`firmware.ripple.RippleKalman`.  One
    second-order oscillator block per :class:`Oscillator`, rotated each step by the
    tachometer velocity; ``r`` is R (Eq. 7), ``p0`` the initial covariance P = p0·I
    (listing: ``P[i][i] = 1.0``), the oscillators' ``q`` the diagonal of Q.  Ignores
    ``phase_source``, ``residual_q`` and ``standstill_radps``.

    ``mode = "recommended"`` (the default): our angle-locked harmonic regression
    Kalman filter, :class:`firmware.ripple.HarmonicKalman`.  Per oscillator the
    coefficients (a, b) of ``a cos(m φ) + b sin(m φ)``, random walks of variance ``q``
    per step, plus one residual-torque state (random walk, variance ``residual_q`` per
    step) that takes the low-frequency torque the expected-torque model misses.

    - ``phase_source``: ``"encoder"`` (φ from the unwrapped 16-bit encoder count and
      :attr:`Calibration.encoder_counts_per_rev`) or ``"tacho"`` (φ integrated from the
      tachometer velocity, for recordings without an encoder).
    - ``standstill_radps``: below this |motor velocity| the harmonic coefficients are
      not updated (at standstill their regressors are constant and cannot be told
      apart from a torque offset); the learned ripple is still subtracted.
    - ``r``: the measurement-noise variance R (Nm²); ``p0``: P(0) = p0·I (Nm²).

    Defaults by mode (``None`` fields are replaced at construction, so a built config
    holds numbers only):

    ==============  ==========================  ===================================
    field           paper                       recommended
    ==============  ==========================  ===================================
    oscillator q    1e3 motor, 5e-2 output      3e-6 motor, 1e-4 output
    r               1.0                         5e-4 (:data:`RECOMMENDED_R`)
    p0              1.0                         1.0; 25 with an output harmonic
    ==============  ==========================  ===================================

    ``residual_q = 1e-3`` (:data:`RECOMMENDED_Q_RESIDUAL`) and ``standstill_radps = 2.0``
    are recommended-mode only; the
    reasoning behind each default is at its constant above.  They are starting values:
    tune them by maximum likelihood on recorded data.
    """

    oscillators: tuple[Oscillator, ...] = (Oscillator("motor", 2.0), Oscillator("motor", 4.0))
    r: float | None = None
    p0: float | None = None
    mode: FilterMode = "recommended"
    phase_source: PhaseSource = "encoder"
    residual_q: float = RECOMMENDED_Q_RESIDUAL
    standstill_radps: float = RECOMMENDED_STANDSTILL_RADPS

    def __post_init__(self) -> None:
        if self.mode not in ("paper", "recommended"):
            raise ValueError(f"ripple.mode must be 'paper' or 'recommended', got {self.mode!r}")
        if self.phase_source not in ("encoder", "tacho"):
            raise ValueError(
                f"ripple.phase_source must be 'encoder' or 'tacho', got {self.phase_source!r}"
            )
        if len(self.oscillators) < 1:
            raise ValueError("ripple.oscillators must hold at least one oscillator")
        for i, osc in enumerate(self.oscillators):
            if not isinstance(osc, Oscillator):
                raise ValueError(f"ripple.oscillators[{i}] must be an Oscillator, got {osc!r}")
        resolved = tuple(
            dataclasses.replace(osc, q=_default_q(self.mode, osc.source)) if osc.q is None else osc
            for osc in self.oscillators
        )
        object.__setattr__(self, "oscillators", resolved)
        if self.r is None:
            object.__setattr__(self, "r", PAPER_R if self.mode == "paper" else RECOMMENDED_R)
        if self.p0 is None:
            object.__setattr__(self, "p0", self._default_p0())
        check_fields(self, {"r": ">0", "p0": ">0", "residual_q": ">=0", "standstill_radps": ">=0"})

    def _default_p0(self) -> float:
        if self.mode == "paper":
            return PAPER_P0
        if any(osc.source == "output" for osc in self.oscillators):
            return RECOMMENDED_P0_OUTPUT
        return RECOMMENDED_P0

    @property
    def order(self) -> int:
        """Order of the harmonic ripple model as [Taghirad97] counts it: 2 x oscillators
        ("fourth-order harmonic oscillator", §4; "sixth order model", §5)."""
        return 2 * len(self.oscillators)

    @property
    def n_states(self) -> int:
        """Kalman state dimension: :attr:`order` in paper mode, one more (the residual
        torque) in recommended mode."""
        return self.order + (1 if self.mode == "recommended" else 0)


#: Listing A.1 / §4, exactly: 4th order, 2x and 4x motor velocity, Q = 1e3·I, R = 1,
#: P(0) = I, x(0) from the first Delta_T.
LISTING_A1_RIPPLE = RippleFilterConfig(
    oscillators=(Oscillator("motor", 2.0, 1e3), Oscillator("motor", 4.0, 1e3)),
    r=1.0,
    p0=1.0,
    mode="paper",
)

#: Listing A.2: still 4th order, but the 4x harmonic is replaced by the misalignment
#: oscillator at the output velocity (``om2 = velocity * sample_period / 100.0``) with
#: ``Q[2][2] = Q[3][3] = 5e-2``.
LISTING_A2_RIPPLE = RippleFilterConfig(
    oscillators=(Oscillator("motor", 2.0, 1e3), Oscillator("output", 1.0, 5e-2)),
    r=1.0,
    p0=1.0,
    mode="paper",
)

#: §5 text: the 6th-order model (2x, 4x motor velocity and the misalignment block).
#: The text gives no Q for it; the misalignment block takes listing A.2's 5e-2.
SECTION5_RIPPLE = RippleFilterConfig(
    oscillators=(
        Oscillator("motor", 2.0, 1e3),
        Oscillator("motor", 4.0, 1e3),
        Oscillator("output", 1.0, 5e-2),
    ),
    r=1.0,
    p0=1.0,
    mode="paper",
)

#: Recommended mode (the default): harmonics at 2x and 4x the motor angle plus the
#: residual torque, default tuning.
RECOMMENDED_RIPPLE = RippleFilterConfig()

#: Recommended mode with the §5 harmonics: 2x, 4x motor angle and 1x output angle
#: (misalignment, [Taghirad97] §5; q = 1e-4), plus the residual torque; P(0) = 25 Nm²·I for
#: a misalignment of up to 5 Nm.  The output harmonic costs some true torque around the
#: output frequency and 0.6 % up to a few Hz (see :data:`RECOMMENDED_Q_OUTPUT`).
RECOMMENDED_SECTION5_RIPPLE = RippleFilterConfig(
    oscillators=(
        Oscillator("motor", 2.0),
        Oscillator("motor", 4.0),
        Oscillator("output", 1.0),
    )
)


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


@dataclass(frozen=True)
class FrictionModelConfig:
    """The motor-disturbance model ``τ̂d`` of [Vertechy] Eq. 5 (JTF1 with friction
    compensation, ``τm,2 = -[k1 (τ̂s - τsD) + k2 τ̂s' + k3 τ̂lg + k4 τsD] - τ̂d``).

    [Vertechy] §VI: "the experimentally determined motor
    friction torque model ``τ̂d = [-13.7 sign(ϑ̇m)(1 + tanh(|ϑ̇m|/2) - 4)]/2`` Nm, the
    controller implements (5) instead of (4)".  Printed garbled; the reading we take
    (the one that reproduces the paper's ``max(τsD + τ̂d) ≈ 33.7`` Nm with ``τsD`` ≤ 20
    Nm, ``hostsim.plant.DriveTrainConfig``) is a friction that opposes the motion,
    tops out at 13.7 Nm and is smooth through rest::

        τ̂d = -coulomb_Nm · tanh(ω / velocity_scale_radps)

    with ``ω`` the motor velocity the firmware measures (tachometer, rad/s at the motor
    shaft) and ``velocity_scale_radps`` the ``2`` of ``|ϑ̇m|/2`` read at the motor shaft
    (2 rad/s, i.e. 0.02 rad/s at the output).  Torques at the output, the same sign in
    the product convention and [Vertechy]'s (``firmware.isr``).

    ``coulomb_Nm = 0`` (the default) switches the compensation off: the law is Eq. 4 and
    the observer's third state is ``τlgd``; with a model it is ``τlg`` ([Vertechy] §V: "the
    substitution in (8) of τm,1 with (τm,2 + τ̂d) enables to find τ̂lg instead of
    τ̂lgd"), on a vertical joint (τg = 0) the external torque ``τl``.
    """

    coulomb_Nm: float = 0.0
    velocity_scale_radps: float = 2.0

    def __post_init__(self) -> None:
        check_fields(self, {"coulomb_Nm": ">=0", "velocity_scale_radps": ">0"})

    @property
    def active(self) -> bool:
        """True when the law compensates the friction (Eq. 5)."""
        return self.coulomb_Nm > 0.0

    def torque(self, velocity_radps: float) -> float:
        """``τ̂d`` (Nm, output) at the motor velocity ``velocity_radps`` (rad/s, motor)."""
        return -self.coulomb_Nm * math.tanh(velocity_radps / self.velocity_scale_radps)


#: [Vertechy] §VI: the experiment's motor friction model (13.7 Nm, 2 rad/s at the motor).
SEED_FRICTION_MODEL = FrictionModelConfig(coulomb_Nm=13.7, velocity_scale_radps=2.0)

#: [Vertechy] §V: the estimates JTF2 and JTF3 take in the literature ("the estimates τ̂s
#: and τ̂s' are obtained by simply feeding the torque sensor measurement y through basic
#: low-pass and derivative filters"): ``"filters"``; ``"observer"`` takes them from the
#: LQG observer (Eq. 8), as JTF1 does.
Estimates = Literal["observer", "filters"]

#: Cut-off (Hz) of the first-order low-pass giving τ̂s for the ``filters`` estimates.
#: [Vertechy] gives none.  It must pass the 17 Hz joint mode the PD law damps with little
#: phase lag (18.8° at 17 Hz) while cutting the sensor noise (W = 0.12 Nm² per sample,
#: 0.35 Nm rms) to ~0.14 Nm rms (the noise bandwidth of a 50 Hz first-order low-pass is
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


#: The listing's start-up pause (s): [Taghirad97], listing A.1 ``main()``,
#: ``for (pause=0; pause < 0xffff; pause++);`` "Allow for mech. time constant", between
#: ``write_dac0( Vbias )`` and the first interrupt.  The paper gives no clock; on the
#: TMS320C30 the listing names (``C30 node``) at 33 MHz, 60 ns per instruction cycle, an
#: empty counting loop takes about 4 cycles per pass (increment, compare, delayed branch):
#: 65 535 × 4 × 60 ns ≈ 16 ms.  An estimate, stated as one: the pause is far shorter than
#: the 0.19 s mechanical time constant of the free-motion drive, so what it settles is
#: the amplifier and the bias, not the motor.
LISTING_SETTLE_S = 0.016


#: Plausibility: the largest motor acceleration (rad/s², motor side) the joint can do.
#: The papers give no motor data, so this is the drive emulator's default motor
#: (``hostsim.plant.AmplifierConfig`` / ``DriveTrainConfig``, representative of an
#: RHS-20-class drive, not from the papers): current limit 6 A x torque constant
#: 0.06 Nm/A = 0.36 Nm at the motor shaft, over the rotor and wave-generator inertia
#: 0.3 kg m² / 100² = 3e-5 kg m², is 12 000 rad/s² with the load uncoupled (the load only
#: lowers it), times a margin of 1.5 for a flexspline that unwinds into the motor:
#: 18 000 rad/s², 18 rad/s per 1 ms sample.  The fastest clean change measured on the
#: shipped scenarios is far below it (docs/figures.md, "Faults").
PLAUSIBLE_ACCELERATION_RADPS2 = 18_000.0
#: Plausibility: the tachometer noise band (rad/s) added to the velocity bound.  The
#: firmware's tacho channel (12-bit, +/-10 V, 56.2565 rad/s per V; [Taghirad97] listing A.1
#: ``volt2radps``) has an LSB of 0.275 rad/s; two samples each within half an LSB of
#: quantisation and 4 sigma of a 0.05 rad/s rms noise (``hostsim.plant.SensorConfig``)
#: differ by at most 0.275 + 0.4 rad/s; rounded up to 1 rad/s.
PLAUSIBLE_TACHO_NOISE_RADPS = 1.0
#: Plausibility: how far (counts) an encoder increment may be from the one the accepted
#: velocity predicts, Ts (v(k-1) + v(k)) / 2 x counts per rad.  At 8000 counts per
#: revolution (:attr:`Calibration.encoder_counts_per_rev`) a tacho gain error of 5 % at
#: 300 rad/s is 19 counts per 1 ms sample, the tacho quantisation 0.35 counts.  A jump
#: the check lets through (at most 0.016 rad of motor angle, 0.03 rad of phase of the 2x
#: ripple) hardly matters to the ripple filter.
PLAUSIBLE_ENCODER_COUNTS = 20.0
#: Plausibility: at most this many implausible samples in a row are replaced by the
#: prediction (the last of them raises the sensor error, EMCY); the next one is accepted
#: as the new level, so the firmware cannot lock out.  5 ms of hold at 1 kHz.
PLAUSIBLE_REJECTIONS = 5


@dataclass(frozen=True)
class PlausibilityConfig:
    """The sensor plausibility stage (:class:`firmware.stages.SensorPlausibility`; not in
    the papers).  It runs right after calibration and bounds what one sample can change.

    - ``enabled``: ``true`` checks, ``false`` passes every sample through unchecked
      (the listing's handler).  Unset (``None``, the default) means: on, except in paper
      mode (``ripple.mode = "paper"``), which is listing A.1 exactly
      ([Taghirad97], listing A.1 ``c_int10``: ``vel = Tacho *
      volt2radps; acc = Diff_filter( vel);`` uses every sample as read).  A paper
      configuration gets the stage only when it asks for it with ``enabled = true``.
      :attr:`FirmwareConfig.plausibility_active` is the resolved value.
    - ``max_acceleration_radps2``: the largest motor acceleration the joint can do
      (:data:`PLAUSIBLE_ACCELERATION_RADPS2`, where the number comes from).  A velocity
      sample is implausible when it differs from the last accepted one by more than
      ``tacho_noise_radps + n * max_acceleration_radps2 * Ts``, n being the samples
      since that one; the differentiator's acceleration is clamped to ±this value.
    - ``tacho_noise_radps``: the tachometer noise band (:data:`PLAUSIBLE_TACHO_NOISE_RADPS`).
    - ``encoder_tolerance_counts``: how far an encoder increment may be from the
      accepted velocity's (:data:`PLAUSIBLE_ENCODER_COUNTS`).  Only checked when the
      ripple filter takes its phase from the encoder.
    - ``max_rejections``: at most this many implausible samples in a row are replaced
      (:data:`PLAUSIBLE_REJECTIONS`); the last of them raises the sensor error (EMCY),
      the next implausible one is accepted as the new level, and the error clears
      after as many plausible samples in a row.
    """

    enabled: bool | None = None
    max_acceleration_radps2: float = PLAUSIBLE_ACCELERATION_RADPS2
    tacho_noise_radps: float = PLAUSIBLE_TACHO_NOISE_RADPS
    encoder_tolerance_counts: float = PLAUSIBLE_ENCODER_COUNTS
    max_rejections: int = PLAUSIBLE_REJECTIONS
    #: Stuck channel (:class:`firmware.stages.StuckChannels`): the torque or tacho reading
    #: unchanged for ``stuck_samples`` samples while the encoder turned at least
    #: ``stuck_motion_rad`` (motor side) is a stuck sensor (torque: EMCY 0x7300).
    stuck_samples: int = 100
    stuck_motion_rad: float = 2.0
    #: The tacho is stuck only if, besides, the encoder's mean velocity over those samples
    #: differs from the held reading by more than ``stuck_tacho_radps`` plus
    #: ``stuck_tacho_share`` of it (EMCY 0x7301): 2 rad/s is about 7 counts of the
    #: [Taghirad97] tacho channel (0.27 rad/s per count), far above its noise at a steady speed.
    stuck_tacho_radps: float = 2.0
    stuck_tacho_share: float = 0.05

    def __post_init__(self) -> None:
        if self.enabled is not None and not isinstance(self.enabled, bool):
            raise ValueError(f"plausibility.enabled must be true or false, got {self.enabled!r}")
        check_fields(
            self,
            {
                "max_acceleration_radps2": ">0",
                "tacho_noise_radps": ">=0",
                "encoder_tolerance_counts": ">0",
            },
        )
        check_fields(
            self, {"stuck_motion_rad": ">0", "stuck_tacho_radps": ">0", "stuck_tacho_share": ">=0"}
        )
        n = self.stuck_samples
        if isinstance(n, bool) or not isinstance(n, int) or n < 2:
            raise ValueError(f"PlausibilityConfig.stuck_samples must be an integer >= 2, got {n!r}")
        m = self.max_rejections
        if isinstance(m, bool) or not isinstance(m, int) or m < 1:
            raise ValueError(
                f"PlausibilityConfig.max_rejections must be an integer >= 1, got {m!r}"
            )


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
#: with the paper's sensor noise (W = 0.12 Nm² per sample) the noise part of e is
#: about twice the paper design's and the command noise reaches a 150 Nm torque limit.
#: A tuning for the noise-free §VI scenario (the paper's simulation), not for a noisy
#: joint.  ``torque_per_volt`` and ``torque_limit_Nm`` are the defaults; set them to
#: the drive's.
JTF1_FF_TRACKING = ControlConfig(
    law=Law.JTF1_FF,
    weights=LqgWeights(V=1e7),
    feedforward=Feedforward.EXACT,
)


@dataclass(frozen=True)
class FirmwareConfig:
    """Everything the ported interrupt handler needs ([Taghirad97], listing A.1).

    - ``sample_period_s = 1e-3``: listing ``float sample_period = 0.001``, in (0, 1] s.
    - ``num_samples``: listing ``numsamples`` mailbox (``while (samplecount <
      numsamples)``); 0 means "run until stopped".
    - ``J_load = 1.725e-2`` kg m² and ``gear_ratio = 100``: listing
      ``float J_load = 1.725e-2, Gain = 100``.
    - ``diff_tau_s = 0.005``: listing ``Diff_filter``, H(s) = s / (0.005 s + 1).
    - ``ripple``: the torque-ripple filter.  The default is the **recommended** mode
      (:data:`RECOMMENDED_RIPPLE`), not the listing's filter; :func:`paper_config`
      gives the same configuration with the paper filter (:data:`LISTING_A1_RIPPLE`
      for the default harmonics).
    - ``adc`` / ``dac``: 12-bit, +/-10 V converters (our choice: [Taghirad97] names the
      DT1401 board but prints neither its resolution nor its range;
      :class:`hdhil.core.converter.Converter`).
    - ``control``: [Vertechy]'s joint-torque control (:class:`ControlConfig`); off by
      default (``law = none``), in which case the handler is the [Taghirad97] port unchanged.
    - ``startup_settle_s``: the listing's start-up (``main()``: ``write_dac0( Vbias
      ); /* Allow for mech. time constant */ for (pause=0; pause < 0xffff; pause++);``
      before ``t1_start()``): once the drive is in operation the controller outputs
      the start-up code (``reference.bias_V``; zero torque with a control law) for this
      long, answering sensor frames without running the interrupt handler.  Unset: the
      listing's pause (:data:`LISTING_SETTLE_S`) in paper mode, none in recommended
      mode (:attr:`startup_settle_cycles`).
    - ``plausibility``: bounds on velocity and encoder changes per sample
      (:class:`PlausibilityConfig`, not in the papers); on by default, off in paper
      mode unless ``plausibility.enabled = true`` (:attr:`plausibility_active`).
    """

    sample_period_s: float = 1e-3
    num_samples: int = 0
    reference: ReferenceConfig = field(default_factory=ReferenceConfig)
    calibration: Calibration = field(default_factory=Calibration)
    J_load: float = 1.725e-2
    gear_ratio: float = 100.0
    diff_tau_s: float = 0.005
    ripple: RippleFilterConfig = field(default_factory=RippleFilterConfig)
    adc: Converter = field(default_factory=Converter)
    dac: Converter = field(default_factory=Converter)
    control: ControlConfig = field(default_factory=ControlConfig)
    plausibility: PlausibilityConfig = field(default_factory=PlausibilityConfig)
    startup_settle_s: float | None = None

    def __post_init__(self) -> None:
        s = self.startup_settle_s
        if s is not None and (
            isinstance(s, bool) or not isinstance(s, (int, float)) or not 0.0 <= s <= 10.0
        ):
            raise ValueError(f"startup_settle_s must be within [0, 10] s, got {s!r}")
        if not (math.isfinite(self.sample_period_s) and 0.0 < self.sample_period_s <= 1.0):
            raise ValueError(
                f"sample_period_s must be within (0, 1] s, got {self.sample_period_s!r}"
            )
        if isinstance(self.num_samples, bool) or not isinstance(self.num_samples, int):
            raise ValueError(f"num_samples must be an integer >= 0, got {self.num_samples!r}")
        if self.num_samples < 0:
            raise ValueError(
                f"num_samples must be >= 0 (0 = run until stopped), got {self.num_samples!r}"
            )
        check_fields(self, {"J_load": ">0", "gear_ratio": ">0", "diff_tau_s": ">0"})
        for name, expected in (
            ("reference", ReferenceConfig),
            ("calibration", Calibration),
            ("ripple", RippleFilterConfig),
            ("adc", Converter),
            ("dac", Converter),
            ("control", ControlConfig),
            ("plausibility", PlausibilityConfig),
        ):
            if not isinstance(getattr(self, name), expected):
                raise ValueError(f"{name} must be a {expected.__name__}")

    @property
    def startup_settle_cycles(self) -> int:
        """Sample periods the controller holds the start-up output before the first
        interrupt: ``startup_settle_s`` if set, otherwise the listing's pause
        (:data:`LISTING_SETTLE_S`) in paper mode and none in recommended mode."""
        s = self.startup_settle_s
        if s is None:
            s = LISTING_SETTLE_S if self.ripple.mode == "paper" else 0.0
        return math.ceil(round(s / self.sample_period_s, 9))

    @property
    def plausibility_active(self) -> bool:
        """Whether the plausibility stage runs: ``plausibility.enabled`` if set,
        otherwise on in recommended mode and off in paper mode (paper mode is listing
        A.1 sample for sample, [Taghirad97], listing A.1 ``c_int10``)."""
        enabled = self.plausibility.enabled
        return self.ripple.mode != "paper" if enabled is None else enabled


def _same_harmonics(ripple: RippleFilterConfig, mode: FilterMode) -> RippleFilterConfig:
    """``ripple``'s harmonics (source and multiple) in ``mode`` with that mode's default
    tuning (q, p0, r)."""
    return RippleFilterConfig(
        oscillators=tuple(Oscillator(o.source, o.multiple) for o in ripple.oscillators),
        mode=mode,
    )


def paper_config(cfg: FirmwareConfig) -> FirmwareConfig:
    """``cfg`` with the paper filter of [Taghirad97] (for ``--paper`` flags and comparisons).

    A config already in paper mode is returned unchanged (its tuning is kept).  Otherwise
    the ripple filter becomes the paper filter with the same harmonics and the paper's
    tuning (motor blocks Q = 1e3, output blocks 5e-2, R = 1, P0 = I): for the default
    harmonics that is exactly :data:`LISTING_A1_RIPPLE`, for 2x/4x motor plus 1x output
    :data:`SECTION5_RIPPLE`, for 2x motor plus 1x output :data:`LISTING_A2_RIPPLE`.
    """
    if cfg.ripple.mode == "paper":
        return cfg
    return dataclasses.replace(cfg, ripple=_same_harmonics(cfg.ripple, "paper"))


def recommended_config(cfg: FirmwareConfig) -> FirmwareConfig:
    """``cfg`` with the recommended filter: unchanged if already recommended, otherwise
    the same harmonics with the recommended default tuning (encoder phase)."""
    if cfg.ripple.mode == "recommended":
        return cfg
    return dataclasses.replace(cfg, ripple=_same_harmonics(cfg.ripple, "recommended"))
