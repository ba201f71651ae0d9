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

Several outputs that belong together (a trace, its sidecar and the run's fault log) are
renamed into place as one (:func:`commit_together`): every one or, if a rename fails,
none, the old files restored.  An output is never one of the command's own inputs
(:func:`check_not_inputs`, by resolved path and by file identity): refused in one line
before any work starts.

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
from collections.abc import Iterable, Iterator, Sequence
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
    "check_not_inputs",
    "check_output",
    "commit_outputs",
    "commit_together",
    "discard_outputs",
    "display_name",
    "load_json",
    "load_toml",
    "parse_toml",
    "read_config",
    "same_file",
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
            # What is there, never more than the cap (the file may have grown since the
            # check); ``read(cap)`` would allocate the whole cap for every small file.
            raw = fh.read(min(os.fstat(fh.fileno()).st_size, max_bytes) + 1)
            while len(raw) <= max_bytes:
                more = fh.read(min(1 << 16, max_bytes + 1 - len(raw)))
                if not more:
                    break
                raw += more
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


def same_file(a: str | Path, b: str | Path) -> bool:
    """Whether ``a`` and ``b`` name one file: the same path once symbolic links and
    ``..`` are resolved, or (both existing) the same file by device and inode (a hard
    link).  ``-`` (standard output) is no file."""
    if str(a) == "-" or str(b) == "-":
        return False
    try:
        if os.path.realpath(a) == os.path.realpath(b):
            return True
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def check_not_inputs(
    outputs: Iterable[tuple[str | Path | None, str]],
    inputs: Iterable[tuple[str | Path | None, str]],
) -> None:
    """Refuse, with a one-line :class:`UserError`, an output that is one of the
    command's inputs (``(path, what)`` pairs, ``None`` paths skipped) or another of its
    outputs (:func:`same_file`): a command never writes over what it reads, nor two of
    its outputs into one file.  Called before any work starts."""
    outs = [(p, w) for p, w in outputs if p is not None and str(p) not in ("", "-")]
    ins = [(p, w) for p, w in inputs if p is not None and str(p) not in ("", "-")]
    for i, (out, what) in enumerate(outs):
        for src, src_what in ins:
            if same_file(out, src):
                raise UserError(
                    f"{_label(out, what)}: would overwrite the {src_what} {src} this "
                    "command reads; refused (name another file)"
                )
        for other, other_what in outs[:i]:
            if same_file(out, other):
                raise UserError(
                    f"{_label(out, what)}: is also the {other_what} {other} this command "
                    "writes; refused (two outputs cannot be one file)"
                )


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


def commit_together(items: Sequence[tuple[Path, Path, str]]) -> None:
    """Rename each temporary over its target (``(temporary, target, label)``), as one
    output: every target replaced, or none.

    Every target must (still) be a regular file or absent, checked before the first
    rename.  An existing target is kept under a hard link first (no data copied, no
    space needed); if a rename fails, the targets already replaced get their old files
    back (or are removed where there was none).  Every temporary is removed in the end,
    whatever happened; a failure is a one-line :class:`UserError` naming the output."""
    backups: list[tuple[Path, Path | None]] = []  # (target, its old file's link or None)
    done: list[tuple[Path, Path | None]] = []
    try:
        for tmp, target, label in items:
            try:
                st = os.lstat(target)
            except FileNotFoundError:
                st = None
            except OSError as exc:
                raise UserError(f"{label}: cannot write ({exc.strerror or exc})") from None
            if st is not None and not stat.S_ISREG(st.st_mode):
                raise UserError(f"{label}: became {_kind(st.st_mode)} while writing; not replaced")
            with contextlib.suppress(OSError):  # the old file's permissions (or umask's)
                os.chmod(tmp, stat.S_IMODE(st.st_mode) if st else 0o666 & ~_umask())
            keep = None
            if st is not None and len(items) > 1:
                keep = _backup_link(target)
            backups.append((target, keep))
        for (tmp, target, label), (_, keep) in zip(items, backups, strict=True):
            try:
                os.replace(tmp, target)
            except OSError as exc:
                raise UserError(f"{label}: cannot write ({exc.strerror or exc})") from None
            _LIVE.discard(str(tmp))
            done.append((target, keep))
        done = []  # every one in place: nothing to undo
    finally:
        for target, keep in reversed(done):  # undo, newest first
            with contextlib.suppress(OSError):
                if keep is not None:
                    os.replace(keep, target)
                else:
                    os.unlink(target)
        for _, keep in backups:
            if keep is not None:
                discard_temporary(keep)
        for tmp, _, _ in items:
            discard_temporary(tmp)


def _backup_link(target: Path) -> Path | None:
    """A hard link to ``target`` beside it, registered for removal (``None`` where the
    file system has no hard links: that target cannot be restored)."""
    name = f"{target.parent}/.{target.name}.hdhil-{os.getpid()}-{os.urandom(4).hex()}.old"
    try:
        os.link(target, name)
    except OSError:
        return None
    _LIVE.add(name)
    return Path(name)


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

    ``deferred=True``: a clean exit only closes the complete temporary; several such
    outputs of one command are then renamed into place together by
    :func:`commit_outputs` (all or none).
    """

    def __init__(self, path: str | Path, what: str = "", binary: bool = False,
                 open_file: bool = True, deferred: bool = False) -> None:  # fmt: skip
        self.label = "stdout" if str(path) == "-" else _label(path, what)
        self.target = check_output(path, what)
        self.binary = binary
        self.open_file = open_file
        self.deferred = deferred
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
        if not self.deferred:
            commit_temporary(self.path, self.target, self.label)


def commit_outputs(outputs: Sequence[AtomicOutput]) -> None:
    """Rename the complete temporaries of ``outputs`` (each written with
    ``deferred=True``) into place together (:func:`commit_together`): all or none."""
    commit_together([(o.path, o.target, o.label) for o in outputs
                     if o.path is not None and o.target is not None])  # fmt: skip


def discard_outputs(outputs: Sequence[AtomicOutput]) -> None:
    """Remove the temporaries of deferred ``outputs`` (the command failed)."""
    for o in outputs:
        if o.path is not None:
            discard_temporary(o.path)


@contextlib.contextmanager
def atomic_path(path: str | Path, what: str = "", deferred: AtomicOutput | None = None
                ) -> Iterator[Path]:  # fmt: skip
    """A temporary path to hand to a library that writes by name; it replaces ``path``
    when the block ends without an exception (with ``deferred``, an
    ``AtomicOutput(path, what, open_file=False, deferred=True)``: when
    :func:`commit_outputs` renames it with the command's other outputs)."""
    with deferred or AtomicOutput(path, what, open_file=False) as out:
        if out.path is None:
            raise UserError(f"{out.label}: standard output is not possible here")
        yield out.path


def write_text(path: str | Path, text: str, what: str = "",
               deferred: AtomicOutput | None = None) -> None:  # fmt: skip
    """Write ``text`` to ``path`` (``-``: standard output) atomically (with ``deferred``,
    an ``AtomicOutput(path, what, deferred=True)``: renamed by :func:`commit_outputs`)."""
    with deferred or AtomicOutput(path, what) as out:
        assert out.file is not None
        out.file.write(text)
