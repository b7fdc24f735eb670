"""The filter interface that SIR, SVGD and ESCORT share, with input validation.

A filter is stateless apart from its configuration: the belief is passed in and returned.
Filters know nothing of TorchRL; they see plain tensors and a model (SPEC §2).

Filters never return NaN or inf silently. With ``check_finite`` on (the default), ``init`` and
``update`` raise :class:`~escort_rl.belief.checks.NonFiniteError` (a ``ValueError``) naming the
culprit: a non-finite ``belief.particles`` or ``belief.log_weights`` in the input, a model method that
returned NaN or inf (``-inf`` from a log-density is a zero likelihood, and allowed), or a result that
overflowed. The checks cost one host synchronisation per update when all is finite
(:class:`~escort_rl.belief.checks.FiniteGuard`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from torch import Tensor

from escort_rl.belief.checks import FiniteGuard
from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.models.protocol import check_model


class BeliefFilter(ABC):
    """Base class: ``init`` draws the prior, ``update`` folds in one (action, observation) pair.

    Attributes:
        check_finite: check that the input belief, what the model's methods return and the result
            are finite, and raise a ``ValueError`` naming the culprit if not (default ``True``). The
            check costs one host synchronisation per update; turn it off (``filt.check_finite =
            False``) only where the caller validates the beliefs and the model elsewhere.
    """

    @property
    def check_finite(self) -> bool:
        return self.__dict__.get("_check_finite", True)

    @check_finite.setter
    def check_finite(self, value: bool) -> None:
        self._check_finite = validate_check_finite(type(self).__name__, value)

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
        guard = FiniteGuard(type(self).__name__, tuple(batch_shape), enabled=self.check_finite)
        guard.model_values("model.initial_belief", particles)
        guard.verify()
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

        Returns the posterior belief with particles ``[*B, N, d]``. With ``check_finite``, raises
        ``NonFiniteError`` (a ``ValueError``) naming ``belief.particles``, ``belief.log_weights`` or the
        model method that gave a NaN or inf, after one host synchronisation.
        """
        validate_update_inputs(model, belief, action, observation)
        if observation.dtype != belief.particles.dtype:  # e.g. float64 observations of a float32 belief
            observation = observation.to(belief.particles.dtype)
        guard = FiniteGuard(type(self).__name__, belief.batch_shape, enabled=self.check_finite)
        guard.input_belief(belief)
        with guard.diagnosing():  # a NaN that makes a factorisation fail is named, not a deep traceback
            posterior = self._update(model, belief, action, observation, generator, guard=guard)
        guard.result(posterior)
        guard.verify()
        return posterior

    @abstractmethod
    def _update(
        self,
        model,
        belief: ParticleBelief,
        action: Tensor,
        observation: Tensor,
        generator: torch.Generator | None,
        *,
        guard: FiniteGuard | None = None,
    ) -> ParticleBelief:
        """The update itself, on validated inputs. It records what the model's methods return in
        ``guard`` (``None``: no checks), which :meth:`update` then verifies with one host sync."""


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
    if not isinstance(observation, Tensor) or observation.shape != (*batch, model.obs_dim):
        shape = tuple(observation.shape) if isinstance(observation, Tensor) else type(observation).__name__
        raise ValueError(
            f"observation: expected shape {(*batch, model.obs_dim)} (batch, model.obs_dim), got {shape}"
        )
    # the action range and the observation's finiteness in one host sync; the messages only on failure
    ok = torch.isfinite(observation).all()
    if action.numel():
        ok = ok & (action >= 0).all() & (action < model.n_actions).all()
    if bool(ok):
        return
    if action.numel() and (int(action.min()) < 0 or int(action.max()) >= model.n_actions):
        raise ValueError(
            f"action: values must lie in [0, {model.n_actions}), got min {int(action.min())}, "
            f"max {int(action.max())}"
        )
    bad = (~torch.isfinite(observation)).reshape(-1, model.obs_dim).any(-1).nonzero().flatten()
    raise ValueError(
        f"observation: contains NaN or Inf (flat batch indices {bad.tolist()[:8]}); "
        "filters need finite observations"
    )


def validate_check_finite(owner: str, value: object) -> bool:
    """``value`` if it is a bool, else ``ValueError`` naming ``{owner}.check_finite``."""
    if not isinstance(value, bool):
        raise ValueError(f"{owner}.check_finite: must be True or False, got {value!r}")
    return value
