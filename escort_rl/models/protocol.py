"""The POMDP model protocol: the one source of truth that envs and filters share.

Every function is batched over leading dimensions and written in torch. States end in
``state_dim``, observations in ``obs_dim``, and integer actions have the leading shape of the
state they act on (real actions, of a model with continuous actions, are ``[*S, action_dim]``).
Log densities are differentiable in the state (filters take scores with autograd, or from a model's
optional closed-form ``observation_score``).

The protocol is structural: any object with these attributes and methods is a model, including a
user's class that imports nothing from ``escort_rl``.
"""

from __future__ import annotations

import weakref
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from escort_rl.models.action_kinds import action_shape, is_continuous  # noqa: F401  (re-exported; apart for the probe)


@runtime_checkable
class POMDPModel(Protocol):
    """A POMDP with continuous states, continuous observations and discrete actions.

    Actions are integers ``a [*S]`` in ``[0, n_actions)``. A model with continuous actions declares,
    instead of ``n_actions``, ``action_dim: int`` and the box ``action_low``, ``action_high`` (float
    tensors ``[action_dim]``), and receives actions as float tensors ``a [*S, action_dim]`` in that box
    (:func:`is_continuous`, :func:`action_shape`). Below, ``a [*S]`` reads ``a [*S, action_dim]`` for it.

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
    e.g. the mean over several targets), ``distance_to_goal(s)``; ``state_parts``, a dict of named groups of
    state indices on which the benchmarks compare beliefs with a reference (default: the position and the
    velocity; the first part is the frontier's), and ``behaviour_action(s [d], generator)`` -> an action, the
    behaviour policy of the benchmarks' shared trajectories (default: uniform random actions), with
    ``behaviour_description``, a sentence saying what it does.

    Optional, used by policies (``actor.head=per_coordinate``): ``action_coordinates``, ``G`` tuples of
    ``k`` state indices, the coordinates that each group of actions acts on; discrete actions come in
    ``G`` groups of ``n_actions / G`` consecutive indices (continuous ones: ``action_dim = G``).
    """

    state_dim: int
    obs_dim: int
    # and n_actions: int (discrete actions), or action_dim: int with action_low, action_high (real
    # ones): not declared here, so that isinstance(model, POMDPModel) accepts either; check_model checks.

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


_PROBED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
"""The models that passed :func:`~escort_rl.models.probe.probe_model`, each with whether its densities
were probed too (checked once, then remembered)."""


def check_model(model: object, densities: bool = True) -> None:
    """Raise ``TypeError`` naming the first problem if ``model`` is not a POMDPModel.

    It needs ``state_dim`` and ``obs_dim``, the methods, and either ``n_actions`` (discrete actions) or
    ``action_dim`` with ``action_low`` and ``action_high`` of shape ``[action_dim]`` (continuous). The
    first time it meets a model it also calls every method on a tiny batch and checks shapes, dtypes,
    finiteness and the log-densities' gradients (:func:`~escort_rl.models.probe.probe_model`);
    ``densities=False`` probes only what a simulator needs (an env's own model, e.g. POPGym's
    deterministic dynamics, which have no transition density). A class passed instead of an instance
    is named as such."""
    if isinstance(model, type):
        raise TypeError(f"model: got the class {model.__name__}, not an instance of it; pass "
                        f"{model.__name__}(...) instead")
    check_model_structure(model)
    try:
        if _PROBED.get(model, False) or (not densities and model in _PROBED):
            return
    except TypeError:  # not weakly referenceable or not hashable: probed every time
        pass
    from escort_rl.models.probe import probe_model

    probe_model(model, densities=densities)
    try:
        _PROBED[model] = densities or _PROBED.get(model, False)
    except TypeError:
        pass


def check_model_structure(model: object) -> None:
    """The attributes and methods :func:`check_model` requires, without calling them."""
    for name in ("state_dim", "obs_dim"):
        if not isinstance(getattr(model, name, None), int):
            raise TypeError(
                f"model.{name}: expected an int attribute on {type(model).__name__}; "
                "a model must follow escort_rl.models.POMDPModel"
            )
    if is_continuous(model):
        check_action_box(model)
    elif not isinstance(getattr(model, "n_actions", None), int):
        raise TypeError(
            f"model.n_actions: expected an int attribute on {type(model).__name__} (or, for continuous actions, "
            "action_dim with action_low and action_high); a model must follow escort_rl.models.POMDPModel"
        )
    elif isinstance(model.n_actions, bool) or model.n_actions < 1:
        raise TypeError(f"model.n_actions: expected a positive int (the number of actions) on {type(model).__name__}, "
                        f"got {model.n_actions!r}")
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



def check_action_box(model) -> tuple[Tensor, Tensor]:
    """``(action_low, action_high)`` of a continuous-action model as float tensors ``[action_dim]``;
    ``TypeError`` naming the field when ``action_dim`` is not a positive int or the box does not fit it."""
    name = type(model).__name__
    dim = getattr(model, "action_dim", None)
    if not isinstance(dim, int) or isinstance(dim, bool) or dim < 1:
        raise TypeError(f"model.action_dim: expected a positive int on {name}, got {dim!r}")
    bounds = []
    for field in ("action_low", "action_high"):
        value = getattr(model, field, None)
        if not isinstance(value, Tensor) or tuple(value.shape) != (dim,) or not value.dtype.is_floating_point:
            got = f"shape {tuple(value.shape)}, dtype {value.dtype}" if isinstance(value, Tensor) else repr(value)
            raise TypeError(f"model.{field}: expected a float tensor of shape ({dim},) (one bound per action "
                            f"dimension) on {name}, got {got}")
        bounds.append(value)
    low, high = bounds
    if not bool(torch.isfinite(low).all() & torch.isfinite(high).all() & (low < high).all()):
        raise TypeError(f"model.action_low, model.action_high: expected finite bounds with low < high on {name}, "
                        f"got {low.tolist()} and {high.tolist()}")
    return low, high


def per_particle(model, action: Tensor, lead: tuple[int, ...]) -> Tensor:
    """An action batch ``[*B]`` (``[*B, action_dim]``) broadcast to the particles, ``lead = (*B, N)``:
    ``[*B, N]`` (``[*B, N, action_dim]``). A view, no copy.

    Example:
        >>> from escort_rl.models import LightDark10D
        >>> per_particle(LightDark10D(), torch.tensor([1, 2]), (2, 5)).shape
        torch.Size([2, 5])
    """
    event = action_shape(model)
    return action.unsqueeze(-1 - len(event)).expand(*lead, *event)


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


def action_in_range(model, action: Tensor) -> Tensor:
    """Which actions ``model`` accepts, ``[*B]`` bool (no host sync): integers in ``[0, n_actions)``, or
    finite real vectors ``[*B, action_dim]`` inside ``[action_low, action_high]``."""
    if not is_continuous(model):
        return (action >= 0) & (action < model.n_actions)
    low, high = (b.to(action.device, action.dtype) for b in (model.action_low, model.action_high))
    return (torch.isfinite(action) & (action >= low) & (action <= high)).all(-1)


def describe_action_range(model, action: Tensor) -> str:
    """The message for actions outside :func:`action_in_range` (one host sync; for error paths)."""
    if not is_continuous(model):
        return (f"values must lie in [0, {model.n_actions}), got min {int(action.min())}, "
                f"max {int(action.max())}")
    finite = action[torch.isfinite(action)]
    span = f"min {float(finite.min()):.4g}, max {float(finite.max()):.4g}" if finite.numel() else "no finite value"
    nan = "" if bool(torch.isfinite(action).all()) else " and NaN or Inf"
    return (f"real actions must lie in the box [model.action_low, model.action_high] = "
            f"[{model.action_low.tolist()}, {model.action_high.tolist()}], got {span}{nan}; squash the policy's "
            "output into the box (e.g. a TanhNormal, or a clipped Gaussian) or clip it")


def null_action(model, shape: tuple[int, ...] = (), device=None) -> Tensor:
    """The action a reset's first observation is drawn with (``observe(s_0, a)``): the index 0, or for
    continuous actions the zero vector clamped into the box. ``[*shape]`` int64 or
    ``[*shape, action_dim]`` float32."""
    if not is_continuous(model):
        return torch.zeros(shape, dtype=torch.int64, device=device)
    low, high = (b.to(device=device, dtype=torch.float32) for b in (model.action_low, model.action_high))
    return torch.zeros(*shape, model.action_dim, device=device).clamp(low, high)


def random_action(model, shape: tuple[int, ...] = (), generator: torch.Generator | None = None,
                  device=None) -> Tensor:
    """Actions drawn uniformly: indices in ``[0, n_actions)`` (int64 ``[*shape]``), or for continuous
    actions points of the box (float32 ``[*shape, action_dim]``)."""
    if not is_continuous(model):
        return torch.randint(0, model.n_actions, tuple(shape), generator=generator, device=device)
    low, high = (b.to(device=device, dtype=torch.float32) for b in (model.action_low, model.action_high))
    u = torch.rand(*shape, model.action_dim, generator=generator, device=device)
    return low + (high - low) * u
