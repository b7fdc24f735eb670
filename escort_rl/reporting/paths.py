"""Where reports go: portable paths in reports, and one writer for a benchmark's JSON and Markdown."""

from __future__ import annotations

import json
from pathlib import Path

from escort_rl.reporting.metadata import with_metadata


def safe_name(label: str) -> str:
    """``label`` as a file name: letters, digits, ``-``, ``_`` and ``.``; others become ``_``.

    Example:
        >>> safe_name("sir N=1000, look first")
        'sir_N_1000__look_first'
    """
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in label)


def display_path(path: Path) -> str:
    """The path relative to the working directory when it lies below it (reports stay portable)."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def write_results(out: Path, stem: str, result, markdown: str, seconds: float | None = None) -> None:
    """Write a benchmark's ``<stem>.json`` (with the run's commit, versions and hardware under
    ``"run"``: :func:`~escort_rl.reporting.metadata.with_metadata`) and ``<stem>.md`` into ``out``
    (created), print the Markdown
    and where the results are (with the run's seconds, if given)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(with_metadata(result), indent=1))
    (out / f"{stem}.md").write_text(markdown)
    print(markdown)
    print(f"results: {out.resolve()}" + (f" ({seconds:.1f} s)" if seconds is not None else ""))
