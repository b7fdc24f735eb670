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


def section(heading: str, *blocks) -> list[str]:
    """The lines of a Markdown section: ``heading``, then each block (a paragraph, or a list of lines
    such as a table), each followed by a blank line.

    Examples:
        >>> section("## Rows", "Some text.", ["| a |", "| b |"])
        ['## Rows', '', 'Some text.', '', '| a |', '| b |', '']
    """
    lines = [heading, ""]
    for block in blocks:
        lines += [block, ""] if isinstance(block, str) else [*block, ""]
    return lines


def key_values(mapping: dict) -> str:
    """``"k=v, k=v"``: settings as the reports print them.

    Examples:
        >>> key_values({"num_steps": 10, "compile": "true"})
        'num_steps=10, compile=true'
    """
    return ", ".join(f"{k}={v}" for k, v in mapping.items())


def changed_settings(per_method: dict) -> list[str]:
    """A sentence (and a blank line) naming the filter settings changed from the configs, per method
    (``method -> {key: value}``); no lines when nothing changed.

    Examples:
        >>> changed_settings({"escort": {"num_steps": "10"}, "sir": {}})
        ['Filter settings changed from the configs: escort: num_steps=10.', '']
        >>> changed_settings({"sir": {}})
        []
    """
    changed = [f"{m}: {key_values(kv)}" for m, kv in per_method.items() if kv]
    return [f"Filter settings changed from the configs: {'; '.join(changed)}.", ""] if changed else []
