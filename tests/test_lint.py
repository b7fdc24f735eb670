"""The repository passes ``ruff check`` (settings in ``pyproject.toml``: 120 columns, pycodestyle,
pyflakes, import order). ruff comes with the ``dev`` extra."""

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
