"""Markdown tables with one row per method and one column per domain (or target)."""

from __future__ import annotations


def method_table(columns: list[str], methods: list[str], cells: dict, label=str) -> list[str]:
    """The lines of a Markdown table: a header ``| method | <columns> |``, then one row per method
    that has at least one cell.

    ``cells``: ``(column, method) -> str``; a missing cell is printed ``—``. ``label(method)``: the
    row's name.

    Examples:
        >>> method_table(["a", "b"], ["sir"], {("a", "sir"): "1.0"})
        ['| method | a | b |', '| --- | --- | --- |', '| sir | 1.0 | — |']
    """
    lines = ["| method | " + " | ".join(columns) + " |", "| --- | " + " | ".join("---" for _ in columns) + " |"]
    for m in methods:
        if any((c, m) in cells for c in columns):
            lines.append(f"| {label(m)} | " + " | ".join(cells.get((c, m), "—") for c in columns) + " |")
    return lines
