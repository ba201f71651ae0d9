"""Ctrl-C at any moment of every command: one line ``hdhil: interrupted`` and exit code 130
(or the command's own code if it had already finished; 0 for ``emulate`` and ``log``
stopped cleanly in their loop), never a traceback, never a kill by the signal, and long
loops stop within a bound.

Moments: *first* is the earliest moment hdhil's code can answer, detected from outside
as the process catching SIGHUP (``hdhil.console`` installs its start-up handlers for
SIGINT, SIGTERM and SIGHUP as its first action; plain Python catches only SIGINT), i.e.
while the command's libraries are still being imported; *then* 0.4 s later (parsing,
reading inputs) and, for the commands with a long loop, 1.5 s later (in the loop).
Python's own start-up before that is out of any Python program's reach (README, "Exit
codes").  Each case is bounded in time, so CI stays fast.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hdhil.cli import main

pytestmark = [pytest.mark.slow, pytest.mark.subprocess]

#: How long a command may take to end after the signal (s): a cycle boundary, the
#: trace writer finishing its file, the interpreter's exit; generous for a loaded machine.
STOP_BOUND_S = 8.0


def _command() -> list[str]:
    script = Path(sys.executable).with_name("hdhil")
    return [str(script)] if script.exists() else [sys.executable, "-m", "hdhil"]


def _catches_sighup(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("SigCgt:"):
                    return bool(int(line.split()[1], 16) & (1 << (signal.SIGHUP - 1)))
    except OSError:
        pass
    return False


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    d = tmp_path_factory.mktemp("signals")
    trace = d / "ok.blf"
    assert main(["run", "--duration", "0.6", "--trace", str(trace), "--no-evaluate"]) == 0
    return {"trace": str(trace), "d": str(d)}


VIRTUAL = ["--interface", "virtual", "--channel", "hdhil-signals"]

#: Every command, with arguments that make it work for a while where it can.
CASES: dict[str, list[str]] = {
    "run": ["run", "--duration", "30", "--trace", "{out}/r.blf", "--no-evaluate"],
    "dump": ["dump", "{trace}", "--stats"],
    "filter": ["filter", "{trace}", "--out", "{out}/f.csv"],
    "evaluate": ["evaluate", "{trace}"],
    "tune": ["tune", "{trace}"],
    "plot": ["plot", "{trace}", "--out", "{out}/p.png"],
    "calibrate": ["calibrate", "--out", "{out}/c.toml"],
    "design": ["design", "lqg"],
    "identify": ["identify", "{trace}"],
    "emulate": ["emulate", *VIRTUAL, "--duration", "30"],
    "firmware": ["firmware", *VIRTUAL, "--duration", "30", "--boot-timeout", "20"],
    "log": ["log", *VIRTUAL, "--duration", "30", "{out}/l.blf"],
    "soak": ["soak", "--duration", "60", "--trace", "{out}/s.blf"],
    "bench": ["bench", "--quick"],
    "campaign": ["campaign", "smoke", "--workers", "1", "--out", "{out}/camp"],
    "dbc": ["dbc", "export", "{out}/all.dbc"],
    "sdo": ["sdo", *VIRTUAL, "--timeout", "20", "read", "2", "0x1000"],
    "nmt": ["nmt", *VIRTUAL, "start", "2"],
}


def _interrupt(argv: list[str], after_s: float, group: bool = False) -> tuple[int, str, float]:
    """Start ``hdhil argv``, send SIGINT ``after_s`` after hdhil's first handler is in
    place (to the whole process group with ``group``, as a terminal's Ctrl-C is); the
    exit code, stderr and the seconds from the signal to the end."""
    proc = subprocess.Popen(
        [*_command(), *argv], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        start_new_session=group,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not _catches_sighup(proc.pid) and proc.poll() is None:
            assert time.monotonic() < deadline, "hdhil never started"
            time.sleep(0.0005)
        time.sleep(after_s)
        if group:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGINT)
        sent = time.monotonic()
        _, err = proc.communicate(timeout=60)
        return proc.returncode, err, time.monotonic() - sent
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL) if group else proc.kill()


def _check(code: int, err: str, took: float) -> None:
    assert "Traceback" not in err and "Exception ignored" not in err, err
    assert code in (0, 1, 2, 130), (code, err)  # never -2: killed by the signal
    lines = [line for line in err.splitlines() if line.strip()]
    if code == 130:  # also a run stopped cleanly by the signal (summary on stdout)
        assert lines and lines[-1].startswith("hdhil: interrupted"), err
    if code == 2:
        assert len(lines) == 1 and lines[0].startswith("hdhil: error:"), err
    assert took < STOP_BOUND_S, f"ended {took:.1f} s after the signal"


#: Commands with a long loop: also interrupted once they are well into it.
LONG = ("run", "emulate", "firmware", "log", "soak", "bench", "campaign")
#: The servers: a signal is how they end, so a stop in their loop exits 0 (as can.logger);
#: 130 only while they start (``hdhil: interrupted``).
SERVERS = ("emulate", "log")
MOMENTS = [(name, after_s) for name in sorted(CASES) for after_s in (0.0, 0.4)] + [
    (name, 1.5) for name in LONG
]


@pytest.mark.parametrize(
    ("name", "after_s"), MOMENTS, ids=[f"{n}-{a:g}s" for n, a in MOMENTS]
)  # fmt: skip
def test_ctrl_c_at_any_moment_is_a_clean_exit(name, after_s, inputs, tmp_path):
    argv = [a.format(trace=inputs["trace"], out=tmp_path) for a in CASES[name]]
    code, err, took = _interrupt(argv, after_s)
    _check(code, err, took)
    if after_s == 0.0:
        assert code == 130, (code, err)  # still importing: it cannot have finished
    if name in SERVERS and code == 130:  # never 130 after a clean stop in the loop
        assert err.strip().endswith("hdhil: interrupted"), (code, err)
    if name in SERVERS and after_s == 1.5:
        assert code in (0, 130), (code, err)
    assert not [p for p in tmp_path.rglob("*") if ".hdhil-" in p.name]


@pytest.mark.parametrize("name", ["run", "campaign", "soak"])
def test_ctrl_c_to_the_whole_process_group_is_a_clean_exit(name, inputs, tmp_path):
    """A terminal's Ctrl-C reaches every process of the group: the trace writer and the
    campaign's workers ignore it and the command still ends cleanly."""
    argv = [a.format(trace=inputs["trace"], out=tmp_path) for a in CASES[name]]
    code, err, took = _interrupt(argv, 1.5, group=True)
    _check(code, err, took)
    assert code == 130
    assert not [p for p in tmp_path.rglob("*") if ".hdhil-" in p.name]


def test_bench_stops_promptly_in_each_section():
    """``hdhil bench`` (its full run takes minutes) ends within about a second of
    Ctrl-C wherever it is: lockstep runs, stage timing, the real-time run."""
    for after_s in (1.0, 4.0, 9.0):
        code, err, took = _interrupt(["bench", "--realtime-s", "20"], after_s)
        _check(code, err, took)
        assert code == 130 and took < 2.5, (after_s, took)


def test_ctrl_c_while_the_signal_handlers_are_imported(tmp_path):
    """The console's first handler is in place before it imports anything of hdhil: a
    Ctrl-C while :mod:`hdhil.core.signals` itself is being imported (sent by an import
    hook, so the moment is exact) still ends with the one line and 130."""
    script = (
        "import importlib.abc, os, signal, sys\n"
        "class Hook(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'hdhil.core.signals':\n"
        "            os.kill(os.getpid(), signal.SIGINT)\n"
        "        return None\n"
        "sys.meta_path.insert(0, Hook())\n"
        "from hdhil.console import run\n"
        "sys.argv = ['hdhil', '--version']\n"
        "run()\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    assert proc.returncode == 130, (proc.returncode, proc.stderr)
    assert proc.stderr == "hdhil: interrupted\n"
