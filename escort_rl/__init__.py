"""ESCORT-RL: particle belief tracking for POMDPs (SIR, SVGD, ESCORT) and policies trained on those
beliefs, for TorchRL users. Subpackages: ``models``, ``envs``, ``belief``, ``transforms``,
``modules``, ``trainers``, ``bench``."""

__version__ = "0.2.0"

import escort_rl.envs  # noqa: E402,F401  registers the gymnasium ids, as ``import ale_py`` does

_ENTRY_POINTS = {"train": "escort_rl.trainers.entry", "evaluate": "escort_rl.trainers.evaluate",
                 "load_policy": "escort_rl.trainers.loading", "make_filter": "escort_rl.trainers.builders"}


def __getattr__(name: str):
    """``escort_rl.train`` (:func:`escort_rl.trainers.entry.train`), ``escort_rl.evaluate``
    (:func:`escort_rl.trainers.evaluate.evaluate`), ``escort_rl.load_policy``
    (:func:`escort_rl.trainers.loading.load_policy`) and ``escort_rl.make_filter``
    (:func:`escort_rl.trainers.builders.make_filter`: a filter by its config name), imported on first
    use so that ``import escort_rl`` stays light."""
    if name in _ENTRY_POINTS:
        import importlib

        return getattr(importlib.import_module(_ENTRY_POINTS[name]), name)
    raise AttributeError(f"module 'escort_rl' has no attribute '{name}'")
