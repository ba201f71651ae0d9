"""Every file a command reads or writes goes through here.

Outputs (:func:`check_output`, :class:`AtomicOutput`, :func:`write_text`): only a regular
file (or ``-``, standard output) is ever written.  A path naming a character or block
device, a FIFO, a socket, a directory or a symbolic link to one of those is refused with a
one-line error before any work starts.  The data goes to a temporary file in the target's
directory, which replaces the target (``os.replace``, atomic on POSIX) only when complete:
a reader never sees half a file, and an interrupted command leaves the old file as it was.
Temporary files are removed on every exit path: normal return, exception, Ctrl-C
(``KeyboardInterrupt``), SIGTERM/SIGHUP (turned into ``KeyboardInterrupt`` by
:func:`hdhil.core.signals.terminate_as_interrupt`) and interpreter exit.  SIGKILL cannot
be caught; the temporary file of a killed process (its name carries the pid) is removed
by the next write to the same target.

Inputs (:func:`check_input`, :func:`read_config`, :func:`load_toml`): configuration and
data files must be regular files (a FIFO, ``/dev/zero`` or a directory would block or
never end), under a size cap; TOML and JSON documents under a nesting cap.  Every
mistake is a :class:`~hdhil.core.errors.UserError` naming the file.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import re
import shutil
import stat
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from hdhil.core.errors import UserError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: Largest configuration file (TOML/JSON) read: scenario, override, calibration, --config.
CONFIG_MAX_BYTES = 4 * 1024 * 1024
#: Largest data file (trace, signal CSV) read.
DATA_MAX_BYTES = 64 * 1024**3
#: Deepest nesting of tables/arrays accepted in a TOML or JSON document (hdhil's own
#: configurations nest at most 5 deep).
MAX_DEPTH = 32
#: Longest line read from a text data file (text trace, signal CSV): an ASC CAN FD frame
#: line of 64 bytes is about 300 characters; a longer line is no data.
MAX_LINE_CHARS = 4096

__all__ = [
    "CONFIG_MAX_BYTES",
    "DATA_MAX_BYTES",
    "MAX_DEPTH",
    "MAX_LINE_CHARS",
    "AtomicOutput",
    "bounded_lines",
    "check_depth",
    "check_input",
    "check_output",
    "display_name",
    "load_json",
    "load_toml",
    "parse_toml",
    "read_config",
    "write_text",
]


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def display_name(name: str | bytes | os.PathLike[Any]) -> str:
    """``name`` as text that can be printed anywhere and stays on one line: bytes that are
    not UTF-8 (a str holds them as lone surrogates, ``os.fsdecode``) shown as ``\\xff``,
    control characters (a newline, an escape) as Python writes them in a string literal;
    any other name unchanged.  Also good for a message that holds names."""
    text = os.fsdecode(name) if isinstance(name, (bytes, os.PathLike)) else name
    if text.isprintable():
        return text
    try:
        text = text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:  # a surrogate that no undecodable byte produces
        text = text.encode("utf-8", "backslashreplace").decode("utf-8")
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode() for c in text)


def _label(path: Path | str, what: str) -> str:
    return f"{what} {path}" if what else str(path)


# ------------------------------------------------------------------------------- input
def shipped_or_path(text: str, folder: Path, kind: str, known: list[str]) -> Path:
    """A shipped TOML file of ``folder`` for a bare name (``free-motion``), else ``text``
    as a path (anything ending in ``.toml`` or holding a path separator). An unknown name
    or a missing file is a :class:`ConfigError` naming ``kind`` and the shipped names."""
    from hdhil.core.errors import ConfigError

    if not (text.endswith(".toml") or "/" in text or "\\" in text):
        path = folder / f"{text}.toml"
        with contextlib.suppress(OSError):  # e.g. a name too long for the file system
            if path.is_file():
                return path
        raise ConfigError(
            f"unknown {kind} {text!r} (known: {', '.join(known) or 'none'}; "
            "or give a path to a .toml file)"
        )
    path = Path(text)
    if not path.exists():
        raise ConfigError(f"{kind} file not found: {text}")
    return path  # the loader refuses what is not a regular file, naming it


def check_input(path: str | Path, what: str = "", max_bytes: int = DATA_MAX_BYTES) -> Path:
    """``path`` as a :class:`Path` if it names a readable regular file of at most
    ``max_bytes`` bytes (symbolic links followed); else a one-line :class:`UserError`
    naming ``what path``."""
    p = Path(path)
    label = _label(p, what)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise UserError(f"{label}: no such file") from None
    except OSError as exc:
        raise UserError(f"{label}: cannot read ({exc.strerror or exc})") from None
    if not stat.S_ISREG(st.st_mode):
        raise UserError(f"{label}: {_kind(st.st_mode)}, not a regular file")
    if st.st_size > max_bytes:
        raise UserError(f"{label}: {st.st_size} bytes, more than the {max_bytes} accepted")
    if not os.access(p, os.R_OK):
        raise UserError(f"{label}: cannot read (permission denied)")
    return p


def bounded_lines(stream: IO[str], label: str, max_chars: int = MAX_LINE_CHARS) -> Iterator[str]:
    """The lines of text ``stream``, none held longer than ``max_chars`` characters: a
    longer one is a :class:`UserError` naming ``label`` and the line number (a file of
    junk with no line end is not read whole into memory)."""
    lineno = 0
    while line := stream.readline(max_chars + 1):
        lineno += 1
        if len(line) > max_chars and not line.endswith(("\n", "\r")):
            raise UserError(f"{label}:{lineno}: a line longer than {max_chars} characters")
        yield line


def read_config(path: str | Path, what: str = "", max_bytes: int = CONFIG_MAX_BYTES) -> str:
    """The text of configuration file ``path`` (UTF-8), checked by :func:`check_input`."""
    p = check_input(path, what, max_bytes)
    label = _label(p, what)
    try:
        with p.open("rb") as fh:
            raw = fh.read(max_bytes + 1)  # the file may have grown since the check
    except OSError as exc:
        raise UserError(f"{label}: cannot read ({exc.strerror or exc})") from None
    if len(raw) > max_bytes:
        raise UserError(f"{label}: more than the {max_bytes} bytes accepted")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{label}: not a UTF-8 text file (byte {exc.start})") from None


def check_depth(data: Any, label: str, max_depth: int = MAX_DEPTH) -> None:
    """Refuse documents nested deeper than ``max_depth`` (iteratively: no recursion)."""
    stack: list[tuple[Any, int]] = [(data, 0)]
    while stack:
        node, depth = stack.pop()
        if depth > max_depth:
            raise UserError(f"{label}: nested more than {max_depth} levels deep")
        if isinstance(node, dict):
            stack.extend((v, depth + 1) for v in node.values())
        elif isinstance(node, list):
            stack.extend((v, depth + 1) for v in node)


def _prescan_depth(text: str, label: str, max_depth: int) -> None:
    """A cheap bound before parsing: more than ``max_depth`` brackets opened in a row
    (ignoring whitespace) is nesting no parser should recurse into."""
    if len(text) > 4 * max_depth and re.search(rf"(?:[\[{{]\s*){{{max_depth + 2}}}", text):
        raise UserError(f"{label}: nested more than {max_depth} levels deep")


def parse_toml(text: str, label: str, max_depth: int = MAX_DEPTH) -> dict[str, Any]:
    """``text`` parsed as TOML with one-line errors naming ``label``."""
    _prescan_depth(text, label, max_depth)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{label}: invalid TOML: {exc}") from None
    except RecursionError:
        raise UserError(f"{label}: nested more than {max_depth} levels deep") from None
    except ValueError as exc:  # e.g. an integer of more digits than Python converts
        raise UserError(f"{label}: invalid TOML: {str(exc).split(';')[0]}") from None
    check_depth(data, label, max_depth)
    return data


def load_toml(path: str | Path, what: str = "") -> dict[str, Any]:
    """TOML file ``path`` as nested dicts: regular file, size and depth capped."""
    return parse_toml(read_config(path, what), _label(path, what))


def load_json(path: str | Path, what: str = "") -> Any:
    """JSON file ``path``: regular file, size and depth capped."""
    label = _label(path, what)
    text = read_config(path, what)
    _prescan_depth(text, label, MAX_DEPTH)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise UserError(f"{label}: invalid JSON: {exc}") from None
    except (RecursionError, ValueError) as exc:
        raise UserError(f"{label}: invalid JSON: {str(exc).split(';')[0]}") from None
    check_depth(data, label)
    return data


# ------------------------------------------------------------------------------ output
#: Temporary files of this process not yet renamed into place or removed.
_LIVE: set[str] = set()


def _unlink(name: str) -> None:
    """Remove a temporary file, or a temporary directory and what it holds."""
    with contextlib.suppress(OSError):
        if os.path.isdir(name) and not os.path.islink(name):
            shutil.rmtree(name, ignore_errors=True)
        else:
            os.unlink(name)


def _remove_live() -> None:
    for name in list(_LIVE):
        _unlink(name)
        _LIVE.discard(name)


atexit.register(_remove_live)


def check_output(path: str | Path, what: str = "") -> Path | None:
    """The file to write for ``path`` (``None`` for ``-``, standard output).

    Refused with a one-line :class:`UserError`: anything that exists and is not a regular
    file (device, FIFO, socket, directory; a symbolic link is followed and judged by what
    it points to), a missing directory, a directory without write permission.  For a link
    to a regular file the link's target is returned, so the link stays a link.
    """
    if str(path) == "-":
        return None
    p = Path(path)
    label = _label(p, what)
    if str(p) == "":
        raise UserError(f"{label or 'output'}: empty file name")
    try:
        st = p.stat()
    except FileNotFoundError:
        if p.is_symlink():
            raise UserError(f"{label}: a dangling symbolic link") from None
        st = None
    except OSError as exc:
        raise UserError(f"{label}: cannot write ({exc.strerror or exc})") from None
    if st is not None:
        if not stat.S_ISREG(st.st_mode):
            raise UserError(f"{label}: {_kind(st.st_mode)}; only regular files are written")
        if p.is_symlink():
            p = p.resolve()
    parent = p.parent
    if not parent.is_dir():
        raise UserError(f"{label}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UserError(f"{label}: cannot write in directory {parent} (permission denied)")
    _check_temporary_name(p, label)
    return p


def _check_temporary_name(target: Path, label: str) -> None:
    """Refuse up front a name whose temporary file (:func:`temporary_for`: the name with
    about 30 bytes around it) would be longer than the file system allows: the write
    would fail only once the work is done."""
    longest = f".{target.name}.hdhil-{'9' * 7}-{'x' * 8}.tmp{target.suffix}"
    try:
        limit = os.pathconf(target.parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    size = len(os.fsencode(longest))
    if limit > 0 and size > limit:
        raise UserError(
            f"{label}: name too long ({len(os.fsencode(target.name))} bytes): the temporary "
            f"file written beside it takes up to {size}, more than the {limit} the file "
            "system allows"
        )


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _remove_stale(target: Path) -> None:
    """Remove temporaries for ``target`` left by killed processes (SIGKILL)."""
    prefix = f".{target.name}.hdhil-"
    with contextlib.suppress(OSError):
        for entry in os.scandir(target.parent):
            if not entry.name.startswith(prefix):
                continue
            m = re.match(r"(\d+)-", entry.name[len(prefix) :])
            if m and int(m.group(1)) != os.getpid() and not _pid_alive(int(m.group(1))):
                _unlink(entry.path)


def temporary_for(target: Path) -> Path:
    """A new empty temporary file beside ``target``, with ``target``'s suffix (libraries
    that choose a format by extension see the right one), registered for removal."""
    _remove_stale(target)
    fd, name = tempfile.mkstemp(
        prefix=f".{target.name}.hdhil-{os.getpid()}-", suffix=f".tmp{target.suffix}",
        dir=target.parent,
    )  # fmt: skip
    os.close(fd)
    _LIVE.add(name)
    return Path(name)


def temporary_dir_for(target: Path) -> Path:
    """A new empty private directory beside ``target``, registered for removal, for a
    writer that must be given ``target``'s own file name (python-can's ``Logger`` picks
    the format from every suffix: ``run.asc.gz``): it writes ``DIR / target.name``,
    which :func:`commit_temporary_dir` renames into place."""
    _remove_stale(target)
    name = tempfile.mkdtemp(
        prefix=f".{target.name}.hdhil-{os.getpid()}-", suffix=".tmp", dir=target.parent
    )
    _LIVE.add(name)
    return Path(name)


def commit_temporary_dir(tmp_dir: Path, target: Path, label: str) -> None:
    """Rename ``tmp_dir / target.name`` over ``target`` (as :func:`commit_temporary`),
    then remove ``tmp_dir``; on an error both are removed and ``target`` is left."""
    try:
        commit_temporary(tmp_dir / target.name, target, label)
    finally:
        discard_temporary(tmp_dir)


def release_temporary(tmp: Path) -> None:
    """Stop tracking ``tmp`` for removal at exit: another process (the trace writer)
    owns it now and renames or removes it itself."""
    _LIVE.discard(str(tmp))


def commit_temporary(tmp: Path, target: Path, label: str) -> None:
    """Rename ``tmp`` over ``target`` if ``target`` is (still) a regular file or absent."""
    try:
        st = os.lstat(target)
    except FileNotFoundError:
        st = None
    if st is not None and not stat.S_ISREG(st.st_mode):
        discard_temporary(tmp)
        raise UserError(f"{label}: became {_kind(st.st_mode)} while writing; not replaced")
    with contextlib.suppress(OSError):  # keep the old file's permissions (or umask's)
        os.chmod(tmp, stat.S_IMODE(st.st_mode) if st else 0o666 & ~_umask())
    try:
        os.replace(tmp, target)
    except OSError as exc:
        discard_temporary(tmp)
        raise UserError(f"{label}: cannot write ({exc.strerror or exc})") from None
    _LIVE.discard(str(tmp))


def discard_temporary(tmp: Path) -> None:
    """Remove temporary file (or directory) ``tmp``, if it is still there."""
    _unlink(str(tmp))
    _LIVE.discard(str(tmp))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


class AtomicOutput:
    """A context manager writing ``path`` atomically (``-``: standard output).

    ``with AtomicOutput(path, "--out") as out:`` gives ``out.file`` (an open text file,
    or binary with ``binary=True``) and ``out.path`` (the temporary file's path, for
    libraries that want a file name, e.g. ``savefig``; ``None`` for standard output).
    On a clean exit the temporary file replaces the target; on any exception, Ctrl-C
    included, it is removed and the target is left as it was.
    """

    def __init__(self, path: str | Path, what: str = "", binary: bool = False,
                 open_file: bool = True) -> None:  # fmt: skip
        self.label = "stdout" if str(path) == "-" else _label(path, what)
        self.target = check_output(path, what)
        self.binary = binary
        self.open_file = open_file
        self.path: Path | None = None
        self.file: IO[Any] | None = None

    def __enter__(self) -> AtomicOutput:
        if self.target is None:
            self.file = sys.stdout.buffer if self.binary else sys.stdout
            return self
        try:
            self.path = temporary_for(self.target)
        except OSError as exc:
            raise UserError(f"{self.label}: cannot write ({exc.strerror or exc})") from None
        if self.open_file:
            mode = "wb" if self.binary else "w"
            kwargs: dict[str, Any] = {} if self.binary else {"encoding": "utf-8", "newline": ""}
            self.file = open(self.path, mode, **kwargs)
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if self.target is None:
            if exc_type is None and self.file is not None:
                self.file.flush()
            return
        assert self.path is not None
        try:
            if self.file is not None:
                self.file.close()
        except OSError as err:
            discard_temporary(self.path)
            if exc_type is None:
                raise UserError(f"{self.label}: cannot write ({err.strerror or err})") from None
            return
        if exc_type is not None:
            discard_temporary(self.path)
            return
        commit_temporary(self.path, self.target, self.label)


@contextlib.contextmanager
def atomic_path(path: str | Path, what: str = "") -> Iterator[Path]:
    """A temporary path to hand to a library that writes by name; it replaces ``path``
    when the block ends without an exception."""
    with AtomicOutput(path, what, open_file=False) as out:
        if out.path is None:
            raise UserError(f"{out.label}: standard output is not possible here")
        yield out.path


def write_text(path: str | Path, text: str, what: str = "") -> None:
    """Write ``text`` to ``path`` (``-``: standard output) atomically."""
    with AtomicOutput(path, what) as out:
        assert out.file is not None
        out.file.write(text)
