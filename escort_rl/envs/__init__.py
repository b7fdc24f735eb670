"""Environments: a batched TorchRL env over any model, gymnasium adapters, and flickering Atari."""

from escort_rl.envs.atari import register_atari_envs
from escort_rl.envs.belief_observation import BeliefObservation
from escort_rl.envs.gym_adapter import register_gymnasium_envs
from escort_rl.envs.pomdp_env import POMDPEnv, check_action

register_gymnasium_envs()
register_atari_envs()  # ale-py is imported only when one of these envs is made

__all__ = ["BeliefObservation", "POMDPEnv", "check_action", "register_atari_envs", "register_gymnasium_envs"]
