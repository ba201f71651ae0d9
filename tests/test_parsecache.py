"""hdhil.dbc.parsecache: a parse is read back from disk equal to a fresh one, and every
failure of the cache (corrupt entry, unusable directory, failed write) falls back to
parsing without leaving anything behind."""

from __future__ import annotations

import hashlib
import os
import pickle
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

import cantools
import pytest

from hdhil.canopen import od as od_mod
from hdhil.dbc import dbc_path, eds_path, parsecache
from hdhil.dbc.parsecache import cached, cached_pickle
from tests.test_od_cache import variables


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    directory = tmp_path / "cache"
    monkeypatch.setenv("HDHIL_CACHE_DIR", str(directory))
    return directory


@pytest.fixture
def fresh_od_caches() -> Iterator[None]:
    """The per-process caches of hdhil.canopen.od emptied before and after the test."""
    clear = (od_mod._parser, od_mod._pickled_od, od_mod._parsed_od, od_mod._object_names)
    for f in clear:
        f.cache_clear()
    yield
    for f in clear:
        f.cache_clear()


class Counted:
    """A parse that counts its calls."""

    def __init__(self, parse: Callable[[], object]) -> None:
        self.parse = parse
        self.calls = 0

    def __call__(self) -> object:
        self.calls += 1
        return self.parse()


def dbc_summary(db: cantools.database.can.Database) -> list[tuple]:
    return [
        (m.name, m.frame_id, m.length, m.senders,
         [(s.name, s.start, s.length, s.scale, s.offset, s.is_signed, s.is_float,
           s.byte_order, s.minimum, s.maximum, s.unit) for s in m.signals])
        for m in db.messages
    ]  # fmt: skip


def entries(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir())


def test_dbc_hit_equals_fresh_parse(cache: Path) -> None:
    path = str(dbc_path("control"))
    parse = Counted(lambda: cantools.database.load_file(path))
    first = cached(path, "dbc", parse, ("cantools",))
    second = cached(path, "dbc", parse, ("cantools",))
    assert parse.calls == 1
    assert second is not first
    fresh = cantools.database.load_file(path)
    assert dbc_summary(second) == dbc_summary(fresh)
    assert [n.name for n in second.nodes] == [n.name for n in fresh.nodes]
    assert [e for e in entries(cache) if e.startswith("dbc-")]


@pytest.mark.parametrize(("name", "node_id"), [("controller", 1), ("drive", 2)])
def test_od_hit_equals_fresh_parse(
    cache: Path, fresh_od_caches: None, monkeypatch: pytest.MonkeyPatch, name: str, node_id: int
) -> None:
    path = eds_path(name)
    fresh = od_mod.load_od(path, node_id)  # parsed, and stored
    assert any(e.startswith(f"od-{node_id}-") for e in entries(cache))
    od_mod._parser.cache_clear()
    od_mod._pickled_od.cache_clear()
    od_mod._parsed_od.cache_clear()

    def no_parse(*args: object, **kwargs: object) -> None:
        raise AssertionError("parsed although the cache holds the file")

    monkeypatch.setattr(od_mod.canopen, "import_od", no_parse)
    hit = od_mod.load_od(path, node_id)
    assert variables(hit) == variables(fresh)


def test_eds_names_and_limits_come_back_equal(cache: Path) -> None:
    path = eds_path("drive")
    parse = Counted(lambda: od_mod._object_names.__wrapped__(od_mod._file_key(path)))
    first = cached(path, "names-test", parse)
    assert cached(path, "names-test", parse) == first
    assert parse.calls == 1


@pytest.mark.parametrize("damage", ["truncate", "flip", "garbage", "empty"])
def test_corrupt_entry_falls_back_and_is_replaced(cache: Path, damage: str) -> None:
    path = str(dbc_path("truth"))
    parse = Counted(lambda: {"parsed": Path(path).read_text(encoding="utf-8")})
    expected = cached(path, "corrupt", parse)
    (entry,) = cache.iterdir()
    data = entry.read_bytes()
    damaged = {
        "truncate": data[: len(data) // 2],
        "flip": data[:-5] + bytes([data[-5] ^ 0xFF]) + data[-4:],
        "garbage": b"not a cache entry at all",
        "empty": b"",
    }[damage]
    entry.write_bytes(damaged)
    assert cached(path, "corrupt", parse) == expected
    assert parse.calls == 2
    assert entry.read_bytes() == data  # replaced by the fresh parse
    assert cached(path, "corrupt", parse) == expected
    assert parse.calls == 2


def test_an_entry_that_does_not_unpickle_falls_back(cache: Path) -> None:
    path = str(dbc_path("truth"))
    parse = Counted(lambda: 42)
    cached(path, "unpickle", parse)
    (entry,) = cache.iterdir()
    payload = b"cno_such_module_hdhil\nThing\n."  # a valid pickle of a missing class
    entry.write_bytes(parsecache._MAGIC + hashlib.sha256(payload).digest() + payload)
    assert cached(path, "unpickle", parse) == 42
    assert parse.calls == 2
    assert pickle.loads(cached_pickle(path, "unpickle", parse)) == 42
    assert parse.calls == 2


def test_unusable_directory_still_parses(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv("HDHIL_CACHE_DIR", str(blocker / "cache"))
    parse = Counted(lambda: "parsed")
    assert cached(dbc_path("truth"), "blocked", parse) == "parsed"
    assert cached(dbc_path("truth"), "blocked", parse) == "parsed"
    assert parse.calls == 2


def test_shared_directory_is_not_used(cache: Path) -> None:
    cache.mkdir(mode=0o700)
    os.chmod(cache, 0o777)  # anyone could plant an entry: never unpickled from here
    parse = Counted(lambda: "parsed")
    cached(dbc_path("truth"), "shared", parse)
    cached(dbc_path("truth"), "shared", parse)
    assert parse.calls == 2
    assert entries(cache) == []


def test_unwritable_directory_still_parses(cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cache.mkdir(mode=0o700)

    def read_only(*args: object, **kwargs: object) -> None:
        raise PermissionError("read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    parse = Counted(lambda: "parsed")
    assert cached(dbc_path("truth"), "ro", parse) == "parsed"
    assert pickle.loads(cached_pickle(dbc_path("truth"), "ro", parse)) == "parsed"
    assert parse.calls == 2
    assert entries(cache) == []


def test_failed_write_leaves_no_temporary(cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def fail(*args: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    assert cached(dbc_path("truth"), "full", lambda: "parsed") == "parsed"
    assert entries(cache) == []


def test_no_temporary_after_writes(cache: Path) -> None:
    for kind in ("a", "b", "c"):
        cached(dbc_path("control"), kind, lambda: list(range(1000)))
    assert len(entries(cache)) == 3
    assert all(name.endswith(".pickle") and not name.startswith(".") for name in entries(cache))


def test_only_a_regular_file_is_replaced(cache: Path) -> None:
    path = dbc_path("truth")
    cached(path, "regular", lambda: "parsed")
    (entry,) = cache.iterdir()
    entry.unlink()
    target = cache.parent / "elsewhere"
    target.write_text("not ours")
    entry.symlink_to(target)
    parse = Counted(lambda: "parsed")
    assert cached(path, "regular", parse) == "parsed"
    assert parse.calls == 1  # the link is not read ...
    assert entry.is_symlink() and target.read_text() == "not ours"  # ... nor replaced
    assert entries(cache) == [entry.name]


def test_changed_file_is_a_new_key(cache: Path, tmp_path: Path) -> None:
    path = tmp_path / "copy.dbc"
    shutil.copyfile(dbc_path("control"), path)
    load = Counted(lambda: cantools.database.load_file(str(path)))
    before = cached(path, "dbc", load, ("cantools",))
    text = path.read_text(encoding="utf-8").replace("BO_ ", "BO_  ", 1)
    text = text.replace("SG_ ", "SG_  ", 1)
    path.write_text(text.replace('"rad"', '"deg"', 1), encoding="utf-8")
    after = cached(path, "dbc", load, ("cantools",))
    assert load.calls == 2
    assert len(entries(cache)) == 2
    assert dbc_summary(after) == dbc_summary(cantools.database.load_file(str(path)))
    assert dbc_summary(before) == dbc_summary(cantools.database.load_file(dbc_path("control")))


def test_a_changed_parser_is_a_new_key(cache: Path, tmp_path: Path) -> None:
    """The parser's own source is part of the key: an edited parser never reads the
    entries of the old one (the versions stay the same in a development checkout)."""
    data, parser = tmp_path / "data.txt", tmp_path / "parser.py"
    data.write_text("payload")
    parser.write_text("def parse(): return 1\n")
    assert cached(data, "k", lambda: "old", code=(parser,)) == "old"
    assert cached(data, "k", lambda: "unused", code=(parser,)) == "old"  # a hit
    parser.write_text("def parse(): return 2\n")
    assert cached(data, "k", lambda: "new", code=(parser,)) == "new"


def test_another_python_is_a_new_key(cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    parse = Counted(lambda: "parsed")
    cached(dbc_path("truth"), "py", parse)
    parsecache._versions.cache_clear()
    monkeypatch.setattr(sys, "version", sys.version + " (another build)")
    try:
        cached(dbc_path("truth"), "py", parse)
    finally:
        parsecache._versions.cache_clear()
    assert parse.calls == 2
    assert len(entries(cache)) == 2


def test_empty_variable_disables_the_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HDHIL_CACHE_DIR", "")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert parsecache.cache_dir() is None
    parse = Counted(lambda: "parsed")
    cached(dbc_path("truth"), "off", parse)
    cached(dbc_path("truth"), "off", parse)
    assert parse.calls == 2
    assert list(tmp_path.iterdir()) == []


def test_default_directories(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("HDHIL_CACHE_DIR")
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert parsecache.cache_dir() == tmp_path / "xdg" / "hdhil"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert parsecache.cache_dir() == tmp_path / ".cache" / "hdhil"


def test_the_suite_caches_outside_home() -> None:
    directory = parsecache.cache_dir()
    assert directory is not None
    assert not directory.is_relative_to(Path.home() / ".cache")
