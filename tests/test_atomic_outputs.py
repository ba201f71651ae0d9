"""Every output is written whole or not at all, also on a full disk, and never over an
input: a trace and its sidecar land together (with the run's fault log) or leave the
old files exactly as they were; the fault log is written through a temporary; a command
that could not write an output exits non-zero with one ``hdhil: error:`` line and leaves
no temporary behind; an output naming one of the command's inputs (or another of its
outputs) is refused before any work; only regular files are ever replaced.

The full-disk tests mount a small tmpfs of their own (root only; they skip otherwise).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from conftest import fill_fs

from hdhil.cli import main
from hdhil.core.errors import UserError
from hdhil.core.faultbase import FaultLog
from hdhil.core.files import temporary_for
from hdhil.rig.scenario import scenario_path

#: Frames of a short run are a deterministic function of these (``--start-time`` fixed).
RUN = ["run", "--duration", "0.3", "--no-evaluate", "-q", "--start-time", "0"]
#: Faults enough to fill a page of fault log within the run.
FAULTS = ["--fault", "control.loss_rate=0.2"]
OLD = b"the old file\n"


# ----------------------------------------------------------------------------- helpers
_fill = fill_fs


def _pages(n: int) -> int:
    return -(-n // 4096) * 4096


def _stray(*dirs: Path) -> list[str]:
    """Temporaries (and backups) hdhil left in ``dirs``."""
    return [p.name for d in dirs for p in d.iterdir() if ".hdhil-" in p.name]


def _errors(capsys: pytest.CaptureFixture[str]) -> list[str]:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return [line for line in err.splitlines() if line.startswith("hdhil: error:")]


def _old(*paths: Path) -> None:
    for p in paths:
        p.write_bytes(OLD)


@pytest.fixture(scope="module")
def traces(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short free-motion trace ``r.blf`` with its sidecar."""
    where = tmp_path_factory.mktemp("traces")
    assert main([*RUN, "--trace", str(where / "r.blf")]) == 0
    return where


@pytest.fixture(scope="module")
def chirp(traces: Path) -> Path:
    """A chirp short enough to be cheap and long enough to identify: ``c.blf``."""
    override = traces / "short-chirp.toml"
    override.write_text("[firmware.reference]\nchirp_end_Hz = 30.0\nchirp_duration_s = 3.0\n")
    assert main(["run", "--scenario", "chirp", "--override", str(override), "--duration", "3",
                 "--no-evaluate", "-q", "--trace", str(traces / "c.blf")]) == 0  # fmt: skip
    return traces


# ------------------------------------------------------ 1. the trace and its sidecar
@pytest.mark.slow
def test_a_sidecar_the_disk_cannot_take_leaves_the_old_trace_and_sidecar(tmp_path, tiny_fs, capsys):
    # the trace of these settings is byte-identical whatever the directory: its size is
    # known, and the disk is left room for exactly the trace, not for its sidecar
    assert main([*RUN, "--trace", str(tmp_path / "probe.blf")]) == 0
    size = (tmp_path / "probe.blf").stat().st_size
    capsys.readouterr()
    trace, side = tiny_fs / "r.blf", tiny_fs / "r.blf.json"
    trace.write_bytes(b"")  # an empty old trace: replacing it frees no page
    side.write_bytes(OLD)
    _fill(tiny_fs, _pages(size))
    assert main([*RUN, "--trace", str(trace)]) == 2
    errors = _errors(capsys)
    assert len(errors) == 1 and "sidecar" in errors[0] and "No space" in errors[0]
    assert trace.read_bytes() == b"" and side.read_bytes() == OLD  # the old pair, as it was
    assert _stray(tiny_fs) == []


# ------------------------------------------------------------------- 2. the fault log
@pytest.mark.slow
@pytest.mark.parametrize("with_trace", [False, True])
def test_a_fault_log_the_disk_cannot_take_leaves_the_old_log(tmp_path, tiny_fs, capsys, with_trace):
    log = tiny_fs / "faults.jsonl"
    trace = tmp_path / "r.blf"
    _old(log, trace, tmp_path / "r.blf.json")
    _fill(tiny_fs)
    args = [*RUN, *FAULTS, "--fault-log", str(log), "--trace", str(trace) if with_trace else ""]
    assert main(args) == 2
    errors = _errors(capsys)
    assert len(errors) == 1 and f"fault log {log}" in errors[0] and "No space" in errors[0]
    assert log.read_bytes() == OLD
    # one output: the trace and its sidecar are not replaced either
    assert trace.read_bytes() == OLD and (tmp_path / "r.blf.json").read_bytes() == OLD
    assert _stray(tiny_fs, tmp_path) == []


@pytest.mark.slow
def test_the_fault_log_lands_with_the_trace(tmp_path, capsys):
    log, trace = tmp_path / "faults.jsonl", tmp_path / "r.blf"
    _old(log)
    assert main([*RUN, *FAULTS, "--fault-log", str(log), "--trace", str(trace)]) == 0
    lines = log.read_text().splitlines()
    assert lines and all(line.startswith("{") for line in lines)
    assert trace.exists() and _stray(tmp_path) == []


@pytest.mark.slow
def test_a_run_without_faults_writes_an_empty_fault_log(tmp_path):
    log = tmp_path / "faults.jsonl"
    _old(log)  # a previous run's log never passes for this one's
    assert main([*RUN, "--trace", "", "--fault-log", str(log)]) == 0
    assert log.read_bytes() == b"" and _stray(tmp_path) == []


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_killed_run_keeps_every_fault_with_its_trace(tmp_path):
    """SIGKILL of the run: the trace writer renames the fault log (flushed per fault)
    into place with the trace and its sidecar."""
    trace, log = tmp_path / "killed.blf", tmp_path / "faults.jsonl"
    _old(trace, log)
    script = textwrap.dedent(f"""
        import os, signal, can
        from pathlib import Path
        from hdhil.can.traces.writer import WriterProcess
        from hdhil.core.faultbase import FaultLog
        log = FaultLog(Path({str(log)!r}))
        w = WriterProcess(Path({str(trace)!r}), metadata={{"kind": "test"}},
                          companions=(log.hand_over(),))
        for i in range(3):
            log.record(i * 1e-3, "control", "loss", 0x181)
            w.on_message_received(can.Message(timestamp=i * 1e-3, arbitration_id=0x80,
                                              data=bytes([i]), channel=0))
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], timeout=60)
    assert proc.returncode == -9
    deadline = time.monotonic() + 30
    while (_stray(tmp_path) or log.read_bytes() == OLD) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert [json.loads(line)["kind"] for line in log.read_text().splitlines()] == ["loss"] * 3
    assert trace.read_bytes()[:4] == b"LOGG" and (tmp_path / "killed.blf.json").exists()
    assert _stray(tmp_path) == []


def test_a_fault_log_is_written_through_a_temporary(tmp_path):
    path = tmp_path / "faults.jsonl"
    _old(path)
    log = FaultLog(path)
    log.record(0.5, "control", "loss", 0x181)
    assert path.read_bytes() == OLD  # the old log until the new one is complete
    (tmp,) = _stray(tmp_path)
    assert '"loss"' in (tmp_path / tmp).read_text()  # flushed as the fault is injected
    log.close()
    assert '"loss"' in path.read_text() and _stray(tmp_path) == []
    again = FaultLog(path)
    again.record(1.0, "control", "loss", 0x182)
    again.discard()  # a failed run: the log it replaced stays
    assert '"loss"' in path.read_text() and "0.5" in path.read_text()
    assert _stray(tmp_path) == []


# ---------------------------------------------- 3. every output on a full disk fails
def _sweep(traces: Path, fs: Path) -> dict[str, tuple[list[str], Path]]:
    """Each output of every command (but campaign's), on the full disk ``fs``."""
    r, c = traces / "r.blf", traces / "c.blf"
    return {
        "run trace": ([*RUN, "--trace", str(fs / "o.blf")], fs / "o.blf"),
        "run fault log": ([*RUN, *FAULTS, "--trace", "", "--fault-log", str(fs / "o.jsonl")],
                          fs / "o.jsonl"),
        "soak trace": (["soak", "--duration", "0.5", "-q", "--trace", str(fs / "o.blf")],
                       fs / "o.blf"),
        "dump --csv": (["dump", str(r), "--csv", str(fs / "o.csv")], fs / "o.csv"),
        "dump --csv --per-frame": (["dump", str(r), "--per-frame", "--csv", str(fs / "o.csv")],
                                   fs / "o.csv"),
        "filter --out": (["filter", str(r), "--out", str(fs / "o.csv")], fs / "o.csv"),
        "plot --out": (["plot", str(r), "--out", str(fs / "o.png")], fs / "o.png"),
        "tune --out": (["tune", str(r), "-q", "--max-evals", "1", "--skip", "0",
                        "--out", str(fs / "o.toml")], fs / "o.toml"),
        "calibrate --out": (["calibrate", "-q", "--positions", "1", "--samples", "10",
                             "--out", str(fs / "o.toml")], fs / "o.toml"),
        "calibrate --plot": (["calibrate", "-q", "--positions", "1", "--samples", "10",
                              "--plot", str(fs / "o.png")], fs / "o.png"),
        "identify --plot": (["identify", str(c), "-q", "--segment", "1",
                             "--plot", str(fs / "o.png")], fs / "o.png"),
        "dbc export": (["dbc", "export", str(fs / "o.dbc")], fs / "o.dbc"),
    }  # fmt: skip


SWEEP = list(_sweep(Path("r"), Path("fs")))


@pytest.mark.slow
@pytest.mark.parametrize("case", SWEEP)
def test_every_output_on_a_full_disk_is_an_error_and_leaves_the_old_file(
    chirp, tiny_fs, capsys, case
):
    args, out = _sweep(chirp, tiny_fs)[case]
    _old(out)
    _fill(tiny_fs)
    capsys.readouterr()
    assert main(args) == 2
    errors = _errors(capsys)
    assert len(errors) == 1, errors
    assert "No space" in errors[0]
    assert out.read_bytes() == OLD
    assert _stray(tiny_fs) == []


@pytest.mark.slow
def test_calibrate_writes_its_plot_and_its_file_together_or_neither(tmp_path, tiny_fs, capsys):
    plot, out = tmp_path / "cal.png", tiny_fs / "cal.toml"
    _old(plot, out)
    _fill(tiny_fs)
    args = ["calibrate", "-q", "--positions", "1", "--samples", "10"]
    assert main([*args, "--plot", str(plot), "--out", str(out)]) == 2
    assert len(_errors(capsys)) == 1
    assert plot.read_bytes() == OLD and out.read_bytes() == OLD
    assert _stray(tmp_path, tiny_fs) == []


@pytest.mark.slow
@pytest.mark.subprocess
def test_standard_output_to_a_full_disk_is_an_error(tiny_fs):
    out = tiny_fs / "version.txt"
    _fill(tiny_fs)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    with open(out, "wb") as fh:
        done = subprocess.run([sys.executable, "-m", "hdhil", "--version"], stdout=fh,
                              stderr=subprocess.PIPE, text=True, env=env)  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [
        "hdhil: error: cannot write standard output (No space left on device)"
    ]


# ------------------------------------------------ 4. never over one of its own inputs
def _own_inputs(traces: Path, tmp: Path) -> dict[str, tuple[list[str], Path]]:
    r = tmp / "r.blf"
    shutil.copy(traces / "r.blf", r)
    shutil.copy(traces / "r.blf.json", tmp / "r.blf.json")
    (tmp / "link.png").symlink_to(r)
    os.link(r, tmp / "hard.csv")
    scenario = tmp / "s.toml"
    shutil.copy(scenario_path("free-motion"), scenario)
    override = tmp / "o.toml"
    override.write_text("[firmware]\n")
    side = str(tmp / "r.blf.json")
    return {
        "dump --csv the sidecar": (["dump", str(r), "--csv", side], tmp / "r.blf.json"),
        "dump --csv a hard link of the trace": (["dump", str(r), "--csv", str(tmp / "hard.csv")],
                                                r),
        "filter --out the sidecar": (["filter", str(r), "--out", side], tmp / "r.blf.json"),
        "tune --out the scenario": (["tune", str(r), "--skip", "0", "--scenario", str(scenario),
                                     "--out", str(scenario)], scenario),
        "plot --out a link to the trace": (["plot", str(r), "--out", str(tmp / "link.png")], r),
        "identify --plot a link to the trace": (["identify", str(r), "--plot",
                                                 str(tmp / "link.png")], r),
        "calibrate --out the scenario": (["calibrate", "--scenario", str(scenario),
                                          "--out", str(scenario)], scenario),
        "run --fault-log an override": ([*RUN, "--override", str(override), "--trace", "",
                                         "--fault-log", str(override)], override),
        "run --fault-log the run's sidecar": ([*RUN, "--trace", str(r), "--fault-log", side],
                                              tmp / "r.blf.json"),
    }  # fmt: skip


OWN_INPUTS = [
    "dump --csv the sidecar",
    "dump --csv a hard link of the trace",
    "filter --out the sidecar",
    "tune --out the scenario",
    "plot --out a link to the trace",
    "identify --plot a link to the trace",
    "calibrate --out the scenario",
    "run --fault-log an override",
    "run --fault-log the run's sidecar",
]


@pytest.mark.slow
@pytest.mark.parametrize("case", OWN_INPUTS)
def test_a_command_never_writes_over_its_own_inputs(traces, tmp_path, capsys, case):
    table = _own_inputs(traces, tmp_path)
    assert set(table) == set(OWN_INPUTS)
    args, kept = table[case]
    before = {p: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    capsys.readouterr()
    assert main(args) == 2
    errors = _errors(capsys)
    assert len(errors) == 1 and ("would overwrite" in errors[0] or "also the" in errors[0])
    assert {p: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before
    assert kept.exists() and _stray(tmp_path) == []


def test_an_output_is_checked_against_inputs_and_other_outputs(tmp_path):
    from hdhil.core.files import check_not_inputs

    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    _old(a)
    (tmp_path / "sub").mkdir()
    check_not_inputs([(b, "--out")], [(a, "input")])
    with pytest.raises(UserError, match="would overwrite the input"):
        check_not_inputs([(tmp_path / "sub" / ".." / "a.txt", "--out")], [(a, "input")])
    with pytest.raises(UserError, match="two outputs cannot be one file"):
        check_not_inputs([(b, "--out"), (b, "--plot")], [])
    check_not_inputs([("-", "--out"), (None, "--plot")], [("-", "input")])


# ----------------------------------------------- 5. only regular files are replaced
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["directory", "fifo"])
def test_a_sidecar_that_is_not_a_regular_file_refuses_the_run_before_it_starts(
    tmp_path, capsys, kind
):
    trace, side = tmp_path / "r.blf", tmp_path / "r.blf.json"
    _old(trace)
    if kind == "directory":
        side.mkdir()
    else:
        os.mkfifo(side)
    assert main([*RUN, "--trace", str(trace)]) == 2
    errors = _errors(capsys)
    assert len(errors) == 1 and "sidecar" in errors[0] and "only regular files" in errors[0]
    assert trace.read_bytes() == OLD and _stray(tmp_path) == []


@pytest.mark.slow
@pytest.mark.parametrize("case", SWEEP)
def test_no_output_replaces_anything_but_a_regular_file(chirp, tmp_path, capsys, case):
    args, out = _sweep(chirp, tmp_path)[case]
    os.mkfifo(out)
    assert main(args) == 2
    errors = _errors(capsys)
    assert len(errors) == 1 and "regular file" in errors[0], errors
    assert out.is_fifo() and _stray(tmp_path) == []


@pytest.mark.slow
def test_a_fault_log_that_is_not_a_regular_file_is_refused_without_faults(tmp_path, capsys):
    fifo = tmp_path / "faults.jsonl"
    os.mkfifo(fifo)
    assert main([*RUN, "--trace", "", "--fault-log", str(fifo)]) == 2
    errors = _errors(capsys)
    assert len(errors) == 1 and "a FIFO" in errors[0]


# ------------------------------------------------------------ the commit of several
def test_outputs_committed_together_are_all_replaced_or_none(tmp_path, monkeypatch):
    from hdhil.core.files import commit_together

    a, b = tmp_path / "a", tmp_path / "b"
    _old(a)
    ta, tb = temporary_for(a), temporary_for(b)
    ta.write_text("new a")
    tb.write_text("new b")
    real = os.replace

    def second_fails(src, dst):
        if Path(dst) == b:
            raise OSError(28, "No space left on device")
        real(src, dst)

    monkeypatch.setattr(os, "replace", second_fails)
    with pytest.raises(UserError, match="b: cannot write"):
        commit_together([(ta, a, "a"), (tb, b, "b")])
    monkeypatch.undo()
    assert a.read_bytes() == OLD and not b.exists()  # the first put back as it was
    assert _stray(tmp_path) == []
    ta, tb = temporary_for(a), temporary_for(b)
    ta.write_text("new a")
    tb.write_text("new b")
    commit_together([(ta, a, "a"), (tb, b, "b")])
    assert a.read_text() == "new a" and b.read_text() == "new b" and _stray(tmp_path) == []


@pytest.mark.slow
@pytest.mark.parametrize("free", [0, 4096])
def test_a_campaign_on_a_full_disk_leaves_no_temporary_and_no_empty_folder(
    tiny_fs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], free: int
) -> None:
    """A campaign whose records the disk cannot take: exit 2 naming the file, no record
    temporary left, and the --out folder it created (holding nothing) removed."""
    campaign = tmp_path / "c.toml"
    campaign.write_text('[campaign]\nname = "full"\nscenarios = ["free-motion"]\n'
                        'duration_s = 0.2\ncriteria = ["stopped_early == false"]\n'
                        "[axes]\nseed = [1, 2]\n")  # fmt: skip
    _fill(tiny_fs, free)
    out = tiny_fs / "camp"
    assert main(["campaign", str(campaign), "--workers", "1", "--out", str(out)]) == 2
    errors = _errors(capsys)
    assert len(errors) == 1 and "cannot write" in errors[0] and "camp" in errors[0], errors
    assert sorted(p.name for p in tiny_fs.iterdir()) == ["filler"]
