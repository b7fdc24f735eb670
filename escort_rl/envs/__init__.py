"""Environments: a batched TorchRL env over any model, gymnasium adapters, flickering Atari and MinAtar.

Importing the package registers the gymnasium ids (:mod:`escort_rl.envs.registration`); the
environments themselves are imported on first use, so that registering loads no torch.
"""

from __future__ import annotations

import importlib

from escort_rl.envs.registration import register_gymnasium_envs

register_gymnasium_envs()

_LAZY = {"BeliefObservation": "belief_observation", "POMDPEnv": "pomdp_env", "check_action": "pomdp_env",
         "register_atari_envs": "atari", "register_minatar_envs": "minatar",
         "make_flickering_torchrl_env": "flickering"}

__all__ = [*_LAZY, "register_gymnasium_envs"]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f"escort_rl.envs.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'escort_rl.envs' has no attribute '{name}'")
