"""The shipped readings of [Vertechy] Fig. 7 that approach its 0.3 Nm
(``lqg-tracking-slow-link``, ``lqg-tracking-squared-weights``): each is ``lqg-tracking``
with only its reading changed."""

from __future__ import annotations

from typing import Any

import pytest
from runs import lockstep

from hdhil.rig.scenario import load_scenario, scenario_data


def _flat(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _changed(name: str) -> dict[str, Any]:
    base = _flat(scenario_data(load_scenario("lqg-tracking")))
    variant = _flat(scenario_data(load_scenario(name)))
    assert set(base) == set(variant)
    header = ("scenario.name", "scenario.description", "scenario.duration_s")
    return {k: variant[k] for k in base if base[k] != variant[k] and k not in header}


def test_slow_link_changes_only_the_link_frequency() -> None:
    assert _changed("lqg-tracking-slow-link") == {"plant.link.frequency_Hz": 0.5}
    # scored over the whole common period of the 0.5 Hz link and the 0.2 Hz τsD
    s = load_scenario("lqg-tracking-slow-link")
    assert s.duration_s - s.evaluate_from_s >= 10.0


def test_squared_weights_changes_only_q1_q2_to_their_squares() -> None:
    assert _changed("lqg-tracking-squared-weights") == {
        "firmware.control.weights.q1": 500.0**2,
        "firmware.control.weights.q2": pytest.approx(0.1**2),
    }


@pytest.mark.slow
@pytest.mark.parametrize("name", ["lqg-tracking-slow-link", "lqg-tracking-squared-weights"])
def test_each_reading_comes_near_the_printed_figure(name: str) -> None:
    """Over the bus, where the printed reading gives 1.21 Nm, each comes within 0.1 Nm of
    the printed 0.3 Nm (docs/papers.md has the figures)."""
    r = lockstep(name, seed=1, evaluate=False)
    assert r.tracking is not None
    assert r.tracking["max_abs_error"] < 0.4
