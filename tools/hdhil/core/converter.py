"""The converters between the firmware and the drive: counts and volts, one definition.

The DSP board of [Taghirad97] (DT1401 A/D, DAC0 to the MAX-100 servo amplifier; listing
A.1, ``DT1401Read`` / ``write_dac0``) works in volts; on the CAN link the drive transmits
ADC counts and receives DAC counts.  This module is the one place that defines how
counts and volts relate, so both nodes agree by construction.  12 bits and +/-10 V are
our defaults; the papers give neither.

A converter with ``bits`` bits and full scale ``full_scale_V`` has the two's complement
code range ``[-2**(bits-1), 2**(bits-1) - 1]`` and an LSB of ``full_scale_V /
2**(bits-1)``.  Conversions saturate at the code range.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Converter:
    """A bipolar converter, 12 bits and +/-10 V by default.

    The defaults are ours: [Taghirad97]'s listing names the DT1401 board (``DT140X.h``,
    ``DT1401Read``) but prints neither its resolution nor its input range; 12 bits and
    +/-10 V are the common figures of that class of board, not from the papers.
    """

    bits: int = 12
    full_scale_V: float = 10.0
    #: Derived once (the conversions run several times per 1 kHz cycle).
    code_min: int = field(init=False, repr=False, compare=False)
    code_max: int = field(init=False, repr=False, compare=False)
    lsb_V: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not 2 <= self.bits <= 16:
            raise ValueError(f"converter bits must be 2..16 (a 16-bit CAN signal), got {self.bits}")
        if not self.full_scale_V > 0:
            raise ValueError(f"converter full_scale_V must be > 0, got {self.full_scale_V}")
        object.__setattr__(self, "code_min", -(1 << (self.bits - 1)))
        object.__setattr__(self, "code_max", (1 << (self.bits - 1)) - 1)
        object.__setattr__(self, "lsb_V", self.full_scale_V / (1 << (self.bits - 1)))

    def to_counts(self, volts: float) -> int:
        """Quantize (round to nearest) and saturate a voltage to a code.

        NaN reads as 0; an infinite voltage (or one whose code overflows a float)
        saturates like any other out-of-range one."""
        if volts != volts:  # NaN never reaches the hardware as a number
            return 0
        try:
            code = round(volts / self.lsb_V)
        except OverflowError:  # volts / lsb is infinite: beyond either end of the range
            return self.code_max if volts > 0 else self.code_min
        if code > self.code_max:
            return self.code_max
        if code < self.code_min:
            return self.code_min
        return code

    def to_volts(self, counts: int) -> float:
        """The voltage a code stands for (codes outside the range are clipped)."""
        if counts > self.code_max:
            counts = self.code_max
        elif counts < self.code_min:
            counts = self.code_min
        return counts * self.lsb_V

    def saturated(self, counts: int) -> bool:
        return counts >= self.code_max or counts <= self.code_min
