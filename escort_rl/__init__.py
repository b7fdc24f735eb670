"""ESCORT-RL: particle belief tracking for POMDPs (SIR, SVGD, ESCORT) and policies trained on those
beliefs, for TorchRL users. Subpackages: ``models``, ``envs``, ``belief``, ``transforms``,
``modules``, ``trainers``, ``bench``."""

__version__ = "0.2.0"

import escort_rl.envs  # noqa: E402,F401  registers the gymnasium ids, as ``import ale_py`` does


def __getattr__(name: str):
    """``escort_rl.load_policy`` (:func:`escort_rl.trainers.loading.load_policy`), imported on first
    use so that ``import escort_rl`` stays light."""
    if name == "load_policy":
        from escort_rl.trainers.loading import load_policy

        return load_policy
    raise AttributeError(f"module 'escort_rl' has no attribute '{name}'")
