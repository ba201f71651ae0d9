"""The documentation stays true to the code: the generated reference pages equal what
``tools/docs/reference.py`` writes now, and every relative link in README.md and
docs/ points at a file that exists."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "tools" / "docs" / "reference.py"


def _reference_module():
    spec = importlib.util.spec_from_file_location("hdhil_docs_reference", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_generated_reference_pages_are_current(tmp_path):
    reference = _reference_module()
    written = reference.write(tmp_path)
    assert {p.name for p in written} == set(reference.PAGES)
    stale = [
        p.name
        for p in written
        if not (reference.OUT_DIR / p.name).is_file()
        or (reference.OUT_DIR / p.name).read_text(encoding="utf-8") != p.read_text(encoding="utf-8")
    ]
    assert not stale, (
        f"docs/reference/{', '.join(stale)} out of date: run `{reference.REGENERATE}` "
        "and commit the result"
    )


_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
_CODE = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _documents() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _relative_links(path: Path) -> list[str]:
    text = _CODE.sub("", _FENCE.sub("", path.read_text(encoding="utf-8")))
    links = []
    for target in _LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # another site, mail, or an anchor in the same page
        links.append(target.split("#", 1)[0])
    return links


@pytest.mark.parametrize("document", _documents(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_point_at_existing_files(document):
    missing = [t for t in _relative_links(document) if not (document.parent / t).exists()]
    assert not missing, f"{document.relative_to(ROOT)}: links to missing files {missing}"


def test_the_readme_and_the_docs_have_links_to_check():
    assert _relative_links(ROOT / "README.md")
    assert len(_documents()) > 4
