"""POPGym's Stateless Pendulum (``PositionOnlyPendulum``) and its noisy variant, as a known torch model.

POPGym (Morad et al., ICLR 2023, the ``popgym`` package) hides the angular velocity of gymnasium's
Pendulum: the agent sees ``[cos θ, sin θ]`` only. This model reproduces it step for step
(``tests/models/test_popgym_models.py`` checks it against ``popgym``):

- State ``s = [θ, θ̇]`` (``state_dim = 2``), ``θ`` not wrapped (gymnasium does not wrap it either);
  the action is a torque ``u ∈ [−2, 2]`` (``action_dim = 1``, float ``[*S, 1]``; continuous actions:
  ``action_low = [−2]``, ``action_high = [2]``, no ``n_actions``).
- Dynamics: gymnasium's Pendulum (g = 10, m = 1, l = 1, dt = 0.05, max speed 8), the torque clipped
  to ``[−2, 2]`` first:

      θ̇' = clip(θ̇ + (3g/(2l) sin θ + 3/(m l²) u)·dt, −8, 8),    θ' = θ + θ̇'·dt

- No termination. Start: ``θ ~ U(−π, π)``, ``θ̇ ~ U(−1, 1)``.
- Observation ``o = [cos θ', sin θ']``; the noisy tasks add ``N(0, σ²)`` per coordinate and clip to
  ``[−1, 1]``; the stateless tasks add nothing.
- Reward: POPGym's ``reward_transform`` of gymnasium's ``r = −(norm(θ)² + 0.1 θ̇² + 0.001 u²)`` (on the
  state *before* the step, ``norm`` wrapping the angle into ``[−π, π)``, ``u`` clipped):
  ``(r + c)/(c·L)`` with ``c = 16.2736044/2`` (half of the largest cost) and ``L =
  max_episode_length``, so each step pays in ``[−1/L, 1/L]`` and an episode's return lies in ``[−1, 1]``.
- The time limit is not part of the state: ``max_episode_length`` (POPGym's: 200, 150, 100 for Easy,
  Medium, Hard; 200 for every noisy task) is for the env's truncation (``POMDPEnv(max_steps=...)``).

**The densities a filter needs, which POPGym does not have** (as for
:mod:`escort_rl.models.popgym_cartpole`):

- ``process_noise``: a filter-side Gaussian process noise, independent per coordinate, with std
  ``process_noise × TYPICAL_STEP``. ``TYPICAL_STEP = (0.2, 0.5)`` is the RMS one-step change of
  ``θ`` and ``θ̇`` under a random policy (measured on 40 000 POPGym steps: 0.177, 0.526), so the
  default 0.05 is 5% of a typical step (std 0.01 and 0.025): enough spread to keep resampled
  particles apart, small enough that a prediction stays within a few percent of the deterministic
  one. It is added after the speed clip, so a particle may exceed ``|θ̇| = 8`` by that much. With
  ``process_noise = 0``, :meth:`transition` is POPGym's step exactly and
  :meth:`transition_log_prob` raises.
- ``obs_noise_floor``: the density's std is ``max(obs_noise, obs_noise_floor)``; the default 0.01 is
  a tenth of the smallest noise POPGym adds (0.1), a twentieth of a typical step of ``θ``.
  :meth:`observe` draws with ``obs_noise`` itself (none on the stateless tasks).
- The observation density is the censored Gaussian of :mod:`escort_rl.models.clipped_gaussian`.

Example:
    >>> import torch
    >>> m = POPGymPendulum.from_name("PositionOnlyPendulumHard")
    >>> m.max_episode_length, m.action_dim, m.action_high.tolist()
    (100, 1, [2.0])
    >>> m.transition_mean(torch.tensor([0.0, 0.0]), torch.tensor([2.0]))  # full torque from rest
    tensor([0.0150, 0.3000])
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from escort_rl.config.params import HasParams, build_params
from escort_rl.models.clipped_gaussian import ClippedGaussianObservation
from escort_rl.models.gaussian import FilterNoiseTransition
from escort_rl.models.popgym_task import POPGymParams, POPGymTask

GRAVITY, MASS, LENGTH, DT, MAX_SPEED, MAX_TORQUE = 10.0, 1.0, 1.0, 0.05, 8.0, 2.0
"""gymnasium Pendulum's constants (``g = 10`` is its default)."""
REWARD_LOW = -16.2736044
"""POPGym's lowest reward, ``−(π² + 0.1·8² + 0.001·2²)``; its ``reward_transform`` maps
``[REWARD_LOW, 0]`` onto ``[−1, 1]`` and divides by the episode length."""
START_HIGH = (math.pi, 1.0)
TYPICAL_STEP = (0.2, 0.5)
"""The RMS one-step change of ``[θ, θ̇]`` under a random policy; the unit of ``process_noise``."""

PENDULUM_TASKS = {
    "PositionOnlyPendulumEasy": {"max_episode_length": 200, "obs_noise": 0.0},
    "PositionOnlyPendulumMedium": {"max_episode_length": 150, "obs_noise": 0.0},
    "PositionOnlyPendulumHard": {"max_episode_length": 100, "obs_noise": 0.0},
    "NoisyPositionOnlyPendulumEasy": {"max_episode_length": 200, "obs_noise": 0.1},
    "NoisyPositionOnlyPendulumMedium": {"max_episode_length": 200, "obs_noise": 0.2},
    "NoisyPositionOnlyPendulumHard": {"max_episode_length": 200, "obs_noise": 0.3},
}
"""POPGym's Pendulum tasks -> their parameters (popgym 1.0: the noisy tasks keep the default length)."""


def angle_normalize(theta: Tensor) -> Tensor:
    """gymnasium's ``((θ + π) mod 2π) − π``, into ``[−π, π)`` (``torch.remainder`` takes the divisor's
    sign, as Python's ``%``)."""
    return torch.remainder(theta + math.pi, 2 * math.pi) - math.pi


@dataclass(frozen=True)
class POPGymPendulumParams(POPGymParams):
    """:class:`POPGymPendulum`'s parameters: :class:`~escort_rl.models.popgym_task.POPGymParams`, with
    episodes of 200, 150, 100 steps for Easy, Medium, Hard."""


class POPGymPendulum(POPGymTask, HasParams, FilterNoiseTransition, ClippedGaussianObservation):
    """POPGym's (Noisy) PositionOnlyPendulum as a model with a continuous action; float32 tensors on
    ``device``.

    Takes :class:`POPGymPendulumParams` (or its fields as keyword arguments) and ``device``;
    :meth:`from_name` builds one of POPGym's six tasks by name.
    """

    Params = POPGymPendulumParams
    TASKS = PENDULUM_TASKS
    SYSTEM = "Pendulum"
    state_dim = 2
    obs_dim = 2
    action_dim = 1
    position_dims = (0,)
    velocity_dims = (1,)

    def __init__(self, params: POPGymPendulumParams | None = None, *, device: torch.device | str | None = None,
                 **kwargs) -> None:
        self.params = p = build_params(POPGymPendulumParams, params, kwargs, owner=type(self).__name__)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        f32 = dict(dtype=torch.float32, device=self.device)
        self.action_high = torch.tensor([MAX_TORQUE], **f32)
        self.action_low = -self.action_high
        self.obs_high = torch.ones(2, **f32)
        self.obs_low = -self.obs_high
        self.start_high = torch.tensor(START_HIGH, **f32)
        self.process_std = p.process_noise * torch.tensor(TYPICAL_STEP, **f32)
        self.observation_std = max(p.obs_noise, p.obs_noise_floor)

    # ------------------------------------------------------------------ dynamics
    def initial_state(self, shape: tuple[int, ...], generator: torch.Generator | None = None) -> Tensor:
        """``θ ~ U(−π, π)``, ``θ̇ ~ U(−1, 1)``, as gymnasium's reset. Returns ``[*shape, 2]``."""
        u = torch.rand(*shape, 2, generator=generator, device=self.device)
        return self.start_high * (2 * u - 1)

    def initial_belief(self, shape: tuple[int, ...], n: int, generator: torch.Generator | None = None) -> Tensor:
        """``n`` draws of the start distribution per batch element: ``[*shape, n, 2]``."""
        return self.initial_state((*shape, n), generator)

    def transition_mean(self, s: Tensor, a: Tensor) -> Tensor:
        """gymnasium's step (the module docstring). ``s`` ``[*S, 2]``, ``a`` ``[*S, 1]`` (clipped to
        ``[−2, 2]``) -> ``[*S, 2]``."""
        theta, theta_dot = s.unbind(-1)
        u = a[..., 0].to(s.dtype).clamp(-MAX_TORQUE, MAX_TORQUE)
        acc = 3 * GRAVITY / (2 * LENGTH) * torch.sin(theta) + 3.0 / (MASS * LENGTH**2) * u
        new_theta_dot = (theta_dot + acc * DT).clamp(-MAX_SPEED, MAX_SPEED)
        return torch.stack([theta + new_theta_dot * DT, new_theta_dot], dim=-1)

    def is_terminal(self, s: Tensor) -> Tensor:
        """Never: Pendulum only truncates. ``[*S, 2]`` -> ``[*S]`` bool (all false)."""
        return torch.zeros(s.shape[:-1], dtype=torch.bool, device=s.device)

    def reward(self, s: Tensor, a: Tensor, s_next: Tensor) -> Tensor:
        """POPGym's transformed reward of ``(s, u)``: ``(1 − cost/c)/L``, ``cost = norm(θ)² + 0.1 θ̇² +
        0.001 u²`` and ``c = −REWARD_LOW/2``. ``[*S]``, in ``[−1/L, 1/L]``."""
        theta, theta_dot = s[..., 0], s[..., 1]
        u = a[..., 0].to(s.dtype).clamp(-MAX_TORQUE, MAX_TORQUE)
        cost = angle_normalize(theta) ** 2 + 0.1 * theta_dot**2 + 0.001 * u**2
        half = -REWARD_LOW / 2
        return (half - cost) / half / self.max_episode_length

    def position_error(self, estimate: Tensor, truth: Tensor) -> Tensor:
        """``|norm(θ̂ − θ)|``, the angle error wrapped into ``[0, π]`` (``θ`` is not wrapped).
        ``[*S, 2]`` -> ``[*S]``."""
        return angle_normalize(estimate[..., 0] - truth[..., 0]).abs()

    # ------------------------------------------------------------------ observations
    def observation_mean(self, s_next: Tensor) -> Tensor:
        """``[cos θ', sin θ']``: POPGym's noiseless observation. ``[*S, 2]`` -> ``[*S, 2]``."""
        theta = s_next[..., 0]
        return torch.stack([torch.cos(theta), torch.sin(theta)], dim=-1)
