"""Sensor calibration: the gains from volts to physical units ([Taghirad97], Table 1 and
listing A.1 ``volt2Nm``, ``volt2radps``) and the encoder resolution, which the
recommended ripple filter needs to lock its harmonics to the motor angle.
"""

from __future__ import annotations

from dataclasses import dataclass

from hdhil.core.dataconf import check_fields

__all__ = [
    "Calibration",
]


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
