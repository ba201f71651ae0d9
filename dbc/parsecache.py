"""A per-user on-disk cache of parsed files: each shipped DBC/EDS is parsed once per machine.

Parsing the control DBC (cantools) and the two EDS files (canopen, configparser) is most
of a run's start-up after the imports.  :func:`cached` pickles a parse's result into the
cache directory (``$HDHIL_CACHE_DIR``, else ``$XDG_CACHE_HOME/hdhil``, else
``~/.cache/hdhil``; ``HDHIL_CACHE_DIR=`` empty disables it) under a name made of the
parse's kind and the SHA-256 of the file's bytes together with the versions of hdhil,
the parsing libraries and Python, and the source of the module that parses (its caller
names it), so an entry written by another version, another parser or of another content
is never read.

The cache is an optimisation only: a missing, unwritable or foreign directory, a corrupt
or truncated entry (each carries the SHA-256 of its pickle), an unpickling error, all
fall back to parsing the file, and the fresh parse replaces a bad entry.  Only a
directory owned by the user and writable by nobody else is used, since unpickling runs
code.  An entry is written to a temporary file in the same directory and renamed into
place (readers never see half an entry; the temporary is removed on any failure), and
only a regular file is ever replaced.

It lives in ``hdhil.dbc``, the bottom layer, so the DBC loader, the object dictionary
reader (``hdhil.canopen.od``) and the firmware's limit check can all use it.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import os
import pickle
import stat
import sys
import tempfile
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import TypeVar

__all__ = ["cache_dir", "cached", "cached_pickle"]

T = TypeVar("T")

#: The first bytes of every entry: the format, then the SHA-256 of the pickle after it.
_MAGIC = b"hdhil-parsecache-1\n"
_DIGEST = hashlib.sha256().digest_size


def cache_dir() -> Path | None:
    """The cache directory the environment names, or None when the cache is disabled."""
    env = os.environ.get("HDHIL_CACHE_DIR")
    if env is not None:
        return Path(env) if env else None
    xdg = os.environ.get("XDG_CACHE_HOME")
    if xdg and os.path.isabs(xdg):
        return Path(xdg) / "hdhil"
    try:
        return Path.home() / ".cache" / "hdhil"
    except RuntimeError:  # no home directory to be found
        return None


@cache
def _versions(libraries: tuple[str, ...]) -> bytes:
    from importlib.metadata import PackageNotFoundError, version

    try:
        own = version("hdhil")
    except PackageNotFoundError:
        own = "unknown"
    parts = [f"hdhil {own}", f"python {sys.version}", f"pickle {pickle.HIGHEST_PROTOCOL}"]
    for name in libraries:
        parts.append(f"{name} {getattr(importlib.import_module(name), '__version__', '?')}")
    return "\n".join(parts).encode()


def _entry_name(
    path: str | Path, kind: str, libraries: tuple[str, ...], code: tuple[str | Path, ...]
) -> str:
    with open(path, "rb") as f:
        content = f.read()
    key = hashlib.sha256(_versions(libraries) + b"\0" + kind.encode() + b"\0")
    for source in code:  # the parser's own source: a changed parser misses its old entries
        key.update(Path(source).read_bytes() + b"\0")
    key.update(content)
    return f"{kind}-{key.hexdigest()}.pickle"


def _private_dir(directory: Path) -> bool:
    st = os.stat(directory)
    return (
        stat.S_ISDIR(st.st_mode)
        and st.st_uid == os.getuid()
        and not st.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
    )


def _read(entry: Path) -> bytes | None:
    """The pickle stored in ``entry``, or None (absent, foreign, corrupt or truncated)."""
    fd = os.open(entry, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode) or st.st_uid != os.getuid():
            return None
        data = f.read()
    head = len(_MAGIC) + _DIGEST
    if not data.startswith(_MAGIC) or len(data) <= head:
        return None
    payload = data[head:]
    if hashlib.sha256(payload).digest() != data[len(_MAGIC) : head]:
        return None
    return payload


def _write(entry: Path, payload: bytes) -> None:
    """Store ``payload`` as ``entry`` atomically; never replaces anything but a regular file."""
    try:
        if not stat.S_ISREG(os.lstat(entry).st_mode):
            return
    except FileNotFoundError:
        pass
    fd, tmp = tempfile.mkstemp(prefix=f".{entry.name}.", suffix=".tmp", dir=entry.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(_MAGIC + hashlib.sha256(payload).digest() + payload)
        os.replace(tmp, entry)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _entry(
    path: str | Path, kind: str, libraries: tuple[str, ...], code: tuple[str | Path, ...]
) -> Path | None:
    """Where the entry of ``path``'s parse of ``kind`` lives, or None (no usable cache)."""
    directory = cache_dir()
    if directory is None:
        return None
    try:
        name = _entry_name(path, kind, libraries, code)
        try:
            if not _private_dir(directory):
                return None
        except FileNotFoundError:
            directory.mkdir(mode=0o700, parents=True, exist_ok=True)
            if not _private_dir(directory):
                return None
    except Exception:  # unreadable file or unusable directory: parse instead
        return None
    return directory / name


def _lookup(entry: Path | None) -> bytes | None:
    """The pickle stored in ``entry``, or None (no cache, or no usable entry)."""
    if entry is None:
        return None
    try:
        return _read(entry)
    except Exception:
        return None


def _store(entry: Path | None, payload: bytes) -> None:
    """Keep ``payload`` as ``entry`` for the next process; a failure only loses the entry."""
    if entry is not None:
        with contextlib.suppress(Exception):
            _write(entry, payload)


def cached_pickle(
    path: str | Path,
    kind: str,
    parse: Callable[[], object],
    libraries: tuple[str, ...] = (),
    code: tuple[str | Path, ...] = (),
) -> bytes:
    """The pickle of ``parse()``, the parse of the file at ``path``: read from the cache
    when an entry for the file's content, ``kind``, the versions of hdhil, Python and
    ``libraries`` (module names) and the source files ``code`` (the parser's module) is
    there, else made and stored."""
    entry = _entry(path, kind, libraries, code)
    payload = _lookup(entry)
    if payload is None:
        payload = pickle.dumps(parse(), protocol=pickle.HIGHEST_PROTOCOL)
        _store(entry, payload)
    return payload


def cached(
    path: str | Path,
    kind: str,
    parse: Callable[[], T],
    libraries: tuple[str, ...] = (),
    code: tuple[str | Path, ...] = (),
) -> T:
    """``parse()``, the parse of the file at ``path``, from the cache when it has it (see
    :func:`cached_pickle`); a parse made here is stored for the next process, and an
    entry that does not unpickle is replaced."""
    entry = _entry(path, kind, libraries, code)
    payload = _lookup(entry)
    if payload is not None:
        try:
            value: T = pickle.loads(payload)
            return value
        except Exception:
            pass
    value = parse()
    _store(entry, pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
    return value
