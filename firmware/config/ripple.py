"""Configuration of the torque-ripple filter: its harmonics, its mode and its tuning.

The filter has two modes (:class:`RippleFilterConfig`): ``"paper"`` is the
prediction-type Kalman filter of [Taghirad97] exactly as listings A.1 / A.2 implement it
(:class:`firmware.ripple.RippleKalman`; presets :data:`LISTING_A1_RIPPLE`,
:data:`LISTING_A2_RIPPLE`, :data:`SECTION5_RIPPLE`); ``"recommended"`` (the default) is
our angle-locked harmonic regression filter (:class:`firmware.ripple.HarmonicKalman`),
which keeps the low-frequency torque the paper filter absorbs.  Each mode's default
tuning is a constant here: the paper's cite the listing, the recommended ones give the
reasoning and measurement behind the number.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

from hdhil.core.dataconf import check_fields

__all__ = [
    "LISTING_A1_RIPPLE",
    "LISTING_A2_RIPPLE",
    "PAPER_P0",
    "PAPER_Q_MOTOR",
    "PAPER_Q_OUTPUT",
    "PAPER_R",
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
    "FilterMode",
    "Oscillator",
    "PhaseSource",
    "RippleFilterConfig",
]

FilterMode = Literal["paper", "recommended"]
PhaseSource = Literal["encoder", "tacho"]


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
