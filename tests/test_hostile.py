"""Hostile input beyond the drawn fuzzing of ``test_cli_fuzz.py``: campaign files, fault-log
paths, full disks, names the OS accepts (non-UTF-8 included) and the Python API.

Every case must end cleanly: no traceback, no hang, nothing destroyed
or half-written.  A refused command exits 2 with one ``hdhil: error:`` line and leaves no
file behind; a command that could not write an output exits non-zero and leaves the old
file exactly as it was, with no temporary; a non-regular file is never replaced; the API
raises ``TypeError`` or ``ValueError`` naming the argument.

In-process cases run through :func:`hdhil.cli.main` under ``SIGALRM`` (a hang fails the
test) and a bound on the address space (a reader that slurps a huge file fails the test
instead of taking the machine's memory); the full-disk cases mount a small tmpfs of
their own (root only, else skipped with the reason); cases that start processes
(non-UTF-8 names seen by a real ``argv``, campaign pools, mount) are marked
``subprocess``.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from conftest import CannedExecutor, fill_fs

import hdhil
from hdhil.cli import main

TIME_LIMIT_S = 30

#: A campaign of two variants, short enough to run in a test.
CAMPAIGN = """[campaign]
name = "hostile"
scenarios = ["free-motion"]
duration_s = {duration}
criteria = ["stopped_early == false"]

[axes]
seed = [1, 2]
"""


class Hang(BaseException):
    """Raised by SIGALRM: not an Exception, so no handler of the command can take it."""


@contextlib.contextmanager
def _memory_limit(extra: int = 1 << 30) -> Iterator[None]:
    """At most ``extra`` more bytes of address space for this process (a reader that
    slurps a huge file gets MemoryError here instead of taking the machine's memory)."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with open("/proc/self/statm") as f:
        size = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    limit = size + extra if hard == resource.RLIM_INFINITY else min(hard, size + extra)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


@contextlib.contextmanager
def _time_limit(seconds: int = TIME_LIMIT_S) -> Iterator[None]:
    def alarm(signum: int, frame: object) -> None:
        raise Hang(f"no exit within {seconds} s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def _tree(root: Path) -> dict[str, tuple[int, bytes]]:
    """Every entry under ``root``: its type and, for a regular file, its content."""
    out: dict[str, tuple[int, bytes]] = {}
    for dirpath, dirnames, filenames in os.walk(os.fsencode(root)):
        for name in dirnames + filenames:
            path = os.path.join(dirpath, name)
            st = os.lstat(path)
            data = b""
            if stat.S_ISREG(st.st_mode):
                with open(path, "rb") as f:
                    data = f.read()
            elif stat.S_ISLNK(st.st_mode):
                data = os.readlink(path)
            out[os.fsdecode(os.path.relpath(path, os.fsencode(root)))] = (
                stat.S_IFMT(st.st_mode),
                data,
            )
    return out


def _temporaries(root: Path) -> list[str]:
    return [p for p in _tree(root) if ".hdhil-" in p or p.endswith(".tmp") or ".tmp." in p]


def _cli(argv: list[str], capsys: pytest.CaptureFixture) -> tuple[int, str, str]:
    with _time_limit(), _memory_limit(2 << 30):
        rc = main(argv)
    out, err = capsys.readouterr()
    assert "Traceback" not in err, err
    assert rc in (0, 1, 2, 130), (rc, err)
    return rc, out, err


def _one_error_line(err: str) -> None:
    lines = [ln for ln in err.splitlines() if not ln.startswith("hdhil: warning:")]
    assert len(lines) == 1 and lines[0].startswith("hdhil: error: "), err


def _refused(argv: list[str], capsys: pytest.CaptureFixture, root: Path) -> str:
    """``argv`` exits 2 with one error line and changes nothing under ``root``."""
    before = _tree(root)
    rc, _, err = _cli(argv, capsys)
    assert rc == 2, (rc, err)
    _one_error_line(err)
    assert _tree(root) == before, "a refused command left files behind"
    return err


def _strict_json(text: str) -> object:
    def refuse(constant: str) -> object:
        raise ValueError(f"{constant} is not JSON")

    return json.loads(text, parse_constant=refuse)


# ------------------------------------------------------------------ campaign files

HEAD = '[campaign]\nname = "hostile"\nscenarios = ["free-motion"]\n'

HOSTILE_CAMPAIGNS = {
    "name-carriage-return": '[campaign]\nname = "a\\rb"\nscenarios = ["free-motion"]\n',
    "name-escape-sequence": '[campaign]\nname = "\\u001b[2J"\nscenarios = ["free-motion"]\n',
    "name-nul": '[campaign]\nname = "a\\u0000b"\nscenarios = ["free-motion"]\n',
    "name-bidi-override": '[campaign]\nname = "a\\u202eb"\nscenarios = ["free-motion"]\n',
    "name-not-a-string": '[campaign]\nname = 1\nscenarios = ["free-motion"]\n',
    "duration-nan": HEAD + "duration_s = nan\n",
    "duration-inf": HEAD + "duration_s = inf\n",
    "duration-text": HEAD + 'duration_s = "1"\n',
    "duration-bool": HEAD + "duration_s = true\n",
    "axis-duration-nan": HEAD + "[axes]\nscenario.duration_s = [nan]\n",
    "grid-product-1e9": HEAD
    + "[axes]\n"
    + "".join(
        f"faults.control.{k} = {{ range = [0, 1000] }}\n"
        for k in ("delay_us", "jitter_us", "loss_rate")
    ),
    "grid-range-2**70": HEAD + "[axes]\nseed = { range = [0, 1180591620717411303424] }\n",
    "grid-range-step-0": HEAD + "[axes]\nseed = { range = [0, 10, 0] }\n",
    "grid-range-floats": HEAD + "[axes]\nseed = { range = [0.5, 3] }\n",
    "zip-unequal": HEAD + "[[zip]]\nseed = [1, 2]\nfaults.seed = [1, 2, 3]\n",
    "zip-over-the-cap": HEAD
    + "[[zip]]\nseed = { range = [0, 100000000] }\nfaults.seed = { range = [0, 100000000] }\n",
    "seed-2**63": HEAD + "[axes]\nseed = [9223372036854775808]\n",
    "seed-negative": HEAD + "[axes]\nseed = [-1]\n",
    "seed-float": HEAD + "[axes]\nseed = [1.5]\n",
    "fault-seed-2**70": HEAD + "[axes]\nfaults.seed = [1180591620717411303424]\n",
    "criterion-nan": HEAD + 'criteria = ["eval_rms_err_Nm < nan"]\n',
    "criterion-unknown-metric": HEAD + 'criteria = ["nope < 1"]\n',
    "scenario-devzero": '[campaign]\nname = "x"\nscenarios = ["/dev/zero"]\n',
    "scenario-fifo": '[campaign]\nname = "x"\nscenarios = ["FIFO"]\n',
    "scenario-itself": '[campaign]\nname = "x"\nscenarios = ["SELF"]\n',
    "trace-format-path": HEAD + 'keep_trace = true\ntrace_format = "../../x"\n',
    "unknown-axis-key": HEAD + "[axes]\nplant.nope = [1, 2]\n",
    "plant-nan-axis": HEAD + "[axes]\nplant.drivetrain.J_motor = [nan]\n",
    "deep-nesting": "a = " + "[" * 100_000 + "]" * 100_000 + "\n",
    "utf-16": "UTF16",
    "nul-bytes": "NUL",
}


@pytest.mark.parametrize("case", sorted(HOSTILE_CAMPAIGNS))
def test_a_hostile_campaign_file_is_refused_in_one_line_leaving_nothing(tmp_path, capsys, case):
    text = HOSTILE_CAMPAIGNS[case]
    path = tmp_path / "c.toml"
    fifo = tmp_path / "f.toml"
    os.mkfifo(fifo)
    if text == "UTF16":
        path.write_bytes((HEAD + "duration_s = 0.1\n").encode("utf-16"))
    elif text == "NUL":
        path.write_bytes((HEAD + "duration_s = 0.1\n").encode() + b"\0\0")
    else:
        text = text.replace('"FIFO"', json.dumps(str(fifo))).replace(
            '"SELF"', json.dumps(str(path))
        )
        path.write_text(text, encoding="utf-8")
    for out in (["--out", str(tmp_path / "out")], []):  # --out given, and the default
        cwd = os.getcwd()
        os.chdir(tmp_path)
        try:
            _refused(["campaign", str(path), "--workers", "1", *out], capsys, tmp_path)
        finally:
            os.chdir(cwd)


_Canned = CannedExecutor


@pytest.mark.parametrize("kind", ["sparse-3GB", "binary-junk", "cut-short"])
def test_a_resume_record_that_is_no_file_to_read_is_run_again(tmp_path, kind):
    """A record of the resume store that is a huge (sparse) file, binary junk or cut short
    is one warning and its variant runs again: no memory blow-up, no traceback."""
    from hdhil.rig.campaign import run_campaign
    from hdhil.rig.campaign_file import load_campaign
    from hdhil.rig.campaign_variants import expand

    path = tmp_path / "c.toml"
    path.write_text(CAMPAIGN.format(duration=0.05))
    campaign = load_campaign(path)
    variants = expand(campaign)
    runs = tmp_path / "out" / "runs"
    runs.mkdir(parents=True)
    for v in variants:
        record = {"digest": v.digest, "variant": v.id, "error": None,
                  "result": {"cycles": 10, "controller": {}, "drive": {}},
                  "wall_s": 1.0, "worker": "there:2"}  # fmt: skip
        (runs / f"{v.digest}.json").write_text(json.dumps(record))
    damaged = runs / f"{variants[0].digest}.json"
    if kind == "sparse-3GB":
        with open(damaged, "wb") as f:
            f.truncate(3 << 30)
    elif kind == "binary-junk":
        damaged.write_bytes(bytes(range(256)) * 64)
    else:
        damaged.write_bytes(damaged.read_bytes()[:30])
    warnings: list[str] = []
    _Canned.submitted = 0
    with _time_limit(), _memory_limit():
        run = run_campaign(campaign, variants, tmp_path / "out", _Canned,
                           on_warning=warnings.append)  # fmt: skip
    assert run.ran == 1 and _Canned.submitted == 1
    assert len(warnings) == 1 and "\n" not in warnings[0], warnings
    assert str(damaged) in warnings[0], warnings


@pytest.mark.parametrize("kind", ["fifo", "devzero-link", "directory", "dangling-link"])
def test_a_resume_record_that_is_no_regular_file_is_refused_before_anything_runs(tmp_path, kind):
    """A record that is a FIFO, a link to /dev/zero, a directory or a dangling link: the
    campaign says so in one line before any variant runs (or warns and runs it again),
    without hanging on the FIFO or reading /dev/zero without end."""
    from hdhil.core.errors import UserError
    from hdhil.rig.campaign import run_campaign
    from hdhil.rig.campaign_file import load_campaign
    from hdhil.rig.campaign_variants import expand

    path = tmp_path / "c.toml"
    path.write_text(CAMPAIGN.format(duration=0.05))
    campaign = load_campaign(path)
    variants = expand(campaign)
    runs = tmp_path / "out" / "runs"
    runs.mkdir(parents=True)
    damaged = runs / f"{variants[0].digest}.json"
    if kind == "fifo":
        os.mkfifo(damaged)
    elif kind == "devzero-link":
        damaged.symlink_to("/dev/zero")
    elif kind == "directory":
        damaged.mkdir()
    else:
        damaged.symlink_to(tmp_path / "nowhere")
    warnings: list[str] = []
    _Canned.submitted = 0
    try:
        with _time_limit(), _memory_limit():
            run_campaign(campaign, variants, tmp_path / "out", _Canned, on_warning=warnings.append)
    except (UserError, ValueError) as e:
        assert "\n" not in str(e) and str(damaged) in str(e)
        assert _Canned.submitted == 0, "refused after variants ran"
    else:
        assert len(warnings) == 1 and str(damaged) in warnings[0], warnings


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_resumed_campaign_with_damaged_records_equals_an_uninterrupted_one(tmp_path):
    """Three records damaged three ways (cut short, null, binary junk): three one-line
    warnings, those variants run again, and results.csv byte-identical to the
    uninterrupted run's."""
    path = tmp_path / "c.toml"
    path.write_text(CAMPAIGN.format(duration=0.05).replace("seed = [1, 2]", "seed = [1, 2, 3, 4]"))
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        "-m",
        "hdhil",
        "campaign",
        str(path),
        "--workers",
        "1",
        "--out",
        str(out),
    ]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert first.returncode in (0, 1), first.stderr
    reference = (out / "results.csv").read_bytes()
    records = sorted((out / "runs").glob("*.json"))
    records[0].write_bytes(records[0].read_bytes()[:20])
    records[1].write_text("null")
    records[2].write_bytes(bytes(range(256)))
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert "Traceback" not in again.stderr
    assert again.returncode in (0, 1), again.stderr
    warnings = [ln for ln in again.stderr.splitlines() if ln.startswith("hdhil: warning:")]
    assert len(warnings) == 3, again.stderr
    assert (out / "results.csv").read_bytes() == reference
    assert not _temporaries(tmp_path)


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_campaign_with_stopped_workers_ends_on_sigint(tmp_path):
    """SIGSTOP every worker, then SIGINT the campaign: it ends with 130 within the grace
    period, and leaves no worker behind."""
    path = tmp_path / "c.toml"
    path.write_text(CAMPAIGN.format(duration=5.0))
    cmd = [sys.executable, "-m", "hdhil", "campaign", str(path), "--workers", "2",
           "--out", str(tmp_path / "out")]  # fmt: skip
    env = {**os.environ, "HDHIL_HOSTILE_MARK": str(tmp_path)}
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=env, preexec_fn=_default_signals)  # fmt: skip
    stopped: list[int] = []
    try:
        deadline = time.monotonic() + 60
        while len(_descendants(proc.pid)) < 2:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no worker started"
            time.sleep(0.05)
        time.sleep(0.5)
        for pid in _descendants(proc.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGSTOP)
                stopped.append(pid)
        sent = time.monotonic()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
        took = time.monotonic() - sent
    finally:
        for pid in stopped:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        proc.wait()
    assert "Traceback" not in err
    assert proc.returncode == 130, (proc.returncode, err)
    assert took < 15, took
    time.sleep(0.5)
    left = [pid for pid in stopped if _alive(pid)]
    for pid in left:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    assert not left, "stopped workers outlived the campaign"


def _default_signals() -> None:
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_DFL)


def _descendants(pid: int) -> list[int]:
    found, todo = [], [pid]
    while todo:
        parent = todo.pop()
        for task in Path(f"/proc/{parent}/task").glob("*"):
            with contextlib.suppress(OSError):
                for child in (task / "children").read_text().split():
                    found.append(int(child))
                    todo.append(int(child))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


# ------------------------------------------------------------------ fault-log paths

RUN = ["run", "--duration", "0.1", "--no-evaluate", "-q", "--fault", "control.loss_rate=0.3"]


def _special(path: Path, kind: str) -> None:
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "directory":
        path.mkdir()
    elif kind == "devnull-link":
        path.symlink_to("/dev/null")
    elif kind == "dangling-link":
        path.symlink_to(path.parent / "nowhere" / "x")
    elif kind == "link-loop":
        path.symlink_to(path)


@pytest.mark.parametrize("kind", ["fifo", "directory", "devnull-link", "dangling-link", "link-loop",
                                  "missing-folder"])  # fmt: skip
def test_a_fault_log_that_is_no_regular_file_is_refused_before_the_run(tmp_path, capsys, kind):
    log = tmp_path / ("no/f.jsonl" if kind == "missing-folder" else "f.jsonl")
    _special(log, kind)
    _refused([*RUN, "--trace", "", "--fault-log", str(log)], capsys, tmp_path)


def _inputs(tmp_path: Path) -> dict[str, Path]:
    scenario = tmp_path / "s.toml"
    shutil.copy(
        Path(hdhil.rig.scenario.__file__).parent / "scenarios" / "free-motion.toml", scenario
    )
    override = tmp_path / "o.toml"
    override.write_text("[firmware.ripple]\nmode = 'paper'\n")
    trace = tmp_path / "t.blf"
    return {"scenario": scenario, "override": override, "trace": trace,
            "sidecar": tmp_path / "t.blf.json"}  # fmt: skip


@pytest.mark.parametrize("target", ["scenario", "override", "trace", "sidecar"])
def test_the_fault_log_never_writes_over_an_input_or_another_output(tmp_path, capsys, target):
    files = _inputs(tmp_path)
    argv = [*RUN, "--scenario", str(files["scenario"]), "--override", str(files["override"]),
            "--trace", str(files["trace"]), "--fault-log", str(files[target])]  # fmt: skip
    err = _refused(argv, capsys, tmp_path)
    assert str(files[target]) in err


def test_an_old_fault_log_is_kept_when_the_run_is_refused_late(tmp_path, capsys):
    """A run refused after its options were read (an unknown scenario key) keeps the old
    fault log as it was."""
    log = tmp_path / "f.jsonl"
    log.write_text("old\n")
    override = tmp_path / "o.toml"
    override.write_text("[plant.drivetrain]\nnope = 1\n")
    _refused([*RUN, "--trace", "", "--override", str(override), "--fault-log", str(log)], capsys,
             tmp_path)  # fmt: skip
    assert log.read_text() == "old\n"


# ------------------------------------------------------------------ full disks


@pytest.fixture
def full_disk(tiny_fs: Path) -> Callable[[int], Path]:
    """The test's own 256 KiB tmpfs (conftest ``tiny_fs``); call it with the bytes to
    leave free."""

    def fill(free: int) -> Path:
        fill_fs(tiny_fs, free)
        return tiny_fs

    return fill


FULL = {
    "run-trace": (["run", "--duration", "0.3", "--no-evaluate", "-q", "--trace", "OUT"], "t.blf"),
    "run-fault-log": ([*RUN, "--trace", "", "--fault-log", "OUT"], "f.jsonl"),
    "dump-csv": (["dump", "TRACE", "--csv", "OUT"], "d.csv"),
    "calibrate": (["calibrate", "--out", "OUT"], "cal.toml"),
    "dbc": (["dbc", "export", "OUT"], "x.dbc"),
}


@pytest.fixture(scope="module")
def small_trace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    trace = tmp_path_factory.mktemp("hostile") / "ok.blf"
    assert main(["run", "--duration", "0.3", "--no-evaluate", "-q", "--trace", str(trace)]) == 0
    return trace


@pytest.mark.slow
@pytest.mark.subprocess  # mount and umount
@pytest.mark.parametrize("free", [0, 8192])
@pytest.mark.parametrize("command", sorted(FULL))
def test_a_full_disk_keeps_the_old_output_and_no_temporary(full_disk, small_trace, capsys, command,
                                                           free):  # fmt: skip
    argv, name = FULL[command]
    disk = full_disk(1 << 20)  # not yet full: the old output first
    target = disk / name
    target.write_bytes(b"old output\n")
    full_disk(free)
    args = [str(target) if a == "OUT" else str(small_trace) if a == "TRACE" else a for a in argv]
    before = _tree(disk)
    rc, _, err = _cli(args, capsys)
    assert not _temporaries(disk), _temporaries(disk)
    if rc == 0:  # it fitted: the whole output, nothing else changed
        assert _tree(disk).keys() == before.keys()
        assert target.read_bytes() != b"old output\n" and target.stat().st_size > 0
    else:
        assert target.read_bytes() == b"old output\n", "the old output was destroyed"
        _one_error_line(err)
        assert _tree(disk) == before


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_campaign_on_a_full_disk_leaves_no_temporary_and_exits_non_zero(full_disk, tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(CAMPAIGN.format(duration=0.05))
    disk = full_disk(0)
    out = disk / "camp"
    done = subprocess.run(
        [sys.executable, "-m", "hdhil", "campaign", str(path), "--workers", "1", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert "Traceback" not in done.stderr
    assert done.returncode != 0
    _one_error_line(done.stderr)
    assert not _temporaries(disk), _temporaries(disk)


# ------------------------------------------------------------------ names the OS accepts


NAMES = {
    "non-utf8": b"\xff\xfe",
    "latin-1": b"caf\xe9",
    "newline": b"a\nb",
    "escape": b"\x1b[2J",
    "leading-dash": b"-x",
    "spaces": b" a b ",
    "bidi-override": "a\u202eb".encode(),
}


def _command() -> list[str]:
    script = Path(sys.executable).with_name("hdhil")
    return [str(script)] if script.exists() else [sys.executable, "-m", "hdhil"]


def _run_bytes(argv: list[bytes | str], cwd: Path) -> subprocess.CompletedProcess:
    # A UTF-8 locale as most users have: standard output encodes strictly (the C locale
    # would make it surrogateescape and hide what a user sees).
    env = {**os.environ, "PYTHONIOENCODING": "utf-8:strict"}
    return subprocess.run([*_command(), *argv], cwd=cwd, capture_output=True, timeout=60, env=env)


def _clean(done: subprocess.CompletedProcess) -> None:
    err = done.stderr.decode("utf-8", "replace")
    assert "Traceback" not in err, err
    assert done.returncode in (0, 2), (done.returncode, err)
    if done.returncode == 2:
        _one_error_line(err)


def _written(root: Path, raw: bytes) -> bool:
    return os.path.isfile(os.path.join(os.fsencode(root), raw))


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(set(NAMES) - {"non-utf8", "latin-1"}))
def test_a_name_the_os_accepts_works_or_is_refused_in_one_line(
    tmp_path, small_trace, capsys, monkeypatch, name
):
    """Each name as a trace, a fault log, a dump's input and CSV: written under exactly that
    name, or refused in one line; never a traceback.  (Names that are no UTF-8: below,
    through the real command, whose standard output is what a user's locale makes it.)"""
    monkeypatch.chdir(tmp_path)
    raw = NAMES[name]
    blf, log, csv = (os.fsdecode(raw + ext) for ext in (b".blf", b".jsonl", b".csv"))
    run = [*RUN, "--trace", blf, "--fault-log", log]
    rc, _, err = _cli(run, capsys)
    assert rc in (0, 2), err
    if rc == 2:
        _one_error_line(err)
    else:
        assert _written(tmp_path, raw + b".blf") and _written(tmp_path, raw + b".jsonl")
    shutil.copy(small_trace, tmp_path / ("in" + blf))
    rc, _, err = _cli(["dump", "in" + blf, "--csv", csv], capsys)
    assert rc in (0, 2), err
    if rc == 2:
        _one_error_line(err)
    else:
        assert os.path.getsize(os.path.join(os.fsencode(tmp_path), raw + b".csv")) > 0
    assert not _temporaries(tmp_path)


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("name", ["non-utf8", "latin-1"])
def test_a_non_utf8_name_works_or_is_refused_by_the_real_command(tmp_path, small_trace, name):
    """Bytes that are no UTF-8 reach the command as they do from a shell (surrogate escapes
    in ``sys.argv``), and every message naming them still prints."""
    raw = NAMES[name]
    argv = [*RUN, "--trace", raw + b".blf", "--fault-log", raw + b".jsonl"]
    done = _run_bytes(argv, tmp_path)
    _clean(done)
    if done.returncode == 0:
        assert _written(tmp_path, raw + b".blf") and _written(tmp_path, raw + b".jsonl")
    shutil.copy(small_trace, os.path.join(os.fsencode(tmp_path), raw + b"in.blf"))
    done = _run_bytes(["dump", raw + b"in.blf", "--csv", raw + b".csv"], tmp_path)
    _clean(done)
    done = _run_bytes(["dump", raw + b"missing.blf"], tmp_path)
    _clean(done)
    assert done.returncode == 2
    assert not _temporaries(tmp_path)


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_non_utf8_campaign_file_and_out_work_or_are_refused(tmp_path):
    os.fsencode(tmp_path)
    path = os.path.join(os.fsencode(tmp_path), b"\xff.toml")
    with open(path, "w") as f:
        f.write(CAMPAIGN.format(duration=0.05))
    done = _run_bytes(["campaign", b"\xff.toml", "--workers", "1", "--out", b"\xfe\xff"], tmp_path)
    _clean(done)
    if done.returncode == 0:
        assert os.path.isfile(os.path.join(os.fsencode(tmp_path), b"\xfe\xff", b"results.csv"))


@pytest.mark.parametrize(
    "argv",
    [
        ["dump", "a\nb.blf"],
        ["evaluate", "a\rb.blf"],
        ["run", "--scenario", "a\nb.toml"],
        ["campaign", "a\nb.toml"],
        ["calibrate", "--out", "no\nsuch/c.toml"],
    ],
    ids=["dump", "evaluate", "run", "campaign", "calibrate"],
)
def test_an_error_about_a_name_with_a_line_break_stays_one_line(tmp_path, capsys, argv):
    err = _refused(argv, capsys, tmp_path)
    assert "\r" not in err.rstrip("\n") and err.count("\n") == 1, repr(err)


def test_a_name_longer_than_the_os_allows_is_refused_in_one_line(tmp_path, capsys):
    long = tmp_path / ("a" * 300 + ".blf")
    _refused(["run", "--duration", "0.1", "--no-evaluate", "-q", "--trace", str(long)], capsys,
             tmp_path)  # fmt: skip


# ------------------------------------------------------------------ extreme physics


@pytest.mark.slow
@pytest.mark.parametrize(
    "table, key, value",
    [
        ("plant.drivetrain", "J_load", "1e-12"),
        ("plant.drivetrain", "J_motor", "1e-12"),
        ("plant.drivetrain", "k_flex", "1e15"),
        ("plant.drivetrain", "friction_smoothing", "1e-15"),
        ("plant.amplifier", "current_lag_s", "1e-12"),
    ],
)
def test_an_extreme_plant_is_refused_naming_the_key_or_gives_valid_json(
    tmp_path, capsys, table, key, value
):
    override = tmp_path / "o.toml"
    override.write_text(f"[{table}]\n{key} = {value}\n")
    argv = ["run", "--duration", "0.2", "--trace", "", "--json", "-q", "--override", str(override)]
    rc, out, err = _cli(argv, capsys)
    if rc == 2:  # refused up front, naming the key whose limit the plant exceeds
        _one_error_line(err)
        assert f"{table}." in err
        return
    result = _strict_json(out)
    assert isinstance(result, dict)
    velocity = result["velocity_peak"]
    assert velocity is None or (math.isfinite(velocity) and abs(velocity) < 1e6) or rc == 1, (
        rc,
        velocity,
    )


# ------------------------------------------------------------------ the Python API

API_CASES: list[tuple[str, Callable[[Path], object], type[Exception], str]] = [
    ("read_trace-bytes", lambda t: hdhil.read_trace(os.fsencode(t)), TypeError, "path"),
    ("read_trace-int", lambda t: hdhil.read_trace(3), TypeError, "path"),
    ("read_trace-none", lambda t: hdhil.read_trace(None), TypeError, "path"),
    (
        "evaluate_trace-skip-nan",
        lambda t: hdhil.evaluate_trace(t, skip_s=math.nan),
        ValueError,
        "skip_s",
    ),
    (
        "evaluate_trace-skip-negative",
        lambda t: hdhil.evaluate_trace(t, skip_s=-1.0),
        ValueError,
        "skip_s",
    ),
    (
        "evaluate_trace-scenario-int",
        lambda t: hdhil.evaluate_trace(t, scenario=3),
        TypeError,
        "scenario",
    ),
    (
        "evaluate_trace-scenario-bytes",
        lambda t: hdhil.evaluate_trace(t, scenario=b"free-motion"),
        TypeError,
        "scenario",
    ),
    ("resolve-duration-nan", lambda t: hdhil.resolve(duration_s=math.nan), ValueError, "duration"),
    ("resolve-duration-1e30", lambda t: hdhil.resolve(duration_s=1e30), ValueError, "duration"),
    ("resolve-duration-1e-6", lambda t: hdhil.resolve(duration_s=1e-6), ValueError, "duration"),
    (
        "resolve-duration-bigint",
        lambda t: hdhil.resolve(duration_s=10**400),
        ValueError,
        "duration",
    ),
    ("resolve-seed-2**63", lambda t: hdhil.resolve(seed=2**63), ValueError, "seed"),
    ("resolve-seed-negative", lambda t: hdhil.resolve(seed=-1), ValueError, "seed"),
    (
        "resolve-evaluate-from-nan",
        lambda t: hdhil.resolve(evaluate_from_s=math.nan),
        ValueError,
        "evaluate_from_s",
    ),
    ("resolve-faults-none-item", lambda t: hdhil.resolve(faults=[None]), TypeError, "faults"),
    ("resolve-mapping-unknown", lambda t: hdhil.resolve(mapping="nope"), ValueError, "mapping"),
    (
        "resolve-overrides-nan",
        lambda t: hdhil.resolve(overrides={"plant": {"drivetrain": {"J_load": math.nan}}}),
        ValueError,
        "J_load",
    ),
    (
        "resolve-overrides-not-a-table",
        lambda t: hdhil.resolve(overrides={"plant": 3}),
        ValueError,
        "plant",
    ),
    (
        "resolve-overrides-key-not-str",
        lambda t: hdhil.resolve(overrides={1: 2}),
        ValueError,
        "overrides",
    ),
    (
        "resolve-overrides-self-reference",
        lambda t: hdhil.resolve(overrides=_self_ref()),
        ValueError,
        "overrides",
    ),
    ("load_scenario-bytes", lambda t: hdhil.load_scenario(b"free-motion"), TypeError, "scenario"),
    (
        "run-duration-1e30",
        lambda t: hdhil.run(duration_s=1e30, evaluate=False),
        ValueError,
        "duration",
    ),
    ("run-trace-bytes", lambda t: hdhil.run(duration_s=0.1, trace=b"x.blf"), TypeError, "trace"),
    (
        "run-start-time-nan",
        lambda t: hdhil.run(duration_s=0.1, trace=str(t.parent / "n.blf"), start_time=math.nan),
        ValueError,
        "start_time",
    ),
    (
        "run-controller-factory-int",
        lambda t: hdhil.run(duration_s=0.1, controller_factory=3),
        TypeError,
        "controller_factory",
    ),
    (
        "run-drive-factories-int",
        lambda t: hdhil.run(duration_s=0.1, drive_factories=3),
        TypeError,
        "drive_factories",
    ),
    ("cycle_arrays-none", lambda t: hdhil.cycle_arrays(None), TypeError, "result"),
]


def _self_ref() -> dict:
    d: dict = {}
    d["plant"] = d
    return d


@pytest.mark.parametrize("case", API_CASES, ids=[c[0] for c in API_CASES])
def test_the_api_refuses_a_wrong_argument_naming_it(small_trace, case):
    _, call, kind, name = case
    with _time_limit(), _memory_limit(2 << 30), pytest.raises(kind) as raised:
        call(small_trace)
    assert name in str(raised.value), str(raised.value)
