"""The torque stages around the ripple filter ([Taghirad97], listing A.1, ``c_int10``):
the expected torque ``T_mod``, the filter's measurement ``Delta_T`` and the ripple-free
torque ``Torque_f``.  The Kalman filter itself is in :mod:`firmware.ripple`.
"""

from __future__ import annotations

__all__ = [
    "expected_torque",
    "filtered_torque",
    "torque_error",
]


def expected_torque(acc: float, J_load: float, gear_ratio: float) -> float:
    """The crude expected torque: the load's inertial torque.

    Ports ``T_mod = J_load * acc / Gain`` ([Taghirad97], listing A.1, ``c_int10``;
    §4: "the expected torque can be estimated simply by the inertial part of the
    output torque which is the load inertia multiplied to the load acceleration").
    ``acc`` is the motor acceleration, so ``acc / gear_ratio`` is the load's.
    """
    return J_load * acc / gear_ratio


def torque_error(T_meas: float, T_expected: float) -> float:
    """The Kalman filter's measurement y(k) = T_meas(k) − T_exp(k) ([Taghirad97], §4 text
    under Eq. 6; listing A.1 ``Delta_T = T_meas - T_mod``)."""
    return T_meas - T_expected


def filtered_torque(T_meas: float, ripple_predicted: float) -> float:
    """The ripple-free torque, ``Torque_f = T_meas - T_ripple`` ([Taghirad97], listing A.1).

    ``ripple_predicted`` is the ripple the Kalman filter predicted for this sample
    at the previous interrupt (prediction-type filter, Eq. 8; listing comment
    "Finding torque ripple for next iteration: Prediction-Type KF").
    """
    return T_meas - ripple_predicted
