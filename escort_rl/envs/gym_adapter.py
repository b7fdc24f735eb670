"""Gymnasium adapters: a single (unbatched) POMDP model as a ``gymnasium.Env``."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

from escort_rl.models.protocol import check_model, is_continuous, null_action


class POMDPGymEnv(gym.Env):
    """One environment of a POMDP model with the gymnasium API.

    Observations are ``float32`` arrays ``[obs_dim]``; actions are ``Discrete(n_actions)``, or
    ``Box(action_low, action_high, (action_dim,))`` for a model with continuous actions.
    ``info["true_state"]`` holds the hidden state (for evaluation). Randomness comes from a torch
    generator seeded from ``self.np_random`` at each ``reset(seed=...)``.
    """

    metadata = {"render_modes": []}

    def __init__(self, model) -> None:
        check_model(model, densities=False)  # a simulator
        self.model = model
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(model.obs_dim,), dtype=np.float32)
        self.action_space = action_space(model)
        self._generator = torch.Generator()
        self._state: torch.Tensor | None = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._generator.manual_seed(int(self.np_random.integers(0, 2**62)))
        s0 = self.model.initial_state((), self._generator)
        self._state = s0
        obs = self.model.observe(s0, null_action(self.model), self._generator)
        return obs.numpy().astype(np.float32), {"true_state": s0.numpy().copy()}

    def step(self, action):
        if self._state is None:
            raise RuntimeError("step() called before reset()")
        if not self.action_space.contains(np.asarray(action, dtype=self.action_space.dtype)
                                          if is_continuous(self.model) else action):
            raise ValueError(f"action: expected an element of {self.action_space}, got {action!r}")
        a = model_action(self.model, action)
        s_next = self.model.transition(self._state, a, self._generator)
        obs = self.model.observe(s_next, a, self._generator)
        reward = float(self.model.reward(self._state, a, s_next))
        terminated = bool(self.model.is_terminal(s_next))
        self._state = s_next
        return obs.numpy().astype(np.float32), reward, terminated, False, {"true_state": s_next.numpy().copy()}


def action_space(model) -> gym.spaces.Space:
    """The gymnasium action space of ``model``: ``Discrete(n_actions)``, or for continuous actions
    ``Box(action_low, action_high, (action_dim,), float32)``."""
    if is_continuous(model):
        return gym.spaces.Box(model.action_low.cpu().numpy().astype(np.float32),
                              model.action_high.cpu().numpy().astype(np.float32), dtype=np.float32)
    return gym.spaces.Discrete(model.n_actions)


def model_action(model, action, batch: tuple[int, ...] = (), device=None) -> torch.Tensor:
    """A gymnasium action as the model takes it: int64 ``[*batch]``, or float32 ``[*batch, action_dim]``
    for continuous actions."""
    if is_continuous(model):
        return torch.as_tensor(np.asarray(action, dtype=np.float32), device=device).reshape(*batch, model.action_dim)
    return torch.as_tensor(np.asarray(action), dtype=torch.long, device=device).reshape(batch)


def make_domain_gym(domain: str, **model_kwargs) -> POMDPGymEnv:
    """Entry point of the registered ids: the domain's model, its parameters the defaults of its
    ``Params`` (the paper's domain) but those in ``model_kwargs``."""
    from escort_rl.models import GYM_DOMAINS

    return POMDPGymEnv(GYM_DOMAINS[domain](**model_kwargs))
