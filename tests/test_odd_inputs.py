"""Odd file names and hostile input files: any name the OS accepts works or is refused in
one line ``hdhil: error: ...``, printing it never raises, and reading a file of junk
takes bounded memory whatever its size."""

from __future__ import annotations

import io
import os
import signal
import sys
import tracemalloc
import zlib
from pathlib import Path

import pytest

from hdhil.can.traces import reader as trace_reader
from hdhil.can.traces.reader import TraceError, read_trace
from hdhil.can.traces.sidecar import read_metadata
from hdhil.cli import main
from hdhil.core.files import CONFIG_MAX_BYTES, display_name, load_toml

#: A name that is no UTF-8 (a byte 0xff), as Python holds it: a lone surrogate.
BAD = os.fsdecode(b"tr\xff")


# ----------------------------------------------------------------------- display
@pytest.mark.parametrize(
    ("name", "shown"),
    [
        (b"tr\xff.blf", "tr\\xff.blf"),
        (f"{BAD}.blf", "tr\\xff.blf"),
        ("a\nb.blf", "a\\nb.blf"),
        ("\x1b[31mred", "\\x1b[31mred"),
        ("grün é.blf", "grün é.blf"),
        (Path("dir") / "x.blf", "dir/x.blf"),
    ],
)
def test_display_name_escapes_what_cannot_be_printed_on_one_line(name, shown):
    text = display_name(name)
    assert text == shown
    text.encode("utf-8")  # printable anywhere: no lone surrogate left


# ------------------------------------------------------------ non-UTF-8 names (1)
def test_a_non_utf8_output_name_is_written_and_printed(tmp_path, monkeypatch):
    # Standard output that encodes UTF-8 strictly, as outside the C locale (or with
    # PYTHONIOENCODING=utf-8): printing the name raised UnicodeEncodeError.
    stdout = io.TextIOWrapper(io.BytesIO(), encoding="utf-8", errors="strict")
    monkeypatch.setattr(sys, "stdout", stdout)
    out = tmp_path / f"{BAD}.dbc"
    assert main(["dbc", "export", str(out)]) == 0
    assert out.is_file()
    stdout.flush()
    assert b"tr\\xff.dbc" in stdout.buffer.getvalue()  # escaped as in errors, not raised
    assert stdout.errors == "strict"  # as it was


@pytest.mark.slow
def test_plot_and_tune_of_a_trace_with_a_non_utf8_name(tmp_path, capsys):
    """The figure's title and the tuned TOML's comment name the trace: matplotlib refused
    the lone surrogate, and the TOML file (UTF-8) could not hold it."""
    trace = tmp_path / f"{BAD}.blf"
    assert main(["run", "-q", "--duration", "0.6", "--no-evaluate", "--trace", str(trace)]) == 0
    out = tmp_path / f"{BAD}.png"
    assert main(["plot", str(trace), "--out", str(out)]) == 0
    assert out.stat().st_size > 0
    tuned = tmp_path / f"{BAD}.toml"
    argv = ["tune", "-q", str(trace), "--max-evals", "2", "--skip", "0.1", "--out", str(tuned)]
    assert main(argv) == 0
    assert "tr\\xff.blf" in tuned.read_text(encoding="utf-8")
    assert "firmware" in load_toml(tuned)
    assert "hdhil: error" not in capsys.readouterr().err


@pytest.mark.slow
def test_campaign_parquet_in_a_non_utf8_folder(tmp_path):
    """pyarrow refused a file name that is not UTF-8; the table goes through a buffer."""
    pytest.importorskip("pyarrow")
    from hdhil.rig.campaign_file import load_campaign
    from hdhil.rig.campaign_report import columns, write_parquet

    campaign = load_campaign("smoke")
    folder = tmp_path / f"{BAD}-out"
    folder.mkdir()
    row = dict.fromkeys(columns(campaign))
    row.update(variant="v0", scenario="free-motion", seed=1, status="pass")
    path = folder / "results.parquet"
    assert write_parquet(path, campaign, [row]) is None
    import pyarrow.parquet as pq

    table = pq.read_table(io.BytesIO(path.read_bytes()))  # pyarrow takes no such path
    assert table.column("variant").to_pylist() == ["v0"]
    assert [p.name for p in folder.iterdir()] == ["results.parquet"]  # no temporary left


# ---------------------------------------------------------- one error line (2)
LONG = "x" * 300  # > NAME_MAX (255 bytes)
DEEP = "/".join(["d" * 200] * 25)  # > PATH_MAX (4096 bytes)
ODD_NAMES = {"newline": "a\nb", "escape": "\x1b[2J", "long": LONG, "deep": DEEP, "bad": BAD}


def _commands(stem: str, tmp: Path) -> dict[str, list[str]]:
    name = str(tmp / stem) if not stem.startswith("d" * 200) else stem
    return {
        "dump": ["dump", f"{name}.blf"],
        "evaluate": ["evaluate", f"{name}.blf"],
        "run-scenario": ["run", "--trace", "", "--scenario", f"{name}.toml"],
        "run-trace": ["run", "--duration", "0.05", "--trace", f"{name}/x.blf"],
        "campaign": ["campaign", f"{name}.toml"],
        "filter": ["filter", f"{name}.csv", "--out", f"{name}.out.csv"],
        "tune-out": ["tune", f"{name}.blf", "--out", f"{name}/t.toml"],
    }


CASES = [(kind, cmd) for kind in ODD_NAMES for cmd in _commands("x", Path("."))]


@pytest.mark.parametrize(("kind", "command"), CASES, ids=[f"{k}-{c}" for k, c in CASES])
def test_an_odd_name_is_refused_in_one_line(kind, command, tmp_path, capsys):
    argv = _commands(ODD_NAMES[kind], tmp_path)[command]
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("hdhil: error: "), err
    assert lines[0].isprintable(), lines[0]  # no control character for the terminal
    lines[0].encode("utf-8")  # no lone surrogate either


# ------------------------------------------------------------ bounded reading (4)
def _peak_while(fn) -> int:
    """Peak Python allocation (bytes) while ``fn`` runs."""
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _refused(path: Path) -> str:
    with pytest.raises(TraceError) as info:
        read_trace(path)
    return str(info.value)


JUNK_BYTES = 6 * 1024 * 1024
#: What reading may allocate, far below the junk's size.
READ_BOUND = 1024 * 1024


@pytest.mark.parametrize(
    "junk",
    [
        b"x" * JUNK_BYTES,  # one endless line
        b"not a frame, not a comment\n" * (JUNK_BYTES // 27),  # lines the reader skips
    ],
    ids=["one-line", "many-lines"],
)
@pytest.mark.parametrize("suffix", [".asc", ".log", ".csv", ".trc"])
def test_a_junk_text_trace_is_refused_in_bounded_memory(junk, suffix, tmp_path):
    path = tmp_path / f"junk{suffix}"
    path.write_bytes(junk)
    message = []
    peak = _peak_while(lambda: message.append(_refused(path)))
    assert peak < READ_BOUND, f"{peak} bytes allocated reading {len(junk)} bytes of junk"
    assert "not a readable" in message[0]


def test_legitimate_lines_without_a_frame_are_read_up_to_a_bound(tmp_path, monkeypatch):
    """Comment lines are no damage, but a file of nothing else is given up on."""
    monkeypatch.setattr(trace_reader, "MAX_LEADING_CHARS", 64 * 1024)
    path = tmp_path / "comments.asc"
    path.write_bytes(b"// a comment line\n" * 100_000)  # 1.8 MB
    message = []
    peak = _peak_while(lambda: message.append(_refused(path)))
    assert peak < READ_BOUND
    assert "no CAN frame in the first 65536 characters" in message[0]


def _blf_with_container(tmp_path: Path, payload: bytes) -> Path:
    """A BLF file (header of a real one) holding one zlib log container of ``payload``."""
    from can.io import blf

    real = tmp_path / "real.blf"
    with blf.BLFWriter(str(real)) as writer:
        writer.on_message_received(__import__("can").Message(arbitration_id=1, data=b"\x01"))
    header = real.read_bytes()[: blf.FILE_HEADER_SIZE]
    packed = zlib.compress(payload, 9)
    body = blf.LOG_CONTAINER_STRUCT.pack(blf.ZLIB_DEFLATE, len(payload)) + packed
    size = blf.OBJ_HEADER_BASE_STRUCT.size + len(body)
    obj = blf.OBJ_HEADER_BASE_STRUCT.pack(
        b"LOBJ", blf.OBJ_HEADER_BASE_STRUCT.size, 1, size, blf.LOG_CONTAINER
    )
    path = tmp_path / "bomb.blf"
    path.write_bytes(header + obj + body + b"\0" * (size % 4))
    return path


def test_a_blf_container_that_decompresses_to_gigabytes_is_refused(tmp_path, monkeypatch):
    """A few kilobytes of zlib can inflate to gigabytes (here 16 MiB, the cap lowered)."""
    limit = 1024 * 1024
    monkeypatch.setattr(trace_reader, "MAX_BLF_OBJECT_BYTES", limit, raising=False)
    path = _blf_with_container(tmp_path, b"\0" * (16 * limit))
    assert path.stat().st_size < 64 * 1024
    message = []
    peak = _peak_while(lambda: message.append(_refused(path)))
    assert peak < 2 * limit + READ_BOUND
    assert "decompressing to more than" in message[0]


def test_a_huge_sidecar_is_not_read(tmp_path):
    trace = tmp_path / "t.blf"
    side = tmp_path / "t.blf.json"
    side.write_text('{"seed": 1, "pad": "' + "x" * CONFIG_MAX_BYTES + '"}')
    assert read_metadata(trace) is None
    side.write_text('{"seed": 1}')
    assert read_metadata(trace) == {"seed": 1}


def test_a_stream_in_place_of_a_sidecar_is_not_read(tmp_path):
    trace = tmp_path / "t.blf"
    os.mkfifo(tmp_path / "t.blf.json")  # reading it would block for ever

    def blocked(signum, frame):
        raise AssertionError("read_metadata blocked on a FIFO")

    previous = signal.signal(signal.SIGALRM, blocked)
    signal.alarm(5)
    try:
        assert read_metadata(trace) is None
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.mark.parametrize(
    "junk",
    [
        b"time,T_meas,velocity\n" + b"1," * (JUNK_BYTES // 2) + b"\n",  # millions of fields
        b"time,T_meas,velocity\n" + b"1" * JUNK_BYTES,  # one endless field
        b"t" * JUNK_BYTES,  # an endless header
    ],
    ids=["many-fields", "long-field", "long-header"],
)
def test_a_junk_signal_csv_is_refused_in_bounded_memory(junk, tmp_path):
    from hdhil.core.errors import UserError
    from hdhil.firmware.config import FirmwareConfig
    from hdhil.rig.offline import filter_signal_csv

    path = tmp_path / "junk.csv"
    path.write_bytes(junk)
    FirmwareConfig()  # built once before measuring

    class Rows:
        def writerow(self, row: object) -> None:
            raise AssertionError("no row of junk is a sample")

    def read() -> None:
        with pytest.raises(UserError, match="longer than 4096 characters"):
            filter_signal_csv(path, False, FirmwareConfig(), Rows())

    assert _peak_while(read) < READ_BOUND


@pytest.mark.parametrize(("command", "kind"), [("run", "scenario"), ("campaign", "campaign")])
def test_a_bare_name_too_long_for_a_file_is_an_unknown_name(command, kind, capsys):
    argv = ["run", "--trace", "", "--scenario", LONG] if command == "run" else [command, LONG]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"hdhil: error: unknown {kind} 'xxx") and err.count("\n") == 1


@pytest.mark.parametrize("length", [222, 240])
def test_a_name_whose_temporary_or_sidecar_would_be_too_long_is_refused_up_front(
    length, tmp_path, capsys
):
    """The name itself is valid, but the trace's temporary (at 240) or its sidecar's (at
    222: NAME.blf.json beside a temporary) is not: the trace was written and the sidecar
    then failed, after the whole run."""
    trace = tmp_path / ("v" * length + ".blf")
    assert main(["run", "-q", "--duration", "0.05", "--no-evaluate", "--trace", str(trace)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "name too long" in err, err
    assert list(tmp_path.iterdir()) == []


FRAME = "   {t:.6f} 1  181             Rx   d 8 00 00 00 00 00 00 00 00\n"
ASC_HEAD = "date Thu Nov 26 12:00:00.000 am 2026\nbase hex  timestamps absolute\n"
ASC_HEAD += "no internal events logged\n"


def test_a_trace_whose_sidecar_name_would_be_too_long_is_read(tmp_path, capsys):
    """255 bytes is a valid name; the sidecar's (the name plus .json) is not, and looking
    for it must not refuse the trace."""
    path = tmp_path / ("x" * 251 + ".asc")
    path.write_text(ASC_HEAD + FRAME.format(t=0.0) + FRAME.format(t=0.001))
    assert main(["dump", str(path), "--stats"]) == 0
    assert "hdhil: error" not in capsys.readouterr().err


def test_damage_warnings_stay_one_line_each_whatever_the_name(tmp_path, capsys):
    text = ASC_HEAD + FRAME.format(t=0.0) + "garbage\n" + FRAME.format(t=0.001)
    path = tmp_path / "a\nb.asc"
    path.write_text(text)
    assert main(["dump", str(path)]) == 1
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) >= 2 and all(line.startswith("hdhil: ") for line in lines), err
    assert "a\\nb.asc: damaged after frame 1" in err


def test_stats_of_countless_identifiers_and_channels_stay_bounded(monkeypatch):
    """``dump --stats`` keeps a record per identifier and per bus: a trace of random
    identifiers on random channels (junk that parses as frames) grew them without end."""
    import can

    from hdhil.can.traces import stats as trace_stats

    monkeypatch.setattr(trace_stats, "MAX_IDS", 50, raising=False)
    monkeypatch.setattr(trace_stats, "MAX_BUSES", 4, raising=False)
    acc = trace_stats.StatsAccumulator()
    for i in range(1000):
        ident = 0x100000 + i
        msg = can.Message(timestamp=i * 1e-3, arbitration_id=ident, is_extended_id=True)
        msg.channel, msg.data = 10 + i % 20, bytearray(1)
        acc.add(msg)
    result = acc.result()
    assert len(result["ids"]) == 50 and result["unlisted_frames"] == 950
    assert len(result["buses"]) == 5  # four channels, then "other"
    assert sum(b["frames"] for b in result["buses"].values()) == 1000
    assert all(b["unknown_ids"] <= 50 for b in result["buses"].values())
    assert "950 frames of identifiers beyond the first 50" in trace_stats.format_stats(result)


def test_a_blf_object_size_beyond_the_file_is_refused_before_reading(tmp_path):
    """A damaged size field (512 MiB here) was handed to ``read``, which allocates
    that much before finding the file shorter."""
    from can.io import blf

    path = _blf_with_container(tmp_path, b"\0" * 64)
    data = bytearray(path.read_bytes())
    blf.OBJ_HEADER_BASE_STRUCT.pack_into(
        data, blf.FILE_HEADER_SIZE, b"LOBJ", blf.OBJ_HEADER_BASE_STRUCT.size, 1, 512 << 20, 10
    )
    path.write_bytes(bytes(data))
    message = []
    peak = _peak_while(lambda: message.append(_refused(path)))
    assert peak < READ_BOUND
    assert "a damaged BLF size field: 536870896 bytes to read at byte 160" in message[0]
