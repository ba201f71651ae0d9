"""Frequency response of the firmware's torque filter: true torque in, filtered torque out.

What fraction of a true torque at frequency f survives in ``T_filtered``?  An ideal
ripple canceller has gain 1 everywhere except at the ripple harmonics.  The paper filter
of [Taghirad97] does not: it models all of y = T_meas − T_exp as ripple, so its
oscillators absorb slow true torque that the inertia-only T_exp misses.

Method: simulation through the real thing.  The firmware's own
:class:`firmware.isr.TorqueFilterChain` runs at a constant motor speed (tacho and
encoder as the drive emulator produces them) on a torque ``A cos(2π f t)`` without
ripple.  Both filters are linear in the torque for a given speed profile, so the
response is the difference between a run with the sinusoid and a reference run with
zero torque (which cancels the differentiator's start-up transient exactly),
demodulated at f over a Hann window and divided by A.  The filters rotate with the
angle, so a sinusoid also produces components at f ± the harmonic frequencies; only the
component at f is measured.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from hdhil.firmware.config import FirmwareConfig
from hdhil.firmware.isr import TorqueFilterChain

__all__ = ["torque_response", "torque_transfer"]

_ENCODER_MODULUS = 1 << 16


def _run(cfg: FirmwareConfig, speed: float, torque: np.ndarray) -> np.ndarray:
    """``T_filtered`` of a fresh chain over ``torque`` at constant motor ``speed``."""
    chain = TorqueFilterChain(cfg)
    step = chain.step
    Ts = cfg.sample_period_s
    counts_per_rad = cfg.calibration.encoder_counts_per_rev / (2.0 * math.pi)
    floor = math.floor
    out = np.empty(len(torque))
    for k, T in enumerate(torque.tolist()):
        encoder = floor(speed * k * Ts * counts_per_rad) % _ENCODER_MODULUS
        out[k] = step(T, speed, encoder)[3]
    return out


def torque_response(
    cfg: FirmwareConfig,
    speed_radps: float,
    freqs_Hz: Sequence[float] | np.ndarray,
    *,
    amplitude_Nm: float = 1.0,
    settle_s: float = 10.0,
    measure_s: float = 4.0,
) -> np.ndarray:
    """Complex response from true torque to ``T_filtered`` at each frequency (Hz, ≥ 0)
    for the filter configured in ``cfg``, at constant motor speed ``speed_radps``.

    ``settle_s`` of simulated time are discarded before a ``measure_s`` window; the
    defaults (10 s, 4 s) let the recommended filter settle at 20 rad/s.  Each
    frequency is a separate run of ``settle_s + measure_s``, plus one shared
    zero-torque reference run.
    """
    freqs = np.atleast_1d(np.asarray(freqs_Hz, dtype=np.float64))
    Ts = cfg.sample_period_s
    if not (math.isfinite(speed_radps)):
        raise ValueError(f"speed_radps must be finite, got {speed_radps!r}")
    if np.any(~np.isfinite(freqs)) or np.any(freqs < 0) or np.any(freqs >= 0.5 / Ts):
        raise ValueError(f"frequencies must be within [0, {0.5 / Ts:g}) Hz, got {freqs_Hz!r}")
    if not (math.isfinite(amplitude_Nm) and amplitude_Nm > 0):
        raise ValueError(f"amplitude_Nm must be > 0, got {amplitude_Nm!r}")
    if not (settle_s >= 0 and measure_s > 0):
        raise ValueError("settle_s must be >= 0 and measure_s > 0")
    k0 = round(settle_s / Ts)
    n = k0 + max(2, round(measure_s / Ts))
    t = np.arange(n) * Ts
    reference = _run(cfg, speed_radps, np.zeros(n))
    window = np.hanning(n - k0)
    gains = np.empty(len(freqs), dtype=np.complex128)
    for i, f in enumerate(freqs.tolist()):
        phase = 2.0 * math.pi * f * t
        response = _run(cfg, speed_radps, amplitude_Nm * np.cos(phase)) - reference
        demod = np.exp(-1j * phase[k0:])
        scale = (2.0 if f > 0 else 1.0) / (amplitude_Nm * window.sum())
        gains[i] = scale * np.sum(window * response[k0:] * demod)
    return gains


def torque_transfer(
    cfg: FirmwareConfig,
    speed_radps: float,
    freqs_Hz: Sequence[float] | np.ndarray,
    **kwargs: float,
) -> np.ndarray:
    """|H(f)| from true torque to ``T_filtered``: :func:`torque_response`'s magnitude.

    1 means the torque at f passes untouched; 0 means the filter removes it (as it
    should at the ripple harmonics, and as the paper filter wrongly does at low
    frequencies).
    """
    return np.abs(torque_response(cfg, speed_radps, freqs_Hz, **kwargs))
