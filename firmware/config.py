"""Typed configuration of the ported firmware (the 1 kHz interrupt handler of seed 000).

Every value the C listing of seed 000 (``/work/shared/seeds/000_ae0a3dbe24949b7c.txt``,
Appendix A.1 ``free_kalman.c``, and A.2) kept in a global variable, a host mailbox or a
literal inside a function is a field here, with the listing's value as the default.
All classes are frozen dataclasses that check their ranges in ``__post_init__`` and
raise ``ValueError`` naming the field and the allowed range, so that
``hdhil.dataconf.from_dict`` turns a bad scenario value into a one-line ``ConfigError``.

Example (plain data, as from a TOML scenario)::

    from hdhil.dataconf import from_dict
    cfg = from_dict(FirmwareConfig, {
        "reference": {"wave": "step", "amplitude_V": 1.0, "step_time_s": 0.1},
        "ripple": {"oscillators": [{"source": "motor", "multiple": 2.0},
                                   {"source": "output", "multiple": 1.0, "q": 5e-2}]},
    })
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Literal

from hdhil.converter import Converter
from hdhil.dataconf import check_fields

__all__ = [
    "LISTING_A1_RIPPLE",
    "LISTING_A2_RIPPLE",
    "SECTION5_RIPPLE",
    "Calibration",
    "FirmwareConfig",
    "Oscillator",
    "ReferenceConfig",
    "RippleFilterConfig",
    "Wave",
]


class Wave(enum.IntEnum):
    """Reference wave types (seed 000, listing A.1: ``int wavetype = 0; /* no wave
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


@dataclass(frozen=True)
class ReferenceConfig:
    """The reference generator's host mailboxes (seed 000, listing A.1 ``main()``:
    ``copy(parm_ptr, &Nbias ...)``, ``Namplitude``, ``wavetype``, ``freq``, ``duty``).

    The listing receives ``Nbias`` / ``Namplitude`` as host numbers and converts them
    with ``PC2V_linear_conv``; here they are given directly in volts at the DAC.  Any
    finite value is accepted: the 12-bit, +/-10 V DAC saturates what lies outside.
    The listing's global default ``duty = 1.0`` makes a square wave constant; we use
    0.5 (a symmetric square wave) as default.  The listing's ``freq = 0`` default is
    replaced by 1 Hz because the frequency must be > 0 here.
    """

    wave: Wave = Wave.NONE
    bias_V: float = 0.0
    amplitude_V: float = 0.0
    frequency_Hz: float = 1.0
    duty: float = 0.5
    step_time_s: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.wave, Wave):
            raise ValueError(f"reference.wave must be one of {[w.name.lower() for w in Wave]}")
        check_fields(self, {"bias_V": "finite", "amplitude_V": "finite", "frequency_Hz": ">0"})
        if not (math.isfinite(self.duty) and 0.0 <= self.duty <= 1.0):
            raise ValueError(f"reference.duty must be within [0, 1], got {self.duty!r}")
        if not (math.isfinite(self.step_time_s) and self.step_time_s >= 0.0):
            raise ValueError(
                f"reference.step_time_s must be a finite number >= 0, got {self.step_time_s!r}"
            )


@dataclass(frozen=True)
class Calibration:
    """Sensor gains, volts to physical units.

    - ``volt2Nm = 6.6``: torque sensor gain, seed 000, Table 1 (6.60 Nm/V, 2 %
      consistency over 8 experiments) and listing A.1 ``float volt2Nm = 6.6``.
    - ``volt2radps = 56.2565``: tachometer gain, seed 000, listing A.1
      ``float volt2radps = 56.2565``.
    - ``volt2amp``: the servo amplifier's current-monitor scaling (A per V).  Not in
      the seed: the listing stores ``MotorCurrOut`` in volts, uncalibrated; 1.0 keeps
      that behaviour.
    - ``torque_offset_V``: bridge offset subtracted before scaling (not in the seed;
      the listing assumes a zeroed bridge amplifier).

    The gains may be negative (a sensor wired with the opposite sign convention) but
    must be finite and non-zero.
    """

    volt2Nm: float = 6.6
    volt2radps: float = 56.2565
    volt2amp: float = 1.0
    torque_offset_V: float = 0.0

    def __post_init__(self) -> None:
        check_fields(
            self,
            {"volt2Nm": "!=0", "volt2radps": "!=0", "volt2amp": "!=0", "torque_offset_V": "finite"},
        )


@dataclass(frozen=True)
class Oscillator:
    """One second-order harmonic-oscillator block of the ripple model (seed 000, Eq. 6).

    Its angular frequency is ``multiple * velocity`` (``source = "motor"``: the meshing
    ripple, seed 000 §4, ω1 = 2θ̇, ω2 = 4θ̇) or ``multiple * velocity / gear_ratio``
    (``source = "output"``: the misalignment block, seed 000 §5, ω3 = vel / Gear Ratio;
    listing A.2 ``om2 = velocity * sample_period / 100.0``), where ``velocity`` is the
    motor velocity in rad/s.  ``q`` is the process-noise variance of both states of
    the block (the diagonal of Q: 1e3 in §4 and listing A.1, 5e-2 for the
    misalignment block of listing A.2 ``Q[2][2] = Q[3][3] = 5e-2``).
    """

    source: Literal["motor", "output"] = "motor"
    multiple: float = 2.0
    q: float = 1e3

    def __post_init__(self) -> None:
        if self.source not in ("motor", "output"):
            raise ValueError(f"oscillator.source must be 'motor' or 'output', got {self.source!r}")
        check_fields(self, {"multiple": ">0"})
        if not (math.isfinite(self.q) and self.q >= 0.0):
            raise ValueError(f"oscillator.q must be a finite number >= 0, got {self.q!r}")


@dataclass(frozen=True)
class RippleFilterConfig:
    """The prediction-type Kalman filter of the torque ripple (seed 000, Eqs. 5-10).

    Defaults: the 4th-order model of §4 and listing A.1 (2x and 4x motor velocity,
    Q = 1e3·I, R = 1, P(0) = I).  ``r`` is the measurement-noise variance R (Eq. 7),
    ``p0`` the initial covariance P = p0·I (listing: ``P[i][j] = 1.0`` on the diagonal).
    """

    oscillators: tuple[Oscillator, ...] = (
        Oscillator("motor", 2.0, 1e3),
        Oscillator("motor", 4.0, 1e3),
    )
    r: float = 1.0
    p0: float = 1.0

    def __post_init__(self) -> None:
        if len(self.oscillators) < 1:
            raise ValueError("ripple.oscillators must hold at least one oscillator")
        for i, osc in enumerate(self.oscillators):
            if not isinstance(osc, Oscillator):
                raise ValueError(f"ripple.oscillators[{i}] must be an Oscillator, got {osc!r}")
        check_fields(self, {"r": ">0", "p0": ">0"})

    @property
    def order(self) -> int:
        """State dimension n = 2 x number of oscillators."""
        return 2 * len(self.oscillators)


#: Listing A.1 / §4: 4th order, 2x and 4x motor velocity, Q = 1e3·I, R = 1.
LISTING_A1_RIPPLE = RippleFilterConfig()

#: Listing A.2: still 4th order, but the 4x harmonic is replaced by the misalignment
#: oscillator at the output velocity (``om2 = velocity * sample_period / 100.0``) with
#: ``Q[2][2] = Q[3][3] = 5e-2``.
LISTING_A2_RIPPLE = RippleFilterConfig(
    oscillators=(Oscillator("motor", 2.0, 1e3), Oscillator("output", 1.0, 5e-2))
)

#: §5 text: the 6th-order model (2x, 4x motor velocity and the misalignment block).
#: The text gives no Q for it; the misalignment block takes listing A.2's 5e-2.
SECTION5_RIPPLE = RippleFilterConfig(
    oscillators=(
        Oscillator("motor", 2.0, 1e3),
        Oscillator("motor", 4.0, 1e3),
        Oscillator("output", 1.0, 5e-2),
    )
)


@dataclass(frozen=True)
class FirmwareConfig:
    """Everything the ported interrupt handler needs (seed 000, listing A.1).

    - ``sample_period_s = 1e-3``: listing ``float sample_period = 0.001``, in (0, 1] s.
    - ``num_samples``: listing ``numsamples`` mailbox (``while (samplecount <
      numsamples)``); 0 means "run until stopped".
    - ``J_load = 1.725e-2`` kg m² and ``gear_ratio = 100``: listing
      ``float J_load = 1.725e-2, Gain = 100``.
    - ``diff_tau_s = 0.005``: listing ``Diff_filter``, H(s) = s / (0.005 s + 1).
    - ``adc`` / ``dac``: the DT1401's 12-bit, +/-10 V converters.
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

    def __post_init__(self) -> None:
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
        ):
            if not isinstance(getattr(self, name), expected):
                raise ValueError(f"{name} must be a {expected.__name__}")
