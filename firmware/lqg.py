"""The runtime LQG joint-torque regulator of [Vertechy]: observer update (Eq. 8,
discretised) and control law (Eq. 4 / Eq. 5), once per sample.

The offline design it runs (gains, Kalman gain, discrete observer, loop analysis) is
:mod:`firmware.lqg_design`; torques use [Vertechy]'s sign convention inside these two
modules only.
"""

from __future__ import annotations

from hdhil.firmware.lqg_design import ControlLaw, LqGains, LqgDesign

__all__ = ["LqgController"]


class LqgController:
    """Runtime LQG regulator of [Vertechy]: observer (Eq. 8, discretised) + Eq. 4 / Eq. 5.

    Call :meth:`step` once per sample with the measured sensor torque; it returns the
    motor torque command ([Vertechy]'s sign convention, output-shaft units).  Scalar arithmetic
    on preallocated float attributes (no numpy in the loop; its time per call is in
    ``hdhil bench``'s stage table).

    Args:
        design: from :func:`design_lqg`.
        law: which JTF law (JTF1, JTF1_FF, JTF2, JTF3).
        delay_samples: 1 (synchronous PDO: the command from sample k acts from
            t(k+1); the observer is fed the previous command) or 0 (acts at once).
        predict: with ``delay_samples = 1``, apply Eq. 4 to the one-step prediction
            ``z(k+1)`` of the state (and ``τsD + Ts τsD'``) at the time the command takes
            effect, instead of the current estimate.
        gains: override the gains of ``law`` (e.g. hand-tuned).
    """

    def __init__(
        self,
        design: LqgDesign,
        law: ControlLaw = ControlLaw.JTF1,
        *,
        delay_samples: int = 1,
        predict: bool = True,
        gains: LqGains | None = None,
    ) -> None:
        if delay_samples not in (0, 1):
            raise ValueError(f"delay_samples must be 0 or 1, got {delay_samples!r}")
        self.design = design
        self.law = ControlLaw(law)
        self.delay_samples = delay_samples
        self.predict = bool(predict) and delay_samples == 1
        self.gains = gains if gains is not None else design.gains_for(self.law)
        g = self.gains
        ob = design.observer
        self._Ts = ob.Ts
        (
            (self._a00, self._a01, self._a02),
            (self._a10, self._a11, self._a12),
            (
                self._a20,
                self._a21,
                self._a22,
            ),
        ) = (tuple(float(v) for v in row) for row in ob.Ad)
        self._bu0, self._bu1, self._bu2 = (float(v) for v in ob.Bd[:, 0])
        self._by0, self._by1, self._by2 = (float(v) for v in ob.Bd[:, 1])
        self._m0, self._m1, self._m2 = (float(v) for v in ob.M)
        # Eq. 4 expanded:  tau_m = -[k1 x0 + k2 x1 + k3 x2 + (k4 - k1) τsD + kd τsD'] - τ̂d
        ff = self.law is ControlLaw.JTF1_FF
        self._k1, self._k2, self._k3 = float(g.k1), float(g.k2), float(g.k3)
        self._ksd = float(g.k4 - g.k1)
        self._ksdd = float(g.k5 - g.k2) if ff else 0.0
        self.reset()

    def reset(self, tau_s: float = 0.0, tau_lgd: float = 0.0) -> None:
        """Restart the observer at rest (``tau_s' = 0``) with the given torques."""
        self._z0, self._z1, self._z2 = float(tau_s), 0.0, float(tau_lgd)
        self._u_prev = 0.0
        self._last_cmd = 0.0
        self.tau_s_hat = float(tau_s)
        self.tau_s_dot_hat = 0.0
        self.tau_lgd_hat = float(tau_lgd)

    @property
    def estimate(self) -> tuple[float, float, float]:
        """Current estimate ``(τ̂s, τ̂s', τ̂lgd)`` (τ̂lg when a τ̂d model is passed, Eq. 5)."""
        return (self.tau_s_hat, self.tau_s_dot_hat, self.tau_lgd_hat)

    def step(
        self,
        tau_s_measured: float,
        tau_sD: float,
        tau_sD_dot: float = 0.0,
        tau_d_hat: float | None = None,
    ) -> float:
        """One sample: observer update, then Eq. 4 (or Eq. 5 if ``tau_d_hat`` is given).

        With ``tau_d_hat`` (a model of the motor disturbance τd, [Vertechy] §VI), the command
        is ``tau_m,2 = -[...] - τ̂d`` (Eq. 5) and the observer is driven by
        ``tau_m,2 + τ̂d`` ([Vertechy] §V), so its third state estimates ``tau_lg`` instead of
        ``tau_lgd``.  ``tau_sD_dot`` is used by ``JTF1_FF`` (and by the prediction).
        """
        y = tau_s_measured
        d = 0.0 if tau_d_hat is None else tau_d_hat
        z0, z1, z2 = self._z0, self._z1, self._z2
        r = y - z0
        x0 = z0 + self._m0 * r
        x1 = z1 + self._m1 * r
        x2 = z2 + self._m2 * r
        self.tau_s_hat, self.tau_s_dot_hat, self.tau_lgd_hat = x0, x1, x2
        if self.delay_samples:
            # torque acting on the motor over [t(k), t(k+1)): the previous command
            n0, n1, n2 = self._observer_predict(z0, z1, z2, self._u_prev + d, y)
        if self.predict:  # delay_samples == 1: act on the one-sample prediction
            s0, s1, s2, sd = n0, n1, n2, tau_sD + self._Ts * tau_sD_dot
        else:
            s0, s1, s2, sd = x0, x1, x2, tau_sD
        cmd = (
            -(
                self._k1 * s0
                + self._k2 * s1
                + self._k3 * s2
                + self._ksd * sd
                + self._ksdd * tau_sD_dot
            )
            - d
        )
        if self.delay_samples:
            self._u_prev = cmd
        else:
            n0, n1, n2 = self._observer_predict(z0, z1, z2, cmd + d, y)
        self._z0, self._z1, self._z2 = n0, n1, n2
        self._last_cmd = cmd
        return cmd

    def _observer_predict(
        self, z0: float, z1: float, z2: float, u: float, y: float
    ) -> tuple[float, float, float]:
        """Observer time update ``z(k+1) = Ad z(k) + Bd [u; y]`` ([Vertechy] Eq. 8, discretised
        as in the module docstring)."""
        return (
            self._a00 * z0 + self._a01 * z1 + self._a02 * z2 + self._bu0 * u + self._by0 * y,
            self._a10 * z0 + self._a11 * z1 + self._a12 * z2 + self._bu1 * u + self._by1 * y,
            self._a20 * z0 + self._a21 * z1 + self._a22 * z2 + self._bu2 * u + self._by2 * y,
        )

    def set_applied(self, tau_m: float) -> None:
        """Tell the observer the command actually applied (e.g. after saturation).

        Call after :meth:`step` with the clipped value of its return.
        """
        delta = tau_m - self._last_cmd
        if self.delay_samples:
            self._u_prev = tau_m
        else:
            self._z0 += self._bu0 * delta
            self._z1 += self._bu1 * delta
            self._z2 += self._bu2 * delta
        self._last_cmd = tau_m
