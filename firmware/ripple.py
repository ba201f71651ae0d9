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
from types import MethodType

import numpy as np

from hdhil.firmware.config import RippleFilterConfig

__all__ = ["HarmonicKalman", "RippleKalman"]


def _p(i: int, j: int) -> str:
    """Local-variable name of P[i][j] (= P[j][i]) in the generated kernels."""
    return f"p{min(i, j)}_{max(i, j)}"


def _symmetric(upper: tuple[float, ...], n: int) -> np.ndarray:
    """The full n × n matrix from its upper triangle stored row by row."""
    P = np.zeros((n, n))
    P[np.triu_indices(n)] = upper
    return P + np.triu(P, 1).T


def _paper_kernel_source(blocks: int) -> str:
    """Python source of :class:`RippleKalman`'s step for ``blocks`` oscillator blocks.

    The listing's update (``Kalman``, Eqs. 8-10) term for term, in its order: Φ(k) from
    the velocity; PC = P Cᵀ, CPC = C PC, K = Φ PC / (R + CPC); P = Q + (Φ − K C) P Φᵀ via
    Pp = P Φᵀ; x = (Φ − K C) x + K y; output C x.  Unrolled for n = 2·blocks states over
    local floats, with the products by the entries that Φ, C and K C have zero for good
    left out (Φ is block diagonal, C = [1 0 1 0 ...]): adding those exact zeros changes
    nothing.  P is symmetric (the update maps a symmetric P to a symmetric one, and
    P(0) = p0·I), so only its upper triangle is computed and stored, and only the
    entries of Pp that it needs.  The numbers are the listing's up to the order of the
    additions in each sum.  Straight-line code is what makes a 4th-order step a few
    microseconds in CPython (with numpy, a call's overhead is larger than the arithmetic
    at this size).
    """
    m = blocks
    n = 2 * m
    idx = range(n)
    upper = [(a, b) for a in idx for b in range(a, n)]
    P_names = ", ".join(_p(a, b) for a, b in upper)
    x_names = ", ".join(f"x{a}" for a in idx)
    k_names = ", ".join(f"k{a}" for a in idx)
    cs_names = ", ".join(f"c{i}, s{i}" for i in range(m))
    w_names = ", ".join(f"w{i}" for i in range(m))
    q_names = ", ".join(f"q{i}" for i in range(m))
    even = range(0, n, 2)

    def row(a: int) -> list[tuple[int, str]]:
        """Row a of Φ − K C as (column, factor), its non-zero entries only; a factor
        "-k" is subtracted: Φ's two entries in a's block (the even one less K_a) and
        -K_a in the other blocks' even columns."""
        i = a // 2
        out: list[tuple[int, str]] = []
        for col in idx:
            if col == 2 * i:
                out.append((col, f"m{a}"))
            elif col == 2 * i + 1:
                out.append((col, f"s{i}" if a % 2 == 0 else f"c{i}"))
            elif col % 2 == 0:
                out.append((col, f"-k{a}"))
        return out

    def dot(entries: list[tuple[int, str]], operand: str) -> str:
        terms = ""
        for col, factor in entries:
            term = operand.format(col)
            if factor.startswith("-"):
                terms += f" - {factor[1:]} * {term}" if terms else f"-{factor[1:]} * {term}"
            else:
                terms += f" + {factor} * {term}" if terms else f"{factor} * {term}"
        return terms

    lines = [
        "def step(self, y, velocity):",
        "    if not (isfinite(y) and isfinite(velocity)):",
        "        return self._skip()",
        "    if not self._initialized:",
        "        self._initialize(y)",
        f"    {P_names}, = self._P",
        f"    {x_names}, = self._x",
        f"    R, {w_names}, {q_names}, = self._const",
        "    # Phi(k), Eq. 6: rotation by om_i = w_i velocity in block i",
    ]
    for i in range(m):
        lines += [f"    om = w{i} * velocity", f"    c{i} = cos(om)", f"    s{i} = sin(om)"]
    lines.append("    # 1: K = Phi P C' / (R + C P C')  (Eq. 9)")
    for a in idx:
        lines.append(f"    pc{a} = " + " + ".join(_p(a, b) for b in even))
    lines += [
        "    S = R + (" + " + ".join(f"pc{b}" for b in even) + ")",
        "    e = y - (" + " + ".join(f"x{b}" for b in even) + ")  # y - C x, Eq. 8",
    ]
    for i in range(m):
        a, b = 2 * i, 2 * i + 1
        lines += [
            f"    k{a} = (c{i} * pc{a} + s{i} * pc{b}) / S",
            f"    k{b} = (c{i} * pc{b} - s{i} * pc{a}) / S",
        ]
    lines.append("    # 2: P = Q + (Phi - K C) P Phi'  (Eq. 10), Pp = P Phi'")
    needed = {(c, b) for a, b in upper for c, _ in row(a)}
    for c in idx:
        for b in idx:
            if (c, b) not in needed:
                continue
            i = b // 2
            u, v = 2 * i, 2 * i + 1
            if b == u:
                lines.append(f"    pp{c}_{b} = {_p(c, u)} * c{i} + {_p(c, v)} * s{i}")
            else:
                lines.append(f"    pp{c}_{b} = {_p(c, v)} * c{i} - {_p(c, u)} * s{i}")
    lines.append("    # the entries of Phi - K C in the columns both fill")
    for i in range(m):
        lines += [f"    m{2 * i} = c{i} - k{2 * i}", f"    m{2 * i + 1} = -s{i} - k{2 * i + 1}"]
    for a, b in upper:
        q = f" + q{a // 2}" if a == b else ""
        lines.append(f"    {_p(a, b)} = {dot(row(a), f'pp{{}}_{b}')}{q}")
    lines.append("    # 3: x = (Phi - K C) x + K y  (Eq. 8)")
    for a in idx:
        lines.append(f"    x1_{a} = {dot(row(a), 'x{}')}")
    for a in idx:
        lines.append(f"    x{a} = k{a} * y + x1_{a}")
    lines += [
        f"    self._P = ({P_names},)",
        f"    self._x = ({x_names},)",
        f"    self._K = ({k_names},)",
        f"    self._cs = ({cs_names},)",
        "    self._innovation = e",
        "    self._innovation_variance = S",
        "    # output: C x = x[0] + x[2] + ...",
        "    out = " + " + ".join(f"x{b}" for b in even),
        "    self._prediction = out",
        "    self.steps += 1",
        "    return out",
    ]
    return "\n".join(lines) + "\n"


def _compiled_step(source: str, name: str) -> Callable[..., float]:
    """The ``step`` function a generated kernel's ``source`` defines, compiled under
    ``name`` (shown in tracebacks and profiles), with the math it calls in scope."""
    namespace: dict[str, object] = {
        "cos": math.cos,
        "sin": math.sin,
        "isfinite": math.isfinite,
        "INF": math.inf,
    }
    exec(compile(source, name, "exec"), namespace)
    return namespace["step"]  # type: ignore[return-value]


@cache
def _paper_kernel(blocks: int) -> Callable[..., float]:
    """The compiled step function of :class:`RippleKalman` for ``blocks`` blocks."""
    return _compiled_step(_paper_kernel_source(blocks), f"<RippleKalman kernel, {blocks}>")


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

    The step is generated straight-line code for the configured number of blocks
    (:func:`_paper_kernel_source`, :attr:`kernel_source`), like
    :class:`HarmonicKalman`'s: the firmware's interrupt and the offline replay of
    :mod:`hdhil.rig.evaluate` run the same code.  x, P (its upper triangle, row by row)
    and K are kept as tuples of floats; the properties return numpy copies.
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
        self.blocks = m
        self.n = 2 * m
        self.r = float(cfg.r)
        self._p0 = float(cfg.p0)
        # ω_i T per rad/s of motor velocity, one per block.
        self._wT: tuple[float, ...] = tuple(
            float(osc.multiple)
            * self.sample_period_s
            / (self.gear_ratio if osc.source == "output" else 1.0)
            for osc in cfg.oscillators
        )
        self._q: tuple[float, ...] = tuple(float(osc.q) for osc in cfg.oscillators)
        self._const = (self.r, *self._wT, *self._q)
        self._kernel = _paper_kernel(m)
        # The kernel bound as this instance's ``step``: the per-sample call goes straight
        # to the generated code, without the wrapper's extra frame (:meth:`step` below
        # documents the call and does the same).
        self.step = MethodType(self._kernel, self)  # type: ignore[method-assign]
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Back to the freshly constructed state (listing ``kal_count = 1``): the next
        valid call re-initialises x, P from its measurement; ``skipped`` is zeroed."""
        n = self.n
        self._initialized = False
        self._x: tuple[float, ...] = (0.0,) * n
        self._P: tuple[float, ...] = (0.0,) * (n * (n + 1) // 2)
        self._K: tuple[float, ...] = (0.0,) * n
        self._cs: tuple[float, ...] = (1.0, 0.0) * self.blocks  # Φ = I until the first step
        self._prediction = 0.0
        self._innovation = math.nan
        self._innovation_variance = math.nan
        self.skipped = 0
        self.steps = 0

    def _initialize(self, y: float) -> None:
        """Matrix Initialization: "if (kal_count == 1) /* only true for first iteration */":
        x[2i] = y (``x[0] = x[2] = Delta_T``), P = p0·I."""
        n, p0 = self.n, self._p0
        self._x = (float(y), 0.0) * self.blocks
        self._P = tuple(p0 if a == b else 0.0 for a in range(n) for b in range(a, n))
        self._initialized = True

    def _skip(self) -> float:
        """A non-finite input: no update, the previous prediction."""
        self.skipped += 1
        self._innovation = self._innovation_variance = math.nan
        return self._prediction

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
        return np.array(self._x, dtype=np.float64)

    @property
    def P(self) -> np.ndarray:
        """A copy of the error covariance P(k+1), as a full symmetric matrix."""
        return _symmetric(self._P, self.n)

    @property
    def K(self) -> np.ndarray:
        """A copy of the last Kalman gain K_e(k) (Eq. 9)."""
        return np.array(self._K, dtype=np.float64)

    @property
    def phi(self) -> np.ndarray:
        """A copy of the last transition matrix Φ(k) (Eq. 6)."""
        phi = np.zeros((self.n, self.n))
        for i in range(self.blocks):
            c, s = self._cs[2 * i], self._cs[2 * i + 1]
            phi[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = ((c, s), (-s, c))
        return phi

    @property
    def Q(self) -> np.ndarray:
        """A copy of the process-noise covariance Q (Eq. 7)."""
        return np.diag(np.repeat(np.array(self._q, dtype=np.float64), 2))

    @property
    def C(self) -> np.ndarray:
        """A copy of the output row C = [1 0 1 0 ...] (Eq. 5)."""
        return np.tile(np.array([1.0, 0.0]), self.blocks)

    @property
    def kernel_source(self) -> str:
        """The generated source of this filter's step (for reading and debugging)."""
        return _paper_kernel_source(self.blocks)

    # ------------------------------------------------------------------- step
    def step(self, delta_T: float, velocity: float) -> float:
        """One interrupt: measurement y = ``delta_T`` (Nm), motor ``velocity`` (rad/s).

        Returns the ripple predicted for the next sample (listing
        ``T_ripple = Kalman(Delta_T, vel, sample_period)``).
        """
        return self._kernel(self, delta_T, velocity)


# ====================================================================== recommended mode
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
    return _compiled_step(_kernel_source(harmonics), f"<HarmonicKalman kernel, {harmonics}>")


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
    harmonics (see :func:`_kernel_source`), like the paper filter's; ``hdhil bench``'s
    stage table has the time of both.
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
        # The kernel bound as this instance's ``step`` (as in :class:`RippleKalman`).
        self.step = MethodType(self._kernel, self)  # type: ignore[method-assign]
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
        return _symmetric(self._P, self.n)

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
