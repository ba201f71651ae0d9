"""Typed configuration of the ported firmware (the 1 kHz interrupt handler of [Taghirad97]).

Every value the C listing of [Taghirad97] (Appendix A.1 ``free_kalman.c``, and A.2) keeps
in a global variable, a host mailbox or a literal inside a function is a field here, with
the listing's value as the default; the torque control of [Vertechy] is
:class:`ControlConfig`.  All classes are frozen dataclasses that check their ranges in
``__post_init__``, so ``hdhil.core.dataconf.from_dict`` turns a bad scenario value into a
one-line ``ConfigError`` naming the key (docs/reference/scenario-keys.md lists them).

One module per area: :mod:`.reference` (reference generator), :mod:`.calibration`
(sensor gains), :mod:`.ripple` (ripple filter, its two modes and their tuning),
:mod:`.control` ([Vertechy]'s control laws), :mod:`.plausibility` (sensor plausibility
limits) and :mod:`.firmware` (:class:`FirmwareConfig`, which holds them all, and
:func:`paper_config` / :func:`recommended_config`, which switch the ripple filter mode).
Import the names from this package: it is the public interface.
"""

from __future__ import annotations

from hdhil.firmware.config.calibration import Calibration
from hdhil.firmware.config.control import (
    JTF1_FF_TRACKING,
    JTF_DERIVATIVE_HZ,
    JTF_LOWPASS_HZ,
    SEED_FRICTION_MODEL,
    ControlConfig,
    ControlFeedback,
    DesiredTorqueConfig,
    Estimates,
    FrictionForm,
    FrictionModelConfig,
    Law,
)
from hdhil.firmware.config.firmware import (
    LISTING_SETTLE_S,
    FirmwareConfig,
    paper_config,
    recommended_config,
)
from hdhil.firmware.config.plausibility import (
    PLAUSIBLE_ACCELERATION_RADPS2,
    PLAUSIBLE_ENCODER_COUNTS,
    PLAUSIBLE_REJECTIONS,
    PLAUSIBLE_TACHO_NOISE_RADPS,
    PlausibilityConfig,
)
from hdhil.firmware.config.reference import ReferenceConfig, SpeedLoopConfig, Wave
from hdhil.firmware.config.ripple import (
    LISTING_A1_RIPPLE,
    LISTING_A2_RIPPLE,
    PAPER_P0,
    PAPER_Q_MOTOR,
    PAPER_Q_OUTPUT,
    PAPER_R,
    RECOMMENDED_P0,
    RECOMMENDED_P0_OUTPUT,
    RECOMMENDED_Q_HARMONIC,
    RECOMMENDED_Q_OUTPUT,
    RECOMMENDED_Q_RESIDUAL,
    RECOMMENDED_R,
    RECOMMENDED_RIPPLE,
    RECOMMENDED_SECTION5_RIPPLE,
    RECOMMENDED_STANDSTILL_RADPS,
    SECTION5_RIPPLE,
    FilterMode,
    Oscillator,
    PhaseSource,
    RippleFilterConfig,
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
    "ControlFeedback",
    "DesiredTorqueConfig",
    "Estimates",
    "FilterMode",
    "FirmwareConfig",
    "FrictionForm",
    "FrictionModelConfig",
    "Law",
    "Oscillator",
    "PhaseSource",
    "PlausibilityConfig",
    "ReferenceConfig",
    "RippleFilterConfig",
    "SpeedLoopConfig",
    "Wave",
    "paper_config",
    "recommended_config",
]
