"""The house rules: the repository passes ``ruff check`` (settings in ``pyproject.toml``: 120
columns, pycodestyle, pyflakes, import order; ruff comes with the ``dev`` extra), and the package's
modules and functions stay small."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import escort_rl

ROOT = Path(escort_rl.__file__).resolve().parent.parent


def test_ruff_check_is_clean():
    done = subprocess.run([sys.executable, "-m", "ruff", "check", str(ROOT)], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, f"ruff check failed:\n{done.stdout}{done.stderr}"


MAX_MODULE_LINES, MAX_FUNCTION_LINES = 600, 80


def test_modules_and_functions_stay_small():
    """No module of the package over 600 lines and no function over 80: a longer one is split by
    concept (the benchmarks into spec, cells, run, report and cli)."""
    import ast

    package = Path(escort_rl.__file__).parent
    long_modules, long_functions = [], []
    for path in sorted(package.rglob("*.py")):
        source = path.read_text()
        if len(source.splitlines()) > MAX_MODULE_LINES:
            long_modules.append(str(path.relative_to(package)))
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    long_functions.append(f"{path.relative_to(package)}:{node.name} ({length} lines)")
    assert not long_modules and not long_functions, (long_modules, long_functions)
