"""Configuration of the sensor plausibility stage and the stuck-channel check (not in the
papers): how much one sample may change, how long an implausible value is held, and when
an unchanged reading counts as a stuck sensor.

The stages are :class:`firmware.stages.SensorPlausibility` and
:class:`firmware.stages.StuckChannels`.  The papers give no motor data, so each limit
states where its number comes from.
"""

from __future__ import annotations

from dataclasses import dataclass

from hdhil.core.dataconf import check_fields

__all__ = [
    "PLAUSIBLE_ACCELERATION_RADPS2",
    "PLAUSIBLE_ENCODER_COUNTS",
    "PLAUSIBLE_REJECTIONS",
    "PLAUSIBLE_TACHO_NOISE_RADPS",
    "PlausibilityConfig",
]

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
