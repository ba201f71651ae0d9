"""Line-by-line ports of [Taghirad97]'s C listings, shared by the
tests that hold the firmware against them (ripple filter, paper mode)."""

from __future__ import annotations

import math


class ListingKF:
    """[Taghirad97], listing A.1 / A.2 ``Kalman``, loop for loop, with its locals made static."""

    def __init__(self, a2: bool) -> None:
        self.a2 = a2
        self.kal_count = 1

    def __call__(self, Delta_T: float, velocity: float, sample_period: float) -> float:
        if self.kal_count == 1:
            self.R = 1.0
            self.x = [0.0] * 4
            self.C = [0.0] * 4
            self.P = [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]
            self.Q = [[1000.0 if i == j else 0.0 for j in range(4)] for i in range(4)]
            self.x[0] = self.x[2] = Delta_T
            self.C[0] = self.C[2] = 1.0
            if self.a2:
                self.Q[2][2] = self.Q[3][3] = 5e-2
            self.kal_count += 1
        x, C, R, P, Q = self.x, self.C, self.R, self.P, self.Q
        om1 = 2.0 * velocity * sample_period
        om2 = velocity * sample_period / 100.0 if self.a2 else 2.0 * om1
        phi = [[0.0] * 4 for _ in range(4)]
        phi[0][0] = math.cos(om1)
        phi[0][1] = math.sin(om1)
        phi[1][0] = -math.sin(om1)
        phi[1][1] = math.cos(om1)
        phi[2][2] = math.cos(om2)
        phi[2][3] = math.sin(om2)
        phi[3][2] = -math.sin(om2)
        phi[3][3] = math.cos(om2)
        PC = [sum(P[i][j] * C[j] for j in range(4)) for i in range(4)]
        pPC = [sum(phi[i][j] * PC[j] for j in range(4)) for i in range(4)]
        CPC = sum(C[j] * PC[j] for j in range(4))
        K = [pPC[i] / (R + CPC) for i in range(4)]
        Pp = [[sum(P[i][k] * phi[j][k] for k in range(4)) for j in range(4)] for i in range(4)]
        KC = [[K[i] * C[j] for j in range(4)] for i in range(4)]
        p_KC = [[phi[i][j] - KC[i][j] for j in range(4)] for i in range(4)]
        gb = [[sum(p_KC[i][k] * Pp[k][j] for k in range(4)) for j in range(4)] for i in range(4)]
        self.P = [[Q[i][j] + gb[i][j] for j in range(4)] for i in range(4)]
        x1 = [sum(p_KC[i][j] * x[j] for j in range(4)) for i in range(4)]
        self.x = [K[i] * Delta_T + x1[i] for i in range(4)]
        return self.x[0] + self.x[2]
