"""Collection of the docstring examples (``--doctest-modules`` over ``escort_rl``): a module whose
import needs an optional extra that is not installed (``ale_py`` for Atari, ``ray``, ``minatar``) is
left out, decided when the tests start from the module's own top-level imports, so a machine with
only the core dependencies still collects every other module."""

from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

OPTIONAL_EXTRAS = ("ale_py", "ray", "minatar")


def top_level_imports(path: Path) -> set[str]:
    """The top-level package of every module-level ``import`` in the file at ``path``."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module.split(".")[0])
    return names


def modules_needing_missing_extras(root: Path) -> list[str]:
    """Paths (relative to this folder) of the modules under ``root`` that import a missing extra."""
    missing = {e for e in OPTIONAL_EXTRAS if importlib.util.find_spec(e) is None}
    if not missing:
        return []
    here = Path(__file__).parent
    return sorted(str(p.relative_to(here)) for p in root.rglob("*.py") if top_level_imports(p) & missing)


collect_ignore = modules_needing_missing_extras(Path(__file__).parent / "escort_rl")
