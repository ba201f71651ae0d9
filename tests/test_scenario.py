"""Scenario files: loading, overrides and error reporting (hostsim.scenario)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from hdhil.dataconf import ConfigError
from hostsim.plant import PlantConfig
from hostsim.scenario import Scenario, list_scenarios, load_scenario

SHIPPED = Path(__file__).resolve().parents[1] / "hostsim" / "scenarios"

MINIMAL = """\
[scenario]
name = "tiny"
duration_s = 0.5
"""


def write(tmp_path: Path, text: str, name: str = "s.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_list_scenarios_names_every_shipped_file() -> None:
    names = list_scenarios()
    assert "free-motion" in names
    assert names == sorted(p.stem for p in SHIPPED.glob("*.toml"))


def test_every_shipped_scenario_loads() -> None:
    for name in list_scenarios():
        scn = load_scenario(name)
        assert isinstance(scn, Scenario)
        assert isinstance(scn.plant, PlantConfig)
        assert scn.duration_s > 0


def test_free_motion_by_name_and_by_path_agree(tmp_path: Path) -> None:
    by_name = load_scenario("free-motion")
    copy = tmp_path / "copy.toml"
    shutil.copy(SHIPPED / "free-motion.toml", copy)
    by_path = load_scenario(str(copy))
    assert by_path == by_name
    assert load_scenario(copy) == by_name  # a Path works too
    assert by_name.name == "free-motion"
    assert by_name.firmware["reference"]["wave"] == "step"


def test_free_motion_step_is_an_exact_dac_code() -> None:
    """The step reaches the amplifier unchanged through the 12-bit DAC."""
    scn = load_scenario("free-motion")
    amplitude = scn.firmware["reference"]["amplitude_V"]
    dac = scn.plant.dac
    assert dac.to_volts(dac.to_counts(amplitude)) == amplitude


def test_minimal_file_gets_defaults(tmp_path: Path) -> None:
    scn = load_scenario(write(tmp_path, MINIMAL))
    assert scn == Scenario("tiny", "", 0.5, 0, PlantConfig(), {})


def test_overrides_merge_into_the_file() -> None:
    base = load_scenario("free-motion")
    scn = load_scenario(
        "free-motion",
        {
            "scenario": {"seed": 9},
            "plant": {"drivetrain": {"b_motor": 2.5}, "substeps": 8},
            "firmware": {"reference": {"amplitude_V": 0.5}},
        },
    )
    assert scn.seed == 9
    assert scn.duration_s == base.duration_s
    assert scn.plant.drivetrain.b_motor == 2.5
    assert scn.plant.drivetrain.J_motor == base.plant.drivetrain.J_motor
    assert scn.plant.ripple == base.plant.ripple
    assert scn.plant.substeps == 8
    assert scn.firmware["reference"]["amplitude_V"] == 0.5
    assert scn.firmware["reference"]["step_time_s"] == base.firmware["reference"]["step_time_s"]
    # the shipped scenario itself is untouched by an earlier override
    assert load_scenario("free-motion") == base


def one_line_error(*args, match: str) -> str:
    with pytest.raises(ConfigError, match=match) as info:
        load_scenario(*args)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_unknown_name_lists_the_known_ones() -> None:
    message = one_line_error("free-motoin", match="unknown scenario 'free-motoin'")
    assert "free-motion" in message


def test_missing_file() -> None:
    one_line_error("/nonexistent/dir/x.toml", match="not found")


def test_malformed_toml_reports_the_line(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL + "[plant.drivetrain]\nb_motor = = 2\n")
    message = one_line_error(path, match="invalid TOML")
    assert "line 5" in message
    assert str(path) in message


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        ("[plant.drivetrain]\nb_motr = 2.0\n", r"unknown key plant\.drivetrain\.b_motr"),
        ("[plant]\nsubstep = 2\n", r"unknown key plant\.substep"),
        (
            '[plant.drivetrain]\nb_motor = "high"\n',
            r"plant\.drivetrain\.b_motor: expected a number",
        ),
        ("[plant]\nsubsteps = 2.5\n", r"plant\.substeps: expected an integer"),
        ("[plant.drivetrain]\nJ_load = -1.0\n", r"J_load must be > 0"),
        ("[plant.adc]\nbits = 40\n", r"bits must be 2\.\.16"),
        ("[plant]\ndrivetrain = 3\n", r"plant\.drivetrain: expected a table"),
        ("[bus]\nbitrate = 500000\n", r"unknown table \[bus\]"),
        ("firmware = 3\n", r"firmware: expected a table"),
    ],
)
def test_bad_content_gives_config_error_naming_the_key(
    tmp_path: Path, extra: str, match: str
) -> None:
    # bare keys must precede tables in TOML: put a top-level key before [scenario]
    text = extra + MINIMAL if not extra.startswith("[") else MINIMAL + extra
    one_line_error(write(tmp_path, text), match=match)


@pytest.mark.parametrize(
    ("header", "match"),
    [
        ('[scenario]\nname = "x"\n', r"missing key scenario\.duration_s"),
        ("[scenario]\nduration_s = 1.0\n", r"missing key scenario\.name"),
        ('[scenario]\nname = "x"\nduration_s = -1.0\n', r"duration_s must be > 0"),
        ('[scenario]\nname = "x"\nduration_s = 1.0\nseed = -3\n', r"seed must be an integer >= 0"),
        ('[scenario]\nname = ""\nduration_s = 1.0\n', r"name must be a non-empty string"),
        ('[scenario]\nname = "x"\nduration_s = 1.0\nseeds = 3\n', r"unknown key scenario\.seeds"),
        ("[plant]\nsubsteps = 2\n", r"missing \[scenario\]"),
    ],
)
def test_bad_header(tmp_path: Path, header: str, match: str) -> None:
    one_line_error(write(tmp_path, header), match=match)


def test_override_with_bad_value_is_reported() -> None:
    one_line_error(
        "free-motion", {"plant": {"sensors": {"volt2Nm": 0}}}, match=r"volt2Nm must be > 0"
    )
