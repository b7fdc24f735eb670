"""Where the shipped Hydra configs live, and the options of a group."""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def config_dir() -> Path:
    """The folder holding ``config.yaml`` and the groups ``env/``, ``filter/``, ``trainer/``."""
    return Path(str(resources.files("escort_rl.configs")))


def option_names(group: str) -> list[str]:
    """The options of a Hydra group: the yaml files in ``configs/<group>/``."""
    return sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))
