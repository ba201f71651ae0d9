"""Command-line fuzzing: every command, drawn arguments and TOML documents.

Hypothesis draws an argument list for each command from that command's options with
values a hurried user might type (NaN, inf, 1e300, negative, 5,000-digit integers, empty
strings, text) and from files of every kind (missing, a directory, a FIFO, a character
device, a symbolic link to one, binary junk, empty, a drawn TOML document, TOML nested
100,000 deep).  Every draw must end cleanly:

- exit code 0 or 1 (a result, or a verdict), 2 with exactly one ``hdhil: error: ...``
  line on stderr, or 130 (never seen here: no signals are sent in-process);
- no traceback, and no uncaught exception out of :func:`hdhil.cli.main`;
- within :data:`TIME_LIMIT_S` (``SIGALRM``; a hang fails the test);
- every non-regular file used as an output is still what it was (never replaced).

The commands run in-process through :func:`hdhil.cli.main` (fast: no interpreter start);
durations are drawn from values that are either refused or short, so a valid draw runs a
fraction of a second.  A subprocess sample sends SIGINT and SIGTERM to commands during
their start-up and checks the exit code 130 and that no temporary file is left behind.

Examples are capped (``FUZZ_EXAMPLES``, default 80 per command) to keep the suite's
run time small; set the variable higher for a longer local sweep.
"""

from __future__ import annotations

import contextlib
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hdhil.cli import COMMANDS, main

EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "80"))
TIME_LIMIT_S = 60

BAD_NUMBERS = ["nan", "inf", "-inf", "1e300", "-1", "0", "-0", "1e-320", "9" * 5000, "", "x",
               "0x10", "1_000", "3.4e39", "-1e300"]  # fmt: skip
SHORT_SECONDS = ["0.05", "0.1", "0.2"]
#: Values every option refuses (for commands whose valid runs take minutes).
REFUSED = ["nan", "inf", "-inf", "1e300", "-1", "0", "", "x", "9" * 5000, "3.4e39"]

FILE_KINDS = ("missing", "dir", "fifo", "chr", "link_chr", "junk", "empty", "toml", "deep",
              "bigint", "trace", "asc")  # fmt: skip
OUTPUT_KINDS = ("new_csv", "new_toml", "new_png", "fifo", "chr", "link_chr", "dir",
                "missing_dir", "stdout")  # fmt: skip

#: Keys of the configuration tables a drawn TOML document uses (real and misspelt).
TOML_KEYS = {
    "scenario": ["name", "duration_s", "seed", "evaluate_from_s", "bogus"],
    "firmware": ["sample_period_s", "num_samples", "reference", "ripple", "calibration", "x"],
    "firmware.reference": ["wave", "amplitude_V", "bias_V", "frequency_Hz", "duty"],
    "firmware.ripple": ["mode", "r", "residual_q"],
    "firmware.calibration": ["volt2Nm", "volt2radps"],
    "faults.control": ["loss_rate", "delay_us", "jitter_us", "duplicate_rate", "silence"],
    "plant.drivetrain": ["b_motor", "Jm"],
}
TOML_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.booleans(),
    st.text(max_size=8),
    st.lists(st.integers(-3, 3), max_size=3),
    st.sampled_from([1e300, -1e300, 1e9, 3.5e38, 0.0, -1.0, 0.5]),
)


def _toml_value(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        if v != v:
            return "nan"
        if v in (float("inf"), float("-inf")):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return '"' + v.encode("unicode_escape").decode("ascii").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return str(v)


@st.composite
def toml_documents(draw: st.DrawFn) -> str:
    lines = []
    for table in draw(st.lists(st.sampled_from(sorted(TOML_KEYS)), max_size=4, unique=True)):
        lines.append(f"[{table}]")
        for key in draw(st.lists(st.sampled_from(TOML_KEYS[table]), max_size=3, unique=True)):
            lines.append(f"{key} = {_toml_value(draw(TOML_VALUES))}")
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("fuzz")
    out: dict[str, Path] = {"missing": d / "missing.toml", "dir": d / "adir"}
    out["dir"].mkdir()
    out["fifo"] = d / "fifo.csv"
    os.mkfifo(out["fifo"])
    if os.geteuid() == 0:  # a character device of our own (same numbers as /dev/null)
        out["chr"] = d / "chr.csv"
        os.mknod(out["chr"], 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    else:
        out["chr"] = out["fifo"]
    out["link_chr"] = d / "link.csv"
    out["link_chr"].symlink_to(out["chr"])
    out["junk"] = d / "junk.toml"
    out["junk"].write_bytes(bytes(range(256)) * 4)
    out["empty"] = d / "empty.toml"
    out["empty"].write_text("")
    out["deep"] = d / "deep.toml"
    out["deep"].write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    out["bigint"] = d / "bigint.toml"
    out["bigint"].write_text("[firmware.ripple]\nr = " + "9" * 5000 + "\n")
    out["toml"] = d / "drawn.toml"
    trace = d / "ok.blf"
    assert main(["run", "--duration", "0.6", "--trace", str(trace), "--no-evaluate"]) == 0
    out["trace"] = trace
    out["asc"] = d / "ok.asc"
    assert main(["run", "--duration", "0.3", "--trace", str(out["asc"]), "--no-evaluate"]) == 0
    out["new_csv"] = d / "out.csv"
    out["new_toml"] = d / "out.toml"
    out["new_png"] = d / "out.png"
    out["missing_dir"] = d / "no" / "out.csv"
    out["stdout"] = Path("-")
    return out


def _kinds(files: dict[str, Path]) -> dict[Path, int]:
    """The file type of every special file used as an output (must never change)."""
    return {files[k]: os.lstat(files[k]).st_mode for k in ("fifo", "chr", "link_chr", "dir")}


INPUT = st.sampled_from(FILE_KINDS)
OUTPUT = st.sampled_from(OUTPUT_KINDS)
NUMBER = st.sampled_from(BAD_NUMBERS)
SECONDS = st.sampled_from([v for v in BAD_NUMBERS if v not in ("1_000", "0x10")] + SHORT_SECONDS)
BAD = st.sampled_from(REFUSED)
VIRTUAL = ["--interface", "virtual", "--channel", "fuzz"]

#: Per command: options and what their values are drawn from.  "IN"/"OUT" are files.
OPTIONS: dict[str, dict[str, object]] = {
    "run": {"--duration": SECONDS, "--skip": SECONDS, "--seed": NUMBER, "--bitrate": NUMBER,
            "--override": INPUT, "--calibration": INPUT, "--scenario": INPUT,
            "--fault": st.sampled_from(["control.loss_rate=0.05", "control.delay_us=1e300",
                                        "control.jitter_us=nan", "control.loss_rate=2",
                                        "truth.silence=[{node=2,start_s=0}]", "x=1", "=",
                                        "control.duplicate_rate=0.01"]),
            "--fault-log": OUTPUT, "--trace": OUTPUT},
    "dump": {"TRACE": INPUT, "--limit": NUMBER, "--csv": OUTPUT, "--stats": None},
    "filter": {"INPUT": INPUT, "--out": OUTPUT, "--config": INPUT, "--paper": None},
    "evaluate": {"TRACE": INPUT, "--skip": SECONDS, "--scenario": INPUT},
    "tune": {"TRACE": INPUT, "--skip": SECONDS, "--max-evals": st.sampled_from(["1", "2", "0",
             "nan", "-1"]), "--out": OUTPUT},
    "plot": {"TRACE": INPUT, "--out": OUTPUT, "--window": NUMBER},
    "calibrate": {"--samples": st.sampled_from(["0", "-1", "nan", "1", "2"]),
                  "--positions": st.sampled_from(["0", "1", "x"]), "--seed": NUMBER,
                  "--out": OUTPUT},
    "design": {"SUB": st.sampled_from(["lqg", "nope", "--help"])},
    "identify": {"TRACE": INPUT, "--segment": SECONDS, "--torque-per-volt": NUMBER,
                 "--plot": OUTPUT},
    "emulate": {"--duration": SECONDS, "--seed": NUMBER, "--scenario": INPUT,
                "--fault": st.sampled_from(["sensors.tacho_spike_rate=0.1", "control.loss_rate=0.1",
                                            "x.y=1"])},
    "firmware": {"--duration": SECONDS, "--boot-timeout": st.sampled_from([*BAD_NUMBERS, "0.05"]),
                 "--scenario": INPUT},
    "log": {"TRACE": OUTPUT, "--duration": SECONDS},
    "sdo": {"ACTION": st.sampled_from(["read", "write", "x"]), "NODE": NUMBER,
            "ADDR": st.sampled_from(["0x1000", "0x123456:1", "0x1000:300", "x", "0x2400:3"]),
            "--timeout": st.sampled_from([*BAD_NUMBERS, "0.05"])},
    "nmt": {"ACTION": st.sampled_from(["start", "stop", "reset", "x"]), "NODE": NUMBER},
    "conformance": {"--node": NUMBER, "--master-id": NUMBER, "--eds": INPUT,
                    "--junit": OUTPUT, "--retries": NUMBER,
                    "--only": st.sampled_from(["nmt", "objects,sdo", "x", ",", ""]),
                    "--skip": st.sampled_from(["timing", "nope", ""])},
    "bench": {"--duration": BAD, "--repeat": BAD},
    "campaign": {"FILE": INPUT, "--workers": BAD, "--json": None},
    "dbc": {"ACTION": st.sampled_from(["export", "x", "--help"]), "TRACE": INPUT, "OUT": OUTPUT,
            "--scenario": INPUT},
    "plan": {"--scenario": INPUT, "--seed": NUMBER, "--override": INPUT, "--json": None},
    "soak": {"--duration": BAD, "--every": BAD},
}  # fmt: skip


def _path(files: dict[str, Path], kind: str) -> str:
    return str(files[kind])


@st.composite
def argv_for(draw: st.DrawFn, command: str, files: dict[str, Path]) -> list[str]:
    argv = [command]
    options = OPTIONS[command]
    chosen = draw(st.lists(st.sampled_from(sorted(options)), max_size=4, unique=True))
    positional = [o for o in options if not o.startswith("-")]
    for name in positional:  # positionals in their order, usually present
        if name in chosen or draw(st.integers(0, 4)) > 0:
            argv.append(_value(draw, options[name], files))
    if command in ("emulate", "firmware", "log", "sdo", "nmt", "conformance"):
        argv += VIRTUAL
    if command == "conformance":  # nobody answers on the fuzz bus: one short boot wait
        argv += ["--boot-timeout", "0.05", "--quiet"]
    if command in ("emulate", "firmware", "log") and "--duration" not in chosen:
        argv += ["--duration", "0.1"]
    if command in ("bench", "soak") and not [c for c in chosen if c.startswith("-")]:
        chosen = ["--duration"]  # a valid draw of these would run for minutes
    for name in chosen:
        if not name.startswith("-"):
            continue
        strategy = options[name]
        argv.append(name)
        if strategy is not None:
            argv.append(_value(draw, strategy, files))
    if command == "run" and "--trace" not in chosen:
        argv += ["--trace", ""]
    if command == "run":
        argv.append("--no-evaluate")
    if command == "plan":  # the CPU prediction measures the cost model: a second a draw
        argv.append("--no-cpu")
    return argv


def _value(draw: st.DrawFn, strategy: object, files: dict[str, Path]) -> str:
    if strategy is INPUT:
        kind = draw(INPUT)
        if kind == "toml":
            files["toml"].write_text(draw(toml_documents()))
        return _path(files, kind)
    if strategy is OUTPUT:
        return _path(files, draw(OUTPUT))
    return draw(strategy)  # type: ignore[arg-type]


class Hang(BaseException):
    """Raised by SIGALRM: not an Exception, so no handler of the command can take it."""


def _alarm(signum: int, frame: object) -> None:
    raise Hang(f"no exit within {TIME_LIMIT_S} s")


def _check_one(argv: list[str], files: dict[str, Path], capsys: pytest.CaptureFixture) -> None:
    kinds = _kinds(files)
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(TIME_LIMIT_S)
    try:
        rc = main(argv)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    _, err = capsys.readouterr()
    assert "Traceback" not in err, (argv, err)
    assert rc in (0, 1, 2), (argv, rc, err)
    if rc == 2:
        lines = [line for line in err.splitlines() if line.startswith("hdhil: error:")]
        assert len(lines) == 1, (argv, err)
        assert "\n" not in lines[0]
    assert _kinds(files) == kinds, argv  # no device, FIFO, link or directory replaced
    leftovers = [p.name for p in files["new_csv"].parent.iterdir() if ".hdhil-" in p.name]
    assert not leftovers, (argv, leftovers)


@pytest.mark.slow
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_ends_cleanly_on_drawn_input(command, files, capsys) -> None:
    @settings(max_examples=EXAMPLES, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))  # fmt: skip
    @given(data=st.data())
    def check(data: st.DataObject) -> None:
        _check_one(data.draw(argv_for(command, files)), files, capsys)

    check()


# ------------------------------------------------------------------ signals (subprocess)
SIGNAL_CASES = [
    (["run", "--duration", "3", "--trace", "{d}/s.blf"], 0.4),
    (["run", "--duration", "3", "--trace", "{d}/s.blf"], 1.5),
    (["filter", "{trace}", "--out", "{d}/f.csv"], 0.6),
    (["calibrate", "--out", "{d}/c.toml"], 0.6),
    (["emulate", *VIRTUAL, "--duration", "5"], 0.8),
    (["dump", "{trace}"], 0.3),
]


@pytest.mark.slow
@pytest.mark.subprocess
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.parametrize(("argv", "delay"), SIGNAL_CASES)
def test_a_signal_during_start_up_is_a_clean_exit_130(argv, delay, sig, files, tmp_path):
    args = [a.format(d=tmp_path, trace=files["trace"]) for a in argv]
    # The console script, as a user starts it (``hdhil`` beside the interpreter).
    script = Path(sys.executable).with_name("hdhil")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "hdhil"]
    proc = subprocess.Popen([*command, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)  # fmt: skip
    time.sleep(delay)
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
    assert "Traceback" not in err, err
    # The command may have finished before the signal arrived (0): never anything else.
    assert proc.returncode in (0, 130), (proc.returncode, err)
    assert not [p.name for p in tmp_path.iterdir() if ".hdhil-" in p.name]
