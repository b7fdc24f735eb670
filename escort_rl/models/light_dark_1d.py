"""Light-Dark 1D: a small discrete-action POMDP for testing planners.

The classic problem of Platt et al. (2010), in the discrete-action form used by the POMCP and
POMCPOW papers: the agent must end the episode inside the goal region ``|x| < goal_radius`` but starts
unsure where it is, and it only sees its position clearly near a light at ``x = light_position``.
The best first moves are therefore towards the light (to localise), then to the goal.

State ``s = (x, ended)`` (``state_dim = 2``): the position and a flag that is 1 once the agent has
declared (an absorbing terminal state, as the ``status`` field of POMDPs.jl's LightDark1D).

Actions (``n_actions = 3``): ``0`` left (``x - step_size``), ``1`` declare (stay and end the episode),
``2`` right (``x + step_size``); the displacement is ``(a - 1)·step_size``.

Dynamics: ``x' = x + (a - 1)·step_size·(1 - ended) + η``, ``η ~ N(0, process_noise_std²)``;
``ended' = max(ended, [a = declare])``.

Observation: ``o = x' + σ(x')·ε`` with ``σ(x) = sigma_min + noise_slope·|x - light_position|``; once
ended, ``o = ε`` (the observation after declaring carries no information about ``x``, so a planner
cannot learn from it where the declaration was made).

Reward ``R(s, a, s')`` (zero once ended): ``+correct_reward`` for declaring with ``|x| < goal_radius``,
``-wrong_declare_penalty`` for declaring elsewhere, ``-step_cost`` for a move.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from escort_rl.config.errors import ConfigError
from escort_rl.config.params import HasParams, build_params, param

DECLARE = 1
"""The action that ends the episode (the other two move left and right)."""


@dataclass(frozen=True)
class LightDark1DParams:
    """:class:`LightDark1D`'s parameters.

    Attributes:
        light_position: where observations are sharpest.
        goal_radius: declaring at ``|x| < goal_radius`` earns ``correct_reward``.
        step_size: distance of one move.
        process_noise_std: std of the position noise per step.
        sigma_min, noise_slope: observation noise ``σ(x) = sigma_min + noise_slope·|x - light_position|``.
        correct_reward, wrong_declare_penalty, step_cost: the reward law (see the module docstring).
        start_low, start_high: the start position is uniform in ``[start_low, start_high]``, for the
            true state and the prior alike (``start_low < start_high``).
    """

    light_position: float = param(2.0)
    goal_radius: float = param(0.5, gt=0)
    step_size: float = param(1.0, gt=0)
    process_noise_std: float = param(0.05, gt=0)
    sigma_min: float = param(0.05, gt=0)
    noise_slope: float = param(1.0, ge=0)
    correct_reward: float = param(100.0)
    wrong_declare_penalty: float = param(100.0)
    step_cost: float = param(5.0)
    start_low: float = param(-1.5)
    start_high: float = param(1.5)


def check_start_box(p: LightDark1DParams) -> None:
    """Raise unless the start interval is not empty."""
    if not p.start_low < p.start_high:
        raise ConfigError(f"LightDark1D.start_low: must be < start_high, got {p.start_low} >= {p.start_high}")


class LightDark1D(HasParams):
    """The 1-D Light-Dark POMDP. All tensors are float32 on ``device``.

    Takes :class:`LightDark1DParams` (or its fields as keyword arguments) and ``device``, where the
    model's tensors live.

    The status flag moves deterministically, so ``transition_scale_tril`` has a zero on its
    diagonal and ``transition_log_prob`` is ``-inf`` when the flag does not follow the action: the
    model is meant for planners and the SIR filter, not for the filters that invert the process noise.
    """

    Params = LightDark1DParams

    state_dim = 2
    obs_dim = 1
    n_actions = 3
    position_dims = (0,)

    def __init__(self, params: LightDark1DParams | None = None, *, device: torch.device | str | None = None,
                 **kwargs) -> None:
        self.params = p = build_params(LightDark1DParams, params, kwargs, owner=type(self).__name__)
        check_start_box(p)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        moves = torch.tensor([(a - 1) * p.step_size for a in range(self.n_actions)], device=self.device)
        declares = torch.tensor([float(a == DECLARE) for a in range(self.n_actions)], device=self.device)
        self._action_delta = torch.stack([moves, declares], dim=-1)  # [n_actions, 2]
        self._noise_scale = torch.tensor([p.process_noise_std, 0.0], device=self.device)

    def observation_std(self, x: Tensor) -> Tensor:
        """``σ(x) = sigma_min + noise_slope·|x - light_position|``, elementwise."""
        return self.sigma_min + self.noise_slope * (x - self.light_position).abs()

    # ------------------------------------------------------------------ protocol
    def initial_state(self, shape: tuple[int, ...], generator: torch.Generator | None = None) -> Tensor:
        """``x ~ U[start_low, start_high]``, not ended. Returns ``[*shape, 2]``."""
        u = torch.rand(tuple(shape), generator=generator, device=self.device)
        x = self.start_low + (self.start_high - self.start_low) * u
        return torch.stack([x, torch.zeros_like(x)], dim=-1)

    def initial_belief(self, shape: tuple[int, ...], n: int, generator: torch.Generator | None = None) -> Tensor:
        """``n`` draws of the start distribution per batch element: ``[*shape, n, 2]``."""
        return self.initial_state((*shape, n), generator)

    def transition_mean(self, s: Tensor, a: Tensor) -> Tensor:
        """Noise-free dynamics ``s + Δ_a·(1 - ended)`` with ``Δ_a = ((a - 1)·step_size, [a = declare])``.

        ``s``: ``[*S, 2]``, ``a``: ``[*S]`` -> ``[*S, 2]``.
        """
        return s + self._action_delta[a.long()] * (1.0 - s[..., 1:])

    def transition(self, s: Tensor, a: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """``x' = mean + η``, the flag unchanged by noise. ``[*S, 2]``."""
        mean = self.transition_mean(s, a)
        eta = torch.randn((*mean.shape[:-1], 1), generator=generator, device=mean.device, dtype=mean.dtype)
        return mean + eta * self._noise_scale

    def transition_log_prob(self, s_next: Tensor, s: Tensor, a: Tensor) -> Tensor:
        """``log N(x' - mean_x; 0, process_noise_std²)`` when the flag matches, else ``-inf``. ``[*S]``."""
        mean = self.transition_mean(s, a)
        z = (s_next[..., 0] - mean[..., 0]) / self.process_noise_std
        log_p = -0.5 * z * z - math.log(self.process_noise_std) - 0.5 * math.log(2 * math.pi)
        return torch.where(s_next[..., 1] == mean[..., 1], log_p, torch.full_like(log_p, -math.inf))

    def transition_scale_tril(self) -> Tensor:
        """``diag(process_noise_std, 0)``: the flag has no noise. ``[2, 2]``."""
        return torch.diag(self._noise_scale)

    def observe(self, s_next: Tensor, a: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """``o = x' + σ(x')·ε`` while running; ``o = ε`` once ended. ``s_next``: ``[*S, 2]`` -> ``[*S, 1]``."""
        mean, std = self._observation_mean_std(s_next)
        eps = torch.randn(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype)
        return (mean + std * eps).unsqueeze(-1)

    def observation_log_prob(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor:
        """``log N(o; x', σ(x')²)`` while running, ``log N(o; 0, 1)`` once ended.
        ``o``: ``[*S, 1]``, ``s_next``: ``[*S, 2]`` (broadcast) -> ``[*S]``."""
        mean, std = self._observation_mean_std(s_next)
        z = (o[..., 0] - mean) / std
        return -0.5 * z * z - torch.log(std) - 0.5 * math.log(2 * math.pi)

    def observation_score(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor:
        """``∇_{s'} log O(o | s')`` in closed form. With ``r = 1 - ended``, ``σ_run = σ(x')``, mean
        ``μ = x'·r``, std ``σ = σ_run·r + (1 - r)`` and ``z = (o - μ)/σ``, the log-density has
        ``∂/∂μ = z/σ`` and ``∂/∂σ = (z² - 1)/σ``, so

            ∂/∂x'     = r·(z/σ + (z² - 1)/σ · noise_slope·sign(x' - light_position))
            ∂/∂ended  = -x'·z/σ + (1 - σ_run)·(z² - 1)/σ

        (``sign(0) = 0``, the gradient autograd gives ``|·|`` at 0).
        ``o``: ``[*S, 1]``, ``s_next``: ``[*S, 2]`` (broadcast) -> ``[*S, 2]``."""
        x, running = s_next[..., 0], 1.0 - s_next[..., 1]
        mean, std = self._observation_mean_std(s_next)
        z = (o[..., 0] - mean) / std
        d_mean, d_std = z / std, (z * z - 1.0) / std
        d_x = running * (d_mean + d_std * self.noise_slope * torch.sign(x - self.light_position))
        d_ended = -x * d_mean + (1.0 - self.observation_std(x)) * d_std
        return torch.stack([d_x, d_ended], dim=-1)

    def _observation_mean_std(self, s_next: Tensor) -> tuple[Tensor, Tensor]:
        """Mean and std of the observation, ``[*S]`` each: ``(x', σ(x'))`` while running and ``(0, 1)``
        once ended, so that the observation after declaring says nothing about where the agent was."""
        x, running = s_next[..., 0], 1.0 - s_next[..., 1]
        return x * running, self.observation_std(x) * running + (1.0 - running)

    def reward(self, s: Tensor, a: Tensor, s_next: Tensor) -> Tensor:
        """Declaring pays ``+correct_reward`` in the goal and ``-wrong_declare_penalty`` elsewhere; a
        move costs ``step_cost``; nothing once ended. ``[*S]``."""
        x, ended = s[..., 0], s[..., 1] > 0.5
        declare_reward = torch.where(x.abs() < self.goal_radius, self.correct_reward, -self.wrong_declare_penalty)
        r = torch.where(a == DECLARE, declare_reward, -self.step_cost)
        return torch.where(ended, torch.zeros_like(r), r)

    def is_terminal(self, s: Tensor) -> Tensor:
        """Ended (declared). ``[*S]`` bool."""
        return s[..., 1] > 0.5

    def distance_to_goal(self, s: Tensor) -> Tensor:
        """``|x|``. ``[*S]``."""
        return s[..., 0].abs()
