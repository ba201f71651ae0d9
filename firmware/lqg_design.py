"""LQG joint-torque control of a flexible joint ([Vertechy]: Vertechy et al., "Linear-
Quadratic-Gaussian Torque Control: Application to a Flexible Joint of a Rehabilitation
Exoskeleton", [Vertechy]).

Offline design, pure numerics: Riccati equations, discretisation, loop analysis; no
CAN, no plant.  The runtime controller that runs a design once per sample
(observer update + control law) is :class:`firmware.lqg.LqgController`.

Sign convention (kept exactly as in the seed, inside this module only)
----------------------------------------------------------------------
[Vertechy] §II defines the sensor torque as ``tau_s = k (theta_l - theta_m)``: a
*positive* motor torque ``tau_m`` winds the spring the other way and makes ``tau_s``
*negative* (``B`` below has ``-k/Jm``).  To hold ``tau_s = tau_s^D`` (Eq. 2 at
equilibrium) the motor therefore has to deliver
``tau_m = -(1 + Jm/Jl) tau_s^D + (Jm/Jl) tau_lgd``,
which is why the seed's k4 (Eq. 4: ``tau_m = -[... + k4 tau_s^D]``) is positive.
Every torque handed to or returned by this module (``tau_s``, ``tau_s^D``, ``tau_lgd``,
``tau_m``, ``tau_d``) is in that convention, reduced to the output shaft.
``hostsim.plant`` reports ``T_true = -tau_s`` (positive when the motor drives the
load), so a caller working in the plant's convention passes
``tau_s_measured = -T_meas`` and ``tau_sD = -T_desired`` and applies the returned
``tau_m`` unchanged (the motor torque has the same sign in both conventions).

Model ([Vertechy] Eqs. 1-3, 7)
----------------------------
Two-mass joint reduced to the output shaft (Jm, Jl, k, c), ``J = Jm Jl / (Jm + Jl)``::

    tau_s'' + (c/J) tau_s' + (k/J) tau_s = (k/Jl) tau_lgd - (k/Jm) tau_m      (Eq. 2)
    tau_lgd = tau_l + tau_g - tau_d Jl/Jm

Control design model (Eq. 3), error state ``e = [tau_s - tau_s^D, tau_s']``, exogenous
input ``tau_0 = [tau_lgd, tau_s^D]`` with ``tau_0' = 0``::

    e' = A e + B tau_m + E tau_0
    A = [[0, 1], [-k/J, -c/J]],  B = [0, -k/Jm]ᵀ,  E = [[0, 0], [k/Jl, -k/J]]

Observer meta-system (Eq. 7), meta-state ``x = [tau_s, tau_s', tau_lgd]``,
``tau_lgd' = v`` (Wiener process of intensity V), ``y = tau_s^m = C x + w``
(variance W)::

    A' = [[0, 1, 0], [-k/J, -c/J, k/Jl], [0, 0, 0]],  B' = [0, -k/Jm, 0]ᵀ,
    Γ = [0, 0, 1]ᵀ,  C = [1, 0, 0]

The reading of the seed that reproduces its printed numbers (§VI)
-----------------------------------------------------------------
**LQ gains (Eqs. 4, 6).**  The printed gains come out of the CARE when the weights
enter *linearly*, ``Q = diag(q1, q2)``, ``R = 1``, i.e. the cost actually minimised is
``∫ q1 (tau_s - tau_s^D)² + q2 tau_s'² + tau_m² dt`` — not the ``q1², q2²`` printed in
Eq. 6.  With ``G = R⁻¹BᵀP`` and ``u = tau_m = -G e - G0 tau_0`` the seed's gains are
``[k1, k2] = G`` and ``[k3, k4] = G0`` with the sign of Eq. 4 as printed, and G0 is
Friedland's steady-state gain for exogenous inputs (ref. [26]): the costate
``λ = P e + N tau_0`` with ``tau_0' = A0 tau_0`` gives
``(A - B G)ᵀ N + N A0 + P E = 0``, ``G0 = R⁻¹ Bᵀ N``; for ``A0 = 0``
``G0 = -R⁻¹ Bᵀ (A - B G)⁻ᵀ P E``.  With the seed's Jm, Jl, k, c, q1, q2 this gives
``k1..k4 = -18.252, -0.32990, -2.8561, 3.6558`` against the printed
``-18.3, -0.33, -2.81, 3.62`` (-0.26 %, -0.03 %, +1.6 %, +1.0 %).

Readings that do *not* reproduce the numbers:

- ``Q = diag(q1², q2²)`` (Eq. 6 as printed): ``k1..k4 = -495.4, -0.626, -3.54, 4.53``.
- ``G0 = +R⁻¹Bᵀ(Aᵀ - PBR⁻¹Bᵀ)⁻¹PE`` (the sign-flipped costate solution):
  ``k3, k4 = +2.86, -3.66`` (wrong signs).
- Zero-steady-state-error feedforward ``G0 = B⁺E`` (``k3 = -Jm/Jl``,
  ``k4 = 1 + Jm/Jl``): ``-3.571, 4.571`` (27 % off); offered as
  :attr:`Feedforward.EXACT`.
- A discrete-time LQ design at Ts = 1 ms (DARE on the ZOH model):
  ``k1..k4 = -10.6, -0.224, -3.09, 3.96``.

The residual 1-1.6 % on k3, k4 is not rounding of the *gains*: any G0 of this form has
``k3/k4 = E[1,0]/E[1,1] = -Jm/(Jm+Jl) = -0.78125`` exactly, while the printed values
give -0.7762 (at most -0.7787 allowing for their rounding).  It is the parameters: with
``Jl = 0.7125`` kg m² instead of the rounded 0.7 (nothing else changed) all four gains
*and* the three Kalman gains below are reproduced within 0.22 %.

Consequence (documented, tested): the LQ feedforward is the optimal *compromise*
between error and effort, not a zero-error feedforward.  The closed-loop equilibrium
for constant ``tau_0`` is the minimiser of ``eᵀQe + uᵀRu`` subject to
``A e + B u + E tau_0 = 0`` (the costate's stationarity conditions are exactly the KKT
conditions of that static problem), so with the seed's weights the static error is
``e = -0.0401 tau_s^D + 0.0313 tau_lgd`` (about -0.9 % of ``tau_s^D`` when the link is
at rest, ``tau_lgd = tau_s``).  Zero static error needs ``k3 = -Jm/Jl`` and
``k4 = Jm/J = 1 + Jm/Jl`` whatever k1, k2 are (equilibrium of Eq. 3 with ``e = 0``):
JTF2's k4 is exactly that, with k3 = 0 (no disturbance compensation); JTF3's ``k4 = 1``
leaves an error even without disturbance.

**Kalman gain (Eq. 8).**  ``L = P Cᵀ W⁻¹`` from the filter CARE
``A'P + PA'ᵀ - P Cᵀ W⁻¹ C P + Γ V Γᵀ = 0`` with W = 0.12 and V = 1e4 taken as numbers
in one and the same convention gives ``L = [199.99, 19997.8, 288.68]`` against the
printed ``[199, 19854, 289]`` (+0.5 %, +0.7 %, -0.1 %; ``L3 = sqrt(V/W)``).  W as a
standard deviation (variance 0.0144) gives ``[332, 55028, 833]``; V as a standard
deviation (1e8) gives ``[1243, 772301, 28868]``.

**One reading of W (the only one in this project).**  [Vertechy] §I: "torque sensor
variance W = 0.12 Nm (measured with the motor driver turned on)".  W is the variance
of each torque sample, 0.12 Nm², measured on the sampled signal at the loop's 1 kHz
(:data:`W_SAMPLE_PERIOD_S`; the seed does not state its rate, 1 ms is the rig's).  The
emulated sensor of a "seed noise" variant therefore has a standard deviation of
``sqrt(W) = 0.3464`` Nm per sample (``hostsim.plant.SensorConfig.torque_noise_Nm``).
The continuous filter of Eq. 8 needs intensities: white noise whose 1 ms samples have
variance W has intensity ``W · 1 ms`` (Nm² s), and the seed's V is read in the same
convention, ``V · 1 ms``.  The Kalman gain L depends on V/W only, so L is the printed
one under this reading too, and the discrete filter at any Ts (``Rd = W · 1 ms / Ts``,
Van Loan ``Qd`` from ``V · 1 ms``) has exactly the gain it has with W and V taken as
bare intensities (a common factor on Qd and Rd does not change a DARE's gain).  At
Ts = 1 ms, ``Rd = W``: the design assumes the very noise the emulated sensor has, and
its predicted innovation variance (0.147 Nm²) is what a run measures (tested).  A
1000x different reading, a per-sample Rd = W next to V taken as an intensity, is the
design with V = 1e7 (as :data:`firmware.config.JTF1_FF_TRACKING` chooses explicitly).

Discretisation for the 1 kHz loop
---------------------------------
k1..k5 are static gains and are used as they are.  The observer (Eq. 8) is a
continuous filter; :func:`discretize_observer` offers two discrete versions, both in
the form (``z`` = a-priori estimate of x at sample k from the samples before k)::

    x̂(k)   = z(k) + M (y(k) - C z(k))                   current estimate (used by Eq. 4)
    z(k+1) = Ad z(k) + Bd [tau_m(k); y(k)]              tau_m(k): torque acting on [t_k, t_k+1)

- ``zoh-kalman`` (default): the meta-system (A', B', Γ) discretised by zero-order hold,
  process noise ``Qd = ∫_0^Ts e^{A's} Γ V' Γᵀ e^{A'ᵀs} ds`` (Van Loan) with ``V' = V ·
  1 ms``, measurement noise ``Rd = W · 1 ms / Ts`` (the per-sample variance at Ts of
  the white noise whose 1 ms samples have variance W: "One reading of W"), steady-state
  gain from the DARE: ``M = P Cᵀ (C P Cᵀ + Rd)⁻¹``, ``Ad = Φ (I - M C)``,
  ``Bd = [Γu, Φ M]``.  Its poles map onto the continuous observer poles
  (-55.6 ± 143.1j, -110.3 rad/s, i.e. |s| ≈ 24 Hz and 18 Hz, far below the 500 Hz
  Nyquist frequency) to better than 1e-6 relative.
- ``zoh-observer``: the continuous observer itself, ``(A' - L C, [B', L])``, discretised
  by ZOH with ``y`` held over the sample (``M = 0``): exactly the seed's L, an extra
  half-sample of lag on ``y``; same poles as above (``exp(s Ts)``).

Actuation delay.  With synchronous PDOs the command computed from the sample at
``t(k)`` acts from ``t(k+1)`` (docs/design.md, timing semantics).  :class:`LqgController`
feeds its observer the torque actually acting in each interval (the previous command
when ``delay_samples = 1``) and, with ``predict=True`` (default), applies Eq. 4 to the
one-step prediction ``z(k+1)`` — the state when the command takes effect.
:func:`loop_analysis` gives the discrete closed-loop poles and margins.

Robustness: the link is not always free.  The separation principle covers the plant
of Eq. 2 with ``tau_lgd`` exogenous.  When the link is held (stiff contact, a user
gripping the handle) ``tau_lgd = tau_s + (c/k) tau_s' + Jl theta_l''`` depends on the
state and the disturbance estimate closes another loop: with the link clamped the seed's
design (V = 1e4) is still stable at 1 kHz with one sample of delay, but only just
(max |z| = 0.9924, gain margin 3.5 dB, phase margin 22 deg); V = 5e3 is marginal
(0.9998) and V <= 3e3 is unstable, for JTF3 too, and also without delay at 100 kHz, so
this is a property of the seed's design, not of the discretisation.
:func:`loop_analysis` ``clamped=True`` and the CLI report it.

Seed §VI simulation (Fig. 7: ``tau_s^D = 20 sin(0.4 pi t)``, link moved as
``theta_l = 20 deg sin(2 pi t)``, no noise), reproduced in the tests with this
module's observer at 1 kHz: max |e| is about 1.2 Nm for JTF1, 2.1 for JTF3, 5.4 for
JTF2 -- the seed's ranking, but not its "|e| <= 0.3 Nm" (true states instead of the
observer still give 0.73 Nm; the zero-error feedforward 0.38 Nm).  With the link held
still JTF1 gives 0.18 Nm.

Desired-torque-derivative feedforward (seed §IV, "more demanding applications")
-------------------------------------------------------------------------------
``e = [tau_s - tau_s^D, tau_s' - tau_s^D']``, ``tau_0 = [tau_lgd, tau_s^D, tau_s^D']``,
``E = [[0, 0, 0], [k/Jl, -k/J, -c/J]]`` (``tau_s^D'' ≈ 0``), ``tau_0' = 0`` as in Eq.
3.2: same A, B, Q so k1, k2 (and k3, k4) are unchanged, and
``k5 = G0[2] = k4 c / k`` (0.00685 s for the seed).  The law is
``tau_m = -[k1 (tau_s - tau_s^D) + k2 (tau_s' - tau_s^D') + k3 tau_lgd + k4 tau_s^D
+ k5 tau_s^D']``.  (Modelling ``tau_s^D`` as a ramp instead, ``A0`` with
``(tau_s^D)' = tau_s^D'``, would give k5 = -0.0050 s; the zero-error value is
``Jm c / (J k)`` = 0.00856 s.)  Caveat: the feedforward relies on ``τ̂s'``, which the
observer gets wrong at low frequency whenever ``tau_lgd`` drifts (a lag ``δ`` in
``τ̂lgd`` comes with an error ``(k J / (c Jl)) δ`` ≈ 417 δ in ``τ̂s'``, the direction
the measurement cannot resolve at DC).  On a free link (``tau_lgd`` constant) it cuts
the ramp-tracking error more than tenfold; with the link held still, where
``tau_lgd`` follows ``tau_s``, it makes the §VI sine tracking worse (0.18 -> 0.44 Nm).

Motor torque saturation is the caller's job: clip the returned command and report the
clipped value with :meth:`LqgController.set_applied` so the observer is fed the torque
that really acts.
"""

from __future__ import annotations

import cmath
import enum
import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.linalg import LinAlgError  # the class scipy.linalg raises too

from hdhil.core.dataconf import check_fields


def _linalg() -> Any:
    """:mod:`scipy.linalg`, imported when a design is computed: it is slow to import,
    and a firmware without a control law never needs it."""
    import scipy.linalg

    return scipy.linalg


__all__ = [
    "W_SAMPLE_PERIOD_S",
    "ControlLaw",
    "DesignError",
    "DiscreteObserver",
    "Feedforward",
    "JointParams",
    "LoopAnalysis",
    "LqGains",
    "LqgDesign",
    "LqgWeights",
    "ObserverMethod",
    "design_kalman",
    "design_lq",
    "design_lqg",
    "discretize_observer",
    "error_model",
    "gains_for_law",
    "jtf2_gains",
    "jtf3_gains",
    "kalman_riccati",
    "loop_analysis",
    "lq_riccati",
    "observer_model",
    "zoh",
]

#: The sample period at which the seed's torque-sensor variance W is read (s): W is the
#: variance of each 1 kHz sample (module docstring, "One reading of W").
W_SAMPLE_PERIOD_S = 1e-3


class DesignError(ValueError):
    """The design problem has no stabilising solution (not stabilisable/detectable)."""


class ControlLaw(enum.Enum):
    """Joint-torque-feedback laws compared in [Vertechy] (§IV, Fig. 7)."""

    #: Eq. 4 (or Eq. 5 with a motor-disturbance model): LQ gains k1..k4.
    JTF1 = "jtf1"
    #: Eq. 4 with the desired-torque-derivative feedforward of §IV (k2 on
    #: ``tau_s' - tau_s^D'`` and the extra gain k5 on ``tau_s^D'``).
    JTF1_FF = "jtf1_ff"
    #: PD JTF of refs. [17, 18]: k3 = 0, k4 = 1 + Jm/Jl (k1, k2 as JTF1).
    JTF2 = "jtf2"
    #: PD JTF of refs. [19, 20]: k3 = 0, k4 = 1 (k1, k2 as JTF1).
    JTF3 = "jtf3"


class ObserverMethod(enum.Enum):
    """How the continuous observer of Eq. 8 becomes a 1 kHz filter (module docstring)."""

    ZOH_KALMAN = "zoh-kalman"
    ZOH_OBSERVER = "zoh-observer"


class Feedforward(enum.Enum):
    """How k3, k4, k5 (the gains on the exogenous inputs) are chosen."""

    #: Friedland's steady-state LQ gain for exogenous inputs (reproduces the seed).
    LQ = "lq"
    #: Zero steady-state error: ``G0 = B⁺E`` (k3 = -Jm/Jl, k4 = 1 + Jm/Jl, k5 = Jm c/(J k)).
    EXACT = "exact"


@dataclass(frozen=True)
class JointParams:
    """Flexible-joint parameters, all reduced to the output shaft ([Vertechy] §I-II).

    Attributes:
        Jm: motor-side inertia [kg m²]; [Vertechy] §I, AG1 "motor shaft inertia reduced
            to the joint output shaft J_m = 2.5 Kgm²".
        Jl: link-side inertia [kg m²]; [Vertechy] §I, test-rig link "J_l = 0.7 Kg m²".
        k: joint torsional stiffness [Nm/rad]; [Vertechy] §I, "k = 6.3 kNm/rad".
        c: joint damping [Nms/rad]; [Vertechy] §II, half-power bandwidth, "c = 11.8".
    """

    Jm: float = 2.5
    Jl: float = 0.7
    k: float = 6300.0
    c: float = 11.8

    def __post_init__(self) -> None:
        check_fields(self, {"Jm": ">0", "Jl": ">0", "k": ">0", "c": ">=0"})

    @property
    def J(self) -> float:
        """Reduced inertia ``J = Jm Jl / (Jm + Jl)`` ([Vertechy], after Eq. 2) [kg m²]."""
        return self.Jm * self.Jl / (self.Jm + self.Jl)

    @property
    def natural_frequency_hz(self) -> float:
        """``sqrt(k/J) / 2π`` ([Vertechy] §II: "≈ 17 Hz" for the defaults) [Hz]."""
        return math.sqrt(self.k / self.J) / (2.0 * math.pi)


@dataclass(frozen=True)
class LqgWeights:
    """Tuning of the LQG regulator ([Vertechy] §IV-VI).

    Attributes:
        q1: weight on ``(tau_s - tau_s^D)²`` (seed: 500).  Enters Q *linearly*, see the
            module docstring (Eq. 6 prints ``q1²`` but the printed gains need ``q1``).
        q2: weight on ``tau_s'²`` (seed: 0.1), linearly as q1.
        W: variance of each 1 kHz torque sample (seed §I: "torque sensor variance
            W = 0.12") [Nm²]; the emulated sensor's noise is ``sqrt(W)`` per sample
            (module docstring, "One reading of W").
        V: the Wiener process ``tau_lgd' = v`` in the same convention (seed §VI:
            V = 1e4); only V/W sets the Kalman gain.
    """

    q1: float = 500.0
    q2: float = 0.1
    W: float = 0.12
    V: float = 1e4

    def __post_init__(self) -> None:
        check_fields(self, {"q1": ">=0", "q2": ">=0", "W": ">0", "V": ">0"})


@dataclass(frozen=True)
class LqGains:
    """Gains of Eq. 4: ``tau_m = -[k1 (τ̂s - τsD) + k2 τ̂s' + k3 τ̂lgd + k4 τsD]``.

    ``k5`` multiplies ``tau_s^D'`` in the feedforward variant (:attr:`ControlLaw.JTF1_FF`,
    where k2 acts on ``τ̂s' - τsD'``); it is ignored by the other laws.
    """

    k1: float
    k2: float
    k3: float
    k4: float
    k5: float = 0.0

    def as_dict(self) -> dict[str, float]:
        return {"k1": self.k1, "k2": self.k2, "k3": self.k3, "k4": self.k4, "k5": self.k5}


# --------------------------------------------------------------------------- models


def error_model(
    params: JointParams, derivative_ff: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(A, B, E)`` of [Vertechy] Eq. 3.3 (``E`` gains a column ``-c/J`` on ``τsD'``
    when ``derivative_ff``, the §IV variant with ``e2 = τs' - τsD'``)."""
    p = params
    kj = p.k / p.J
    A = np.array([[0.0, 1.0], [-kj, -p.c / p.J]])
    B = np.array([[0.0], [-p.k / p.Jm]])
    E = np.array([[0.0, 0.0], [p.k / p.Jl, -kj]])
    if derivative_ff:
        E = np.hstack([E, np.array([[0.0], [-p.c / p.J]])])
    return A, B, E


def observer_model(params: JointParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(A', B', Γ, C)`` of the observer meta-system, [Vertechy] Eq. 7.2."""
    p = params
    Ap = np.array([[0.0, 1.0, 0.0], [-p.k / p.J, -p.c / p.J, p.k / p.Jl], [0.0, 0.0, 0.0]])
    Bp = np.array([[0.0], [-p.k / p.Jm], [0.0]])
    G = np.array([[0.0], [0.0], [1.0]])
    C = np.array([[1.0, 0.0, 0.0]])
    return Ap, Bp, G, C


def zoh(A: np.ndarray, B: np.ndarray, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order-hold discretisation ``(e^{A Ts}, ∫_0^Ts e^{A s} ds B)`` (one expm)."""
    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n] = A
    M[:n, n:] = B
    F = _linalg().expm(M * Ts)
    return F[:n, :n], F[:n, n:]


def _check_Ts(Ts: float) -> None:
    if isinstance(Ts, bool) or not isinstance(Ts, (int, float)) or not (math.isfinite(Ts)):
        raise ValueError(f"Ts must be a finite number, got {Ts!r}")
    if Ts <= 0:
        raise ValueError(f"Ts must be > 0, got {Ts!r}")


# --------------------------------------------------------------------------- LQ design


def _care_residual(A: np.ndarray, S: np.ndarray, Q: np.ndarray, P: np.ndarray) -> float:
    """Entry-wise relative residual of ``AᵀP + PA - PSP + Q = 0``."""
    terms = (A.T @ P, P @ A, P @ S @ P, Q)
    res = terms[0] + terms[1] - terms[2] + terms[3]
    return float(np.max(np.abs(res) / (sum(np.abs(t) for t in terms) + 1e-300)))


def _solve_care(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``solve_continuous_are`` plus one Newton-Kleinman step.

    On lightly damped, very stiff joints scipy's Schur solution leaves a relative
    residual up to ~1e-6; one Newton step (``Acl = A - S P``,
    ``Aclᵀ X + X Acl = -(Q + P S P)``) brings it to ~1e-9.  The step is kept only if it
    lowers the residual.
    """
    with warnings.catch_warnings():
        # scipy warns (and perturbs) on Hamiltonian eigenvalues on the imaginary axis;
        # the callers check the result is stabilising and raise DesignError otherwise.
        warnings.simplefilter("ignore", RuntimeWarning)
        P = _linalg().solve_continuous_are(A, B, Q, R)
    S = B @ np.linalg.solve(R, B.T)
    Acl = A - S @ P
    X = _linalg().solve_continuous_lyapunov(Acl.T, -(Q + P @ S @ P))
    X = 0.5 * (X + X.T)
    if np.all(np.isfinite(X)) and _care_residual(A, S, Q, X) < _care_residual(A, S, Q, P):
        return X
    return 0.5 * (P + P.T)


def lq_riccati(params: JointParams, weights: LqgWeights) -> np.ndarray:
    """Stabilising solution P of ``AᵀP + PA - PBR⁻¹BᵀP + Q = 0`` with
    ``Q = diag(q1, q2)``, ``R = 1`` ([Vertechy] Eqs. 3, 6; weights linear, see module doc).

    Raises :class:`DesignError` when (A, Q^½) is not detectable (``q1 = q2 = 0`` on an
    undamped joint) or the solver fails.
    """
    A, B, _ = error_model(params)
    Q = np.diag([weights.q1, weights.q2])
    R = np.eye(1)
    if weights.q1 == 0 and weights.q2 == 0 and params.c == 0:
        # (A, Q^½) detectable iff some weight is positive or the joint is damped.
        raise DesignError("LQ problem not detectable: q1 = q2 = 0 on an undamped joint (c = 0)")
    try:
        P = _solve_care(A, B, Q, R)
    except (LinAlgError, ValueError) as exc:
        raise DesignError(f"LQ Riccati equation has no stabilising solution ({exc})") from None
    G = B.T @ P
    tol = 1e-12 * np.linalg.norm(A)
    if not np.all(np.isfinite(P)) or np.max(np.linalg.eigvals(A - B @ G).real) >= -tol:
        raise DesignError(
            "LQ design is not stabilising (weights q1 = q2 = 0 on an undamped joint?)"
        )
    return P


def _exogenous_gain(
    Acl: np.ndarray, B: np.ndarray, P: np.ndarray, E: np.ndarray, A0: np.ndarray | None = None
) -> np.ndarray:
    """Friedland's steady-state gain on exogenous inputs ([Vertechy] ref. [26]).

    For ``e' = A e + B u + E x0``, ``x0' = A0 x0`` and cost ``∫ eᵀQe + uᵀRu`` (R = 1),
    the costate ``λ = P e + N x0`` gives ``Aclᵀ N + N A0 + P E = 0`` and
    ``u = -G e - G0 x0`` with ``G0 = Bᵀ N``.
    """
    if A0 is None:
        A0 = np.zeros((E.shape[1], E.shape[1]))
    N = _linalg().solve_sylvester(Acl.T, A0, -P @ E)
    return (B.T @ N).ravel()


def design_lq(
    params: JointParams = JointParams(),
    weights: LqgWeights = LqgWeights(),
    *,
    feedforward: Feedforward = Feedforward.LQ,
) -> LqGains:
    """LQ gains k1..k5 of [Vertechy] Eqs. 4 and 6 (and the §IV τsD' feedforward k5).

    ``[k1, k2] = R⁻¹BᵀP`` from :func:`lq_riccati`; ``[k3, k4, k5]`` from Friedland's
    exogenous-input solution (``Feedforward.LQ``, reproduces the seed) or the
    zero-static-error feedforward ``B⁺E`` (``Feedforward.EXACT``).
    """
    A, B, _ = error_model(params)
    E = error_model(params, derivative_ff=True)[2]
    P = lq_riccati(params, weights)
    G = (B.T @ P).ravel()
    if feedforward is Feedforward.LQ:
        G0 = _exogenous_gain(A - B @ G[None, :], B, P, E)
    else:
        G0 = (np.linalg.pinv(B) @ E).ravel()
    return LqGains(*(float(v) for v in (G[0], G[1], G0[0], G0[1], G0[2])))


def jtf2_gains(params: JointParams = JointParams(), weights: LqgWeights = LqgWeights()) -> LqGains:
    """JTF2 of [Vertechy] §IV (refs. [17, 18]): k3 = 0, k4 = 1 + Jm/Jl.

    k1, k2 are taken from the LQ design (the seed compares the laws with the same
    feedback part, Fig. 7); k4 = 1 + Jm/Jl = Jm/J is the zero-error feedforward on τsD.
    """
    g = design_lq(params, weights)
    return LqGains(g.k1, g.k2, 0.0, 1.0 + params.Jm / params.Jl, 0.0)


def jtf3_gains(params: JointParams = JointParams(), weights: LqgWeights = LqgWeights()) -> LqGains:
    """JTF3 of [Vertechy] §IV (refs. [19, 20]): k3 = 0, k4 = 1 (k1, k2 from the LQ design)."""
    g = design_lq(params, weights)
    return LqGains(g.k1, g.k2, 0.0, 1.0, 0.0)


def gains_for_law(
    law: ControlLaw,
    params: JointParams = JointParams(),
    weights: LqgWeights = LqgWeights(),
    feedforward: Feedforward = Feedforward.LQ,
) -> LqGains:
    """The gain set a :class:`ControlLaw` uses (k5 zeroed unless ``JTF1_FF``)."""
    if law is ControlLaw.JTF2:
        return jtf2_gains(params, weights)
    if law is ControlLaw.JTF3:
        return jtf3_gains(params, weights)
    g = design_lq(params, weights, feedforward=feedforward)
    return g if law is ControlLaw.JTF1_FF else LqGains(g.k1, g.k2, g.k3, g.k4, 0.0)


# --------------------------------------------------------------------------- Kalman design


def kalman_riccati(params: JointParams, W: float, V: float) -> np.ndarray:
    """Stabilising P of ``A'P + PA'ᵀ - PCᵀW⁻¹CP + ΓVΓᵀ = 0`` ([Vertechy] Eqs. 7-8)."""
    Ap, _, G, C = observer_model(params)
    if not (W > 0 and V > 0 and math.isfinite(W) and math.isfinite(V)):
        raise ValueError(f"need W > 0 and V > 0 (finite), got W={W!r}, V={V!r}")
    try:
        P = _solve_care(Ap.T, C.T, V * (G @ G.T), np.array([[W]]))
    except (LinAlgError, ValueError) as exc:
        raise DesignError(f"Kalman Riccati equation has no stabilising solution ({exc})") from None
    L = P @ C.T / W
    tol = 1e-12 * np.linalg.norm(Ap)
    if not np.all(np.isfinite(P)) or np.max(np.linalg.eigvals(Ap - L @ C).real) >= -tol:
        raise DesignError("Kalman Riccati equation has no stabilising solution")
    return P


def design_kalman(
    params: JointParams = JointParams(), W: float = 0.12, V: float = 1e4
) -> np.ndarray:
    """Steady-state continuous Kalman gain ``L = P Cᵀ W⁻¹`` of Eq. 8 (shape (3,))."""
    P = kalman_riccati(params, W, V)
    C = observer_model(params)[3]
    return (P @ C.T).ravel() / W


@dataclass(frozen=True, eq=False)
class DiscreteObserver:
    """Discrete form of the observer of [Vertechy] Eq. 8 (see module docstring)::

        x̂(k)   = z(k) + M (y(k) - C z(k))
        z(k+1) = Ad z(k) + Bd [tau_m(k); y(k)]

    Attributes:
        method: how it was obtained.
        Ts: sample period [s].
        Ad: (3, 3) a-priori state transition.
        Bd: (3, 2) input matrix, columns: motor torque acting over the interval, sample y.
        C: (1, 3) output ``[1, 0, 0]``.
        M: (3,) measurement-update gain of the current estimate (0 for ``zoh-observer``).
        Phi, Gamma_u: ZOH model of the meta-system (``z(k+1) = Phi x̂(k) + Gamma_u tau_m``
            for ``zoh-kalman``).
    """

    method: ObserverMethod
    Ts: float
    Ad: np.ndarray
    Bd: np.ndarray
    C: np.ndarray
    M: np.ndarray
    Phi: np.ndarray
    Gamma_u: np.ndarray

    @property
    def poles(self) -> np.ndarray:
        """Eigenvalues of Ad (z-plane)."""
        return np.linalg.eigvals(self.Ad)

    @property
    def poles_s(self) -> np.ndarray:
        """``log(z) / Ts``: the continuous-time equivalents of :attr:`poles` [rad/s]."""
        return np.log(self.poles.astype(complex)) / self.Ts


def discretize_observer(
    params: JointParams = JointParams(),
    *,
    W: float = 0.12,
    V: float = 1e4,
    Ts: float = 1e-3,
    method: ObserverMethod = ObserverMethod.ZOH_KALMAN,
    L: np.ndarray | None = None,
) -> DiscreteObserver:
    """The 1 kHz observer (module docstring, "Discretisation").

    ``zoh-kalman``: DARE on the ZOH meta-system with Van Loan ``Qd`` from the intensity
    ``V · 1 ms`` and ``Rd = W · 1 ms / Ts`` (W the per-sample variance at 1 kHz; module
    docstring, "One reading of W").  ``zoh-observer``: ZOH of ``(A' - L C, [B', L])``
    with ``L`` given or from :func:`design_kalman`.
    """
    _check_Ts(Ts)
    method = ObserverMethod(method)
    Ap, Bp, G, C = observer_model(params)
    Phi, Gu = zoh(Ap, Bp, Ts)
    if method is ObserverMethod.ZOH_OBSERVER:
        Lc = design_kalman(params, W, V) if L is None else np.asarray(L, float).reshape(3)
        Ad, Bd = zoh(Ap - np.outer(Lc, C[0]), np.hstack([Bp, Lc[:, None]]), Ts)
        M = np.zeros(3)
    else:
        if not (W > 0 and V > 0):
            raise ValueError(f"need W > 0 and V > 0, got W={W!r}, V={V!r}")
        # Van Loan: expm([[-A', ΓVΓᵀ], [0, A'ᵀ]] Ts) = [[., F12], [0, Φᵀ]], Qd = Φ F12
        vl = np.zeros((6, 6))
        vl[:3, :3] = -Ap
        vl[:3, 3:] = V * W_SAMPLE_PERIOD_S * (G @ G.T)
        vl[3:, 3:] = Ap.T
        F = _linalg().expm(vl * Ts)
        Qd = Phi @ F[:3, 3:]
        Qd = 0.5 * (Qd + Qd.T)
        Rd = W * W_SAMPLE_PERIOD_S / Ts
        try:
            P = _linalg().solve_discrete_are(Phi.T, C.T, Qd, np.array([[Rd]]))
        except (LinAlgError, ValueError) as exc:
            raise DesignError(f"discrete Kalman Riccati equation failed ({exc})") from None
        M = (P @ C.T).ravel() / float((C @ P @ C.T)[0, 0] + Rd)
        Ad = Phi @ (np.eye(3) - np.outer(M, C[0]))
        Bd = np.hstack([Gu, (Phi @ M)[:, None]])
    return DiscreteObserver(method, float(Ts), Ad, Bd, C, M, Phi, Gu)


# --------------------------------------------------------------------------- bundle


@dataclass(frozen=True, eq=False)
class LqgDesign:
    """Everything the LQG regulator of [Vertechy] needs, designed from params and weights.

    Build it with :func:`design_lqg`.
    """

    params: JointParams
    weights: LqgWeights
    gains: LqGains
    L: np.ndarray
    observer: DiscreteObserver
    feedforward: Feedforward = Feedforward.LQ
    lq_poles: np.ndarray = field(default_factory=lambda: np.zeros(0))
    observer_poles: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def Ts(self) -> float:
        return self.observer.Ts

    def gains_for(self, law: ControlLaw) -> LqGains:
        """Gains of ``law`` (JTF2/JTF3 keep k1, k2 of this design)."""
        g = self.gains
        if law is ControlLaw.JTF2:
            return LqGains(g.k1, g.k2, 0.0, 1.0 + self.params.Jm / self.params.Jl, 0.0)
        if law is ControlLaw.JTF3:
            return LqGains(g.k1, g.k2, 0.0, 1.0, 0.0)
        if law is ControlLaw.JTF1:
            return LqGains(g.k1, g.k2, g.k3, g.k4, 0.0)
        return g

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able data (complex poles as ``[re, im]`` pairs)."""
        ob = self.observer
        loop = loop_analysis(self, ControlLaw.JTF1, delay_samples=1, predict=True)
        return {
            "params": {
                "Jm": self.params.Jm,
                "Jl": self.params.Jl,
                "k": self.params.k,
                "c": self.params.c,
                "J": self.params.J,
                "natural_frequency_hz": self.params.natural_frequency_hz,
            },
            "weights": {
                "q1": self.weights.q1,
                "q2": self.weights.q2,
                "W": self.weights.W,
                "V": self.weights.V,
            },
            "feedforward": self.feedforward.value,
            **self.gains.as_dict(),
            "jtf2": self.gains_for(ControlLaw.JTF2).as_dict(),
            "jtf3": self.gains_for(ControlLaw.JTF3).as_dict(),
            "L": [float(v) for v in self.L],
            "Ts": ob.Ts,
            "method": ob.method.value,
            "Ad": ob.Ad.tolist(),
            "Bd": ob.Bd.tolist(),
            "C": ob.C.tolist(),
            "M": ob.M.tolist(),
            "poles": {
                "lq": _pairs(self.lq_poles),
                "observer": _pairs(self.observer_poles),
                "observer_discrete": _pairs(ob.poles),
                "observer_discrete_s": _pairs(ob.poles_s),
                "loop_delay1": _pairs(loop.poles),
            },
            "loop_delay1": loop.as_dict(),
        }


def _pairs(z: np.ndarray) -> list[list[float]]:
    return [[float(np.real(v)), float(np.imag(v))] for v in _sorted(z)]


def _sorted(z: np.ndarray) -> np.ndarray:
    z = np.asarray(z, complex)
    return z[np.lexsort((z.imag, z.real))]


def design_lqg(
    params: JointParams = JointParams(),
    weights: LqgWeights = LqgWeights(),
    *,
    Ts: float = 1e-3,
    method: ObserverMethod = ObserverMethod.ZOH_KALMAN,
    feedforward: Feedforward = Feedforward.LQ,
) -> LqgDesign:
    """LQ gains, continuous Kalman gain and the discrete observer at ``Ts``."""
    _check_Ts(Ts)
    gains = design_lq(params, weights, feedforward=feedforward)
    L = design_kalman(params, weights.W, weights.V)
    obs = discretize_observer(
        params,
        W=weights.W,
        V=weights.V,
        Ts=Ts,
        method=ObserverMethod(method),
        L=L,
    )
    A, B, _ = error_model(params)
    Ap, _, _, C = observer_model(params)
    lq_poles = np.linalg.eigvals(A - B @ np.array([[gains.k1, gains.k2]]))
    obs_poles = np.linalg.eigvals(Ap - np.outer(L, C[0]))
    return LqgDesign(params, weights, gains, L, obs, Feedforward(feedforward), lq_poles, obs_poles)


# --------------------------------------------------------------------------- loop analysis


@dataclass(frozen=True, eq=False)
class LoopAnalysis:
    """Discrete closed loop (plant ZOH at Ts, actuation delay, observer, Eq. 4).

    Attributes:
        poles: closed-loop eigenvalues (z-plane); stable iff all ``|z| < 1``.
        gain_margin_db: smallest gain change (dB, from the phase crossovers of the loop
            broken at the plant input) that destabilises; ``inf`` if none.
        phase_margin_deg: smallest phase margin at a unity-gain crossover; ``inf`` if none.
        modulus_margin: ``min |1 + L(e^{jωTs})|`` over frequency (distance to -1).
    """

    poles: np.ndarray
    gain_margin_db: float
    phase_margin_deg: float
    modulus_margin: float

    @property
    def spectral_radius(self) -> float:
        return float(np.max(np.abs(self.poles)))

    @property
    def stable(self) -> bool:
        return self.spectral_radius < 1.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "spectral_radius": self.spectral_radius,
            "stable": self.stable,
            "gain_margin_db": _finite(self.gain_margin_db),
            "phase_margin_deg": _finite(self.phase_margin_deg),
            "modulus_margin": self.modulus_margin,
        }


def _finite(x: float) -> float | None:
    """``x``, or ``None`` (JSON ``null``) when infinite (no crossover)."""
    return x if math.isfinite(x) else None


def _controller_ss(
    design: LqgDesign, law: ControlLaw, delay_samples: int, predict: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """State space ``(Ak, Bk, Ck, Dk)`` of the compensator y -> tau_m (τsD = τlgd = 0)."""
    g = design.gains_for(law)
    K = np.array([g.k1, g.k2, g.k3])
    ob = design.observer
    C = ob.C[0]
    IMC = np.eye(3) - np.outer(ob.M, C)
    bu, by = ob.Bd[:, 0], ob.Bd[:, 1]
    if delay_samples == 0:
        cz, cy = -K @ IMC, float(-K @ ob.M)
        Ak = ob.Ad + np.outer(bu, cz)
        Bk = (by + bu * cy)[:, None]
        return Ak, Bk, cz[None, :], np.array([[cy]])
    # states [z, u_prev]: z⁺ = Ad z + bu u_prev + by y ; u_prev⁺ = u
    if predict:
        cz, cu, cy = -K @ ob.Ad, float(-K @ bu), float(-K @ by)
    else:
        cz, cu, cy = -K @ IMC, 0.0, float(-K @ ob.M)
    Ak = np.zeros((4, 4))
    Ak[:3, :3] = ob.Ad
    Ak[:3, 3] = bu
    Ak[3, :3] = cz
    Ak[3, 3] = cu
    Bk = np.zeros((4, 1))
    Bk[:3, 0] = by
    Bk[3, 0] = cy
    Ck = np.append(cz, cu)[None, :]
    return Ak, Bk, Ck, np.array([[cy]])


def loop_analysis(
    design: LqgDesign,
    law: ControlLaw = ControlLaw.JTF1,
    *,
    delay_samples: int = 1,
    predict: bool = True,
    plant: JointParams | None = None,
    clamped: bool = False,
    n_freq: int = 20000,
) -> LoopAnalysis:
    """Closed-loop poles and margins of the sampled LQG loop at ``design.Ts``.

    The plant is Eq. 2 (states ``[tau_s, tau_s']``, exogenous inputs zero) discretised by
    ZOH; the command computed at sample k acts from ``t(k + delay_samples)``; the
    compensator is :class:`LqgController`'s (same ``delay_samples`` and ``predict``).
    Margins: loop broken at the plant input, ``L(z) = -K(z) z^-d P(z)``.

    ``plant`` (default: the design's parameters) checks robustness to a different joint;
    ``clamped=True`` holds the link still (infinite load inertia, e.g. a stiff contact):
    then ``tau_s'' = -(k/Jm)(tau_s + tau_m) - (c/Jm) tau_s'`` and ``tau_lgd`` is no longer
    exogenous (``tau_lgd = tau_s + (c/k) tau_s'``), so the k3 feedback of its estimate
    closes an extra loop that the separation principle does not cover.
    """
    if delay_samples not in (0, 1):
        raise ValueError(f"delay_samples must be 0 or 1, got {delay_samples!r}")
    pp = design.params if plant is None else plant
    if clamped:
        A = np.array([[0.0, 1.0], [-pp.k / pp.Jm, -pp.c / pp.Jm]])
        B = np.array([[0.0], [-pp.k / pp.Jm]])
    else:
        A, B, _ = error_model(pp)
    Phi, Gam = zoh(A, B, design.Ts)
    Cp = np.array([[1.0, 0.0]])
    Ak, Bk, Ck, Dk = _controller_ss(design, law, delay_samples, predict)
    nk = Ak.shape[0]
    # closed loop, state [xp (2), xk (nk), d (delay_samples)]
    n = 2 + nk + delay_samples
    Acl = np.zeros((n, n))
    u_row = np.zeros(n)  # command as a function of the closed-loop state
    u_row[:2] = (Dk @ Cp).ravel()
    u_row[2 : 2 + nk] = Ck.ravel()
    Acl[2 : 2 + nk, :2] = Bk @ Cp
    Acl[2 : 2 + nk, 2 : 2 + nk] = Ak
    Acl[:2, :2] = Phi
    if delay_samples:
        Acl[:2, -1] = Gam[:, 0]
        Acl[-1, :] = u_row
    else:
        Acl[:2, :] += np.outer(Gam[:, 0], u_row)
    poles = np.linalg.eigvals(Acl)

    zs = np.exp(1j * np.linspace(1e-4, math.pi, n_freq))  # ω Ts from ~0 to Nyquist
    Kz = _freq_response(Ak, Bk, Ck, Dk, zs)
    Pz = _freq_response(Phi, Gam, Cp, np.zeros((1, 1)), zs)
    Lw = -Kz * Pz * zs ** (-delay_samples)
    return LoopAnalysis(poles, *_margins(Lw), float(np.min(np.abs(1.0 + Lw))))


def _freq_response(
    A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, zs: np.ndarray
) -> np.ndarray:
    """SISO ``C (zI - A)⁻¹ B + D`` at every ``z`` in ``zs`` (batched solve)."""
    n = A.shape[0]
    M = zs[:, None, None] * np.eye(n) - A
    rhs = np.broadcast_to(B.astype(complex), (zs.size, n, 1))
    return (C @ np.linalg.solve(M, rhs))[:, 0, 0] + D[0, 0]


def _margins(Lw: np.ndarray) -> tuple[float, float]:
    gm = math.inf
    im = Lw.imag
    for i in np.nonzero(np.sign(im[:-1]) != np.sign(im[1:]))[0]:
        t = im[i] / (im[i] - im[i + 1])
        re = Lw[i].real + t * (Lw[i + 1].real - Lw[i].real)
        if re < 0:
            gm = min(gm, abs(20.0 * math.log10(-1.0 / re)))
    pm = math.inf
    mag = np.abs(Lw) - 1.0
    for i in np.nonzero(np.sign(mag[:-1]) != np.sign(mag[1:]))[0]:
        t = mag[i] / (mag[i] - mag[i + 1])
        zc = Lw[i] + t * (Lw[i + 1] - Lw[i])
        ph = math.degrees(cmath.phase(zc))  # in (-180, 180]
        pm = min(pm, 180.0 - abs(ph))
    return gm, pm
