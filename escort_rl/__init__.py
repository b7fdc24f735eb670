"""ESCORT-RL: particle belief tracking for POMDPs (SIR, SVGD, ESCORT) and policies trained on those
beliefs, for TorchRL users. Subpackages: ``models``, ``envs``, ``belief``, ``transforms``,
``modules``, ``trainers``, ``bench``."""

__version__ = "0.2.0"

import escort_rl.envs  # noqa: E402,F401  registers the gymnasium ids, as ``import ale_py`` does
