"""Prediction-type Kalman filter of the harmonic-drive torque ripple.

Ports ``Kalman(Delta_T, velocity, sample_period)`` of seed 000
(``/work/shared/seeds/000_ae0a3dbe24949b7c.txt``, Appendix A.1 ``free_kalman.c`` and
A.2), which implements the text's Eqs. 5-10, generalised from the listing's fixed
two blocks to a bank of any number of harmonic-oscillator blocks
(:class:`firmware.config.Oscillator`), so the same code runs

- the 4th-order model of §4 / listing A.1 (2x and 4x motor velocity),
- listing A.2 (2x motor velocity and the misalignment block at the output velocity,
  still 4th order although the §5 text speaks of a 6th-order model),
- the 6th-order model of §5 (2x, 4x and the misalignment block).

Model (Eqs. 5, 6), with n = 2 x (number of blocks) states::

    x(k+1) = Φ(k) x(k) + w(k),      Φ(k) = blockdiag(Φ_1(k), ..., Φ_m(k))
    y(k)   = C x(k) + v(k),         C = [1 0 1 0 ... 1 0]
    Φ_i(k) = [[cos ω_i T, sin ω_i T], [-sin ω_i T, cos ω_i T]]

Filter (Eqs. 8-10), in the listing's order and grouping::

    K = Φ P Cᵀ / (R + C P Cᵀ)                (Eq. 9, "***** 1 *****")
    P ← Q + (Φ − K C) P Φᵀ                    (Eq. 10, "***** 2 *****")
    x ← (Φ − K C) x + K y                     (Eq. 8, "***** 3 *****")
    return C x                                ("Torque_ripple = x[0] + x[2]")

The return value is x̂(k+1|k)'s output: the ripple predicted for the NEXT sample,
which ``c_int10`` subtracts from the next measured torque.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.lib.stride_tricks import as_strided

from firmware.config import RippleFilterConfig

__all__ = ["RippleKalman"]


class RippleKalman:
    """Time-varying, prediction-type Kalman filter of the torque ripple (seed 000,
    Eqs. 5-10; listing A.1 / A.2 ``Kalman``), one :meth:`step` per interrupt.

    **State persists between calls.**  The printed listing declares ``x``, ``P``,
    ``Q``, ``C`` and ``R`` as plain (automatic) locals of ``Kalman`` and only
    initialises them while ``kal_count == 1``, so as printed it would forget the
    state (and read uninitialised memory) from the second call on.  The filter the
    text describes and whose results Figs. 9 and 11 show must keep them, as if they
    were ``static``; this port keeps them in the object.

    Initialisation (listing, ``if (kal_count == 1)``), done on the first *valid*
    call and then followed by a normal update in the same call:
    x = 0 except x[2i] = y for every block (listing ``x[0] = x[2] = Delta_T``),
    P = p0·I (listing ``P[i][i] = 1.0``), Q = blockdiag(q_i·I2) (listing
    ``Q[i][i] = 1000.0``; A.2 ``Q[2][2] = Q[3][3] = 5e-2``), R = r (``R = 1.0``),
    C = [1 0 1 0 ...] (``C[0] = C[2] = 1.0``).

    Frequencies (Eq. 6 and §5; listing ``om1 = 2.0 * velocity * sample_period;
    om2 = 2.0 * om1`` in A.1, ``om2 = velocity * sample_period / 100.0`` in A.2):
    ω_i = multiple_i·velocity for "motor" blocks and multiple_i·velocity/gear_ratio
    for "output" blocks, velocity being the motor velocity in rad/s.

    Robustness (not in the listing): if ``delta_T`` or ``velocity`` is not finite,
    the update is skipped, :attr:`skipped` is incremented and the previous prediction
    is returned, so one corrupt sample cannot poison x and P for good.

    All arrays are float64 and preallocated; a step allocates nothing but the
    numpy call overhead.
    """

    def __init__(self, cfg: RippleFilterConfig, sample_period_s: float, gear_ratio: float) -> None:
        if not (math.isfinite(sample_period_s) and sample_period_s > 0):
            raise ValueError(
                f"sample_period_s must be a finite number > 0, got {sample_period_s!r}"
            )
        if not (math.isfinite(gear_ratio) and gear_ratio > 0):
            raise ValueError(f"gear_ratio must be a finite number > 0, got {gear_ratio!r}")
        self.cfg = cfg
        self.sample_period_s = float(sample_period_s)
        self.gear_ratio = float(gear_ratio)
        m = len(cfg.oscillators)
        n = 2 * m
        self.n = n
        self.r = float(cfg.r)

        # ω_i T per rad/s of motor velocity, repeated for both states of a block so that
        # cos can be written straight onto Φ's diagonal.
        wT = np.array(
            [
                osc.multiple
                * self.sample_period_s
                / (self.gear_ratio if osc.source == "output" else 1.0)
                for osc in cfg.oscillators
            ],
            dtype=np.float64,
        )
        self._wT = np.repeat(wT, 2)
        self._om = np.zeros(n)  # ω_i T for each state
        self._om_blk = self._om[0::2]  # one ω_i T per block (view)

        self._Q = np.diag(
            np.repeat(np.array([osc.q for osc in cfg.oscillators], dtype=np.float64), 2)
        )
        self._C = np.zeros(n)
        self._C[0::2] = 1.0
        self._x = np.zeros(n)
        self._P = np.zeros((n, n))
        self._K = np.zeros(n)
        self._K_col = self._K[:, np.newaxis]  # K as an n x 1 column (view), for K C

        # Φ(k) and writable strided views onto its diagonal, its (2i, 2i+1) and
        # (2i+1, 2i) entries; the rest of Φ stays zero for good.
        self._phi = np.zeros((n, n))
        item = self._phi.itemsize
        self._phi_diag = as_strided(self._phi, shape=(n,), strides=((n + 1) * item,))
        self._phi_sup = as_strided(self._phi[0:, 1:], shape=(m,), strides=(2 * (n + 1) * item,))
        self._phi_sub = as_strided(self._phi[1:, 0:], shape=(m,), strides=(2 * (n + 1) * item,))

        # Work arrays, named as in the listing.
        self._PC = np.zeros(n)
        self._pPC = np.zeros(n)
        self._Pp = np.zeros((n, n))
        self._KC = np.zeros((n, n))
        self._p_KC = np.zeros((n, n))
        self._gb = np.zeros((n, n))
        self._x1 = np.zeros(n)

        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Back to the freshly constructed state (listing ``kal_count = 1``): the next
        valid call re-initialises x, P from its measurement; ``skipped`` is zeroed."""
        self._initialized = False
        self._x.fill(0.0)
        self._P.fill(0.0)
        self._K.fill(0.0)
        self._prediction = 0.0
        self.skipped = 0
        self.steps = 0

    @property
    def initialized(self) -> bool:
        """True once the first valid sample has initialised the filter."""
        return self._initialized

    @property
    def prediction(self) -> float:
        """The last ripple prediction returned by :meth:`step` (0 before the first)."""
        return self._prediction

    @property
    def x(self) -> np.ndarray:
        """A copy of the state estimate x̂(k+1|k)."""
        return self._x.copy()

    @property
    def P(self) -> np.ndarray:
        """A copy of the error covariance P(k+1)."""
        return self._P.copy()

    @property
    def K(self) -> np.ndarray:
        """A copy of the last Kalman gain K_e(k) (Eq. 9)."""
        return self._K.copy()

    @property
    def phi(self) -> np.ndarray:
        """A copy of the last transition matrix Φ(k) (Eq. 6)."""
        return self._phi.copy()

    @property
    def Q(self) -> np.ndarray:
        """A copy of the process-noise covariance Q (Eq. 7)."""
        return self._Q.copy()

    @property
    def C(self) -> np.ndarray:
        """A copy of the output row C = [1 0 1 0 ...] (Eq. 5)."""
        return self._C.copy()

    # ------------------------------------------------------------------- step
    def step(self, delta_T: float, velocity: float) -> float:
        """One interrupt: measurement y = ``delta_T`` (Nm), motor ``velocity`` (rad/s).

        Returns the ripple predicted for the next sample (listing
        ``T_ripple = Kalman(Delta_T, vel, sample_period)``).
        """
        if not (math.isfinite(delta_T) and math.isfinite(velocity)):
            self.skipped += 1
            return self._prediction

        x = self._x
        P = self._P
        K = self._K
        C = self._C
        phi = self._phi

        # Matrix Initialization: "if (kal_count == 1) /* only true for first iteration */"
        if not self._initialized:
            x.fill(0.0)
            x[0::2] = delta_T  # x[0] = x[2] = Delta_T
            P.fill(0.0)
            np.fill_diagonal(P, self.cfg.p0)  # P = I
            self._initialized = True

        # om_i = multiple_i * velocity * sample_period; System Model (Eq. 6)
        np.multiply(self._wT, velocity, out=self._om)
        np.cos(self._om, out=self._phi_diag)  # phi[2i][2i] = phi[2i+1][2i+1] = cos(om_i)
        np.sin(self._om_blk, out=self._phi_sup)  # phi[2i][2i+1] = sin(om_i)
        np.negative(self._phi_sup, out=self._phi_sub)  # phi[2i+1][2i] = -sin(om_i)

        # ***** 1 ***** Gain update K = phi P C' / (R + C P C')   (Eq. 9)
        PC = np.dot(P, C, out=self._PC)
        CPC = float(C.dot(PC))
        np.dot(phi, PC, out=self._pPC)
        np.divide(self._pPC, self.r + CPC, out=K)

        # ***** 2 ***** P update P = Q + (phi - K C) P phi'   (Eq. 10)
        np.dot(P, phi.T, out=self._Pp)
        np.multiply(self._K_col, C, out=self._KC)  # K C (outer product)
        p_KC = np.subtract(phi, self._KC, out=self._p_KC)
        np.dot(p_KC, self._Pp, out=self._gb)
        np.add(self._Q, self._gb, out=P)

        # ***** 3 ***** x update x = (phi - K C) x + K y   (Eq. 8)
        np.dot(p_KC, x, out=self._x1)
        np.multiply(K, delta_T, out=x)
        np.add(x, self._x1, out=x)

        # Output generation y = C x = x(1) + x(3) [+ x(5) ...]
        self._prediction = float(C.dot(x))
        self.steps += 1
        return self._prediction
