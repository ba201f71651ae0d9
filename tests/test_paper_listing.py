"""Paper mode is listing A.1: ``hdhil filter --paper`` (and the paper-mode interrupt
handler) against a line-by-line port of the listing's arithmetic kept here.

Source: [Taghirad97], Appendix A.1 ``free_kalman.c``: ``c_int10`` (``vel =
Tacho * volt2radps; acc = Diff_filter( vel); T_meas = Torque * volt2Nm; T_mod = J_load *
acc / Gain; Delta_T = T_meas - T_mod; Torque_f = T_meas - T_ripple; T_ripple = Kalman
(Delta_T, vel, sample_period);``), ``Diff_filter`` and ``Kalman`` loop for loop, with the
literals of the listing (``nd``, ``dd``, ``volt2Nm``, ``J_load``, ``Gain``) and the
Kalman locals kept between calls (the port's documented reading, firmware.ripple).

The inputs are the ones the plausibility stage would change: a running start (the first
sample at 156 rad/s, which the listing differentiates from ``v_1 = 0`` into 28 364
rad/s², the stage into 18 000) and 30 rad/s tacho steps.  Paper mode has the stage off
unless asked for (``firmware.config.FirmwareConfig.plausibility_active``).
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from listing_ports import ListingKF

from hdhil.cli import main
from hdhil.firmware.config import FirmwareConfig, PlausibilityConfig, paper_config
from hdhil.firmware.isr import TorqueFilterChain
from hdhil.rig.offline import OUTPUT_COLUMNS


class ListingA1:
    """``c_int10`` of listing A.1 from ``vel`` and ``T_meas`` on, in the listing's order."""

    def __init__(self) -> None:
        # globals: float v_1=0.0, a_1=0.0; float T_ripple = 0.0; int kal_count = 1;
        self.v_1 = 0.0
        self.a_1 = 0.0
        self.T_ripple = 0.0
        self.kal_count = 1
        # float J_load = 1.725e-2, Gain = 100; float sample_period = 0.001;
        self.J_load = 1.725e-2
        self.Gain = 100.0
        self.sample_period = 0.001
        # Kalman, with its locals kept between calls (listing A.1's arithmetic)
        self.Kalman = ListingKF(a2=False)

    def Diff_filter(self, v: float) -> float:
        nd = (181.818181818182, -181.818181818182)
        dd = (1.00000000000000, -0.81818181818182)
        a = nd[0] * v + nd[1] * self.v_1 - dd[1] * self.a_1
        self.v_1 = v
        self.a_1 = a
        return a

    def step(self, T_meas: float, vel: float) -> tuple[float, float, float, float]:
        """``(acc, T_mod, Torque_f, T_ripple used)`` for one interrupt."""
        acc = self.Diff_filter(vel)
        T_mod = self.J_load * acc / self.Gain
        Delta_T = T_meas - T_mod
        ripple = self.T_ripple
        Torque_f = T_meas - ripple
        self.T_ripple = self.Kalman(Delta_T, vel, self.sample_period)
        return acc, T_mod, Torque_f, ripple


def _inputs(n: int = 2500, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A running start at 156 rad/s, 30 rad/s steps at 0.5 s, 1.2 s (down) and 1.9 s, a
    2x/4x ripple on the torque and noise on both."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 1e-3
    vel = 156.0 + 30.0 * ((t >= 0.5).astype(float) - (t >= 1.2) + (t >= 1.9))
    vel = vel + rng.normal(0.0, 0.2, n)
    theta = np.cumsum(vel) * 1e-3
    T = 2.0 + 0.8 * np.sin(2 * theta) + 0.3 * np.sin(4 * theta + 0.4) + rng.normal(0, 0.05, n)
    return t, T, vel


def _listing_rows(T: np.ndarray, vel: np.ndarray) -> np.ndarray:
    listing = ListingA1()
    rows = []
    for Ti, vi in zip(T.tolist(), vel.tolist(), strict=True):
        acc, T_mod, Torque_f, ripple = listing.step(Ti, vi)
        rows.append((Ti, acc, T_mod, ripple, Torque_f))
    return np.array(rows)


def test_the_listing_port_sees_the_running_start_and_the_steps() -> None:
    """The inputs do exercise what the plausibility stage would change."""
    _t, T, vel = _inputs()
    rows = _listing_rows(T, vel)
    assert rows[0, 1] == pytest.approx(181.818181818182 * vel[0])  # ≈ 28 364 rad/s²
    assert rows[0, 1] > 28_000.0
    k = 500
    assert rows[k, 1] > 18_000.0 * 0.25  # the 30 rad/s step: 5 450 rad/s² at once


@pytest.mark.parametrize("source", ["cli", "chain"])
def test_paper_mode_is_listing_a1_sample_for_sample(tmp_path: Path, source: str) -> None:
    t, T, vel = _inputs()
    expected = _listing_rows(T, vel)
    if source == "cli":
        path = tmp_path / "in.csv"
        with path.open("w") as fh:
            fh.write("time,T_meas,velocity\n")
            for row in zip(t.tolist(), T.tolist(), vel.tolist(), strict=True):
                fh.write(",".join(repr(v) for v in row) + "\n")
        out = tmp_path / "out.csv"
        assert main(["filter", str(path), "--out", str(out), "--paper"]) == 0
        with out.open() as fh:
            rows = list(csv.reader(fh))
        header, got = rows[0], np.array([[float(v) for v in r] for r in rows[1:]])
        assert header == list(OUTPUT_COLUMNS)
        got = got[:, 1:]
    else:
        chain = TorqueFilterChain(paper_config(FirmwareConfig()))
        rows = []
        for Ti, vi in zip(T.tolist(), vel.tolist(), strict=True):
            acc, T_mod, _dT, Torque_f, ripple = chain.step(Ti, vi)
            rows.append((Ti, acc, T_mod, ripple, Torque_f))
        got = np.array(rows)
    assert got.shape == expected.shape
    # double precision against double precision; only the summation order of the
    # matrix products and the differentiator's coefficients (scipy's bilinear vs the
    # listing's 15-digit literals) differ
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9)


def test_plausibility_in_paper_mode_only_when_asked_for() -> None:
    paper = paper_config(FirmwareConfig())
    assert not paper.plausibility_active
    assert FirmwareConfig().plausibility_active
    asked = dataclasses.replace(paper, plausibility=PlausibilityConfig(enabled=True))
    assert asked.plausibility_active
    off = dataclasses.replace(FirmwareConfig(), plausibility=PlausibilityConfig(enabled=False))
    assert not off.plausibility_active
    # asked for, the stage clamps the running start's acceleration (not the listing)
    _t, T, vel = _inputs()
    chain = TorqueFilterChain(asked)
    acc0 = chain.step(float(T[0]), float(vel[0]))[0]
    assert acc0 == pytest.approx(asked.plausibility.max_acceleration_radps2)
    assert acc0 != pytest.approx(_listing_rows(T[:1], vel[:1])[0, 1])


def _commands_and_telemetry(trace: Path) -> tuple[list[tuple[float, int]], float]:
    """``(time, DAC code)`` of the drive's RPDO1 with "enable operation", and the time of
    the first controller telemetry frame (the first interrupt's)."""
    import can

    from hdhil.dbc import codec

    rpdo, tele = codec("control", "DRIVE_RPDO1"), codec("control", "CTRL_TPDO1")
    codes: list[tuple[float, int]] = []
    first_tele = math.inf
    with can.LogReader(str(trace)) as reader:
        for msg in reader:
            if msg.arbitration_id == rpdo.frame_id and not msg.is_extended_id:
                dac, controlword, _cycle = rpdo.decode(msg.data)
                if controlword == 0x000F:
                    codes.append((msg.timestamp, int(dac)))
            elif msg.arbitration_id == tele.frame_id and not msg.is_extended_id:
                first_tele = min(first_tele, msg.timestamp)
    return codes, first_tele


@pytest.mark.parametrize("mode", ["paper", "recommended"])
def test_paper_mode_starts_with_vbias_and_the_listing_pause(tmp_path: Path, mode: str) -> None:
    """Listing A.1 ``main()``: ``write_dac0( Vbias )``, the settling pause, then the first
    interrupt.  Paper mode holds the bias code for LISTING_SETTLE_S (16 samples at 1 ms)
    before the handler runs; recommended mode starts the handler at once."""
    import contextlib
    import io

    from hdhil.firmware.config import LISTING_SETTLE_S

    override = tmp_path / "o.toml"
    override.write_text(f'[firmware.ripple]\nmode = "{mode}"\n[firmware.reference]\nbias_V = 1.5\n')
    trace = tmp_path / f"{mode}.blf"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["run", "--scenario", "free-motion", "--duration", "0.1", "--override",
                     str(override), "--trace", str(trace)]) == 0  # fmt: skip
    codes, first_tele = _commands_and_telemetry(trace)
    bias = FirmwareConfig().dac.to_counts(1.5)
    settle = round(LISTING_SETTLE_S / 1e-3) if mode == "paper" else 0
    assert settle in (0, 16)
    # before operation the drive gets zero; then Vbias: during the pause without an
    # interrupt (no telemetry), and from the first interrupt on (the step is at 0.05 s)
    operating = [(t, c) for t, c in codes if c != 0]
    assert codes[: len(codes) - len(operating)] == [
        (t, 0) for t, _ in codes[: len(codes) - len(operating)]
    ]
    before = [c for t, c in operating if t < first_tele - 1e-4]
    assert before == [bias] * settle
    assert operating[settle][1] == bias
    assert operating[settle][0] == pytest.approx(first_tele, abs=2e-4)
