"""The result figures of the documentation are regenerated, not typed: every marked block
of README.md and docs/*.md equals what ``tools/docs/figures.py`` computes now, and its
pictures' data equals the data saved beside them.  The check itself is slow (it runs the
scenarios, calibrations, tuning and campaign the blocks describe); the mechanism is
tested on its own with generators of a test's own."""

from __future__ import annotations

import argparse
import importlib.util
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "tools" / "docs" / "figures.py"


@pytest.fixture(scope="module")
def figures():
    spec = importlib.util.spec_from_file_location("hdhil_docs_figures", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look the module up by name
    spec.loader.exec_module(module)
    yield module
    sys.modules.pop(spec.name, None)


@pytest.fixture
def registry(figures, monkeypatch):
    """The script with empty registries, restored afterwards."""
    monkeypatch.setattr(figures, "BLOCKS", {})
    monkeypatch.setattr(figures, "PICTURES", {})
    return figures


DOC = """# A page

<!-- generated: answer -->

old text

<!-- end generated -->

Hand-written text.

<!-- generated: nobody -->

kept as it is

<!-- end generated -->
"""


def test_check_lists_stale_and_unknown_blocks_and_writes_nothing(registry, tmp_path):
    page = tmp_path / "page.md"
    page.write_text(DOC, encoding="utf-8")
    registry.block("answer")(lambda: "| a |\n| --- |\n| 42 |")
    problems = registry.update(None, check=True, paths=[page], pictures=False, log=lambda _: None)
    assert problems == [
        f"{page}: block 'answer' is stale",
        f"{page}: block 'nobody' has no generator in {registry.REGENERATE}",
    ]
    assert page.read_text(encoding="utf-8") == DOC


def test_write_mode_rewrites_only_the_blocks_and_is_then_current(registry, tmp_path):
    page = tmp_path / "page.md"
    page.write_text(DOC, encoding="utf-8")
    registry.block("answer")(lambda: "The answer is 42.")
    registry.update(None, check=False, paths=[page], pictures=False, log=lambda _: None)
    text = page.read_text(encoding="utf-8")
    assert text == DOC.replace("old text", "The answer is 42.")
    # the block is current now; only the marker without a generator is left
    problems = registry.update(None, check=True, paths=[page], pictures=False, log=lambda _: None)
    assert problems == [f"{page}: block 'nobody' has no generator in {registry.REGENERATE}"]


def test_a_picture_is_checked_by_the_data_it_is_drawn_from(registry, tmp_path):
    png = tmp_path / "pic.png"
    data = ["x,y\n1,2\n"]

    def draw(target: Path) -> None:
        target.write_bytes(b"drawn from " + data[0].encode())

    @registry.picture("pic")
    def _pic():
        return registry.Picture(str(png), data[0], draw)

    def check() -> list[str]:
        registry.PICTURES["pic"].cache_clear()
        return registry.update(None, check=True, paths=[], log=lambda _: None)

    assert check() == [f"{png}: picture 'pic' is stale"]  # neither drawn nor saved yet
    registry.update(None, check=False, paths=[], log=lambda _: None)
    assert png.read_bytes() == b"drawn from x,y\n1,2\n"
    assert png.with_suffix(".csv").read_text() == "x,y\n1,2\n"
    assert check() == []
    data[0] = "x,y\n1,3\n"  # the figure's numbers changed: the picture is stale
    assert check() == [f"{png}: picture 'pic' is stale"]


def test_every_marked_block_has_a_generator_and_every_generator_a_block(figures):
    """Cheap, in the fast tier: markers that pair up, a generator for each name, no
    generator left without a block (the slow check below compares the contents)."""
    used = set()
    for path in figures.documents():
        text = path.read_text(encoding="utf-8")
        names = [m["name"] for m in figures.BLOCK.finditer(text)]
        starts = re.findall(r"^<!-- generated:", text, re.M)
        ends = re.findall(r"^<!-- end generated -->$", text, re.M)
        assert len(starts) == len(names), f"{path}: a marker without its end"
        assert len(ends) == len(names), f"{path}: a stray end marker"
        used.update(names)
    assert used <= set(figures.BLOCKS), f"no generator for {sorted(used - set(figures.BLOCKS))}"
    assert set(figures.BLOCKS) <= used, f"no block for {sorted(set(figures.BLOCKS) - used)}"


def test_a_paragraph_keeps_numbers_with_their_units(figures):
    text = figures.para("word " * 15 + "gives 12.5 % and 0.026 Nm over 20 s", width=80)
    assert "12.5 %" in text and "0.026 Nm" in text and "20 s" in text
    assert max(len(line) for line in text.splitlines()) <= 80


def _walk(parser: argparse.ArgumentParser):
    yield parser.description or ""
    yield parser.epilog or ""
    for action in parser._actions:
        yield action.help or ""
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                yield choice.help or ""
            for sub in action.choices.values():
                yield from _walk(sub)


def test_help_texts_claim_no_results():
    """A result in ``--help`` cannot be regenerated and goes stale unnoticed: the help says
    what an option does and points to the documentation, whose figures are generated."""
    from hdhil.cli import build_parser

    claims = [
        text
        for text in _walk(build_parser(["--help"], load_all=True))
        if re.search(r"reproduc|\bgives\b[^.;]*\d\s*%", text, re.I)
    ]
    assert not claims


@pytest.mark.slow
@pytest.mark.subprocess  # the loss-robustness campaign runs on a process pool
def test_generated_figures_are_current(figures):
    problems = figures.update(None, check=True, log=lambda _: None)
    assert not problems, "\n".join(problems) + f"\nrun `{figures.REGENERATE}` and commit the result"
