"""The POMDP model protocol: the one source of truth that envs and filters share.

Every function is batched over leading dimensions and written in torch. States end in
``state_dim``, observations in ``obs_dim``, and integer actions have the leading shape of the
state they act on. Log densities are differentiable in the state (filters take scores with
autograd, or from a model's optional closed-form ``observation_score``).

The protocol is structural: any object with these attributes and methods is a model, including a
user's class that imports nothing from ``escort_rl``.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from torch import Tensor


@runtime_checkable
class POMDPModel(Protocol):
    """A POMDP with continuous states, continuous observations and discrete actions.

    Shapes (``*S`` is any batch shape; arguments broadcast over it):

    - ``initial_state(shape, generator)`` -> ``[*shape, d]``: the true start state.
    - ``initial_belief(shape, n, generator)`` -> ``[*shape, n, d]``: the prior particles.
    - ``transition(s [*S, d], a [*S], generator)`` -> ``[*S, d]``: a sample of ``s' ~ T(.|s, a)``.
    - ``transition_log_prob(s_next [*S, d], s [*S, d], a [*S])`` -> ``[*S]``: ``log T(s'|s, a)``.
    - ``transition_mean(s [*S, d], a [*S])`` -> ``[*S, d]``: ``E[s'|s, a]``.
    - ``transition_scale_tril()`` -> ``[d, d]``: Cholesky factor of the additive process noise.
    - ``observe(s_next [*S, d], a [*S], generator)`` -> ``[*S, obs_dim]``: ``o ~ O(.|s', a)``.
    - ``observation_log_prob(o [*S, obs_dim], s_next [*S, d], a [*S])`` -> ``[*S]``.
    - ``reward(s, a, s_next)`` -> ``[*S]``.
    - ``is_terminal(s [*S, d])`` -> ``[*S]`` (bool).

    Optional, used by the SVGD/ESCORT filters when present: ``observation_score(o [*S, obs_dim],
    s_next [*S, d], a [*S])`` -> ``[*S, d]``, the score ``∇_{s'} log O(o | s', a)`` in closed form
    (same broadcasting as ``observation_log_prob``; the leading shape is the broadcast one). A filter
    falls back to autograd through ``observation_log_prob`` when a model lacks it, so it is an
    optimisation, never a requirement (:func:`check_model` does not ask for it). It must equal the
    autograd gradient of ``observation_log_prob(o, s_next, a).sum()`` with respect to ``s_next``,
    including its zeros where the log-density is flat (clamps, branches).

    Optional, used by evaluation and benchmarks (see :func:`position_error`): ``position_dims``
    (the state indices of the position), ``velocity_dims`` (of the velocity, see
    :func:`velocity_dims`), ``position_error(estimate, truth)`` (a domain's own error,
    e.g. the mean over several targets), ``distance_to_goal(s)``.
    """

    state_dim: int
    obs_dim: int
    n_actions: int

    def initial_state(self, shape: tuple[int, ...], generator: torch.Generator | None = None) -> Tensor: ...

    def initial_belief(
        self, shape: tuple[int, ...], n: int, generator: torch.Generator | None = None
    ) -> Tensor: ...

    def transition(self, s: Tensor, a: Tensor, generator: torch.Generator | None = None) -> Tensor: ...

    def transition_log_prob(self, s_next: Tensor, s: Tensor, a: Tensor) -> Tensor: ...

    def transition_mean(self, s: Tensor, a: Tensor) -> Tensor: ...

    def transition_scale_tril(self) -> Tensor: ...

    def observe(self, s_next: Tensor, a: Tensor, generator: torch.Generator | None = None) -> Tensor: ...

    def observation_log_prob(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor: ...

    def reward(self, s: Tensor, a: Tensor, s_next: Tensor) -> Tensor: ...

    def is_terminal(self, s: Tensor) -> Tensor: ...


def check_model(model: object) -> None:
    """Raise ``TypeError`` naming the first missing attribute if ``model`` is not a POMDPModel."""
    for name in ("state_dim", "obs_dim", "n_actions"):
        if not isinstance(getattr(model, name, None), int):
            raise TypeError(
                f"model.{name}: expected an int attribute on {type(model).__name__}; "
                "a model must follow escort_rl.models.POMDPModel"
            )
    for name in (
        "initial_state",
        "initial_belief",
        "transition",
        "transition_log_prob",
        "transition_mean",
        "transition_scale_tril",
        "observe",
        "observation_log_prob",
        "reward",
        "is_terminal",
    ):
        if not callable(getattr(model, name, None)):
            raise TypeError(
                f"model.{name}: {type(model).__name__} has no method {name}(); "
                "a model must follow escort_rl.models.POMDPModel"
            )


def has_goal(model) -> bool:
    """Whether ``model`` has a goal: a ``distance_to_goal(s)`` method (episodes that end at the goal
    then count as successes). Without one, evaluation reports the return alone."""
    return callable(getattr(model, "distance_to_goal", None))


def position_dims(model) -> tuple[int, ...]:
    """The state indices of the position: ``model.position_dims``, else the first ``model.n_pos``
    coordinates, else all of them."""
    dims = getattr(model, "position_dims", None)
    if dims is None:
        dims = range(getattr(model, "n_pos", model.state_dim))
    return tuple(int(i) for i in dims)


def velocity_dims(model) -> tuple[int, ...]:
    """The state indices of the velocity: ``model.velocity_dims``, else none (``()``)."""
    return tuple(int(i) for i in getattr(model, "velocity_dims", ()))


def position_error(model, estimate: Tensor, truth: Tensor) -> Tensor:
    """The domain's position error: ``model.position_error(estimate, truth)`` when the model
    defines one, else ``‖estimate[pos] − truth[pos]‖₂`` over :func:`position_dims`.
    ``estimate``, ``truth`` ``[*S, d]`` -> ``[*S]``."""
    own = getattr(model, "position_error", None)
    if callable(own):
        return own(estimate, truth)
    idx = list(position_dims(model))
    return torch.linalg.vector_norm(estimate[..., idx] - truth[..., idx], dim=-1)
