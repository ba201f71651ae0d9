"""Markdown tables for the text reports (``hdhil bench``): columns padded to their widest
cell, numbers right-aligned, the rule row marking the alignment as Markdown does, so a
report reads aligned in a terminal and renders as a table when pasted into docs."""

from __future__ import annotations

from collections.abc import Sequence


def markdown_table(
    header: Sequence[str], rows: Sequence[Sequence[str]], right: Sequence[bool]
) -> list[str]:
    """The lines of a table; ``right[i]``: column i is right-aligned."""
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]

    def line(cells: Sequence[str]) -> str:
        return "| " + " | ".join(
            c.rjust(w) if r else c.ljust(w) for c, w, r in zip(cells, widths, right, strict=True)
        ) + " |"  # fmt: skip

    rule = "| " + " | ".join(("-" * (w - 1) + ":") if r else "-" * w
                              for w, r in zip(widths, right, strict=True)) + " |"  # fmt: skip
    return [line(header), rule, *(line(r) for r in rows)]
