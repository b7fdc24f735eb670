"""Scripted belief controllers: a proportional-derivative (PD) rule on a state estimate.

These are hand-written, non-learned baselines: they turn a point estimate of the state (the
weighted mean of a particle belief, or the true state) into a discrete action. They show what a
filter's belief is worth to a simple controller, with no training in the way, and the true-state
variant is the full-information reference the same rule reaches.

The rule (:func:`pd_action`): with position estimate ``x̂``, velocity estimate ``v̂`` and goal ``g``
(all ``[*B, k]``),

    u = (g − x̂) − gain_v · v̂,

pick the dimension ``i`` with the largest ``|u_i|`` and push dimension ``i`` in the sign of ``u_i``
(``u_i = 0`` counts as positive). Only one dimension can be pushed per step, so the rule spends it
where the PD signal is largest. ``gain_v`` sets the braking: on the switching surface
``g − x = gain_v·v`` the error decays with time constant ``gain_v`` (time units, ``gain_v/Δt`` steps).

Per domain (:func:`scripted_controller_for`):

- :class:`~escort_rl.models.LightDark10D`, state ``s = (x[5], v[5])``, actions ``a = 2i`` push
  dimension ``i`` with ``+force`` and ``a = 2i+1`` with ``−force``: :class:`LightDarkPD`, exactly
  :func:`pd_action` on ``(x̂, v̂, model.goal)``. Success (``is_terminal``) is ``‖x − goal‖ < 0.5``.
- :class:`~escort_rl.models.MultiTargetTracking20D`, state ``[agent | target 1..4]`` with
  ``[x, y, vx, vy]`` per entity: the agent controls only its own acceleration (``accel`` along
  ``model.action_directions[a]``, default ``+x, −x, +y, −y``), and success is the *agent* within
  ``success_radius`` of ``model.goal``; the targets only enter the reward (a collision penalty) and the
  observations. The natural analogue, :class:`MultiTargetPD`, is the same PD signal on the agent's
  position ``s[0:2]`` and velocity ``s[2:4]`` toward the goal, with the action whose acceleration
  direction best aligns with it, ``argmax_a ⟨dir_a, u⟩``. For the default action set this is
  exactly :func:`pd_action` (``+x, −x, +y, −y`` is the ``2i`` / ``2i+1`` encoding with ``k = 2``);
  for other direction sets it stays well defined. It ignores the targets: it does not steer around
  them (the collision penalty costs reward, not success) and does not aim the camera (the heading is
  the chosen direction). The targets' belief therefore does not affect its actions; only the belief
  over the agent's own position and velocity does.
- :class:`~escort_rl.models.HiddenGoal`: :class:`HeaviestModeController`, which reads the whole belief,
  not its mean (the mean of a belief split among candidate goals lies between them, where no goal is):
  it commits to the heaviest mode's goal, or, with ``confidence > 0``, goes to the beacon first while no
  mode weighs that much. Committing at once reaches the goal in about ``1/M`` of the episodes (at a
  wrong candidate nothing the agent sees tells it so): the baseline a learner beats by looking first.
- :class:`~escort_rl.models.KidnappedRobot20D`: no scripted controller. The domain has no goal, its
  reward is ``−1`` every step whatever the action, and ``is_terminal`` is always False: the task is
  localisation, and a controller that "drives the belief-mean position toward the goal" has no goal
  to drive to (and nothing in the return to improve). :func:`scripted_controller_for` raises a
  ``ValueError`` that says so.

Policies (TensorDict in, TensorDict out, so they drop into ``env.rollout(T, policy)`` and TorchRL's
``Collector``): :class:`ScriptedBeliefController` reads the particles ``[*B, N, d]`` (and their log
weights ``[*B, N]``) that :class:`escort_rl.transforms.BeliefTransform` writes and acts on the
weighted mean ``Σ_n softmax(log w)_n · x_n``; :class:`TrueStateController` reads ``"true_state"``
``[*B, d]`` (what :class:`escort_rl.envs.POMDPEnv` writes, for evaluation only).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor

from escort_rl.models.hidden_goal import HiddenGoal
from escort_rl.models.kidnapped_robot import KidnappedRobot20D
from escort_rl.models.light_dark import LightDark10D
from escort_rl.models.light_dark_continuous import LightDark10DContinuous
from escort_rl.models.multi_target import MultiTargetTracking20D
from escort_rl.models.protocol import action_shape, is_continuous

DEFAULT_GAIN_V = 3.0

__all__ = [
    "DEFAULT_GAIN_V",
    "HeaviestModeController",
    "LightDarkContinuousPD",
    "LightDarkPD",
    "MultiTargetPD",
    "ScriptedBeliefController",
    "TrueStateController",
    "action_for_push",
    "belief_mean",
    "controlled_dims",
    "direction_action",
    "pd_action",
    "pd_signal",
    "push_of_action",
    "scripted_controller_for",
]


# ---------------------------------------------------------------------- the PD rule
def _check_gain(gain_v: float) -> float:
    if isinstance(gain_v, bool) or not isinstance(gain_v, (int, float)) or not math.isfinite(gain_v) or gain_v < 0:
        raise ValueError(f"gain_v: must be a finite number >= 0, got {gain_v!r}")
    return float(gain_v)


def pd_signal(position_estimate: Tensor, velocity_estimate: Tensor, goal: Tensor,
              gain_v: float = DEFAULT_GAIN_V) -> Tensor:
    """``u = (goal − x̂) − gain_v·v̂``. Shapes broadcast, ``[*B, k]`` -> ``[*B, k]``."""
    goal = torch.as_tensor(goal, dtype=position_estimate.dtype, device=position_estimate.device)
    return (goal - position_estimate) - gain_v * velocity_estimate


def action_for_push(dim: Tensor, positive: Tensor) -> Tensor:
    """The discrete action that pushes dimension ``dim`` up (``positive``) or down: ``2·dim`` or
    ``2·dim + 1`` (Light-Dark 10D's encoding, and Multi-Target Tracking's default ``+x, −x, +y, −y``)."""
    return (2 * dim.long() + (~positive.bool()).long()).long()


def push_of_action(action: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse of :func:`action_for_push`: ``(dim, positive)`` = ``(a // 2, a even)``."""
    action = action.long()
    return torch.div(action, 2, rounding_mode="floor"), action % 2 == 0


def pd_action(position_estimate: Tensor, velocity_estimate: Tensor, goal: Tensor,
              gain_v: float = DEFAULT_GAIN_V) -> Tensor:
    """The PD action: push the dimension with the largest ``|u_i|`` in the sign of ``u_i``.

    Args:
        position_estimate, velocity_estimate: ``x̂``, ``v̂``: ``[*B, k]``.
        goal: ``[k]`` (or broadcastable to ``[*B, k]``).
        gain_v: the velocity (derivative) gain, ``>= 0``.

    Returns:
        int64 ``[*B]``: ``2i`` to push dimension ``i`` up, ``2i + 1`` to push it down (``u_i = 0``
        pushes up; ties in ``|u_i|`` go to the lowest ``i``).
    """
    gain_v = _check_gain(gain_v)
    if position_estimate.shape[-1:] != velocity_estimate.shape[-1:]:
        raise ValueError(f"pd_action: position_estimate {tuple(position_estimate.shape)} and velocity_estimate "
                         f"{tuple(velocity_estimate.shape)} must have the same last dimension")
    u = pd_signal(position_estimate, velocity_estimate, goal, gain_v)
    dim = u.abs().argmax(-1, keepdim=True)
    positive = torch.gather(u, -1, dim) >= 0
    return action_for_push(dim.squeeze(-1), positive.squeeze(-1))


def direction_action(u: Tensor, directions: Tensor) -> Tensor:
    """The action whose direction best aligns with ``u``: ``argmax_a ⟨directions_a, u⟩``.

    ``u``: ``[*B, k]``, ``directions``: ``[n_actions, k]`` -> int64 ``[*B]`` (ties go to the lowest
    action). For the directions ``+e_0, −e_0, +e_1, −e_1, …`` it equals :func:`pd_action`'s choice.
    """
    scores = u @ directions.to(dtype=u.dtype, device=u.device).T
    return scores.argmax(-1).long()


def belief_mean(particles: Tensor, log_weights: Tensor | None = None) -> Tensor:
    """``Σ_n softmax(log_weights)_n · particles_n``: ``[*B, N, d]`` (and ``[*B, N]``) -> ``[*B, d]``.
    Without log weights, the plain mean. The log weights need not be normalised."""
    if log_weights is None:
        return particles.mean(-2)
    w = torch.softmax(log_weights.to(particles.dtype), dim=-1)
    return (w.unsqueeze(-1) * particles).sum(-2)


# ---------------------------------------------------------------------- per-domain controllers
def controlled_dims(model) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The state indices the domain's scripted controller reads: ``(position, velocity)``.
    Light-Dark 10D: ``s[:5]``, ``s[5:10]``; Multi-Target Tracking 20D: the agent's ``s[0:2]``,
    ``s[2:4]``; other models: ``ValueError`` (as :func:`scripted_controller_for`)."""
    if isinstance(model, LightDark10D):
        k = int(model.n_pos)
        return tuple(range(k)), tuple(range(k, 2 * k))
    if isinstance(model, MultiTargetTracking20D):
        return (0, 1), (2, 3)
    scripted_controller_for(model)  # raises the domain's reason
    raise ValueError(f"controlled_dims: no scripted controller for {type(model).__name__}")


class LightDarkPD:
    """Light-Dark 10D: :func:`pd_action` on ``x̂ = s[..., :5]``, ``v̂ = s[..., 5:10]`` toward
    ``model.goal``. Call it on a state estimate ``[*B, 10]`` to get actions int64 ``[*B]``."""

    def __init__(self, model: LightDark10D, gain_v: float = DEFAULT_GAIN_V) -> None:
        self.model, self.gain_v = model, _check_gain(gain_v)
        self.n_pos = int(model.n_pos)

    def __call__(self, state: Tensor) -> Tensor:
        pos, vel = controlled_dims(self.model)
        return pd_action(state[..., list(pos)], state[..., list(vel)], self.model.goal, self.gain_v)


class LightDarkContinuousPD:
    """Continuous Light-Dark 10D (:class:`~escort_rl.models.LightDark10DContinuous`): the PD law applied
    directly, ``a = clip(u, −force, force)`` with ``u = (g − x̂) − gain_v·v̂`` on every coordinate at
    once (the discrete rule can push only the largest). Far from the goal it pushes every coordinate at
    full force, and it brakes on the same switching surface ``g − x = gain_v·v``.
    ``[*B, 2·n_pos]`` -> float ``[*B, n_pos]``."""

    def __init__(self, model: LightDark10DContinuous, gain_v: float = DEFAULT_GAIN_V) -> None:
        self.model, self.gain_v = model, _check_gain(gain_v)

    def __call__(self, state: Tensor) -> Tensor:
        pos, vel = controlled_dims(self.model)
        u = pd_signal(state[..., list(pos)], state[..., list(vel)], self.model.goal, self.gain_v)
        low, high = (b.to(u.device, u.dtype) for b in (self.model.action_low, self.model.action_high))
        return u.clamp(low, high)


class MultiTargetPD:
    """Multi-Target Tracking 20D: the PD signal on the *agent* (position ``s[..., 0:2]``, velocity
    ``s[..., 2:4]``) toward ``model.goal``, and the action ``argmax_a ⟨model.action_directions_a, u⟩``
    (:func:`pd_action` for the default ``+x, −x, +y, −y``). The targets are ignored: success is the
    agent reaching the goal; see the module docstring. ``[*B, 20]`` -> int64 ``[*B]``."""

    def __init__(self, model: MultiTargetTracking20D, gain_v: float = DEFAULT_GAIN_V) -> None:
        self.model, self.gain_v = model, _check_gain(gain_v)

    def __call__(self, state: Tensor) -> Tensor:
        pos, vel = controlled_dims(self.model)
        u = pd_signal(state[..., list(pos)], state[..., list(vel)], self.model.goal, self.gain_v)
        return direction_action(u, self.model.action_directions)


class HeaviestModeController:
    """The hidden goal (:class:`~escort_rl.models.HiddenGoal`): push toward the goal of the heaviest mode,
    or toward the beacon while no mode weighs ``confidence`` (in ``[0, 1]``; 0, the default, always commits).

    A mode is a candidate goal: each particle belongs to the candidate nearest its goal coordinates
    (``model.mode_of``), the heaviest candidate's weighted mean goal is the target, and the push goes to
    the coordinate where the target is farthest from the belief's mean position (:func:`pd_action` with no
    velocity). Called on a belief, ``particles [*B, N, 2d]`` and ``log_weights [*B, N]`` (or ``None``:
    equal weights) -> int64 ``[*B]``; ``reads_belief`` tells :class:`ScriptedBeliefController` to pass it.

    Example:
        >>> m = HiddenGoal(dim=3, modes=2)
        >>> HeaviestModeController(m)(m.initial_belief((4,), 50), None).shape
        torch.Size([4])
    """

    reads_belief = True

    def __init__(self, model: HiddenGoal, confidence: float = 0.0) -> None:
        if not 0.0 <= float(confidence) <= 1.0:
            raise ValueError(f"HeaviestModeController.confidence: must lie in [0, 1], got {confidence!r}")
        self.model, self.confidence = model, float(confidence)

    @property
    def rule(self) -> str:
        """What it does, in words (the evaluation's summary names it)."""
        look = (f", after the beacon while no mode weighs {self.confidence:g}" if self.confidence > 0 else "")
        return f"toward the goal of the heaviest mode of the same filter's belief{look}"

    def mode_weights(self, particles: Tensor, log_weights: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """The normalised weights ``[*B, N]``, each particle's mode ``[*B, N]`` and each mode's share of the
        belief ``[*B, M]`` (rows sum to 1)."""
        w = (torch.full(particles.shape[:-1], 1.0 / particles.shape[-2], dtype=particles.dtype,
                        device=particles.device) if log_weights is None
             else torch.softmax(log_weights.to(particles.dtype), dim=-1))
        mode = self.model.mode_of(particles[..., self.model.dim:])
        shares = torch.zeros(*particles.shape[:-2], self.model.candidate_goals.shape[0], dtype=particles.dtype,
                             device=particles.device).scatter_add_(-1, mode, w)
        return w, mode, shares

    def heaviest_goal(self, particles: Tensor, log_weights: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """The heaviest mode's share ``[*B]``, the weighted mean goal of its particles ``[*B, d]``, and the
        normalised weights ``[*B, N]``."""
        w, mode, shares = self.mode_weights(particles, log_weights)
        top_share, top = shares.max(-1)
        in_top = (mode == top.unsqueeze(-1)).to(particles.dtype) * w  # [*B, N]
        total = in_top.sum(-1, keepdim=True).clamp_min(1e-12)
        goal = (in_top.unsqueeze(-1) * particles[..., self.model.dim:]).sum(-2) / total
        return top_share, goal, w

    def __call__(self, particles: Tensor, log_weights: Tensor | None) -> Tensor:
        top_share, goal, w = self.heaviest_goal(particles, log_weights)
        beacon = self.model.beacon.to(particles.dtype).expand_as(goal)
        target = torch.where((top_share < self.confidence).unsqueeze(-1), beacon, goal)  # [*B, d]
        position = (w.unsqueeze(-1) * particles[..., : self.model.dim]).sum(-2)
        return pd_action(position, torch.zeros_like(position), target, gain_v=0.0)


def scripted_controller_for(model, gain_v: float = DEFAULT_GAIN_V, **options) -> Callable[[Tensor], Tensor]:
    """The scripted controller of ``model``'s domain: a callable from a state estimate ``[*B, d]`` to
    actions int64 ``[*B]`` (float ``[*B, action_dim]`` for continuous actions).

    - :class:`~escort_rl.models.LightDark10D` -> :class:`LightDarkPD`;
    - :class:`~escort_rl.models.LightDark10DContinuous` -> :class:`LightDarkContinuousPD` (real actions);
    - :class:`~escort_rl.models.MultiTargetTracking20D` -> :class:`MultiTargetPD`;
    - :class:`~escort_rl.models.HiddenGoal` -> :class:`HeaviestModeController`, committing at once unless
      ``options`` give its ``confidence`` (it has no velocity: ``gain_v`` does not apply);
    - :class:`~escort_rl.models.KidnappedRobot20D` -> ``ValueError``: the domain has no goal, a
      constant reward and no terminal state, so there is nothing for a goal-seeking rule to do;
    - anything else -> ``ValueError``.

    ``options``: keyword arguments of the domain's controller beyond the gain (the hidden goal's
    ``confidence``); a controller that takes none, or an unknown name, is a ``ValueError`` naming it.
    """
    gain_v = _check_gain(gain_v)
    if isinstance(model, HiddenGoal):
        unknown = sorted(set(options) - {"confidence"})
        if unknown:
            raise ValueError(f"scripted_controller_for: HeaviestModeController takes the option 'confidence', "
                             f"not {', '.join(map(repr, unknown))}")
        return HeaviestModeController(model, **options)
    if options:
        raise ValueError(f"scripted_controller_for: the scripted controller of {type(model).__name__} takes no "
                         f"options beyond its gain, got {', '.join(map(repr, sorted(options)))}")
    if isinstance(model, LightDark10DContinuous):
        return LightDarkContinuousPD(model, gain_v)
    if isinstance(model, LightDark10D):
        return LightDarkPD(model, gain_v)
    if isinstance(model, MultiTargetTracking20D):
        return MultiTargetPD(model, gain_v)
    name = type(model).__name__
    if isinstance(model, KidnappedRobot20D):
        raise ValueError(
            f"scripted_controller_for: no scripted controller for {name}: the domain has no goal "
            "(its reward is -1 every step whatever the action and is_terminal is always False; the task "
            "is localisation), so a rule that drives the belief-mean position toward a goal does not apply"
        )
    raise ValueError(
        f"scripted_controller_for: no scripted controller for {name}; supported models are "
        "LightDark10D, LightDark10DContinuous, MultiTargetTracking20D and HiddenGoal"
    )


# ---------------------------------------------------------------------- TorchRL policies
class _ScriptedPolicy(TensorDictModuleBase):
    """Shared plumbing: a per-domain controller from :func:`scripted_controller_for` (or one given)."""

    def __init__(self, model, action_key: str, gain_v: float,
                 controller: Callable[[Tensor], Tensor] | None) -> None:
        super().__init__()
        self.model = model
        self.action_key = action_key
        self.gain_v = _check_gain(gain_v)
        self.controller = controller if controller is not None else scripted_controller_for(model, gain_v)

    def _act(self, tensordict: TensorDictBase, particles: Tensor, log_weights: Tensor | None) -> TensorDictBase:
        """The controller's action on the belief (``particles [*B, N, d]``, ``log_weights [*B, N]`` or
        ``None``): on the belief itself for a controller that ``reads_belief``, else on its mean."""
        if getattr(self.controller, "reads_belief", False):
            action = self.controller(particles, log_weights)
        else:
            action = self.controller(belief_mean(particles, log_weights))
        action = action.to(torch.float32) if is_continuous(self.model) else action.to(torch.int64)
        tensordict.set(self.action_key, action.reshape(*particles.shape[:-2], *action_shape(self.model)))
        return tensordict


class ScriptedBeliefController(_ScriptedPolicy):
    """Acts on a particle belief with the domain's scripted controller: on its weighted mean, or on the
    belief itself for a controller that reads it (``reads_belief``, e.g. :class:`HeaviestModeController`).

    Keys (``*B`` the tensordict's batch shape): reads ``particles_key`` ``[*B, N, d]`` and, when
    present, ``log_weights_key`` ``[*B, N]`` (the mean is ``Σ_n softmax(log w)_n x_n``; without log
    weights, the plain mean); writes ``action_key`` int64 ``[*B]``. These are the keys
    :class:`escort_rl.transforms.BeliefTransform` writes, so the controller drops into
    ``env.rollout(T, policy)`` and ``torchrl.collectors.Collector`` for a
    ``TransformedEnv(POMDPEnv(model, ...), BeliefTransform(model, filter, N))``.

    Args:
        model: the env's model; it picks the controller (:func:`scripted_controller_for`; raises
            ``ValueError`` for a model without one, e.g. Kidnapped Robot 20D).
        particles_key, log_weights_key, action_key: the tensordict keys.
        gain_v: the velocity gain of the PD rule.
        controller: a callable ``[*B, d] -> [*B]`` to use instead of the model's default.
    """

    def __init__(self, model, particles_key: str = "particles", log_weights_key: str = "particle_log_weights",
                 action_key: str = "action", gain_v: float = DEFAULT_GAIN_V,
                 controller: Callable[[Tensor], Tensor] | None = None) -> None:
        super().__init__(model, action_key, gain_v, controller)
        self.particles_key, self.log_weights_key = particles_key, log_weights_key
        self.in_keys = [particles_key, log_weights_key]
        self.out_keys = [action_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        particles = tensordict.get(self.particles_key, None)
        if particles is None:
            raise KeyError(f"ScriptedBeliefController.particles_key: '{self.particles_key}' is not in the "
                           "tensordict; add a BeliefTransform to the env")
        d = self.model.state_dim
        if particles.dim() < 2 or particles.shape[-1] != d:
            raise ValueError(f"{self.particles_key}: expected shape [*B, N, {d}], got {tuple(particles.shape)}")
        log_weights = tensordict.get(self.log_weights_key, None)
        if log_weights is not None and log_weights.shape != particles.shape[:-1]:
            raise ValueError(f"{self.log_weights_key}: expected shape {tuple(particles.shape[:-1])}, "
                             f"got {tuple(log_weights.shape)}")
        return self._act(tensordict, particles, log_weights)


class TrueStateController(_ScriptedPolicy):
    """The same scripted controller on the true state: reads ``state_key`` (default
    ``"true_state"``, written by :class:`escort_rl.envs.POMDPEnv` for evaluation) ``[*B, d]`` and
    writes ``action_key`` int64 ``[*B]``. The full-information reference for
    :class:`ScriptedBeliefController`; not a policy for the partially observed task."""

    def __init__(self, model, state_key: str = "true_state", action_key: str = "action",
                 gain_v: float = DEFAULT_GAIN_V, controller: Callable[[Tensor], Tensor] | None = None) -> None:
        super().__init__(model, action_key, gain_v, controller)
        self.state_key = state_key
        self.in_keys = [state_key]
        self.out_keys = [action_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        state = tensordict.get(self.state_key, None)
        if state is None:
            raise KeyError(f"TrueStateController.state_key: '{self.state_key}' is not in the tensordict")
        d = self.model.state_dim
        if state.shape[-1:] != (d,):
            raise ValueError(f"{self.state_key}: expected shape [*B, {d}], got {tuple(state.shape)}")
        return self._act(tensordict, state.unsqueeze(-2), None)  # the true state as a one-particle belief
