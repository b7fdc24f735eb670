"""Environments: a batched TorchRL env over any model, and gymnasium adapters."""

from escort_rl.envs.belief_observation import BeliefObservation
from escort_rl.envs.gym_adapter import register_gymnasium_envs
from escort_rl.envs.pomdp_env import POMDPEnv, check_action

register_gymnasium_envs()

__all__ = ["BeliefObservation", "POMDPEnv", "check_action", "register_gymnasium_envs"]
