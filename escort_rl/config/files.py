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


def check_filter_name(value: str | None) -> str | None:
    """``None`` or the name of a ``configs/filter/`` option (a field ``check``)."""
    if value is None:
        return None
    names = option_names("filter")
    return None if value in names else f"no filter config '{value}'; choose one of {', '.join(names)}"
