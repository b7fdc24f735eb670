"""The model probe: every method of the model protocol called on a tiny batch, its outputs checked.

:func:`probe_model` is what :func:`~escort_rl.models.check_model` runs on a model the first time it
meets it (then remembers it passed), wherever an env, a transform, a planner or a run is built. The
filters check their own inputs at every update instead (a model that turns NaN mid-episode), so that a
filter used on its own calls no method it does not need. It calls each protocol method as the filters, the env and the
trainers call it, on a batch of ``B = 3`` states and ``N = 4`` particles each, and checks:

- **shapes**: states ``[*S, d]``, observations ``[*S, obs_dim]``, log-densities, rewards and
  ``is_terminal`` one value per state (``[*S]``, no trailing dimension), ``transition_scale_tril()``
  the ``[d, d]`` lower-triangular factor with a diagonal ``>= 0``; the filters' broadcast shapes too
  (particles ``[B, N, d]`` against an observation ``[B, 1, obs_dim]``, and the prior mixture's
  ``[B, N, 1, d]`` against ``[B, 1, N, d]``);
- **dtypes**: states and observations float32 (the policies and filters run in float32; a model in
  another dtype fails inside their matmuls), ``is_terminal`` bool;
- **finiteness** of every output (log-densities may be ``-inf``, never NaN or ``+inf``);
- **gradients**: ``observation_log_prob`` and ``transition_log_prob`` differentiable in the state,
  with a finite gradient (ESCORT and SVGD move particles along these gradients; a log-density
  computed on a detached state gives none, and the filter would ignore the observation without a
  word).

Each failure raises :class:`ModelProbeError` (a ``TypeError`` and a ``ValueError``) naming the method,
what was expected and what came back.

Example:
    >>> from escort_rl.models import LightDark10D
    >>> probe_model(LightDark10D())
    >>> class Broken(LightDark10D):
    ...     def reward(self, s, a, s_next):
    ...         return super().reward(s, a, s_next).unsqueeze(-1)
    >>> try:
    ...     probe_model(Broken())
    ... except ModelProbeError as err:
    ...     print(str(err).split(";")[0])
    model.reward(s, a, s_next): expected shape (3,) (one value per state: the states' leading dimensions), got (3, 1)
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from escort_rl.models.action_kinds import action_shape, is_continuous

PROBE_BATCH = 3
"""States in the probe's batch."""
PROBE_PARTICLES = 4
"""Particles per batch element in the probe's filter-shaped calls."""


class ModelProbeError(TypeError, ValueError):
    """A model's method returned something the protocol does not allow (the message names it). A
    ``TypeError`` like the protocol's missing attributes, and a ``ValueError`` like the filters' bad
    inputs, so that either caller's handler names it."""


def _describe(value: object) -> str:
    if isinstance(value, Tensor):
        return f"a {value.dtype} tensor of shape {tuple(value.shape)}"
    return f"{type(value).__name__} {value!r}"[:120]


def _call(method: str, signature: str, fn: Callable[[], object]) -> object:
    """``fn()``, or a :class:`ModelProbeError` naming ``model.method(signature)`` with the first line of
    what it raised."""
    try:
        return fn()
    except ModelProbeError:
        raise
    except Exception as err:  # noqa: BLE001 - named, with the first line of the cause
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise ModelProbeError(f"model.{method}({signature}): raised {type(err).__name__}: {first}") from None


def _tensor(method: str, signature: str, value: object, shape: tuple[int, ...], what: str, dtype=None,
            finite: str = "finite") -> Tensor:
    """Check ``value``: a tensor of ``shape`` (``what`` says what each axis is), of ``dtype`` (``None``:
    any floating dtype), with values that are ``finite`` (or ``"not NaN or +inf"``)."""
    where = f"model.{method}({signature})"
    if not isinstance(value, Tensor):
        raise ModelProbeError(f"{where}: expected a tensor of shape {shape} ({what}), got {_describe(value)}")
    if tuple(value.shape) != shape:
        fix = ("return a tensor without the trailing dimension" if tuple(value.shape) == (*shape, 1)
               else "return one entry per state, over the inputs' leading dimensions")
        raise ModelProbeError(f"{where}: expected shape {shape} ({what}), got {tuple(value.shape)}; {fix}")
    if dtype is not None and value.dtype != dtype:
        raise ModelProbeError(f"{where}: expected dtype {dtype}, got {value.dtype}"
                              + ("; compare with < or == (a bool tensor), not arithmetic" if dtype is torch.bool
                                 else "; the policies and filters run in float32: build the model's tensors in it"))
    if dtype is None and not value.dtype.is_floating_point:
        raise ModelProbeError(f"{where}: expected a floating dtype, got {value.dtype}")
    if value.dtype.is_floating_point:
        bad = value.isnan() | (value == float("inf")) if finite != "finite" else ~value.isfinite()
        if bool(bad.any()):
            raise ModelProbeError(f"{where}: expected {finite} values, got {int(bad.sum())} of {value.numel()} "
                                  f"that are not (e.g. {value[bad].flatten()[0].item()})")
    return value


def _gradient(method: str, signature: str, log_prob: Callable[[Tensor], Tensor], states: Tensor) -> None:
    """``log_prob(states)`` must carry a gradient in ``states`` (torch operations on them), finite where
    the log-density is. A flat log-density is allowed (its gradient is zero), written as one that
    depends on the state (``0 * s_next[..., 0]``)."""
    where = f"model.{method}({signature})"
    z = states.detach().clone().requires_grad_(True)
    with torch.enable_grad():
        out = log_prob(z)
        if not out.requires_grad:
            raise ModelProbeError(
                f"{where}: not differentiable in the state (its result carries no gradient); compute it with "
                "torch operations on the state, without .detach(), .item(), numpy or in-place writes: ESCORT and "
                "SVGD move the particles along this gradient (a flat one: 0 * s_next[..., 0])")
        (grad,) = torch.autograd.grad(out[out.isfinite()].sum(), z, allow_unused=True)
    if grad is not None and not bool(grad.isfinite().all()):
        raise ModelProbeError(f"{where}: its gradient in the state is not finite at some probed states")


def _actions(model, shape: tuple[int, ...], device: torch.device, generator: torch.Generator) -> Tensor:
    """Valid actions of ``shape``: integers below ``n_actions``, or points inside the action box."""
    if is_continuous(model):
        low = model.action_low.to(device)
        high = model.action_high.to(device)
        u = torch.rand((*shape, *action_shape(model)), generator=generator, device=device)
        return low + (high - low) * u
    return torch.randint(0, int(model.n_actions), shape, generator=generator, device=device)


def probe_model(model, densities: bool = True) -> None:
    """Call every protocol method of ``model`` on a tiny batch and check what comes back (see the
    module docstring); raise :class:`ModelProbeError` naming the first method that breaks the protocol.
    ``densities=False``: only what a simulator needs (``initial_state``, ``transition``,
    ``transition_mean``, ``observe``, ``reward``, ``is_terminal``, ``distance_to_goal``), not what the
    filters need. The caller has checked the attributes and that the methods exist
    (:func:`~escort_rl.models.check_model`)."""
    b, n, d, m = PROBE_BATCH, PROBE_PARTICLES, int(model.state_dim), int(model.obs_dim)
    device = torch.device(getattr(model, "device", None) or "cpu")
    g = torch.Generator(device=device).manual_seed(0)
    f32 = torch.float32
    state = f"one state per batch element: ({b}, state_dim={d})"

    s = _tensor("initial_state", f"shape=({b},), generator", _call(
        "initial_state", f"shape=({b},), generator", lambda: model.initial_state((b,), g)), (b, d), state, f32)
    a = _actions(model, (b,), device, g)
    s1 = _tensor("transition", "s, a, generator", _call(
        "transition", "s, a, generator", lambda: model.transition(s, a, g)), (b, d), state, f32)
    _tensor("transition_mean", "s, a", _call("transition_mean", "s, a", lambda: model.transition_mean(s, a)),
            (b, d), state, f32)
    o = _tensor("observe", "s_next, a, generator", _call(
        "observe", "s_next, a, generator", lambda: model.observe(s1, a, g)), (b, m),
        f"one observation per batch element: ({b}, obs_dim={m})", f32)
    one = "one value per state: the states' leading dimensions"
    _tensor("reward", "s, a, s_next", _call("reward", "s, a, s_next", lambda: model.reward(s, a, s1)), (b,), one)
    _tensor("is_terminal", "s", _call("is_terminal", "s", lambda: model.is_terminal(s1)), (b,), one, torch.bool)
    if callable(getattr(model, "distance_to_goal", None)):
        _tensor("distance_to_goal", "s", _call("distance_to_goal", "s", lambda: model.distance_to_goal(s1)),
                (b,), one)
    if not densities:
        return

    x = _tensor("initial_belief", f"shape=({b},), n={n}, generator", _call(
        "initial_belief", f"shape=({b},), n={n}, generator", lambda: model.initial_belief((b,), n, g)),
        (b, n, d), f"n={n} particles per batch element: ({b}, n, state_dim)", f32)
    scale = _tensor("transition_scale_tril", "", _call("transition_scale_tril", "", model.transition_scale_tril),
                    (d, d), "the [state_dim, state_dim] Cholesky factor of the process noise covariance, not its "
                    "diagonal", f32)
    if not torch.equal(scale, torch.tril(scale)) or not bool((torch.diagonal(scale) >= 0).all()):
        raise ModelProbeError("model.transition_scale_tril(): expected a lower-triangular matrix with a diagonal "
                              ">= 0 (torch.linalg.cholesky of the covariance; 0 where a coordinate has no noise)")

    log_density = "one log-density per state: the states' leading dimensions"
    may_be_minus_inf = "finite or -inf (not NaN or +inf)"
    _tensor("transition_log_prob", "s_next, s, a", _call(
        "transition_log_prob", "s_next, s, a", lambda: model.transition_log_prob(s1, s, a)),
        (b,), log_density, None, may_be_minus_inf)
    _tensor("observation_log_prob", "o, s_next, a", _call(
        "observation_log_prob", "o, s_next, a", lambda: model.observation_log_prob(o, s1, a)),
        (b,), log_density, None, may_be_minus_inf)

    # the filters' shapes: particles [B, N, d], actions [B, N], the observation [B, 1, obs_dim]; the prior
    # mixture's [B, N, 1, d] against [B, 1, N, d] with actions [B, 1, N]
    a_n = a.unsqueeze(1).expand(b, n, *action_shape(model))
    x1 = _call("transition", "particles [B, N, d], a [B, N], generator", lambda: model.transition(x, a_n, g))
    x1 = _tensor("transition", "particles [B, N, d], a [B, N], generator", x1, (b, n, d),
                 "one state per particle: (B, N, state_dim)", f32)
    o_b = o.unsqueeze(1)
    sig = "o [B, 1, obs_dim], particles [B, N, d], a [B, N]"
    _tensor("observation_log_prob", sig, _call("observation_log_prob", sig,
                                               lambda: model.observation_log_prob(o_b, x1, a_n)),
            (b, n), "one log-density per particle: (B, N), broadcast over the observation's axis of 1", None,
            may_be_minus_inf)
    sig_mix = "s_next [B, N, 1, d], s [B, 1, N, d], a [B, 1, N]"
    a_mix = a_n.unsqueeze(1)
    _tensor("transition_log_prob", sig_mix, _call(
        "transition_log_prob", sig_mix, lambda: model.transition_log_prob(x1.unsqueeze(2), x.unsqueeze(1), a_mix)),
        (b, n, n), "one log-density per pair: (B, N, N), by broadcasting", None, may_be_minus_inf)

    _gradient("observation_log_prob", sig, lambda z: model.observation_log_prob(o_b, z, a_n), x1)
    _gradient("transition_log_prob", "s_next, s, a", lambda z: model.transition_log_prob(z, x, a_n), x1)
