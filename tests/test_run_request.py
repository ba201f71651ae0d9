"""The run model: resolve() into one RunRequest, its plain-data form, the sidecar that
carries it, and one headline figure that run, evaluate, the API and a campaign agree on."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

import hdhil
from hdhil.core.dataconf import ConfigError
from hdhil.firmware.config import FirmwareConfig
from hdhil.rig.request import RunRequest, resolve
from hdhil.rig.scenario import load_scenario, scenario_data, scenario_from_dict


def _hdhil(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "hdhil", *args], capture_output=True, text=True, timeout=300
    )


def test_every_shipped_scenario_survives_its_plain_form() -> None:
    for name in hdhil.list_scenarios():
        scenario = load_scenario(name)
        assert isinstance(scenario.firmware, FirmwareConfig)
        assert scenario_from_dict(scenario_data(scenario)) == scenario


def test_resolve_merges_in_order_and_names_the_source(tmp_path: Path) -> None:
    tuned = tmp_path / "tuned.toml"
    tuned.write_text('[firmware.ripple]\nmode = "paper"\n')
    request = resolve(
        "free-motion",
        overrides=[tuned, {"firmware": {"ripple": {"mode": "recommended"}}}],
        faults=["control.loss_rate=0.01"],
        duration_s=0.25,
        seed=9,
    )
    assert request.firmware.ripple.mode == "recommended"  # the later one wins
    assert request.scenario.faults is not None
    assert request.scenario.faults.control.loss_rate == 0.01
    assert (request.duration_s, request.seed, request.cycles) == (0.25, 9, 250)
    assert request.evaluate_from_s == load_scenario("free-motion").evaluate_from_s
    assert request.sources.overrides == (str(tuned),)
    assert request.sources.faults == ("control.loss_rate=0.01",)

    bad = tmp_path / "bad.toml"
    bad.write_text("[plant.drivetrain]\nJ_motr = 1.0\n")
    with pytest.raises(ConfigError, match=r"override file .*bad.toml: .*plant.drivetrain.J_motr"):
        resolve("free-motion", overrides=[bad])
    with pytest.raises(ConfigError, match="duration must be in"):
        resolve("free-motion", duration_s=1e30)
    with pytest.raises(ConfigError, match="unknown mapping"):
        resolve("free-motion", mapping="canfd")
    with pytest.raises(ConfigError, match="less than one sample period"):
        resolve("free-motion", duration_s=1e-6)


def test_request_round_trips_through_plain_data() -> None:
    request = resolve("lqg-tracking", mapping="cst", duration_s=0.5, seed=4, evaluate_from_s=0.1)
    data = json.loads(json.dumps(request.to_data()))
    assert RunRequest.from_data(data) == request
    with pytest.raises(ConfigError, match="damaged run request"):
        RunRequest.from_data({"scenario": data["scenario"]}, "x.json")


def test_the_api_checks_its_arguments() -> None:
    with pytest.raises(TypeError, match="scenario must be a str"):
        hdhil.resolve(b"free-motion")
    with pytest.raises(TypeError, match="seed must be an int"):
        hdhil.resolve("free-motion", seed="3")
    with pytest.raises(TypeError, match="duration_s must be a number"):
        hdhil.run("free-motion", duration_s="1")
    with pytest.raises(ValueError, match="duration_s must be > 0"):
        hdhil.run("free-motion", duration_s=-1.0)


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize(
    ("scenario", "duration"),
    [("free-motion", "1.5"), ("misalignment", "4.5"), ("torque-steps", "1.5"),
     ("lqg-experiment", "1.5"), ("lqg-tracking", "1.5")],
)  # fmt: skip
def test_run_evaluate_and_api_print_one_headline(
    scenario: str, duration: str, tmp_path: Path
) -> None:
    """`hdhil run`, `hdhil evaluate` of its trace, the API on the same trace and a
    campaign variant of the same settings give the same headline figure."""
    trace = tmp_path / "run.blf"
    run = _hdhil("run", "--scenario", scenario, "--duration", duration, "--seed", "2",
                 "--trace", str(trace), "--json")  # fmt: skip
    assert run.returncode == 0, run.stderr
    from_run = json.loads(run.stdout)["headline"]
    assert from_run is not None and from_run["samples"] > 0
    evaluated = _hdhil("evaluate", str(trace), "--json")
    assert evaluated.returncode == 0, evaluated.stderr
    assert json.loads(evaluated.stdout)["headline"] == from_run
    assert hdhil.evaluate_trace(trace)["headline"] == from_run
    text = _hdhil("evaluate", str(trace)).stdout.splitlines()[0]
    assert f"{from_run['value_Nm']:.4f} Nm" in text and f"{from_run['samples']} samples" in text

    from hdhil.rig.variant import RunSettings, run_settings

    request = resolve(scenario)
    result, _trace, _sidecar = run_settings(
        RunSettings(scenario_data(request.scenario), float(duration), 2, None)
    )
    assert result["headline"] == from_run


@pytest.mark.slow
@pytest.mark.subprocess
def test_tracking_scenario_prints_no_ripple_table(tmp_path: Path) -> None:
    out = _hdhil("run", "--scenario", "lqg-tracking", "--duration", "1.2", "--trace", "")
    assert out.returncode == 0, out.stderr
    assert "headline           tracking error RMS" in out.stdout
    assert "evaluation vs truth" not in out.stdout
    assert "kalman paper" not in out.stdout


@pytest.mark.slow
def test_sample_counts_agree() -> None:
    """The cycles run, the evaluation's samples and the headline's: one count."""
    result = hdhil.run("free-motion", duration_s=0.8, seed=1)
    skipped = round(result.headline["from_s"] / result.sample_period_s)
    assert result.cycles == 800
    assert result.evaluation["samples"] == result.headline["samples"] == 800 - skipped
    assert len(hdhil.cycle_arrays(result)["time_s"]) >= result.cycles


@pytest.mark.slow
def test_a_sidecar_without_the_request_is_read_by_its_scenario_name(tmp_path: Path) -> None:
    """Traces written before sidecars carried the request name their scenario, override
    and calibration files: evaluate loads those again and scores from the scenario's
    evaluation start."""
    trace = tmp_path / "old.blf"
    result = hdhil.run("free-motion", duration_s=0.6, seed=2, trace=trace)
    sidecar = trace.with_name(trace.name + ".json")
    meta = json.loads(sidecar.read_text())
    del meta["request"]
    sidecar.write_text(json.dumps(meta))
    assert hdhil.evaluate_trace(trace)["headline"] == result.headline
    sidecar.unlink()  # no sidecar at all: the firmware defaults, scored from 0 s
    assert hdhil.evaluate_trace(trace)["headline"]["from_s"] == 0.0
