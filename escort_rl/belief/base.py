"""The filter interface that SIR, SVGD and ESCORT share, with input validation.

A filter is stateless apart from its configuration: the belief is passed in and returned.
Filters know nothing of TorchRL; they see plain tensors and a model (SPEC §2).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from torch import Tensor

from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.models.protocol import check_model


class BeliefFilter(ABC):
    """Base class: ``init`` draws the prior, ``update`` folds in one (action, observation) pair."""

    def init(
        self,
        model,
        batch_shape: tuple[int, ...] | torch.Size,
        num_particles: int,
        generator: torch.Generator | None = None,
    ) -> ParticleBelief:
        """The prior belief: ``num_particles`` draws of ``model.initial_belief`` per batch element.

        Returns a belief with particles ``[*batch_shape, num_particles, d]`` and equal weights.
        """
        check_model(model)
        if not isinstance(num_particles, int) or num_particles < 1:
            raise ValueError(f"num_particles: expected a positive int, got {num_particles!r}")
        particles = model.initial_belief(tuple(batch_shape), num_particles, generator)
        if particles.shape[-1] != model.state_dim:
            raise ValueError(
                f"model.initial_belief: returned last dimension {particles.shape[-1]}, "
                f"but model.state_dim is {model.state_dim}"
            )
        return ParticleBelief.uniform(particles)

    def update(
        self,
        model,
        belief: ParticleBelief,
        action: Tensor,
        observation: Tensor,
        generator: torch.Generator | None = None,
    ) -> ParticleBelief:
        """Fold in ``action`` ``[*B]`` (integer) and the next ``observation`` ``[*B, obs_dim]``.

        Returns the posterior belief with particles ``[*B, N, d]``.
        """
        validate_update_inputs(model, belief, action, observation)
        if observation.dtype != belief.particles.dtype:  # e.g. float64 observations of a float32 belief
            observation = observation.to(belief.particles.dtype)
        return self._update(model, belief, action, observation, generator)

    @abstractmethod
    def _update(
        self,
        model,
        belief: ParticleBelief,
        action: Tensor,
        observation: Tensor,
        generator: torch.Generator | None,
    ) -> ParticleBelief: ...


def validate_update_inputs(model, belief: ParticleBelief, action: Tensor, observation: Tensor) -> None:
    """Raise ``ValueError`` naming the field when the update inputs do not fit together."""
    check_model(model)
    batch = belief.batch_shape
    if belief.state_dim != model.state_dim:
        raise ValueError(
            f"belief.particles: last dimension is {belief.state_dim} but model.state_dim is "
            f"{model.state_dim}; build the filter's belief for this model"
        )
    if not isinstance(action, Tensor) or action.shape != batch:
        shape = tuple(action.shape) if isinstance(action, Tensor) else type(action).__name__
        raise ValueError(f"action: expected shape {tuple(batch)} (one integer per belief), got {shape}")
    if action.dtype.is_floating_point or action.dtype == torch.bool:
        raise ValueError(f"action: expected an integer tensor, got dtype {action.dtype}")
    if action.numel() and (int(action.min()) < 0 or int(action.max()) >= model.n_actions):
        raise ValueError(
            f"action: values must lie in [0, {model.n_actions}), got min {int(action.min())}, "
            f"max {int(action.max())}"
        )
    if not isinstance(observation, Tensor) or observation.shape != (*batch, model.obs_dim):
        shape = tuple(observation.shape) if isinstance(observation, Tensor) else type(observation).__name__
        raise ValueError(
            f"observation: expected shape {(*batch, model.obs_dim)} (batch, model.obs_dim), got {shape}"
        )
    if not torch.isfinite(observation).all():
        bad = (~torch.isfinite(observation)).reshape(-1, model.obs_dim).any(-1).nonzero().flatten()
        raise ValueError(
            f"observation: contains NaN or Inf (flat batch indices {bad.tolist()[:8]}); "
            "filters need finite observations"
        )
