"""The package as a user installs it: its version in one place, the gymnasium ids registered by
``import escort_rl``, and the files a user expects beside the code."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import yaml

import escort_rl

ROOT = Path(escort_rl.__file__).resolve().parent.parent


def _fresh(code: str) -> str:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          cwd=ROOT).stdout.strip()


def test_import_escort_rl_registers_the_gymnasium_ids_without_torch():
    out = _fresh("import sys, gymnasium as gym, escort_rl; "
                 "env = gym.make('escort_rl/LightDark10D-v0'); "
                 "print(env.spec.max_episode_steps, 'escort_rl/FlickeringPong-v0' in gym.registry)")
    assert out == "500 True"
    loaded = _fresh("import sys, escort_rl; print(sorted(m for m in ('torch', 'hydra') if m in sys.modules))")
    assert loaded == "[]"


def test_the_version_is_stated_once():
    import importlib.metadata

    assert importlib.metadata.version("escort-rl") == escort_rl.__version__
    assert yaml.safe_load((ROOT / "CITATION.cff").read_text())["version"] == escort_rl.__version__
    assert f"## [{escort_rl.__version__}]" in (ROOT / "CHANGELOG.md").read_text()
    out = subprocess.run([sys.executable, "-m", "escort_rl.cli", "--version"], capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout.strip()
    assert out == f"escort-rl {escort_rl.__version__}"


def test_license_citation_and_type_marker_ship():
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert citation["preferred-citation"]["title"].startswith("ESCORT: Efficient Stein-variational")
    assert len(citation["preferred-citation"]["authors"]) == 5
    assert (ROOT / "escort_rl" / "py.typed").is_file()
