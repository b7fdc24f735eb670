"""Compare two benchmark runs cell by cell (``escort-rl bench compare A B``).

Each run's ``cells/`` folder (:class:`escort_rl.bench.core.runner.CellStore`) holds one JSON file per cell,
named by the cell's key and the hash of its spec, so the same cell has the same relative path in
both runs. Two cells agree when every value outside ``timing`` (the wall-clock figures) is equal:
numbers within ``tolerance`` (0: bit for bit; NaN equals NaN), everything else exactly. Used to
check that the backends give the same numbers (CI runs protocol (a) on the process backend and on
Ray and compares them).

Examples:
    >>> differences({"a": [1.0, float("nan")], "timing": {"s": 1}}, {"a": [1.0, float("nan")], "timing": {"s": 2}})
    []
    >>> differences({"a": [1.0, 2.0]}, {"a": [1.0, 2.5]})
    ['a[1]: 2.0 != 2.5']
"""

from __future__ import annotations

import json
import math
from pathlib import Path

IGNORED = ("timing",)


def differences(a, b, tolerance: float = 0.0, where: str = "") -> list[str]:
    """The paths (``key[index].key``) at which ``a`` and ``b`` differ, outside :data:`IGNORED` keys."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k in IGNORED:
                continue
            path = f"{where}.{k}" if where else str(k)
            if k not in a or k not in b:
                out.append(f"{path}: only in {'the first' if k in a else 'the second'}")
            else:
                out += differences(a[k], b[k], tolerance, path)
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: lengths {len(a)} != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in differences(x, y, tolerance, f"{where}[{i}]")]
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool) and not isinstance(b, bool):
        if (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tolerance or a == b:
            return []
        return [f"{where}: {a!r} != {b!r}"]
    return [] if a == b else [f"{where}: {a!r} != {b!r}"]


def is_cell(path: Path) -> bool:
    """Whether ``path`` is a saved cell: a JSON object with ``spec`` and ``result`` (:class:`CellStore`)."""
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(saved, dict) and "spec" in saved and "result" in saved


def cell_files(run: Path) -> dict[str, Path]:
    """Relative path -> file of every saved cell of ``run`` (its ``cells/`` folder, or ``run`` itself);
    other JSON files (a report such as ``closed_loop.json``, a training run's files) are left out."""
    root = run / "cells" if (run / "cells").is_dir() else run
    return {str(p.relative_to(root)): p for p in sorted(root.rglob("*.json")) if is_cell(p)}


def compare_runs(a: Path, b: Path, tolerance: float = 0.0, common_only: bool = False) -> tuple[int, list[str]]:
    """The number of cells compared and the problems found (empty when the runs agree).

    Raises ``ValueError`` naming the argument when a folder holds no cells. Unless ``common_only``,
    a cell saved in one run only is a problem (with it, such cells are skipped: the equal-time grid
    depends on timings, so its ``N'`` may differ between runs)."""
    files = {}
    for name, run in (("A", Path(a)), ("B", Path(b))):
        files[name] = cell_files(run)
        if not files[name]:
            raise ValueError(f"{name}: '{run}' holds no benchmark cells (give a benchmark's --output or its cells/ "
                             "folder; bench domains --protocol b saves none)")
    problems = []
    if not common_only:
        problems += [f"{k}: only in {side}" for side, other in (("A", "B"), ("B", "A"))
                     for k in sorted(set(files[side]) - set(files[other]))]
    common = sorted(set(files["A"]) & set(files["B"]))
    if not common:
        problems.append("no cell is in both runs")
    for k in common:
        ra = json.loads(files["A"][k].read_text())["result"]
        rb = json.loads(files["B"][k].read_text())["result"]
        problems += [f"{k}: {d}" for d in differences(ra, rb, tolerance)]
    return len(common), problems


def register(subparsers) -> None:
    """Add ``bench compare`` to the ``bench`` subparsers."""
    cmp = subparsers.add_parser("compare", help="check that two benchmark runs agree cell by cell",
                                description="Compares the saved cells of two runs of the same benchmark (e.g. "
                                "--backend process and --backend ray) value by value, wall-clock figures left "
                                "out; exits with status 1 on any difference.")
    cmp.add_argument("first", help="a benchmark's --output folder (or its cells/ folder)")
    cmp.add_argument("second", help="the other run's folder")
    cmp.add_argument("--tolerance", type=float, default=0.0, help="largest absolute difference allowed")
    cmp.add_argument("--common-only", action="store_true",
                     help="compare the cells both runs hold, and allow cells in one run only (equal-time grids)")
    cmp.set_defaults(handler=main)


def main(args) -> int:
    if not (math.isfinite(args.tolerance) and args.tolerance >= 0):
        raise ValueError(f"--tolerance: must be a finite number >= 0, got {args.tolerance}")
    count, problems = compare_runs(Path(args.first), Path(args.second), args.tolerance, args.common_only)
    for p in problems[:50]:
        print(p)
    if problems:
        print(f"{len(problems)} differences in {count} common cells")
        return 1
    print(f"{count} cells agree")
    return 0
