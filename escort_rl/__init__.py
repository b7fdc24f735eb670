"""ESCORT-RL: particle belief tracking for POMDPs (SIR, SVGD, ESCORT) and policies trained on those
beliefs, for TorchRL users. Subpackages: ``models``, ``envs``, ``belief``, ``transforms``,
``modules``, ``trainers``, ``bench``."""

__version__ = "0.1.0"
