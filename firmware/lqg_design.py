"""LQG joint-torque control of a flexible joint ([Vertechy]): the offline design.

Pure numerics, no CAN and no plant: the LQ gains k1..k5 from the continuous Riccati
equation of the error model (Eq. 3) with Friedland's steady-state gains on the constant
exogenous inputs (:func:`design_lq`), the steady-state Kalman gain L of the observer
meta-system (Eq. 7), its discretisation for the 1 kHz loop (:func:`discretize_observer`:
``zoh-kalman``, the default, or ``zoh-observer``), and the closed loop with one sample of
actuation delay, also with the link clamped (:func:`loop_analysis`).  The runtime
controller that runs a design once per sample is :class:`firmware.lqg.LqgController`.

Torques handed to or returned by this module are in [Vertechy]'s sign convention
(``tau_s = k (theta_l - theta_m)``), reduced to the output shaft; ``firmware.isr`` maps
the product convention onto it.  The weights enter as Q = diag(q1, q2), R = 1: the
reading that reproduces the printed gains.  One reading of W: W = 0.12 Nm is the
standard deviation of each 1 kHz torque sample, as its unit says (the emulated sensor's
noise); Eq. 8 takes the number W where the measurement-noise covariance goes, and so does
the design, with V in the same convention: L depends on V/W only and is the printed one.
The filter is thus designed for 0.12 Nm² where the sensor has 0.0144 Nm².  The model,
the readings that do not reproduce the paper, and why its tracking figure does not
reproduce are in docs/papers.md.
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

#: The sample period at which [Vertechy]'s torque-sensor W is read (s): W is per 1 kHz
#: sample (module docstring, "One reading of W").
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
    """How the continuous observer of Eq. 8 becomes a 1 kHz filter (docs/papers.md)."""

    ZOH_KALMAN = "zoh-kalman"
    ZOH_OBSERVER = "zoh-observer"


class Feedforward(enum.Enum):
    """How k3, k4, k5 (the gains on the exogenous inputs) are chosen."""

    #: Friedland's steady-state LQ gain for exogenous inputs (reproduces the paper).
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
        q1: weight on ``(tau_s - tau_s^D)²`` ([Vertechy]: 500).  Enters Q *linearly*, see
            docs/papers.md (Eq. 6 prints ``q1²`` but the printed gains need ``q1``).
        q2: weight on ``tau_s'²`` ([Vertechy]: 0.1), linearly as q1.
        W: the measurement-noise weight of Eq. 8 ([Vertechy] §I: "torque sensor variance
            W = 0.12 Nm"), entered where Eq. 8 puts it; the emulated sensor's noise has
            the standard deviation W per sample (module docstring, "One reading of W").
            ``W = 0.0144`` (0.12²) designs the filter matched to that sensor.
        V: the Wiener process ``tau_lgd' = v`` in the same convention ([Vertechy] §VI:
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


#: Newton-Kleinman steps :func:`_solve_care` takes at most after scipy's solution.
CARE_NEWTON_STEPS = 4


def _solve_care(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``solve_continuous_are`` refined by Newton-Kleinman steps.

    On lightly damped, very stiff joints with a large inertia ratio scipy's Schur
    solution leaves a relative residual up to ~1e-5; each Newton step (``Acl = A - S P``,
    ``Aclᵀ X + X Acl = -(Q + P S P)``) converges quadratically from there, to ~1e-9.
    A step is kept only while it lowers the residual (at most :data:`CARE_NEWTON_STEPS`).
    """
    with warnings.catch_warnings():
        # scipy warns (and perturbs) on Hamiltonian eigenvalues on the imaginary axis;
        # the callers check the result is stabilising and raise DesignError otherwise.
        warnings.simplefilter("ignore", RuntimeWarning)
        P = _linalg().solve_continuous_are(A, B, Q, R)
    P = 0.5 * (P + P.T)
    S = B @ np.linalg.solve(R, B.T)
    residual = _care_residual(A, S, Q, P)
    for _ in range(CARE_NEWTON_STEPS):
        Acl = A - S @ P
        X = _linalg().solve_continuous_lyapunov(Acl.T, -(Q + P @ S @ P))
        X = 0.5 * (X + X.T)
        if not np.all(np.isfinite(X)):
            break
        r = _care_residual(A, S, Q, X)
        if not r < residual:
            break
        P, residual = X, r
    return P


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
    exogenous-input solution (``Feedforward.LQ``, reproduces the paper) or the
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

    k1, k2 are taken from the LQ design ([Vertechy] compares the laws with the same
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
    # Solved for the state [tau_s, tau_s'/w, tau_lgd] (w the joint's natural frequency):
    # tau_s' is w times larger than the torques, and on a stiff joint with a large
    # inertia ratio that spread costs the solver five digits.
    T = np.diag([1.0, math.sqrt(params.k / params.J), 1.0])
    Ti = np.diag(1.0 / np.diag(T))
    As, Cs, Gs = Ti @ Ap @ T, C @ T, Ti @ G
    try:
        P = T @ _solve_care(As.T, Cs.T, V * (Gs @ Gs.T), np.array([[W]])) @ T
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
    """The 1 kHz observer (docs/papers.md, "Discretisation for the 1 kHz loop").

    ``zoh-kalman``: DARE on the ZOH meta-system with Van Loan ``Qd`` from the intensity
    ``V · 1 ms`` and ``Rd = W · 1 ms / Ts`` (W per 1 kHz sample, as Eq. 8 takes it; module
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
