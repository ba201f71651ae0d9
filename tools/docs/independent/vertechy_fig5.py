"""[Vertechy] Fig. 5: the joint's natural frequency and damping from its parameters.

Independent of hdhil (numpy only).  Eq. 2 gives the sensor torque's response to the motor
torque, ``τs/τm = −(k/Jm) / (s² + (c/J) s + k/J)``, ``J = Jm Jl / (Jm + Jl)``: natural
frequency ``sqrt(k/J)/2π``.  The paper reads fn and c off the measured Bode magnitude by
the half-power bandwidth method; applied to the exact magnitude of Eq. 2 with the paper's
c, that method gives what a perfect measurement would: fn at the peak (below the natural
frequency by the factor ``sqrt(1 − 2ζ²)``) and c from ``ζ = Δf / (2 fn)``.  Run ``python
vertechy_fig5.py`` for the numbers.
"""

from __future__ import annotations

import math

import numpy as np

#: [Vertechy] §I-II: Jm, Jl (kg m²), k (Nm/rad), c (Nms/rad), reduced to the output.
JM, JL, K, C = 2.5, 0.7, 6300.0, 11.8


def natural_frequency_Hz(jm: float = JM, jl: float = JL, k: float = K) -> float:
    """``sqrt(k/J)/2π`` ([Vertechy] §II: "≈ 17 Hz")."""
    return math.sqrt(k * (jm + jl) / (jm * jl)) / (2.0 * math.pi)


def half_power(c: float = C, *, n: int = 400_001) -> tuple[float, float]:
    """The half-power bandwidth method on the exact magnitude of Eq. 2, as the paper uses
    it (fn = the peak): ``(fn_Hz, c_Nms_per_rad)``."""
    j = JM * JL / (JM + JL)
    f = np.linspace(5.0, 40.0, n)
    s = 2j * math.pi * f
    mag = np.abs((K / JM) / (s * s + (c / j) * s + K / j))
    i = int(np.argmax(mag))
    fp = float(f[i])
    band = f[mag >= mag[i] / math.sqrt(2.0)]
    zeta = float(band[-1] - band[0]) / (2.0 * fp)
    return fp, 2.0 * zeta * (2.0 * math.pi * fp) * j


def main() -> None:
    fp, c = half_power()
    print("[Vertechy] Fig. 5 (numpy only)")
    print(f"  natural frequency sqrt(k/J)/2pi   {natural_frequency_Hz():.3f} Hz")
    print(f"  half-power method on Eq. 2        fn {fp:.3f} Hz (the peak), c {c:.2f} Nms/rad")


if __name__ == "__main__":
    main()
