"""A gymnasium wrapper whose observation is the particle belief of a filter.

Stable-Baselines3 (``MultiInputPolicy``), CleanRL and other gymnasium users can then train policies
on beliefs instead of raw observations, with any :class:`escort_rl.belief.BeliefFilter`.

Example::

    import gymnasium as gym
    import torch

    import escort_rl.envs  # registers the gymnasium ids
    from escort_rl.belief import SIRFilter
    from escort_rl.envs import BeliefObservation

    env = BeliefObservation(gym.make("escort_rl/LightDark10D-v0"), SIRFilter(), num_particles=64)
    obs, info = env.reset(seed=0)
    obs["particles"].shape    # (64, 10), float32
    obs["log_weights"].shape  # (64,), float32
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    x = torch.as_tensor(obs["particles"])  # ready for a policy network
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch

from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.envs.gym_adapter import action_space, model_action
from escort_rl.models.protocol import check_model, is_continuous

# mixed into the reset seed so that the belief's random stream differs from the inner env's
_BELIEF_STREAM = 0xBE11EF


class BeliefObservation(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Replace a POMDP env's observation by the particle belief that ``filter`` maintains.

    Args:
        env: a gymnasium env with a ``Discrete(n_actions)`` action space (for a model with continuous
            actions, ``Box(action_low, action_high, (action_dim,))``) and ``[obs_dim]``
            observations, e.g. ``gym.make("escort_rl/LightDark10D-v0")``.
        filter: a belief filter (``init`` / ``update``), e.g. ``SIRFilter()`` or
            ``ESCORTFilter(num_steps=5)``.
        num_particles: particles per belief, ``N``.
        model: the POMDP model the filter uses; by default the wrapped env's ``model`` attribute
            (``env.unwrapped.model`` for the package's registered ids).
        seed: the reset seed used by the first ``reset()`` that is given none (so a wrapper built
            with a seed is reproducible without passing one to ``reset``).

    Observations are dicts ``{"particles": float32 [N, d], "log_weights": float32 [N]}``
    (``logsumexp(log_weights) == 0``). Rewards, ``terminated``, ``truncated`` and the info dict are
    the wrapped env's. The filter's randomness comes from a private ``torch.Generator`` seeded at
    every ``reset``: the same reset seed gives the same belief trajectory for the same actions.
    """

    def __init__(self, env: gym.Env, filter, num_particles: int, model=None, seed: int | None = None) -> None:
        if not isinstance(env, gym.Env):
            raise ValueError(f"env: expected a gymnasium.Env, got {type(env).__name__}")
        # recorded so that ``env.spec.make()`` rebuilds the wrapper (filters and models are read-only)
        gym.utils.RecordConstructorArgs.__init__(
            self, filter=filter, num_particles=num_particles, model=model, seed=seed, _disable_deepcopy=True
        )
        gym.Wrapper.__init__(self, env)
        if not (callable(getattr(filter, "init", None)) and callable(getattr(filter, "update", None))):
            raise ValueError(f"filter: expected a belief filter with init() and update(), got {type(filter).__name__}")
        if isinstance(num_particles, bool) or not isinstance(num_particles, (int, np.integer)) or num_particles < 1:
            raise ValueError(f"num_particles: expected a positive int, got {num_particles!r}")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
            raise ValueError(f"seed: expected None or a non-negative int, got {seed!r}")
        model = self._find_model(env) if model is None else model
        try:
            check_model(model)
        except TypeError as err:
            raise ValueError(f"model: not a POMDP model ({err})") from None
        space, expected = env.action_space, action_space(model)
        if type(space) is not type(expected):
            kind = "real vectors" if is_continuous(model) else "integers"
            raise ValueError(f"env: expected a {type(expected).__name__} action space (the model's actions are {kind}, "
                             f"as the filters take them), got {space}")
        if space != expected:
            what = f"its action box is {expected}" if is_continuous(model) else f"n_actions is {model.n_actions}"
            raise ValueError(f"model: {what} but env.action_space is {space}; pass the env's model")
        obs_shape = getattr(env.observation_space, "shape", None)
        if obs_shape is not None and tuple(obs_shape) != (model.obs_dim,):
            raise ValueError(
                f"model: obs_dim is {model.obs_dim} but env.observation_space has shape {tuple(obs_shape)}"
            )

        self.filter = filter
        self.model = model
        self.num_particles = int(num_particles)
        self._initial_seed = None if seed is None else int(seed)
        n, d = self.num_particles, model.state_dim
        self.observation_space = gym.spaces.Dict(
            {
                "particles": gym.spaces.Box(-np.inf, np.inf, shape=(n, d), dtype=np.float32),
                "log_weights": gym.spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float32),
            }
        )
        self._belief_rng: np.random.Generator | None = None
        self._generator = torch.Generator()
        self._belief: ParticleBelief | None = None  # batch shape (1,)

    @staticmethod
    def _find_model(env: gym.Env):
        for get in (lambda: env.get_wrapper_attr("model"), lambda: env.unwrapped.model):
            try:
                model = get()
            except AttributeError:
                continue
            if model is not None:
                return model
        raise ValueError(
            f"model: the wrapped env ({env.unwrapped}) has no 'model' attribute; pass model= explicitly"
        )

    @property
    def belief(self) -> ParticleBelief | None:
        """The current belief, particles ``[N, d]`` (None before the first reset)."""
        if self._belief is None:
            return None
        return ParticleBelief(self._belief.particles[0], self._belief.log_weights[0])

    def _observation(self) -> dict[str, np.ndarray]:
        b = self._belief
        return {
            "particles": np.array(b.particles[0].detach().cpu().numpy(), dtype=np.float32, copy=True),
            "log_weights": np.array(b.log_weights[0].detach().cpu().numpy(), dtype=np.float32, copy=True),
        }

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is None and self._belief_rng is None:
            seed = self._initial_seed
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None:
            self._belief_rng = np.random.default_rng([int(seed), _BELIEF_STREAM])
        elif self._belief_rng is None:
            # unseeded first reset: derive the stream from the inner env's (randomly seeded) rng
            self._belief_rng = np.random.default_rng(int(self.env.np_random.integers(0, 2**62)))
        self._generator.manual_seed(int(self._belief_rng.integers(0, 2**62)))
        self._belief = self.filter.init(self.model, (1,), self.num_particles, self._generator)
        return self._observation(), info

    def step(self, action):
        if self._belief is None:
            raise RuntimeError("step() called before reset()")
        obs, reward, terminated, truncated, info = self.env.step(action)
        particles = self._belief.particles
        a = model_action(self.model, action, (1,), particles.device)
        o = torch.as_tensor(np.asarray(obs), dtype=particles.dtype, device=particles.device).reshape(1, -1)
        self._belief = self.filter.update(self.model, self._belief, a, o, self._generator)
        return self._observation(), reward, terminated, truncated, info
