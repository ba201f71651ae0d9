"""``hdhil identify``: the [Vertechy] joint's resonance from a chirp run ([Vertechy] Fig. 5),
and the firmware's chirp reference that drives it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import can
import numpy as np
import pytest
from runs import lockstep

from hdhil import cli
from hdhil.analysis.identification import FrequencyResponse, half_power, log_decrement
from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.dbc import codec
from hdhil.firmware.config import FirmwareConfig, ReferenceConfig, Wave
from hdhil.firmware.stages import ReferenceGenerator
from hdhil.rig.scenario import load_scenario

#: Goals on the emulator (the issue): fn within 2 %, c within 10 %, and the logarithmic
#: decrement agreeing with the half-power bandwidth within 15 %.
FN_GOAL, C_GOAL, CROSS_CHECK = 0.02, 0.10, 0.15


@pytest.fixture
def hdhil(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]):
    """``hdhil ARGS...`` with ``identify`` registered: (exit code, stdout, stderr)."""

    def run(*args: str) -> tuple[int, str, str]:
        code = cli.main([str(a) for a in args])
        out, err = capsys.readouterr()
        return code, out, err

    return run


@pytest.fixture(scope="module")
def chirp_trace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shipped chirp scenario, end to end over the bus (20 s simulated)."""
    trace = tmp_path_factory.mktemp("chirp") / "c.blf"
    result = lockstep(load_scenario("chirp"), trace=trace, evaluate=False)
    assert result.cycles == 20000 and not result.interrupted
    return trace


# --------------------------------------------------------------------------- chirp wave


def test_chirp_reference_sweeps_linearly_and_repeats() -> None:
    cfg = ReferenceConfig(
        wave=Wave.CHIRP,
        bias_V=0.1,
        amplitude_V=2.0,
        frequency_Hz=2.0,
        chirp_end_Hz=60.0,
        chirp_duration_s=20.0,
    )
    gen = ReferenceGenerator(cfg, 1e-3)
    v = np.array([gen.value(k) for k in range(40000)])
    assert v[0] == pytest.approx(0.1) and v[1] > v[0]  # starts at the bias, rising
    assert v.max() == pytest.approx(2.1, abs=1e-3) and v.min() == pytest.approx(-1.9, abs=1e-3)
    np.testing.assert_allclose(v[20000:], v[:20000], atol=1e-9)  # repeats after 20 s
    # instantaneous frequency from the zero crossings of v - bias: f0 + (f1 - f0) t / T
    x = v[:20000] - 0.1
    i = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
    up = (i + x[i] / (x[i] - x[i + 1])) * 1e-3  # interpolated upward zero crossings
    mid, freq = 0.5 * (up[1:] + up[:-1]), 1.0 / np.diff(up)
    np.testing.assert_allclose(freq, 2.0 + 58.0 * mid / 20.0, rtol=0.005)


def test_chirp_reference_from_a_scenario_table_and_its_errors() -> None:
    fw = from_dict(FirmwareConfig, load_scenario("chirp").firmware, "firmware")
    assert fw.reference.wave is Wave.CHIRP
    assert (fw.reference.frequency_Hz, fw.reference.chirp_end_Hz) == (2.0, 60.0)
    with pytest.raises(ConfigError, match="chirp_duration_s"):
        from_dict(FirmwareConfig, {"reference": {"wave": "chirp", "chirp_duration_s": 0.0}})
    with pytest.raises(ValueError, match="Nyquist"):
        ReferenceGenerator(ReferenceConfig(wave=Wave.CHIRP, chirp_end_Hz=600.0), 1e-3)


# --------------------------------------------------------------------------- the method


def exact_response(band_Hz: tuple[float, float] = (4.0, 56.0)) -> FrequencyResponse:
    """The seed joint's exact T / tau_m on a 4096-point grid at 1 kHz."""
    fs, n = 1000.0, 4096
    f = np.arange(n // 2 + 1) * fs / n
    J = 2.5 * 0.7 / 3.2
    wn, zeta = math.sqrt(6300 / J), 11.8 / (2 * math.sqrt(6300 * J))
    s = 2j * math.pi * f
    H = (0.7 / 3.2) * wn**2 / (s * s + 2 * zeta * wn * s + wn**2)
    pxx = np.where((f >= band_Hz[0]) & (f <= band_Hz[1]), 1.0, 1e-9)
    inside = np.flatnonzero(pxx == 1.0)
    return FrequencyResponse(f, H, pxx, np.ones_like(f), (int(inside[0]), int(inside[-1])), n, fs)


def test_half_power_and_log_decrement_on_the_exact_response() -> None:
    """[Vertechy] §II on Eq. 2's exact response: both methods recover zeta = 0.1005."""
    fr = exact_response()
    hp = half_power(fr)
    zeta, fn = 0.10051658, 17.082301
    assert hp.fn_exact_Hz == pytest.approx(fn, rel=1e-3)
    assert hp.zeta_exact == pytest.approx(zeta, rel=5e-3)
    # the classic reading: the peak of |H| is at fn sqrt(1 - 2 zeta²), zeta 2 % high
    assert hp.f_peak_Hz == pytest.approx(fn * math.sqrt(1 - 2 * zeta**2), rel=1e-3)
    assert hp.zeta == pytest.approx(zeta, rel=0.03)
    ld = log_decrement(fr, hp)
    assert ld.zeta == pytest.approx(zeta, rel=5e-3)
    assert ld.fn_Hz == pytest.approx(fn, rel=5e-3)
    assert ld.peaks >= 3


# --------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_identify_recovers_the_joint_from_a_chirp_run(hdhil, chirp_trace, tmp_path) -> None:
    """[Vertechy] Fig. 5 on the emulator: fn within 2 %, c within 10 %, log decrement
    within 15 % of the half-power bandwidth."""
    figure = tmp_path / "bode.png"
    code, out, err = hdhil("identify", chirp_trace, "--json", "--plot", figure)
    assert code == 0, err
    result = json.loads(out)
    model = result["model"]
    assert model["fn_Hz"] == pytest.approx(17.08, abs=0.01)
    assert model["c_Nms_per_rad"] == 11.8
    methods = result["methods"]
    for name in ("half_power", "half_power_exact", "log_decrement"):
        m = methods[name]
        assert m["fn_Hz"] == pytest.approx(model["fn_Hz"], rel=FN_GOAL), name
        assert m["c_Nms_per_rad"] == pytest.approx(model["c_Nms_per_rad"], rel=C_GOAL), name
    # the exact half-power reading is much closer than the goals
    assert methods["half_power_exact"]["fn_Hz"] == pytest.approx(model["fn_Hz"], rel=0.005)
    assert methods["half_power_exact"]["c_Nms_per_rad"] == pytest.approx(11.8, rel=0.03)
    hp_zeta = methods["half_power"]["zeta"]
    assert methods["log_decrement"]["zeta"] == pytest.approx(hp_zeta, rel=CROSS_CHECK)
    assert result["static_gain"] == pytest.approx(0.7 / 3.2, rel=0.02)
    assert result["coherence_at_peak"] > 0.95
    assert result["torque_saturated"] == 0
    assert result["band_Hz"][0] < 8.0 and result["band_Hz"][1] > 40.0
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_identify_text_summary_and_other_inertias(hdhil, chirp_trace) -> None:
    """The text summary; c = 2 zeta wn J, so twice the inertias give twice the c."""
    code, out, _ = hdhil("identify", chirp_trace, "--scenario", "chirp")
    assert code == 0
    assert "half-power (fn = peak)" in out and "logarithmic decrement" in out
    assert "scenario model" in out and "17.082" in out
    c1 = float(out.split("half-power (fn = peak)")[1].split()[2])
    code, out2, _ = hdhil("identify", chirp_trace, "--json", "--inertias", "5.0", "1.4")
    c2 = json.loads(out2)["methods"]["half_power"]["c_Nms_per_rad"]
    assert c2 == pytest.approx(2 * c1, rel=1e-3)


@pytest.mark.slow
def test_identify_from_python_gives_what_the_command_prints(hdhil, chirp_trace) -> None:
    """The library alone (no argparse): the same figures as ``hdhil identify --json``."""
    from hdhil.analysis.identification import (
        chirp_data_from_trace,
        format_identification,
        identify,
        model_values,
    )

    scenario = load_scenario("chirp")
    plant = scenario.plant
    firmware = from_dict(FirmwareConfig, scenario.firmware, "firmware")
    data = chirp_data_from_trace(chirp_trace, firmware, plant.torque_per_volt)
    ident = identify(data, plant.drivetrain.J_motor, plant.drivetrain.J_load,
                     model=model_values(plant))  # fmt: skip
    code, out, _ = hdhil("identify", chirp_trace, "--json")
    assert code == 0
    cli_result = json.loads(out)
    assert json.loads(json.dumps(ident.as_dict())) == {
        k: v for k, v in cli_result.items() if k not in ("trace", "scenario", "plot")
    }
    code, text, _ = hdhil("identify", chirp_trace)
    assert text.rstrip("\n") == format_identification(ident, f"{chirp_trace} (scenario chirp)")


# --------------------------------------------------------------------------- errors


def write_trace(path: Path, cycles: int, with_commands: bool, dac: int = 100) -> Path:
    sensor, command = codec("control", "DRIVE_TPDO1"), codec("control", "DRIVE_RPDO1")
    with can.Logger(str(path)) as log:
        for k in range(cycles):
            t = k * 1e-3
            log(
                can.Message(
                    timestamp=t,
                    arbitration_id=sensor.frame_id,
                    is_extended_id=False,
                    data=sensor.encode(100, 0, 0, k % 65536),
                    channel=0,
                )
            )
            if with_commands:
                log(
                    can.Message(
                        timestamp=t + 2e-4,
                        arbitration_id=command.frame_id,
                        is_extended_id=False,
                        data=command.encode(dac, 0x000F, k & 0xFF),
                        channel=0,
                    )
                )
    return path


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda d: d / "missing.blf", "no such file"),
        (lambda d: write_trace(d / "no_cmd.asc", 5000, with_commands=False), "no DRIVE_RPDO1"),
        (lambda d: write_trace(d / "short.asc", 1000, with_commands=True), "too short"),
        (lambda d: write_trace(d / "flat.asc", 5000, with_commands=True), "does not vary"),
    ],
)
def test_identify_errors_are_one_line_exit_2(hdhil, tmp_path, make, match) -> None:
    code, out, err = hdhil("identify", make(tmp_path))
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("hdhil: error:") and match in err


@pytest.mark.slow
def test_identify_rejects_a_trace_without_a_resonance(hdhil, tmp_path) -> None:
    """A free-motion step run ([Taghirad97]) has no chirp: no resonance in an excited band."""
    trace = tmp_path / "fm.blf"
    lockstep(load_scenario("free-motion"), duration_s=5.0, trace=trace, evaluate=False)
    code, _, err = hdhil("identify", trace, "--scenario", "free-motion")
    assert code == 2 and err.count("\n") == 1
    assert "resonance" in err or "half power" in err


@pytest.mark.slow
def test_identify_plot_has_phase_and_coherence_panels(chirp_trace) -> None:
    """The figure holds the Bode magnitude, the phase (crossing -90 deg near fn, as a
    second-order resonance does) and the coherence next to the impulse response."""
    from hdhil.analysis.identification import (
        chirp_data_from_trace,
        identify,
        make_figure,
        model_values,
    )
    from hdhil.firmware.config import FirmwareConfig
    from hdhil.rig.scenario import load_scenario

    plant = load_scenario("chirp").plant
    data = chirp_data_from_trace(chirp_trace, FirmwareConfig(), plant.torque_per_volt)
    ident = identify(data, plant.drivetrain.J_motor, plant.drivetrain.J_load, 2.0,
                     model_values(plant))  # fmt: skip
    fig = make_figure(ident)
    labels = [ax.get_ylabel() for ax in fig.axes]
    # One notation for units on every figure: "quantity (unit)" (hdhil.core.plotlabels).
    assert labels == ["magnitude (dB)", "phase (deg)", "coherence", "normalised amplitude"]
    assert {ax.get_xlabel() for ax in fig.axes} == {"frequency (Hz)", "time (s)"}
    phase_ax = fig.axes[1]
    measured = next(line for line in phase_ax.get_lines() if line.get_label() == "arg H1")
    f, phase = (np.asarray(v, dtype=float) for v in measured.get_data())
    crossing = f[np.argmin(np.abs(phase + 90.0))]
    assert crossing == pytest.approx(ident.half_power.fn_exact_Hz, rel=0.05)
    coherence = fig.axes[2].get_lines()[0].get_ydata()
    assert 0.9 < float(np.median(coherence)) <= 1.0
