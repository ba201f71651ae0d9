"""``hdhil campaign`` validation and its resume store: every refusal is one line (keys,
file names and ``--out`` holding line breaks included), a resume store that cannot take
the re-runs is refused before anything runs, a damaged record of any kind (nested past
the stack, truncated, numbers beyond range, too large) is run again with one warning,
and a large grid is built without reading or keeping one scenario per variant."""

from __future__ import annotations

import concurrent.futures as cf
import gc
import json
import os
import queue
import subprocess
import threading
import typing
import weakref
from pathlib import Path

import pytest
from conftest import CannedExecutor

from hdhil.cli import main
from hdhil.core import dataconf
from hdhil.core.files import CONFIG_MAX_BYTES
from hdhil.rig import campaign_variants
from hdhil.rig.campaign import run_campaign
from hdhil.rig.campaign_file import load_campaign
from hdhil.rig.campaign_variants import expand

HEAD = '[campaign]\nname = "bad"\nscenarios = ["free-motion"]\nduration_s = 0.01\n'


def _campaign(tmp_path: Path, body: str, name: str = "c.toml") -> Path:
    path = tmp_path / name
    path.write_text(body, encoding="utf-8")
    return path


def _one_line_error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    captured = capsys.readouterr()
    err = captured.err
    assert err.startswith("hdhil: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    return err


# --------------------------------------------------------------------- one-line errors
@pytest.mark.parametrize(
    "body, shown",
    [
        (HEAD + '[axes]\n"x\\ny" = [1]\n', "'x\\ny'"),
        (HEAD + '[[zip]]\n"seed\\n" = [1]\n', "'seed\\n'"),
        (HEAD + '[axes.plant]\n"a\\rb" = [1]\n', "'plant.a\\rb'"),
    ],
    ids=["axis-key", "zip-key", "nested-axis-key"],
)
def test_an_axis_key_with_a_line_break_is_refused_in_one_line(tmp_path, capsys, body, shown):
    out = tmp_path / "out"
    err = _one_line_error(capsys, ["campaign", str(_campaign(tmp_path, body)), "--out", str(out)])
    assert shown in err and "one printable line" in err
    assert not out.exists()


@pytest.mark.parametrize(
    "body",
    [HEAD + "[axes]\nseed = [-1]\n", "[campaign\n", HEAD + "[nope]\n"],
    ids=["bad-value", "bad-toml", "unknown-table"],
)
def test_a_campaign_file_named_with_a_line_break_is_refused_in_one_line(tmp_path, capsys, body):
    path = _campaign(tmp_path, body, name="my\ncampaign.toml")
    err = _one_line_error(capsys, ["campaign", str(path), "--out", str(tmp_path / "out")])
    assert "my\\ncampaign.toml" in err
    assert not (tmp_path / "out").exists()


def test_a_missing_campaign_file_named_with_a_line_break_is_refused_in_one_line(tmp_path, capsys):
    err = _one_line_error(capsys, ["campaign", str(tmp_path / "no\nsuch.toml")])
    assert "no\\nsuch.toml" in err


def test_an_unusable_out_named_with_a_line_break_is_refused_in_one_line(tmp_path, capsys):
    blocker = tmp_path / "a\nfile"
    blocker.write_text("x")
    path = _campaign(tmp_path, HEAD)
    err = _one_line_error(capsys, ["campaign", str(path), "--out", str(blocker / "out")])
    assert "a\\nfile" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a\nfile", "c.toml"]


@pytest.mark.subprocess
def test_an_out_on_a_read_only_file_system_is_refused_leaving_nothing(tmp_path, capsys):
    if os.geteuid() != 0:
        pytest.skip("mounting a read-only tmpfs needs root")
    mnt = tmp_path / "ro"
    mnt.mkdir()
    mount = ["mount", "-t", "tmpfs", "-o", "ro,size=256k", "tmpfs", str(mnt)]
    if subprocess.run(mount, capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        path = _campaign(tmp_path, HEAD)
        err = _one_line_error(capsys, ["campaign", str(path), "--out", str(mnt / "out")])
        assert "cannot write in --out" in err
        assert list(mnt.iterdir()) == []
    finally:
        subprocess.run(["umount", str(mnt)], check=True)


# ------------------------------------------------------------------------ resume store
_Canned = CannedExecutor


_RESULT = {"cycles": 10, "controller": {}, "drive": {}}


def _stored(tmp_path: Path, body: str = HEAD + "[axes]\nseed = [1, 2]\n"):
    """A campaign of two variants, both with a good stored record."""
    campaign = load_campaign(_campaign(tmp_path, body))
    variants = expand(campaign)
    out = tmp_path / "out"
    (out / "runs").mkdir(parents=True)
    for v in variants:
        record = {"digest": v.digest, "variant": v.id, "result": _RESULT,
                  "error": None, "wall_s": 1.0, "worker": "there:2"}  # fmt: skip
        (out / "runs" / f"{v.digest}.json").write_text(json.dumps(record))
    return campaign, variants, out


@pytest.mark.parametrize(
    "damage, why",
    [
        (lambda rec: "[" * 100_000 + "]" * 100_000, "not JSON"),
        (lambda rec: json.dumps(rec)[:40], "not JSON"),
        (
            lambda rec: json.dumps({**rec, "result": {**_RESULT, "cycles": 1e999}}).replace(
                "Infinity", "1e999"
            ),
            "damaged result (OverflowError)",
        ),
        (lambda rec: json.dumps(rec) + " " * CONFIG_MAX_BYTES, "bytes"),
        (lambda rec: json.dumps({**rec, "wall_s": 1.0}).replace("1.0", "1e999"), "wall_s"),
        (lambda rec: json.dumps({**rec, "result": None}), "neither a result nor an error"),
    ],
    ids=[
        "nested-past-the-stack",
        "truncated",
        "cycles-beyond-int",
        "too-large",
        "wall_s-inf",
        "result-null",
    ],
)
def test_a_damaged_record_is_run_again_with_one_warning(tmp_path, damage, why):
    campaign, variants, out = _stored(tmp_path)
    damaged = out / "runs" / f"{variants[0].digest}.json"
    text = damage(json.loads(damaged.read_text()))
    damaged.write_text(text)
    warnings: list[str] = []
    _Canned.submitted = 0
    run = run_campaign(campaign, variants, out, _Canned, on_warning=warnings.append)
    assert run.resumed == 1 and run.ran == 1 and _Canned.submitted == 1
    assert len(warnings) == 1 and "\n" not in warnings[0], warnings
    assert str(damaged) in warnings[0] and why in warnings[0] and "run again" in warnings[0]
    assert json.loads(damaged.read_text())["error"] == "RuntimeError: canned"  # replaced


def test_a_record_that_is_a_directory_is_refused_before_anything_runs(tmp_path):
    campaign, variants, out = _stored(tmp_path)
    record = out / "runs" / f"{variants[1].digest}.json"
    record.unlink()
    record.mkdir()
    warnings: list[str] = []
    _Canned.submitted = 0
    with pytest.raises(ValueError, match="is not a regular file: variant 0002") as info:
        run_campaign(campaign, variants, out, _Canned, on_warning=warnings.append)
    assert "\n" not in str(info.value)
    assert _Canned.submitted == 0 and warnings == []
    assert record.is_dir() and not any(record.iterdir())


def test_a_trace_path_that_is_a_directory_is_refused_before_anything_runs(tmp_path):
    body = HEAD + 'keep_trace = true\ntrace_format = "asc"\n[axes]\nseed = [1, 2]\n'
    campaign, variants, out = _stored(tmp_path, body)
    trace = out / "traces" / f"{variants[0].id}-{variants[0].digest}.asc"
    trace.mkdir(parents=True)
    _Canned.submitted = 0
    _Canned.trace = b"trace"
    try:
        with pytest.raises(ValueError, match="is not a regular file: variant 0001"):
            run_campaign(campaign, variants, out, _Canned, on_warning=lambda m: None)
    finally:
        _Canned.trace = None
    assert _Canned.submitted == 0
    assert sorted(p.name for p in (out / "traces").iterdir()) == [trace.name]


def test_the_command_refuses_a_store_that_cannot_take_a_rerun_in_one_line(tmp_path, capsys):
    campaign, variants, out = _stored(tmp_path, HEAD)
    record = out / "runs" / f"{variants[0].digest}.json"
    record.unlink()
    record.mkdir()
    argv = ["campaign", campaign.source, "--workers", "1", "--out", str(out)]
    err = _one_line_error(capsys, argv)
    assert "is not a regular file" in err
    assert sorted(p.name for p in out.iterdir()) == ["runs"]


def test_a_finished_variant_s_trace_is_not_kept_while_the_campaign_runs(tmp_path):
    body = HEAD + 'keep_trace = true\ntrace_format = "asc"\n[axes]\nseed = { range = [0, 12] }\n'
    campaign = load_campaign(_campaign(tmp_path, body))
    variants = expand(campaign)
    alive: weakref.WeakSet[cf.Future] = weakref.WeakSet()
    queued: queue.Queue[cf.Future] = queue.Queue()
    recorded = threading.Semaphore(0)
    most = 0

    class OneAtATime(cf.Executor):
        """Finishes one variant, with a trace, once the one before it was recorded."""

        def submit(self, fn, /, *args, **kwargs):
            fut: cf.Future = cf.Future()
            alive.add(fut)
            queued.put(fut)
            return fut

    def finish_in_turn() -> None:
        for _ in variants:
            fut = queued.get(timeout=10)
            fut.set_result({"result": None, "error": "RuntimeError: canned", "trace": b"t",
                            "sidecar": None, "wall_s": 0.0, "worker": "here:1"})  # fmt: skip
            del fut
            if not recorded.acquire(timeout=10):
                return

    def on_record(record) -> None:
        nonlocal most
        gc.collect()
        most = max(most, sum(1 for f in alive if f.done()))
        recorded.release()

    worker = threading.Thread(target=finish_in_turn, daemon=True)
    worker.start()
    run = run_campaign(campaign, variants, tmp_path / "out", OneAtATime, on_record)
    worker.join(timeout=10)
    assert run.ran == 12
    assert most == 1  # only the one being recorded


# ------------------------------------------------------------------------- large grids
def test_variants_that_differ_in_the_seed_share_one_read_and_one_scenario(tmp_path, monkeypatch):
    modes = 'firmware.ripple.mode = ["paper", "recommended"]\n'
    body = HEAD + "[axes]\nseed = { range = [0, 40] }\n" + modes
    campaign = load_campaign(_campaign(tmp_path, body))
    reads: list[str] = []
    real = campaign_variants.scenario_file_data

    def counted(name):
        reads.append(name)
        return real(name)

    monkeypatch.setattr(campaign_variants, "scenario_file_data", counted)
    variants = expand(campaign)
    assert len(variants) == 80 and len({v.digest for v in variants}) == 80
    assert reads == ["free-motion"]
    assert len({id(v.settings.scenario) for v in variants}) == 2


def test_a_dataclass_type_hints_are_resolved_once(monkeypatch):
    from hdhil.rig.scenario import load_scenario

    load_scenario("free-motion")  # every configuration class seen once
    calls: list[type] = []
    real = typing.get_type_hints

    def counted(cls, *args, **kwargs):
        calls.append(cls)
        return real(cls, *args, **kwargs)

    monkeypatch.setattr(dataconf.typing, "get_type_hints", counted)
    load_scenario("free-motion", {"plant": {"drivetrain": {"b_motor": 2.0}}})
    assert calls == []
