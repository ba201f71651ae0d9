"""Kalman filters of the harmonic-drive torque ripple: [Taghirad97]'s and our recommended one.

Two filters, selected by :attr:`firmware.config.RippleFilterConfig.mode`:

- :class:`RippleKalman` (``mode = "paper"``): ``Kalman(Delta_T, velocity, sample_period)``
  of [Taghirad97] listings A.1 and A.2 (Eqs. 5-10), in the listing's update order,
  generalised from its two blocks to a bank of any number of harmonic oscillators
  rotated by Φ(k) from the tacho velocity, so the same code runs §4 / A.1 (2x and 4x
  motor), A.2 (2x motor and the misalignment at the output) and the 6th-order model of
  §5.  It returns the ripple predicted for the next sample, which ``c_int10`` subtracts
  from the next measured torque.  Unlike the listing it keeps its state between calls.
- :class:`HarmonicKalman` (``mode = "recommended"``, the default): our angle-locked
  harmonic regression with a residual-torque state, which keeps the low-frequency torque
  the paper filter absorbs and takes the harmonic phase from the encoder instead of
  integrating the tachometer (see its docstring for the design and why).

The paper filter's known weakness, measured by :mod:`firmware.response`: it takes any
slow torque its inertia-only model misses for ripple (the gain from a 0-5 Hz true
torque to the filtered torque is 0.02-0.05 at 20 rad/s and 0.53 at 156 rad/s; the
recommended filter's is 1.000).  docs/papers.md has the model and its equations.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import cache

import numpy as np
from numpy.lib.stride_tricks import as_strided

from hdhil.firmware.config import RippleFilterConfig

__all__ = ["HarmonicKalman", "RippleKalman"]


class RippleKalman:
    """Time-varying, prediction-type Kalman filter of the torque ripple ([Taghirad97],
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
        if cfg.mode != "paper":
            raise ValueError(
                f"RippleKalman is the paper filter: needs mode 'paper', got {cfg.mode!r}"
            )
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
        self._innovation = math.nan
        self._innovation_variance = math.nan
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
    def innovation(self) -> float:
        """Innovation e(k) = y(k) − C x̂(k) of the last :meth:`step` (Eq. 8's bracket), with
        x̂(k) the prediction made at k − 1 (after the initialisation on the first call);
        NaN before the first step and after a skipped (non-finite) sample."""
        return self._innovation

    @property
    def innovation_variance(self) -> float:
        """Its predicted variance S(k) = R + C P(k) Cᵀ (the denominator of Eq. 9), so
        that e(k) ~ N(0, S(k)) if the model holds; NaN whenever :attr:`innovation` is."""
        return self._innovation_variance

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
            self._innovation = self._innovation_variance = math.nan
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
        self._innovation = delta_T - float(C.dot(x))  # y(k) - C x(k), Eq. 8
        self._innovation_variance = self.r + CPC
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


# ====================================================================== recommended mode
def _p(i: int, j: int) -> str:
    """Local-variable name of P[i][j] (= P[j][i]) in the generated kernel."""
    return f"p{min(i, j)}_{max(i, j)}"


def _kernel_source(harmonics: int) -> str:
    """Python source of :class:`HarmonicKalman`'s step for ``harmonics`` harmonics.

    Straight-line code over local floats, unrolled for the state dimension
    n = 2·harmonics + 1: faster in CPython than the same algorithm as loops over lists,
    or with numpy, whose per-call overhead dominates at n ≤ 7 (the step's time is in
    ``hdhil bench``'s stage table).  The generated text is the algorithm written
    out, nothing more; :attr:`HarmonicKalman.kernel_source` shows it, and the tests
    check it against a plain numpy transcription of the equations.
    """
    h = harmonics
    n = 2 * h + 1
    r = n - 1  # index of the residual-torque state
    idx = range(n)
    upper = [(i, j) for i in idx for j in range(i, n)]
    P_names = ", ".join(_p(i, j) for i, j in upper)
    x_names = ", ".join(f"x{i}" for i in idx)
    w_names = ", ".join(f"w{k}" for k in range(h))
    q_names = ", ".join(f"q{k}" for k in range(h))

    def c(j: int) -> str:  # C[j] as a factor: the residual's regressor is 1
        return "" if j == r else f" * c{j}"

    lines = [
        "def step(self, y, velocity, angle):",
        "    if not (isfinite(y) and isfinite(velocity) and isfinite(angle)):",
        "        return self._skip(angle)",
        "    if not self._initialized:",
        "        self._initialize(y)",
        f"    {P_names}, = self._P",
        f"    {x_names}, = self._x",
        f"    R, q_r, standstill, {w_names}, {q_names}, = self._const",
        "    # C(k) = [cos(m_1 phi), sin(m_1 phi), ..., 1]",
    ]
    for k in range(h):
        lines += [
            f"    a = w{k} * angle",
            f"    c{2 * k} = cos(a)",
            f"    c{2 * k + 1} = sin(a)",
        ]
    lines += [
        "    # ripple(k) = C_ripple(k) x(k|k-1): the harmonic columns only",
        "    ripple = " + " + ".join(f"c{j} * x{j}" for j in range(r)),
        f"    e = y - ripple - x{r}  # innovation y - C x",
        "    # u = P C', S = C P C' + R",
    ]
    for i in idx:
        lines.append(f"    u{i} = " + " + ".join(f"{_p(i, j)}{c(j)}" for j in idx))
    lines += [
        "    S = R + " + " + ".join(f"u{j}{c(j)}" for j in idx),
        "    self._innovation = e",
        "    self._innovation_variance = S",
        "    if not 0.0 < S < INF:",
        "        return self._diverged(ripple)",
        "    if velocity >= standstill or velocity <= -standstill:",
        "        # x += K e, P -= K S K' with K = u / S",
    ]
    for i in idx:
        lines += [f"        k{i} = u{i} / S", f"        x{i} += k{i} * e"]
    for i, j in upper:
        lines.append(f"        {_p(i, j)} -= k{i} * u{j}")
    lines += [
        "    else:",
        "        # standstill: Schmidt (consider) update, harmonic coefficients frozen",
        f"        k{r} = u{r} / S",
        f"        x{r} += k{r} * e",
    ]
    for j in idx:
        lines.append(f"        {_p(j, r)} -= k{r} * u{j}")
    lines.append("    # time update: x(k+1|k) = x(k|k), P(k+1|k) = P(k|k) + Q")
    for k in range(h):
        lines += [f"    {_p(2 * k, 2 * k)} += q{k}", f"    {_p(2 * k + 1, 2 * k + 1)} += q{k}"]
    lines.append(f"    {_p(r, r)} += q_r")
    diag = " and ".join(f"0.0 < {_p(i, i)} < INF" for i in idx)
    lines += [
        f"    if not ({diag} and -INF < {' + '.join(f'x{i}' for i in idx)} < INF):",
        "        return self._diverged(ripple)",
        f"    self._P = ({P_names},)",
        f"    self._x = ({x_names},)",
        "    self._prediction = ripple",
        "    self.steps += 1",
        "    return ripple",
    ]
    return "\n".join(lines) + "\n"


@cache
def _kernel(harmonics: int) -> Callable[..., float]:
    """The compiled step function for ``harmonics`` harmonics (built once per count)."""
    namespace: dict[str, object] = {
        "cos": math.cos,
        "sin": math.sin,
        "isfinite": math.isfinite,
        "INF": math.inf,
    }
    source = _kernel_source(harmonics)
    exec(compile(source, f"<HarmonicKalman kernel, {harmonics}>", "exec"), namespace)
    return namespace["step"]  # type: ignore[return-value]


class HarmonicKalman:
    """Angle-locked harmonic regression Kalman filter of the torque ripple (recommended
    mode).  **Our design**, not [Taghirad97]'s; it keeps its structure (a Kalman filter
    on y = T_meas − T_exp whose ripple estimate is subtracted from T_meas) and changes
    what the paper filter gets wrong.

    Why (measured weaknesses of :class:`RippleKalman`):

    1. The paper filter explains *all* of y by its oscillators, so any slow torque
       the inertia-only T_exp misses (friction, load torque, bridge offset) is taken
       for ripple and removed from the "filtered" torque: 95 % of it at 20 rad/s, 47 %
       at 156 rad/s (4th-order model), 100 % at standstill where Φ = I.
    2. Its oscillators' phase advances by the tachometer velocity times Ts, i.e. it
       integrates a noisy tachometer quantised to 0.27 rad/s per count.

    Model (k = sample index, φ(k) = motor angle in rad)::

        y(k)  = Σ_i [a_i cos(m_i φ(k)) + b_i sin(m_i φ(k))] + r(k) + v(k),  var v = R
        a_i, b_i: random walks, variance q_i per step        (ripple map, changes slowly)
        r:        random walk,  variance q_r per step        (residual torque T_true − T_exp)

    so x = [a_1, b_1, ..., a_h, b_h, r], Φ = I, Q = diag(q_1, q_1, ..., q_r) and
    C(k) = [cos m_1 φ(k), sin m_1 φ(k), ..., 1].  For an "output" harmonic the phase is
    m·φ/gear_ratio (the output angle).

    - **Phase from the measured angle**: φ(k) is the unwrapped encoder count at k
      (:class:`firmware.stages.EncoderUnwrap`), so the harmonic phase is measured,
      not integrated; a tachometer-integrated φ is the fallback for data without an
      encoder (:attr:`RippleFilterConfig.phase_source`).  An unknown constant offset
      of φ (the encoder's power-on count) only rotates (a_i, b_i).
    - **Prediction form without lag** (in the spirit of [Taghirad97] Eqs. 8-10): at sample k,
      ``ripple(k) = C_ripple(k) x̂(k|k−1)`` (harmonic columns only, *not* r) and the
      filtered torque is ``T_filtered(k) = T_meas(k) − ripple(k)``; only then is x̂
      updated with y(k).  The ripple estimate uses information up to k − 1, like the
      paper filter's, but it is evaluated at the angle measured at k, so it has no phase lag.
    - **Why low-frequency torque passes**: the residual r takes the DC and slow part
      of the innovation (its q_r is large), while the harmonic columns average to
      zero over a revolution and cannot represent DC.  At any non-zero constant speed
      the transfer from true torque to T_filtered is 1 at DC and notches only narrow
      bands around the harmonic frequencies (:func:`firmware.response.torque_transfer`).
    - **Standstill**: for |velocity| < ``standstill_radps`` the regressors are
      constant, so a harmonic coefficient cannot be told apart from a torque offset.
      The coefficients are then frozen by a Schmidt (consider) update: only r is
      corrected, with the full innovation variance, and P keeps its cross terms
      consistent (P_hh unchanged, P_rh −= k_r u_h, P_rr −= k_r u_r).  The learned ripple
      map is still subtracted: a position-dependent sensor error is still an error at
      standstill.

    Numerics (hours at 1 kHz): float64 throughout.  P is stored as its upper triangle,
    so it is exactly symmetric by construction; the update ``P −= u uᵀ / S`` (u = P Cᵀ)
    is the symmetric form of ``P − K C P``.  Each step checks cheaply that S and the
    diagonal of P are positive and finite and that x is finite; if not, the step's
    update is discarded, P is reset to P(0) = p0·I and :attr:`covariance_resets` is
    counted.
    Non-finite inputs are skipped and counted in :attr:`skipped` (the ripple map is
    still evaluated at the angle if the angle is finite).  Innovations are **not**
    clamped: a real torque step must reach r at once.

    Initialisation (on the first valid sample, like the listing's ``kal_count == 1``):
    coefficients 0, r = y, P = p0·I; the normal update follows in the same call, so
    the first ripple is 0 and the first filtered torque equals the measurement.

    Speed: the step is generated straight-line code for the configured number of
    harmonics (see :func:`_kernel_source`): 1.4 µs for 2 harmonics, 2.0 µs for 3 on
    CPython 3.11 (the paper filter's numpy step: 8.0 µs for 4th order).
    """

    def __init__(self, cfg: RippleFilterConfig, gear_ratio: float) -> None:
        if cfg.mode != "recommended":
            raise ValueError(
                f"HarmonicKalman is the recommended filter: needs mode 'recommended', "
                f"got {cfg.mode!r}"
            )
        if not (math.isfinite(gear_ratio) and gear_ratio > 0):
            raise ValueError(f"gear_ratio must be a finite number > 0, got {gear_ratio!r}")
        self.cfg = cfg
        self.gear_ratio = float(gear_ratio)
        h = len(cfg.oscillators)
        self.harmonics = h
        self.n = 2 * h + 1
        #: Phase per rad of motor angle of each harmonic (multiple, or multiple / gear).
        self.phase_gains: tuple[float, ...] = tuple(
            float(o.multiple) / (self.gear_ratio if o.source == "output" else 1.0)
            for o in cfg.oscillators
        )
        self._q_diag: tuple[float, ...] = (
            *(float(o.q) for o in cfg.oscillators for _ in range(2)),  # type: ignore[arg-type]
            float(cfg.residual_q),
        )
        self._p0 = float(cfg.p0)  # type: ignore[arg-type]
        self._const = (
            float(cfg.r),  # type: ignore[arg-type]
            float(cfg.residual_q),
            float(cfg.standstill_radps),
            *self.phase_gains,
            *(float(o.q) for o in cfg.oscillators),  # type: ignore[arg-type]
        )
        self._kernel = _kernel(h)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Back to the freshly constructed state: the next valid sample initialises the
        filter; ``skipped``, ``covariance_resets`` and ``steps`` are zeroed."""
        self._initialized = False
        self._x: tuple[float, ...] = (0.0,) * self.n
        self._P: tuple[float, ...] = self._initial_P()
        self._prediction = 0.0
        self._innovation = math.nan
        self._innovation_variance = math.nan
        self.skipped = 0
        self.covariance_resets = 0
        self.steps = 0

    def _initial_P(self) -> tuple[float, ...]:
        """P(0) = p0·I as the stored upper triangle."""
        n, p0 = self.n, self._p0
        return tuple(p0 if i == j else 0.0 for i in range(n) for j in range(i, n))

    def _initialize(self, y: float) -> None:
        self._x = (0.0,) * (self.n - 1) + (float(y),)
        self._P = self._initial_P()
        self._initialized = True

    def _skip(self, angle: float) -> float:
        """A non-finite input: no update; the ripple map at the angle if it is finite."""
        self.skipped += 1
        self._innovation = self._innovation_variance = math.nan
        if math.isfinite(angle):
            self._prediction = self.ripple_at(angle)
        return self._prediction

    def _diverged(self, ripple: float) -> float:
        """The update would leave S, P or x non-positive / non-finite: discard it and
        restart the covariance at P(0) (x keeps its last good value)."""
        self.covariance_resets += 1
        self._P = self._initial_P()
        self._prediction = ripple
        self.steps += 1
        return ripple

    @property
    def initialized(self) -> bool:
        """True once the first valid sample has initialised the filter."""
        return self._initialized

    @property
    def prediction(self) -> float:
        """The ripple returned by the last :meth:`step` (0 before the first)."""
        return self._prediction

    @property
    def innovation(self) -> float:
        """Innovation e(k) = y(k) − C(k) x̂(k|k−1) of the last :meth:`step` (Nm): the
        measurement minus the predicted ripple *and* residual.  NaN before the first step
        and after a skipped (non-finite) sample."""
        return self._innovation

    @property
    def innovation_variance(self) -> float:
        """Its predicted variance S(k) = C(k) P(k|k−1) C(k)ᵀ + R (Nm²), the same S the
        step divides by; with the model right, e(k) ~ N(0, S(k)) and
        Σ ½(log 2πS + e²/S) is the negative log-likelihood :mod:`hdhil.analysis.tuning` minimises.
        NaN whenever :attr:`innovation` is."""
        return self._innovation_variance

    @property
    def x(self) -> np.ndarray:
        """A copy of the state x̂(k+1|k) = [a_1, b_1, ..., a_h, b_h, r]."""
        return np.array(self._x, dtype=np.float64)

    @property
    def residual(self) -> float:
        """The residual-torque estimate r (Nm): T_true − T_exp as the filter sees it."""
        return self._x[-1]

    @property
    def harmonic_amplitudes(self) -> np.ndarray:
        """Amplitude sqrt(a_i² + b_i²) of each harmonic's learned ripple (Nm)."""
        x = self._x
        return np.array([math.hypot(x[2 * i], x[2 * i + 1]) for i in range(self.harmonics)])

    @property
    def P(self) -> np.ndarray:
        """A copy of the error covariance P(k+1|k), as a full symmetric matrix."""
        n = self.n
        P = np.zeros((n, n))
        P[np.triu_indices(n)] = self._P
        return P + np.triu(P, 1).T

    @property
    def Q(self) -> np.ndarray:
        """The process-noise covariance Q = diag(q_1, q_1, ..., q_h, q_h, q_r)."""
        return np.diag(self._q_diag)

    @property
    def kernel_source(self) -> str:
        """The generated source of this filter's step (for reading and debugging)."""
        return _kernel_source(self.harmonics)

    def regressor(self, angle: float) -> np.ndarray:
        """C at motor angle ``angle``: [cos m_1 φ, sin m_1 φ, ..., 1]."""
        C = np.ones(self.n)
        for i, w in enumerate(self.phase_gains):
            C[2 * i] = math.cos(w * angle)
            C[2 * i + 1] = math.sin(w * angle)
        return C

    def ripple_at(self, angle: float) -> float:
        """The learned ripple map at motor angle ``angle`` (no update); the same
        arithmetic, in the same order, as the ripple :meth:`step` returns."""
        x = self._x
        terms = []
        for i, w in enumerate(self.phase_gains):
            a = w * angle
            terms += (math.cos(a) * x[2 * i], math.sin(a) * x[2 * i + 1])
        total = terms[0]
        for term in terms[1:]:
            total += term
        return total

    # ------------------------------------------------------------------- step
    def step(self, delta_T: float, velocity: float, angle: float) -> float:
        """One sample: y = ``delta_T`` (Nm), motor ``velocity`` (rad/s, for the
        standstill test), motor ``angle`` φ(k) (rad).

        Returns ``ripple(k) = C_ripple(k) x̂(k|k−1)``, the ripple to subtract from
        T_meas(k) *now* (``T_filtered = T_meas − ripple``); then updates x̂ with y(k).
        """
        return self._kernel(self, delta_T, velocity, angle)
