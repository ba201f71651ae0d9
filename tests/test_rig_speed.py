"""``hdhil bench``'s joints section (hdhil.analysis.rig_speed): the rigs it measures, the
growth verdict and the report, on given figures; the measurement itself on a tiny run.

No timing threshold anywhere: the machines running the tests are shared and noisy.
"""

from __future__ import annotations

import json
import math

import pytest

from hdhil.analysis import rig_speed
from hdhil.analysis.rig_speed import (
    LINEAR_TOLERANCE,
    format_joints_section,
    joint_rig_overrides,
    linearity,
)
from hdhil.rig.request import resolve


def _row(n: int, cpu: float, plant: str = "independent", label: str | None = None) -> dict:
    return {"label": label or f"{n} joints", "joints": n, "buses": -(-n // 2), "plant": plant,
            "cpu_us": cpu, "wall_us": 2 * cpu, "cpu_us_per_joint": cpu / n,
            "wall_us_per_joint": 2 * cpu / n, "cpu_min_us": cpu, "cpu_max_us": cpu,
            "cycles": 99, "runs": 1}  # fmt: skip


def test_the_measured_rigs_put_two_joints_on_each_bus() -> None:
    for n, buses in ((1, 1), (2, 1), (4, 2), (7, 4)):
        s = resolve("free-motion", overrides=[joint_rig_overrides(n)]).scenario
        assert s.is_rig and s.robot is None and len(s.joints) == n
        on_bus = [sum(j.bus == name for j in s.joints) for name, _ in s.buses]
        assert len(on_bus) == buses and max(on_bus) == min(n, 2) and min(on_bus) >= 1
    with pytest.raises(ValueError):
        joint_rig_overrides(0)


def test_growth_verdict_compares_each_joints_cost_with_one_joints() -> None:
    # a fixed part shared by the joints: the cost per joint falls, linear growth
    linear = [_row(n, 20.0 + 50.0 * n) for n in (1, 2, 4, 7)] + [_row(7, 9e9, "arm", "arm7")]
    v = linearity(linear)
    assert v["met"] is True and v["worst_ratio"] == 1.0
    assert v["ratios"]["7"] == pytest.approx((20 + 350) / 7 / 70)
    assert v["per_joint_us"] == pytest.approx(50.0) and v["fixed_us"] == pytest.approx(20.0)
    # a cost growing with N squared: the ratio climbs past the tolerance
    square = [_row(n, 50.0 * n + 10.0 * n * n) for n in (1, 2, 4, 7)]
    v = linearity(square)
    assert v["met"] is False and v["worst_ratio"] == pytest.approx(120 / 60)
    assert v["worst_ratio"] > LINEAR_TOLERANCE
    assert linearity([_row(2, 100.0)])["met"] is None  # no one-joint row: no verdict


def test_the_joints_section_prints_each_rig_and_the_verdicts() -> None:
    loop = [_row(n, 20.0 + 50.0 * n) for n in (1, 2, 4, 7)] + [_row(4, 500.0, "arm", "rehabexos")]
    whole = [
        {"scenario": "rehabexos", "duration_s": 10.0, "runs": 3, "whole_s": 5.0, "cpu_s": 5.5,
         "start_up_s": 0.8, "loop_s": 4.0, "min_whole_s": 4.9, "max_whole_s": 5.2,
         "real_time_factor": 2.0, "cpu_factor": 1.82, "loop_real_time_factor": 2.5, "goal": 5.0,
         "met": False},
        {"scenario": "arm7", "duration_s": 10.0, "runs": 3, "whole_s": 4.0, "cpu_s": 4.5,
         "start_up_s": 0.8, "loop_s": 3.0, "min_whole_s": 3.9, "max_whole_s": 4.2,
         "real_time_factor": 2.5, "cpu_factor": 2.22, "loop_real_time_factor": 3.3, "goal": 2.0,
         "met": True},
    ]  # fmt: skip
    section = {"loop_s": 2.0, "scenario": "free-motion", "joints_per_bus": 2, "loop": loop,
               "linearity": linearity(loop), "whole": whole, "arm": True}  # fmt: skip
    text = "\n".join(format_joints_section(section))
    json.dumps(section)  # the report is JSON as it stands
    rows: dict[str, list[str]] = {}
    for line in text.splitlines():
        if line.startswith("| ") and not line.startswith("| -"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows.setdefault(cells[0], []).extend(cells[1:])  # rehabexos: loop, then whole
    # joints, buses, plant, CPU us/cycle, min-max, CPU us/joint, wall us/cycle, wall us/joint
    assert rows["1 joints"] == ["1", "1", "independent", "70", "70-70", "70.0", "140", "140.0"]
    assert rows["7 joints"][5] == "52.9"  # 370 / 7 us a joint
    assert rows["rehabexos"][:3] == ["4", "2", "arm"]
    growth = next(line for line in text.splitlines() if line.startswith("growth:"))
    assert "N=7: 0.76" in growth and ": met;" in growth and "20 us + N x 50.0 us" in growth
    assert rows["rehabexos"][-4:] == ["1.82x", "2.00x", ">= 5x", "NOT met"]
    assert rows["arm7"][-3:] == ["2.50x", ">= 2x", "met"]
    section.update(arm=False, whole=[])
    text = "\n".join(format_joints_section(section))
    assert "not measured (needs the arm extra)" in text


@pytest.mark.slow
def test_the_loop_is_measured_per_rig(monkeypatch: pytest.MonkeyPatch) -> None:
    rows = rig_speed.bench_joint_loop(0.02, 1, ns=(1, 2), arm_rigs=())
    assert [(r["joints"], r["buses"], r["plant"]) for r in rows] == [
        (1, 1, "independent"),
        (2, 1, "independent"),
    ]
    for r in rows:
        assert r["cycles"] >= 15 and r["runs"] == 1
        for key in ("cpu_us", "wall_us", "cpu_us_per_joint"):
            assert math.isfinite(r[key]) and r[key] > 0
    assert rows[1]["cpu_us_per_joint"] == rows[1]["cpu_us"] / 2


def test_bench_only_joints_runs_that_section_alone(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from hdhil.cli import main

    asked = []

    def fake(loop_s: float, repeat: int, whole_s: float, whole_runs: int) -> dict:
        asked.append((loop_s, repeat, whole_s, whole_runs))
        loop = [_row(1, 70.0)]
        return {"loop_s": loop_s, "scenario": "free-motion", "joints_per_bus": 2, "loop": loop,
                "linearity": linearity(loop), "whole": [], "arm": False}  # fmt: skip

    monkeypatch.setattr(rig_speed, "bench_joints", fake)
    assert main(["bench", "--only", "joints", "--quick", "--duration", "0.5", "-q"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("hdhil bench --only joints (quick run")
    assert "Loop cost by joint count" in out and "Lockstep real-time factor" not in out
    assert asked == [(0.5, 1, 1.0, 1)]
    assert main(["bench", "--only", "joints", "--json", "-q"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["only"] == "joints" and data["joints"]["loop"][0]["joints"] == 1
    assert asked[-1] == (2.0, 3, 10.0, 3)
