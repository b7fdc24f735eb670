"""POMCPOW: Partially Observable Monte Carlo Planning with Observation Widening
(Sunberg & Kochenderfer, ICAPS 2018), for discrete actions, on the :class:`POMDPModel` protocol.

The tree alternates belief nodes ``h`` (the root, or an observation node ``hao``) and action nodes
``ha``. One simulation starts from a root state ``s ~ b`` and runs, as in the paper's Algorithm 3:

    SIMULATE(s, h, d):
        if d = 0 or s is terminal: return 0
        a  ← ACTION-PROGRESSIVE-WIDENING(h)            (UCB over the children of h)
        s', r ← G(s, a)
        if |C(ha)| ≤ k_o · N(ha)^α_o:                  (observation widening)
            o ← O(s', a); add a new observation node hao to C(ha)
        else:
            o ← an existing child of ha, picked with probability M(hao) / Σ M(hao')
        append (s', r) to B(hao) with weight Z(o | s, a, s')  (observation_log_prob)
        if hao is new:
            total ← r + γ · V̂(s', d − 1)                   (rollout or heuristic leaf value)
        else:
            (s', r) ← draw from B(hao) with probability ∝ W(hao)
            total ← r + γ · SIMULATE(s', hao, d − 1)
        N(h) += 1;  N(ha) += 1;  Q(ha) += (total − Q(ha)) / N(ha)
        return total

ACTION-PROGRESSIVE-WIDENING(h): while ``|C(h)| ≤ k_a · N(h)^α_a`` and some action is untried, add one
untried action, drawn uniformly (so the order of the actions is random); then return the child that
maximises the UCB score ``Q(ha) + c · sqrt(log N(h) / N(ha))``, a child not yet visited first.
The decision is ``argmax_a Q(ha)`` over the root's children.

Observations are continuous, so two generated observations never coincide: every observation
child has ``M(hao) = 1`` and the pick among existing children is uniform.

What is batched: the root states (one weighted draw of all of them from the belief) and the
rollouts (``rollout_count`` random rollouts from a leaf run as one batch per step). The tree walk
itself is sequential by nature: it calls the model on single states ``[d]`` and keeps the tree in
Python lists. Discrete choices inside the tree (observation child, particle, untried action) use a
Python ``random.Random`` seeded from the torch generator, so a seeded plan is reproducible.
"""

from __future__ import annotations

import math
import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Optional

import torch
from torch import Tensor

from escort_rl.config.errors import ConfigError
from escort_rl.config.params import HasParams, build_params, param
from escort_rl.models.protocol import check_model

LeafValue = Callable[[Tensor, int], float]
"""A heuristic value ``V̂(s', d)`` of a state ``[d]`` with ``d`` steps of the search horizon left."""


# ------------------------------------------------------------------------------------- the tree
@dataclass
class ActionNode:
    """``ha``: an action tried at a belief node.

    ``visits`` is ``N(ha)``, ``value`` is ``Q(ha)`` (the running mean of the discounted returns of the
    simulations through it) and ``children`` is ``C(ha)``, the observation nodes.
    """

    action: int
    visits: int = 0
    value: float = 0.0
    children: list[BeliefNode] = field(default_factory=list)


@dataclass
class BeliefNode:
    """``h``: the root (``observation is None``) or an observation node ``hao``.

    An observation node holds the weighted particle collection ``B(hao)``: next states ``[d]``, the
    reward of the step that produced each, and log-weights ``log Z(o | s, a, s')``.
    ``visits`` is ``N(h)`` and ``children`` is ``C(h)``, the action nodes.
    """

    observation: Tensor | None = None
    next_states: list[Tensor] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    log_weights: list[float] = field(default_factory=list)
    visits: int = 0
    children: list[ActionNode] = field(default_factory=list)


@dataclass(frozen=True)
class Decision:
    """The outcome of one :meth:`POMCPOW.plan` call.

    Attributes:
        action: the chosen action, ``argmax_a Q(ha)`` at the root.
        q_values, visits: ``Q(ha)`` and ``N(ha)`` of the root's children, by action.
        simulations: how many simulations ran.
        tree_size: the number of nodes (belief and action nodes, the root included).
        seconds: wall-clock time of the call.
        root: the search tree, for inspection.
    """

    action: int
    q_values: dict[int, float]
    visits: dict[int, int]
    simulations: int
    tree_size: int
    seconds: float
    root: BeliefNode


# ------------------------------------------------------------------------------------- pure helpers
def widening_allows(n_children: int, visits: int, k: float, alpha: float) -> bool:
    """Progressive widening: a node may add a child while ``|children| ≤ k · N^α``."""
    return n_children <= k * visits**alpha


def ucb_score(q_value: float, child_visits: int, parent_visits: int, exploration_constant: float) -> float:
    """``Q(ha) + c · sqrt(log N(h) / N(ha))``; ``+inf`` for a child not yet visited."""
    if child_visits == 0:
        return math.inf
    return q_value + exploration_constant * math.sqrt(math.log(max(parent_visits, 1)) / child_visits)


def sample_index(log_weights: list[float], rng: random.Random) -> int:
    """An index drawn with probability ``∝ exp(log_weights)`` (uniform if every weight is zero)."""
    top = max(log_weights)
    if top == -math.inf:
        return rng.randrange(len(log_weights))
    return rng.choices(range(len(log_weights)), weights=[math.exp(w - top) for w in log_weights])[0]


def sample_root_states(particles: Tensor, log_weights: Tensor, count: int,
                       generator: torch.Generator | None) -> Tensor:
    """``count`` states drawn with replacement from the belief, ``P(i) = softmax(log_weights)_i``.

    ``particles`` ``[N, d]``, ``log_weights`` ``[N]`` -> ``[count, d]``.
    """
    probs = torch.softmax(log_weights.to(torch.float64), dim=-1)
    idx = torch.multinomial(probs, count, replacement=True, generator=generator)
    return particles[idx]


def random_rollout_value(model, state: Tensor, horizon: int, count: int, discount: float,
                         generator: torch.Generator | None) -> float:
    """The mean discounted return of ``count`` uniform-random rollouts of ``horizon`` steps from
    ``state`` ``[d]``, run as one batch: ``V̂(s) = (1/R) Σ_r Σ_{t<H} γ^t r_t``, rewards after a terminal
    state counting as 0."""
    s = state.expand(count, -1)
    alive = ~model.is_terminal(s)
    total = torch.zeros(count, dtype=torch.float64, device=s.device)
    scale = 1.0
    for _ in range(horizon):
        if not bool(alive.any()):
            break
        a = torch.randint(model.n_actions, (count,), generator=generator, device=s.device)
        s_next = model.transition(s, a, generator)
        total += scale * torch.where(alive, model.reward(s, a, s_next).to(torch.float64), 0.0)
        alive = alive & ~model.is_terminal(s_next)
        s, scale = s_next, scale * discount
    return float(total.mean())


def count_nodes(node: BeliefNode) -> int:
    """The number of belief and action nodes in the subtree under ``node`` (``node`` included)."""
    return 1 + sum(1 + sum(count_nodes(child) for child in a.children) for a in node.children)


# ------------------------------------------------------------------------------------- the planner
@dataclass(frozen=True)
class POMCPOWParams:
    """:class:`POMCPOW`'s settings (``configs/planner/<domain>.yaml`` holds each domain's, with the
    paper's values marked there). ``leaf_value``, a callable set in code, is an argument of
    :class:`POMCPOW`, not a setting.

    Attributes:
        n_sim: simulations per decision; ``None`` runs until ``time_budget_s`` is spent.
        time_budget_s: wall-clock seconds per decision; ``None`` runs exactly ``n_sim`` simulations.
            With both set, whichever ends first stops the search. At least one simulation always
            runs; at least one of the two must be set.
        max_depth: the search horizon ``d_max`` in steps (tree plus rollout).
        exploration_constant: ``c`` in the UCB score ``Q(ha) + c · sqrt(log N(h) / N(ha))``.
        k_action, alpha_action: action widening, ``|C(h)| ≤ k_a · N(h)^α_a``.
        k_observation, alpha_observation: observation widening, ``|C(ha)| ≤ k_o · N(ha)^α_o``.
        discount: ``γ``.
        rollout_count: random rollouts per leaf, run as one batch; their mean is the leaf value.
    """

    n_sim: Optional[int] = param(100, ge=1)
    time_budget_s: Optional[float] = param(None, gt=0)
    max_depth: int = param(3, ge=1)
    exploration_constant: float = param(10.0, ge=0)
    k_action: float = param(4.0, gt=0)
    alpha_action: float = param(0.5, ge=0, le=1)
    k_observation: float = param(4.0, gt=0)
    alpha_observation: float = param(0.5, ge=0, le=1)
    discount: float = param(0.95, ge=0, le=1)
    rollout_count: int = param(8, ge=1)


def check_budget(p: POMCPOWParams) -> None:
    """Raise unless the search has a budget: ``n_sim``, ``time_budget_s`` or both."""
    if p.n_sim is None and p.time_budget_s is None:
        raise ConfigError("POMCPOW.n_sim: set n_sim (simulations per decision), time_budget_s, or both")


class POMCPOW(HasParams):
    """POMCPOW with double progressive widening for a model with discrete actions.

    Takes :class:`POMCPOWParams` (or its fields as keyword arguments) and ``leaf_value``, a
    heuristic ``V̂(s', d)`` used instead of rollouts (``None``: rollouts).
    """

    Params = POMCPOWParams

    def __init__(self, params: POMCPOWParams | None = None, *, leaf_value: LeafValue | None = None,
                 **kwargs) -> None:
        self.params = p = build_params(POMCPOWParams, params, kwargs, owner=type(self).__name__)
        check_budget(p)
        if leaf_value is not None and not callable(leaf_value):
            raise ConfigError(f"POMCPOW.leaf_value: must be a callable (state, depth) -> float or None, "
                              f"got {leaf_value!r}")
        self.exploration_constant = float(p.exploration_constant)
        self.k_action, self.alpha_action = float(p.k_action), float(p.alpha_action)
        self.k_observation, self.alpha_observation = float(p.k_observation), float(p.alpha_observation)
        self.discount, self.leaf_value = float(p.discount), leaf_value

    def __repr__(self) -> str:
        return (f"POMCPOW(n_sim={self.n_sim}, time_budget_s={self.time_budget_s}, max_depth={self.max_depth}, "
                f"exploration_constant={self.exploration_constant}, k_action={self.k_action}, "
                f"alpha_action={self.alpha_action}, k_observation={self.k_observation}, "
                f"alpha_observation={self.alpha_observation}, discount={self.discount}, "
                f"rollout_count={self.rollout_count})")

    @torch.no_grad()
    def plan(self, model, particles: Tensor, log_weights: Tensor | None = None,
             generator: torch.Generator | None = None) -> Decision:
        """Search from the belief ``(particles [N, d], log_weights [N])`` and pick an action.

        ``log_weights`` need not be normalised; ``None`` means equal weights. ``generator`` drives every
        random choice (it must live on the particles' device); with the same seed and ``n_sim`` mode
        the decision and the tree are the same.
        """
        check_model(model)
        log_weights = _check_belief(model, particles, log_weights)
        start = time.perf_counter()
        search = _Search(self, model, generator, particles.device)
        chunk = self.n_sim if self.n_sim is not None else 256
        root, simulations = BeliefNode(), 0
        while simulations == 0 or self._has_budget(simulations, time.perf_counter() - start):
            if simulations % chunk == 0:
                root_states = sample_root_states(particles, log_weights, chunk, generator)
            search.simulate(root_states[simulations % chunk], root, self.max_depth)
            simulations += 1
        if root.children:
            action = max(root.children, key=lambda child: child.value).action
        else:  # every sampled root state was terminal: no action changes anything
            action = search.rng.randrange(model.n_actions)
        return Decision(
            action=action,
            q_values={child.action: child.value for child in root.children},
            visits={child.action: child.visits for child in root.children},
            simulations=simulations,
            tree_size=count_nodes(root),
            seconds=time.perf_counter() - start,
            root=root,
        )

    def _has_budget(self, simulations: int, elapsed: float) -> bool:
        if self.n_sim is not None and simulations >= self.n_sim:
            return False
        return self.time_budget_s is None or elapsed < self.time_budget_s


class _Search:
    """One search: the planner's settings, the model and the random streams."""

    def __init__(self, planner: POMCPOW, model, generator: torch.Generator | None, device: torch.device) -> None:
        self.p, self.model, self.generator = planner, model, generator
        seed = int(torch.randint(2**62, (), generator=generator, device=device))
        self.rng = random.Random(seed)
        self.actions = [torch.tensor(a, device=device) for a in range(model.n_actions)]

    def simulate(self, s: Tensor, node: BeliefNode, depth: int) -> float:
        """One simulation from state ``s`` ``[d]`` at ``node`` with ``depth`` steps left; returns the
        discounted return and updates ``N(h)``, ``N(ha)``, ``Q(ha)`` on the way back."""
        model, p = self.model, self.p
        if depth == 0 or bool(model.is_terminal(s)):
            return 0.0
        action_node = self.widen_and_select_action(node)
        a = self.actions[action_node.action]
        s_next = model.transition(s, a, self.generator)
        r = float(model.reward(s, a, s_next))
        is_new = widening_allows(len(action_node.children), action_node.visits, p.k_observation, p.alpha_observation)
        if is_new:
            child = BeliefNode(observation=model.observe(s_next, a, self.generator))
            action_node.children.append(child)
        else:
            child = self.rng.choice(action_node.children)
        child.next_states.append(s_next)
        child.rewards.append(r)
        child.log_weights.append(float(model.observation_log_prob(child.observation, s_next, a)))
        if is_new:
            total = r + p.discount * self.leaf_value(s_next, depth - 1)
        else:
            i = sample_index(child.log_weights, self.rng)
            total = child.rewards[i] + p.discount * self.simulate(child.next_states[i], child, depth - 1)
        node.visits += 1
        action_node.visits += 1
        action_node.value += (total - action_node.value) / action_node.visits
        return total

    def widen_and_select_action(self, node: BeliefNode) -> ActionNode:
        """Add an untried action (uniformly drawn) while ``|C(h)| ≤ k_a · N(h)^α_a``, then pick the
        child with the largest UCB score."""
        p = self.p
        if len(node.children) < self.model.n_actions and widening_allows(
                len(node.children), node.visits, p.k_action, p.alpha_action):
            tried = {child.action for child in node.children}
            untried = [a for a in range(self.model.n_actions) if a not in tried]
            node.children.append(ActionNode(action=self.rng.choice(untried)))
        return max(node.children, key=lambda child: ucb_score(
            child.value, child.visits, node.visits, p.exploration_constant))

    def leaf_value(self, s: Tensor, depth: int) -> float:
        """``V̂(s, d)``: the planner's heuristic if it has one, else batched random rollouts."""
        if depth == 0:
            return 0.0
        if self.p.leaf_value is not None:
            return float(self.p.leaf_value(s, depth))
        return random_rollout_value(self.model, s, depth, self.p.rollout_count, self.p.discount, self.generator)


# ------------------------------------------------------------------------------------- validation
def _check_belief(model, particles: Tensor, log_weights: Tensor | None) -> Tensor:
    """Raise ``ValueError`` naming the field unless ``particles`` is ``[N, model.state_dim]`` and
    ``log_weights`` is ``[N]`` (or ``None``) with some finite weight; return the log-weights."""
    if not isinstance(particles, Tensor) or particles.dim() != 2 or particles.shape[0] < 1:
        shape = tuple(particles.shape) if isinstance(particles, Tensor) else type(particles).__name__
        raise ValueError(f"particles: expected one belief of shape [N, {model.state_dim}] with N >= 1, got {shape}; "
                         "plan one belief at a time (POMCPOWPolicy loops over a batch)")
    if particles.shape[1] != model.state_dim:
        raise ValueError(f"particles: last dimension is {particles.shape[1]} but model.state_dim is "
                         f"{model.state_dim}; pass the belief of this model")
    if not torch.isfinite(particles).all():
        raise ValueError("particles: contain NaN or Inf")
    n = particles.shape[0]
    if log_weights is None:
        return torch.zeros(n, device=particles.device)
    if not isinstance(log_weights, Tensor) or log_weights.shape != (n,):
        shape = tuple(log_weights.shape) if isinstance(log_weights, Tensor) else type(log_weights).__name__
        raise ValueError(f"log_weights: expected shape ({n},) (one per particle), got {shape}")
    if torch.isnan(log_weights).any() or torch.isposinf(log_weights).any() or torch.isneginf(log_weights).all():
        raise ValueError("log_weights: must hold no NaN or +inf and at least one finite value")
    return log_weights
