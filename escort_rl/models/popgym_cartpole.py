"""POPGym's Stateless CartPole (``PositionOnlyCartPole``) and its noisy variant, as a known torch model.

POPGym (Morad et al., ICLR 2023, the ``popgym`` package) hides the velocities of gymnasium's
CartPole: the agent sees the cart position and the pole angle only. This model reproduces it step
for step (``tests/models/test_popgym_models.py`` checks it against ``popgym``):

- State ``s = [x, ẋ, θ, θ̇]`` (``state_dim = 4``); actions ``{0, 1}`` push the cart with force
  ``∓10`` (``n_actions = 2``, int64 ``[*S]``).
- Dynamics: gymnasium's CartPole, explicit Euler with its constants (g = 9.8, cart mass 1.0, pole
  mass 0.1, half-length 0.5, force 10, τ = 0.02):

      temp = (F + m_p l θ̇² sin θ) / M,   θ̈ = (g sin θ − cos θ · temp) / (l (4/3 − m_p cos² θ / M)),
      ẍ = temp − m_p l θ̈ cos θ / M,       s' = s + τ·[ẋ, ẍ, θ̇, θ̈]

- Termination: ``|x| > 2.4`` or ``|θ| > 12°`` (strict, on the new state).
- Start: ``s₀ ~ U(−0.05, 0.05)⁴``.
- Observation ``o = [x', θ']``; the noisy tasks add ``N(0, σ²)`` per coordinate and clip to
  POPGym's box ``±[4.8, 0.4189]`` (twice the termination bounds); the stateless tasks add nothing.
- Reward: POPGym's ``reward_transform`` of gymnasium's: gymnasium pays 1 on every step, the one that
  terminates included, and 0 on a step taken after termination; POPGym maps 0 to −1 and anything
  else to ``1/max_episode_length``, so a full episode returns 1. In the model, a step from a terminal
  state into a terminal state pays −1 and every other ``1/L`` (exact whenever the episode reached
  ``s`` by stepping; gymnasium alone would also pay 0 on leaving the box again after re-entering it).
- The time limit is not part of the state: ``max_episode_length`` (POPGym's: 200, 400, 600 for Easy,
  Medium, Hard; 200 for every noisy task) is for the env's truncation (``POMDPEnv(max_steps=...)``).

**The densities a filter needs, which POPGym does not have.** POPGym's dynamics are deterministic
and its stateless observations are noiseless; a particle filter needs densities for both:

- ``process_noise``: a filter-side Gaussian process noise, independent per coordinate, with std
  ``process_noise × TYPICAL_STEP``. ``TYPICAL_STEP = (0.01, 0.2, 0.015, 0.3)`` is the RMS one-step
  change of each coordinate under a random policy (measured on 4 500 POPGym steps: 0.0104, 0.195,
  0.0155, 0.293), so the default 0.05 is 5% of a typical step: enough spread to keep resampled
  particles apart and to absorb float rounding, small enough that a prediction stays within a few
  percent of the true deterministic one. :meth:`transition` adds it; with ``process_noise = 0`` it
  is exactly POPGym's step (``transition == transition_mean``), and :meth:`transition_log_prob`
  raises, since a filter then has no density.
- ``obs_noise_floor``: the smallest observation std the density uses, ``σ = max(obs_noise,
  obs_noise_floor)``. The default 0.01 is a tenth of the smallest noise POPGym adds (0.1) and about
  one typical step of ``x`` and ``θ``: sharp enough that ten steps of noiseless positions pin the
  velocities down (to ~0.05, against an RMS of 0.5 and 0.8), wide enough that a start prior of width
  0.1 keeps a fair share of particles in play. :meth:`observe` draws with ``obs_noise`` itself (none
  on the stateless tasks), so the env's observations stay POPGym's.
- The observation density is the censored Gaussian of :mod:`escort_rl.models.clipped_gaussian`: the
  Gaussian density inside the box and the log tail mass at a bound, finite and differentiable.

Example:
    >>> import torch
    >>> m = POPGymCartPole.from_name("NoisyPositionOnlyCartPoleHard")
    >>> m.max_episode_length, m.obs_noise
    (200, 0.3)
    >>> m.transition_mean(torch.zeros(4), torch.tensor(1))  # push right from rest
    tensor([ 0.0000,  0.1951,  0.0000, -0.2927])
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

GRAVITY, MASS_CART, MASS_POLE, HALF_LENGTH, FORCE_MAG, TAU = 9.8, 1.0, 0.1, 0.5, 10.0, 0.02
"""gymnasium CartPole's constants (``length`` is half the pole's length, as gymnasium names it)."""
TOTAL_MASS = MASS_POLE + MASS_CART
POLEMASS_LENGTH = MASS_POLE * HALF_LENGTH
X_THRESHOLD = 2.4
THETA_THRESHOLD = 12 * 2 * math.pi / 360
"""The termination bounds: ``|x| > 2.4`` or ``|θ| > 12°``."""
OBS_HIGH = (2 * X_THRESHOLD, 2 * THETA_THRESHOLD)
"""POPGym's observation box ``±OBS_HIGH`` (float32 there), the clip of the noisy task."""
START_HIGH = 0.05
TYPICAL_STEP = (0.01, 0.2, 0.015, 0.3)
"""The RMS one-step change of ``[x, ẋ, θ, θ̇]`` under a random policy; the unit of ``process_noise``."""

CARTPOLE_TASKS = {
    "PositionOnlyCartPoleEasy": {"max_episode_length": 200, "obs_noise": 0.0},
    "PositionOnlyCartPoleMedium": {"max_episode_length": 400, "obs_noise": 0.0},
    "PositionOnlyCartPoleHard": {"max_episode_length": 600, "obs_noise": 0.0},
    "NoisyPositionOnlyCartPoleEasy": {"max_episode_length": 200, "obs_noise": 0.1},
    "NoisyPositionOnlyCartPoleMedium": {"max_episode_length": 200, "obs_noise": 0.2},
    "NoisyPositionOnlyCartPoleHard": {"max_episode_length": 200, "obs_noise": 0.3},
}
"""POPGym's CartPole tasks -> their parameters (popgym 1.0: the noisy tasks keep the default length)."""


@dataclass(frozen=True)
class POPGymCartPoleParams(POPGymParams):
    """:class:`POPGymCartPole`'s parameters: :class:`~escort_rl.models.popgym_task.POPGymParams`, with
    episodes of 200, 400, 600 steps for Easy, Medium, Hard."""


class POPGymCartPole(POPGymTask, HasParams, FilterNoiseTransition, ClippedGaussianObservation):
    """POPGym's (Noisy) PositionOnlyCartPole as a model; float32 tensors on ``device``.

    Takes :class:`POPGymCartPoleParams` (or its fields as keyword arguments) and ``device``;
    :meth:`from_name` builds one of POPGym's six tasks by name.
    """

    Params = POPGymCartPoleParams
    TASKS = CARTPOLE_TASKS
    SYSTEM = "CartPole"
    state_dim = 4
    obs_dim = 2
    n_actions = 2
    position_dims = (0, 2)
    velocity_dims = (1, 3)

    def __init__(self, params: POPGymCartPoleParams | None = None, *, device: torch.device | str | None = None,
                 **kwargs) -> None:
        self.params = p = build_params(POPGymCartPoleParams, params, kwargs, owner=type(self).__name__)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        f32 = dict(dtype=torch.float32, device=self.device)
        self.obs_high = torch.tensor(OBS_HIGH, **f32)
        self.obs_low = -self.obs_high
        self.process_std = p.process_noise * torch.tensor(TYPICAL_STEP, **f32)
        self.observation_std = max(p.obs_noise, p.obs_noise_floor)

    # ------------------------------------------------------------------ dynamics
    def initial_state(self, shape: tuple[int, ...], generator: torch.Generator | None = None) -> Tensor:
        """``U(−0.05, 0.05)⁴``, as gymnasium's reset. Returns ``[*shape, 4]``."""
        u = torch.rand(*shape, 4, generator=generator, device=self.device)
        return START_HIGH * (2 * u - 1)

    def initial_belief(self, shape: tuple[int, ...], n: int, generator: torch.Generator | None = None) -> Tensor:
        """``n`` draws of the start distribution per batch element: ``[*shape, n, 4]``."""
        return self.initial_state((*shape, n), generator)

    def transition_mean(self, s: Tensor, a: Tensor) -> Tensor:
        """gymnasium's Euler step (the module docstring). ``s`` ``[*S, 4]``, ``a`` ``[*S]`` int (1 pushes
        right, anything else left, as gymnasium reads it) -> ``[*S, 4]``."""
        x, x_dot, theta, theta_dot = s.unbind(-1)
        force = torch.where(a == 1, FORCE_MAG, -FORCE_MAG).to(s.dtype)
        cos, sin = torch.cos(theta), torch.sin(theta)
        temp = (force + POLEMASS_LENGTH * theta_dot**2 * sin) / TOTAL_MASS
        theta_acc = (GRAVITY * sin - cos * temp) / (HALF_LENGTH * (4.0 / 3.0 - MASS_POLE * cos**2 / TOTAL_MASS))
        x_acc = temp - POLEMASS_LENGTH * theta_acc * cos / TOTAL_MASS
        return torch.stack([x + TAU * x_dot, x_dot + TAU * x_acc, theta + TAU * theta_dot,
                            theta_dot + TAU * theta_acc], dim=-1)

    def is_terminal(self, s: Tensor) -> Tensor:
        """``|x| > 2.4`` or ``|θ| > 12°``. ``[*S, 4]`` -> ``[*S]`` bool."""
        x, theta = s[..., 0], s[..., 2]
        return (x < -X_THRESHOLD) | (x > X_THRESHOLD) | (theta < -THETA_THRESHOLD) | (theta > THETA_THRESHOLD)

    def reward(self, s: Tensor, a: Tensor, s_next: Tensor) -> Tensor:
        """POPGym's reward: ``−1`` on a step from a terminal state into a terminal one (gymnasium's 0
        after termination), ``1/max_episode_length`` on every other. ``[*S]``."""
        after_end = self.is_terminal(s) & self.is_terminal(s_next)
        return torch.where(after_end, -1.0, 1.0 / self.max_episode_length).to(s_next.dtype)

    # ------------------------------------------------------------------ observations
    def observation_mean(self, s_next: Tensor) -> Tensor:
        """``[x', θ']``: POPGym's noiseless observation. ``[*S, 4]`` -> ``[*S, 2]``."""
        return s_next[..., 0::2]
