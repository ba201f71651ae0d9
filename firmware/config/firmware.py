"""The top-level firmware configuration, the ``[firmware]`` table of a scenario.

:class:`FirmwareConfig` holds the globals of [Taghirad97], listing A.1 (sample period,
``J_load``, ``Gain``, ``Diff_filter``'s time constant, the start-up pause) and the
sections of the other modules: reference, calibration, ripple filter, control,
plausibility, and the converters.  :func:`paper_config` / :func:`recommended_config`
switch a whole configuration between the two ripple filter modes, keeping its harmonics.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from hdhil.core.converter import Converter
from hdhil.core.dataconf import check_fields
from hdhil.firmware.config.calibration import Calibration
from hdhil.firmware.config.control import ControlConfig
from hdhil.firmware.config.plausibility import PlausibilityConfig
from hdhil.firmware.config.reference import ReferenceConfig, SpeedLoopConfig
from hdhil.firmware.config.ripple import FilterMode, Oscillator, RippleFilterConfig

__all__ = [
    "LISTING_SETTLE_S",
    "FirmwareConfig",
    "paper_config",
    "recommended_config",
]

#: The listing's start-up pause (s): [Taghirad97], listing A.1 ``main()``,
#: ``for (pause=0; pause < 0xffff; pause++);`` "Allow for mech. time constant", between
#: ``write_dac0( Vbias )`` and the first interrupt.  The paper gives no clock; on the
#: TMS320C30 the listing names (``C30 node``) at 33 MHz, 60 ns per instruction cycle, an
#: empty counting loop takes about 4 cycles per pass (increment, compare, delayed branch):
#: 65 535 × 4 × 60 ns ≈ 16 ms.  An estimate, stated as one: the pause is far shorter than
#: the 0.19 s mechanical time constant of the free-motion drive, so what it settles is
#: the amplifier and the bias, not the motor.
LISTING_SETTLE_S = 0.016


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
    - ``speed``: a PI loop on the motor speed added to the reference voltage
      (:class:`SpeedLoopConfig`, not in the papers); off by default, ignored with a
      control law.
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
    speed: SpeedLoopConfig = field(default_factory=SpeedLoopConfig)

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
            ("speed", SpeedLoopConfig),
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
