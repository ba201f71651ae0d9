"""``hdhil campaign``: the same bytes on 1 worker, 2 workers and a real Dask cluster;
resume after an interrupt; failing variants recorded, not fatal; a variant is
``hdhil run``; bad campaign files rejected before anything runs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hdhil.cli import main
from hdhil.rig.campaign import local_executor, run_campaign
from hdhil.rig.campaign_file import load_campaign
from hdhil.rig.campaign_variants import expand
from hdhil.rig.variant import WALL_CLOCK_KEYS

distributed = pytest.importorskip("distributed", reason="the cluster extra (hdhil[cluster])")


def _campaign(tmp_path: Path, body: str, name: str = "c.toml") -> Path:
    path = tmp_path / name
    path.write_text(body, encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def cluster():
    """A real Dask cluster: a scheduler and two worker processes on loopback."""
    with distributed.LocalCluster(
        processes=True,
        n_workers=2,
        threads_per_worker=1,
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",  # loopback, any free port
    ) as c:
        yield c


@pytest.fixture(scope="module")
def smoke_local(tmp_path_factory):
    """The shipped smoke campaign on one local worker."""
    out = tmp_path_factory.mktemp("smoke1")
    assert main(["campaign", "smoke", "--workers", "1", "--out", str(out), "--json"]) == 0
    return out


@pytest.mark.slow
@pytest.mark.subprocess
def test_smoke_gives_the_same_results_csv_on_1_and_2_workers_and_a_dask_cluster(
    smoke_local, tmp_path, cluster, capsys
):
    capsys.readouterr()
    two = tmp_path / "two"
    dask = tmp_path / "dask"
    assert main(["campaign", "smoke", "--workers", "2", "--out", str(two), "--json"]) == 0
    summary2 = json.loads(capsys.readouterr().out)
    args = ["campaign", "smoke", "--scheduler", cluster.scheduler_address, "--out", str(dask)]
    assert main([*args, "--json"]) == 0
    summary_dask = json.loads(capsys.readouterr().out)
    one = (smoke_local / "results.csv").read_bytes()
    assert one == (two / "results.csv").read_bytes()
    assert one == (dask / "results.csv").read_bytes()
    lines = one.decode().splitlines()
    assert len(lines) == 1 + 8 and summary2["ran"] == summary_dask["ran"] == 8
    assert [line.split(",")[0] for line in lines[1:]] == [f"{i:04d}" for i in range(1, 9)]
    # The work was spread: two local processes, and the cluster's own workers.
    workers = {line.split(",")[3] for line in (two / "timings.csv").read_text().splitlines()[1:]}
    assert len(workers) == 2
    timings = (dask / "timings.csv").read_text().splitlines()[1:]
    dask_pids = _worker_pids(cluster)
    assert {t.split(",")[3].rsplit(":", 1)[1] for t in timings} <= dask_pids
    for out in (two, dask):
        assert (out / "report.md").read_text().count("| `") == 3  # the three criteria
        assert list((out / "plots").glob("*.png"))
    if _has_pyarrow():
        import pyarrow.parquet as pq

        table = pq.read_table(dask / "results.parquet")
        assert table.num_rows == 8
        assert table.column("filtered_rms_err_Nm").to_pylist() == [
            float(line.split(",")[lines[0].split(",").index("filtered_rms_err_Nm")])
            for line in lines[1:]
        ]


def _worker_pids(cluster) -> set[str]:
    with distributed.Client(cluster) as client:
        return {str(pid) for pid in client.run(os.getpid).values()}


def _has_pyarrow() -> bool:
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.mark.slow
def test_a_variant_is_what_hdhil_run_json_prints_for_the_same_settings(
    smoke_local, tmp_path, capsys
):
    campaign = load_campaign("smoke")
    variant = next(
        v
        for v in expand(campaign)
        if v.values
        == {"firmware.ripple.mode": "paper", "faults.control.loss_rate": 0.02, "seed": 2}
    )
    stored = json.loads((smoke_local / "runs" / f"{variant.digest}.json").read_text())
    override = tmp_path / "paper.toml"
    override.write_text('[firmware.ripple]\nmode = "paper"\n')
    capsys.readouterr()
    code = main(
        ["run", "--scenario", "free-motion", "--duration", "1", "--seed", "2", "--trace", "",
         "--fault", "control.loss_rate=0.02", "--override", str(override), "--json"]
    )  # fmt: skip
    assert code == 0
    printed = json.loads(capsys.readouterr().out)
    for key in WALL_CLOCK_KEYS:
        printed.pop(key, None)
    assert printed["faults"]["loss"] > 0  # the fault did act
    assert json.dumps(stored["result"], sort_keys=True) == json.dumps(printed, sort_keys=True)
    # ... and the row of results.csv carries its figures.
    head, *rows = (smoke_local / "results.csv").read_text().splitlines()
    row = dict(zip(head.split(","), rows[int(variant.id) - 1].split(","), strict=True))
    assert float(row["filtered_rms_err_Nm"]) == printed["headline"]["value_Nm"]
    assert float(row["filtered_rms_err_whole_run_Nm"]) == printed["torque"]["rms_error_filtered"]
    assert int(row["cycles"]) == printed["cycles"] == 1000


FAILING = """
[campaign]
name = "failing"
scenarios = ["free-motion"]
duration_s = 0.4
criteria = ["stopped_early == false", "filtered_rms_err_Nm < {threshold}"]

[axes]
faults.control.loss_rate = [0.0, 1.0]
seed = [1, 2]
"""


@pytest.mark.slow
@pytest.mark.subprocess
def test_stopped_and_errored_variants_are_recorded_and_the_campaign_goes_on(tmp_path, capsys):
    # Every control frame lost: the drive never reaches operation, the run stops in
    # start-up (a verdict: it fails its criteria, with the reason).  The clean variants
    # have a filtered RMS error of about 0.024 Nm from the scenario's evaluation start
    # (0.3 s): 0.01 fails them, 1.0 passes them.
    for threshold, clean_status in ((0.01, "fail"), (1.0, "pass")):
        path = _campaign(tmp_path, FAILING.format(threshold=threshold))
        out = tmp_path / f"out-{threshold}"
        assert main(["campaign", str(path), "--workers", "2", "--out", str(out), "--json"]) == 1
        summary = json.loads(capsys.readouterr().out)
        assert summary["errors"] == 0 and summary["recorded"] == 4
        head, *rows = (out / "results.csv").read_text().splitlines()
        status = head.split(",").index("status")
        by_loss = {}
        for line in rows:
            cells = line.split(",")
            by_loss.setdefault(cells[2], []).append(cells[status])
        assert by_loss == {"0.0": [clean_status] * 2, "1.0": ["fail"] * 2}
        assert "did not reach operation enabled" in (out / "results.csv").read_text()
        assert "did not reach operation enabled" in (out / "report.md").read_text()
    # A re-run keeps the results and runs again only the variants that raised: two
    # stored records are turned into errors, as a worker that failed would leave them.
    stored = sorted((out / "runs").glob("*.json"))
    for record in stored[:2]:
        data = json.loads(record.read_text())
        data.update(result=None, error="RuntimeError: the worker's environment failed")
        record.write_text(json.dumps(data))
    assert main(["campaign", str(path), "--workers", "1", "--out", str(out), "--json"]) == 1
    again = json.loads(capsys.readouterr().out)
    assert again["ran"] == 2 and again["resumed"] == 2 and again["errors"] == 0


RESUME = """
[campaign]
name = "resume"
scenarios = ["free-motion"]
duration_s = 2.0
criteria = ["stopped_early == false"]

[axes]
firmware.ripple.mode = ["paper", "recommended"]
seed = {{ range = [1, {n}] }}
"""


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_an_interrupted_campaign_keeps_its_results_and_a_rerun_completes_it(tmp_path, sig):
    path = _campaign(tmp_path, RESUME.format(n=8))  # 14 variants of 2 s
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "hdhil", "campaign", str(path), "--workers", "1",
           "--out", str(out)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while len(list((out / "runs").glob("*.json"))) < 3:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.01)
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    assert "interrupted" in stderr and "Traceback" not in stderr
    assert "not run" in stdout  # the summary of what finished is still printed
    partial = (out / "results.csv").read_text().splitlines()
    stored = len(list((out / "runs").glob("*.json")))
    assert 3 <= len(partial) - 1 <= stored < 14
    # Run again: only the rest runs, and the result is the uninterrupted campaign's.
    done = subprocess.run([*cmd, "--json"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["resumed"] == stored and summary["ran"] == 14 - stored
    fresh = tmp_path / "fresh"
    assert main(["campaign", str(path), "--workers", "2", "--out", str(fresh)]) == 0
    complete = (out / "results.csv").read_bytes()
    assert complete == (fresh / "results.csv").read_bytes()
    assert set(partial[1:]) <= set(complete.decode().splitlines()[1:])
    resumed = [t.split(",")[4] for t in (out / "timings.csv").read_text().splitlines()[1:]]
    assert resumed.count("true") == stored


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_lost_local_worker_gets_its_variants_run_again(tmp_path):
    path = _campaign(tmp_path, RESUME.format(n=4))  # 6 variants
    campaign = load_campaign(path)
    variants = expand(campaign)
    killed: list[int] = []

    def kill_one_worker(record) -> None:
        if not killed:  # the worker that ran the first variant, busy with the next
            killed.append(int(record.worker.rsplit(":", 1)[1]))
            os.kill(killed[0], signal.SIGKILL)

    run = run_campaign(campaign, variants, tmp_path / "a", lambda: local_executor(2),
                       kill_one_worker)  # fmt: skip
    assert killed and run.lost >= 1
    assert len(run.records) == 6
    assert all(r.error is None and r.status == "pass" for r in run.records.values())


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_lost_dask_worker_gets_its_variant_run_again(tmp_path, cluster):
    path = _campaign(tmp_path, RESUME.format(n=4))
    campaign = load_campaign(path)
    variants = expand(campaign)
    with distributed.Client(cluster) as client:
        pids = set(client.run(os.getpid).values())
        killed: list[int] = []

        def kill_one_worker(record) -> None:
            if not killed:  # the worker that ran the first variant, busy with the next
                killed.append(int(record.worker.rsplit(":", 1)[1]))
                assert killed[0] in pids
                os.kill(killed[0], signal.SIGKILL)

        run = run_campaign(campaign, variants, tmp_path / "d",
                           lambda: client.get_executor(pure=False), kill_one_worker)  # fmt: skip
        assert killed
        assert len(run.records) == 6
        assert all(r.error is None and r.status == "pass" for r in run.records.values())
        client.wait_for_workers(2, timeout=60)  # the nanny restarted it for the next test


@pytest.mark.parametrize(
    "body, message",
    [
        ('criteria = ["filtered_rms_err < 0.1"]', "unknown metric 'filtered_rms_err'"),
        ('criteria = ["stopped_early < 3"]', "stopped_early is true or false"),
        ('criteria = ["filtered_rms_err_Nm ~ 3"]', "is not 'METRIC OP VALUE'"),
        ('plots = ["nope"]', "unknown metric 'nope'"),
        ("[axes]\nplant.drivetrain.b_motr = [1.0, 2.0]", "unknown key plant.drivetrain.b_motr"),
        ('[axes]\nfirmware.ripple.mod = ["paper"]', "unknown key firmware.ripple.mod"),
        ("[axes]\nfaults.control.loss_rate = [0.0, -1.0]", "faults.control.loss_rate"),
        ("[axes]\nseed = { range = [0] }", "range takes 2 or 3 integers"),
        ("[axes]\nsed = [1, 2]", "axis sed: not a scenario key"),
        ("[[zip]]\nseed = [1, 2]\nfaults.seed = [1]", "zipped axes need equal lengths"),
        ("[axes]\nseed = [1, 1]", "same settings as variant 0001"),
        ("[campaign.extra]\nx = 1", "unknown key campaign.extra"),
    ],
)
def test_bad_campaign_files_are_one_line_errors_before_anything_runs(
    tmp_path, capsys, body, message
):
    head = '[campaign]\nname = "bad"\nscenarios = ["free-motion"]\n'
    path = _campaign(tmp_path, head + body + "\n")
    out = tmp_path / "out"
    assert main(["campaign", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hdhil: error: ") and err.count("\n") == 1
    assert message in err
    assert not out.exists()


def test_unknown_campaign_name_and_missing_dask_are_one_line_errors(tmp_path, capsys, monkeypatch):
    assert main(["campaign", "no-such-campaign", "--out", str(tmp_path / "x")]) == 2
    assert "unknown campaign 'no-such-campaign' (known: loss-robustness, smoke" in (
        capsys.readouterr().err
    )
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    out = tmp_path / "y"
    code = main(["campaign", "smoke", "--scheduler", "tcp://127.0.0.1:1", "--out", str(out)])
    assert code == 2
    err = capsys.readouterr().err
    assert err == "hdhil: error: --scheduler needs Dask distributed: pip install 'hdhil[cluster]'\n"
    assert not (out / "runs").exists()


def _stderr_on_a_terminal(argv: list[str]) -> tuple[int, str]:
    """Run hdhil with its standard error on a pseudo-terminal of 120 columns."""
    import fcntl
    import pty
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    proc = subprocess.Popen([sys.executable, "-m", "hdhil", *argv], stdout=subprocess.DEVNULL,
                            stderr=slave)  # fmt: skip
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:  # the terminal closed with the process
            break
        if not data:
            break
        chunks.append(data)
    os.close(master)
    return proc.wait(timeout=120), b"".join(chunks).decode(errors="replace")


@pytest.mark.slow
@pytest.mark.subprocess
def test_progress_on_a_terminal_with_eta_and_running_counts_off_with_json(tmp_path):
    path = _campaign(tmp_path, RESUME.format(n=3))  # 4 variants
    out = tmp_path / "out"
    code, err = _stderr_on_a_terminal(["campaign", str(path), "--workers", "2", "--out", str(out)])
    assert code == 0
    frames = err.split("\r")
    assert any("0/4" in f and "?" in f for f in frames)  # ETA unknown at the start
    assert any("4/4" in f and "pass 4 fail 0 error 0" in f for f in frames)
    assert any("<00:" in f for f in frames)  # elapsed<remaining
    code, err = _stderr_on_a_terminal(["campaign", str(path), "--out", str(out), "--json"])
    assert code == 0 and "4/4" not in err and "pass 4" not in err


@pytest.mark.slow
@pytest.mark.subprocess
def test_an_early_stop_is_recorded_with_the_runs_own_reason():
    from hdhil.rig.campaign_metrics import judge

    variant = expand(load_campaign("smoke"))[0]
    criteria = load_campaign("smoke").criteria
    result = json.loads((Path(__file__).parent / "data" / "campaign-stopped-run.json").read_text())
    metrics, verdicts, reasons = judge(variant, result, None, criteria)
    assert metrics["stopped_early"] is True and metrics["cycles"] == 402
    # A run stopped early has no evaluation: the error criterion cannot pass.
    assert verdicts == {
        "stopped_early == false": False,
        "filtered_rms_err_Nm < 0.1": False,
        "covariance_finite == true": True,
    }
    assert reasons[0] == (
        "stopped early at 0.402 s of 1 s (402 of 1000 samples) by node 1: the drive reported "
        "a fault; EMCY received 0x8130 Life guard or heartbeat error"
    )
    assert reasons[1] == "stopped_early = true, not == false"
