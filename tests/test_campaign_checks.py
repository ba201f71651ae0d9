"""``hdhil campaign`` refuses before it runs or writes anything: names, durations and seeds
every variant's run would refuse, a grid over the variant cap, an unusable ``--out``; a
damaged resume store is run again with a warning; the pool's workers end with the
campaign, even when it is killed."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import CannedExecutor

from hdhil.cli import main
from hdhil.rig.campaign import run_campaign
from hdhil.rig.campaign_file import MAX_VARIANTS, load_campaign
from hdhil.rig.campaign_variants import expand

HEAD = '[campaign]\nname = "bad"\nscenarios = ["free-motion"]\n'


def _campaign(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "c.toml"
    path.write_text(body, encoding="utf-8")
    return path


def _refused(tmp_path: Path, capsys, argv: list[str], out: Path) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("hdhil: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize(
    "body, message",
    [
        (
            '[campaign]\nname = "a\\nb"\nscenarios = ["free-motion"]\n',
            "campaign.name must be one line",
        ),
        (
            '[campaign]\nname = "bad"\nscenarios = ["free\\nmotion"]\n',
            "campaign.scenarios: 'free\\nmotion' must be one line",
        ),
        (HEAD + '[axes]\nscenario.name = ["a\\nb"]\n', "scenario.name must be one line"),
        (HEAD + "duration_s = 1e-6\n", "less than one sample period"),
        (
            HEAD + "[axes]\nscenario.duration_s = [1.0, 1e-6]\nscenario.evaluate_from_s = [0.0]\n",
            "less than one sample period",
        ),
        (HEAD + "duration_s = 1e30\n", "campaign.duration_s must be <= 3.1536e+07, got 1e+30"),
        (
            HEAD + "[axes]\nseed = { range = [0, 100000000] }\n",
            f"100000000 variants (1 scenario x seed 100000000): more than {MAX_VARIANTS}",
        ),
        (
            HEAD + "[axes]\nseed = { range = [0, 5000] }\nfirmware.ripple.mode = "
            '["paper", "recommended", "off"]\n',
            f"15000 variants (1 scenario x seed 5000 x firmware.ripple.mode 3): more than "
            f"{MAX_VARIANTS}",
        ),
        (HEAD + "[axes]\nseed = [1, 1180591620717411303424]\n", "axes.seed: seed must be an"),
        (
            HEAD + "[[zip]]\nseed = [1, 1180591620717411303424]\nfaults.seed = [1, 2]\n",
            "zip[0].seed: seed must be an",
        ),
    ],
    ids=[
        "campaign-name-newline",
        "scenario-name-newline",
        "scenario.name-axis-newline",
        "duration-under-a-sample",
        "axis-duration-under-a-sample",
        "duration-over-a-year",
        "range-over-the-cap",
        "grid-over-the-cap",
        "seed-2**70",
        "zipped-seed-2**70",
    ],
)
def test_a_campaign_the_runs_would_refuse_is_refused_before_anything_is_written(
    tmp_path, capsys, body, message
):
    path = _campaign(tmp_path, body)
    out = tmp_path / "out"
    err = _refused(tmp_path, capsys, ["campaign", str(path), "--out", str(out)], out)
    assert message in err
    assert not out.exists()


def test_the_cap_is_counted_from_the_axes_without_building_the_grid(tmp_path):
    huge = HEAD + "[axes]\nseed = { range = [0, 1000000000000000000] }\n"
    with pytest.raises(Exception, match="1000000000000000000 variants"):
        load_campaign(_campaign(tmp_path, huge))


def test_a_grid_at_the_cap_is_accepted(tmp_path):
    body = HEAD + f"duration_s = 0.01\n[axes]\nseed = {{ range = [0, {MAX_VARIANTS}] }}\n"
    campaign = load_campaign(_campaign(tmp_path, body))
    assert len(campaign.axes[0].values) == MAX_VARIANTS


def _file(tmp_path: Path) -> Path:
    path = tmp_path / "a-file"
    path.write_text("x")
    return path


@pytest.mark.parametrize(
    "where, message",
    [
        (lambda tmp: _file(tmp), "exists and is not a directory"),
        (lambda tmp: _file(tmp) / "out", "cannot write in --out"),
        (lambda tmp: tmp / "no" / "such" / "out", "does not exist"),
        (lambda tmp: tmp, "runs exists and is not a directory"),
    ],
    ids=["regular-file", "under-a-regular-file", "parent-missing", "runs-is-a-file"],
)
def test_an_unusable_out_is_refused_before_any_variant_runs(
    tmp_path, capsys, monkeypatch, where, message
):
    import hdhil.rig.campaign as campaign_module

    def no_run(*args, **kwargs):
        raise AssertionError("a variant ran")

    monkeypatch.setattr(campaign_module, "run_campaign", no_run)
    (tmp_path / "runs").write_text("not a directory")
    out = where(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    argv = ["campaign", "smoke", "--workers", "1", "--out", str(out)]
    err = _refused(tmp_path, capsys, argv, out)
    assert message in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


_Canned = CannedExecutor


@pytest.mark.parametrize(
    "damage, why",
    [
        (lambda rec: json.dumps({k: v for k, v in rec.items() if k != "wall_s"}), "wall_s"),
        (lambda rec: json.dumps({**rec, "wall_s": "soon"}), "wall_s"),
        (lambda rec: json.dumps({**rec, "result": [1]}), "result"),
        (lambda rec: json.dumps({**rec, "result": {"cycles": "ten"}}), "damaged result"),
        (lambda rec: "{not json", "not JSON"),
        (lambda rec: json.dumps([rec]), "not a JSON object"),
    ],
    ids=["no-wall_s", "wall_s-text", "result-list", "result-unjudgeable", "not-json", "not-a-dict"],
)
def test_a_damaged_stored_record_is_run_again_with_a_one_line_warning(tmp_path, damage, why):
    body = HEAD + "duration_s = 0.01\n[axes]\nseed = [1, 2]\n"
    campaign = load_campaign(_campaign(tmp_path, body))
    variants = expand(campaign)
    out = tmp_path / "out"
    (out / "runs").mkdir(parents=True)
    for v in variants:
        record = {"digest": v.digest, "variant": v.id,
                  "result": {"cycles": 10, "controller": {}, "drive": {}},
                  "error": None, "wall_s": 1.0, "worker": "there:2"}  # fmt: skip
        (out / "runs" / f"{v.digest}.json").write_text(json.dumps(record))
    damaged = out / "runs" / f"{variants[0].digest}.json"
    damaged.write_text(damage(json.loads(damaged.read_text())))
    warnings: list[str] = []
    _Canned.submitted = 0
    run = run_campaign(campaign, variants, out, _Canned, on_warning=warnings.append)
    assert run.resumed == 1 and run.ran == 1 and _Canned.submitted == 1
    assert len(warnings) == 1 and "\n" not in warnings[0]
    assert str(damaged) in warnings[0] and why in warnings[0] and "run again" in warnings[0]


def test_the_command_prints_the_warning_of_a_damaged_record(tmp_path, capsys, monkeypatch):
    import hdhil.rig.campaign as campaign_module

    def warn_once(campaign, variants, out, make_executor, on_record=None, lost_errors=(),
                  on_warning=None):  # fmt: skip
        on_warning(f"{out}/runs/x.json: not JSON: run again")
        return campaign_module.CampaignRun({}, 0, 0, False, 0, 0.0)

    import hdhil.rig.campaign_report as report_module

    monkeypatch.setattr(campaign_module, "run_campaign", warn_once)
    monkeypatch.setattr(report_module, "write_outputs", lambda *args: {"passed": 0})
    path = _campaign(tmp_path, HEAD + "duration_s = 0.01\n")
    out = tmp_path / "out"
    main(["campaign", str(path), "--workers", "1", "--out", str(out), "--json"])
    err = capsys.readouterr().err
    assert f"hdhil: warning: {out}/runs/x.json: not JSON: run again\n" in err


def _children(pid: int) -> set[int]:
    found: set[int] = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError):  # the task ended meanwhile
            found |= {int(p) for p in (task / "children").read_text().split()}
    return found


def _alive(pid: int) -> bool:
    """Running (a zombie waiting for whoever adopted it counts as ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.skipif(
    not Path("/proc/self/task").is_dir() or not sys.platform.startswith("linux"),
    reason="Linux only (PR_SET_PDEATHSIG, /proc)",
)
def test_the_workers_end_when_the_campaign_is_killed(tmp_path):
    body = HEAD + "duration_s = 5.0\n[axes]\nseed = { range = [1, 9] }\n"
    path = _campaign(tmp_path, body)
    cmd = [sys.executable, "-m", "hdhil", "campaign", str(path), "--workers", "2",
           "--out", str(tmp_path / "out")]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 60
        while len(workers) < 2:
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
            workers = _children(proc.pid)
        time.sleep(0.5)  # past the workers' initializer
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        deadline = time.monotonic() + 5
        while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not [pid for pid in workers if _alive(pid)]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for pid in workers:  # the orphans of a failed run of this test
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
