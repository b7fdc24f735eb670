"""Configuration: typed schemas (:mod:`.schema`), composing the shipped Hydra configs
(:mod:`.composition`), and :class:`ConfigError`. Resuming a run (which checkpoint, which config,
which run directory) is :mod:`escort_rl.trainers.resume`'s.

The names below are imported on first use, so that a low layer may import
``escort_rl.config.errors`` without loading Hydra.
"""

from __future__ import annotations

import importlib

from escort_rl.config.errors import ConfigError

_LAZY = {
    "compose": "composition", "check_composed": "composition", "hydra_error_line": "composition",
    "is_group_override": "composition",
    "config_dir": "files", "option_names": "files",
}

__all__ = ["ConfigError", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f"escort_rl.config.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'escort_rl.config' has no attribute '{name}'")
