"""Hidden goal: a goal among ``M`` candidates that only a beacon reveals, so the belief stays multi-modal
until the agent goes to look.

The state is ``s = (x, z)``: the agent's position ``x ∈ R^d`` and the goal's position ``z ∈ R^d``.
The goal does not move (up to a small drift); its prior is a mixture of ``M`` tight Gaussians at the
candidate goals ``c_j = (−1)^j · r · e_{⌊j/2⌋}`` (the ends of the first ``⌈M/2⌉`` axes, at distance
``r`` from the start). The agent sees its own position with a little noise everywhere, and the goal
only near the beacon at ``b = −β · e_{d−1}``:

    x' = x + step · u_a + N(0, σ_x² I),     z' = z + N(0, σ_z'² I)
    o  = (x' + N(0, σ_o² I),  ℓ(x') · z' + N(0, σ_g² I)),    ℓ(x) = exp(−‖x − b‖² / (2 w²))

where action ``a = 2i`` pushes coordinate ``i`` by ``+step`` and ``a = 2i + 1`` by ``−step``. Far from
the beacon ``ℓ ≈ 0``: the goal's reading is noise, every candidate explains it, and the posterior over
``z`` keeps the prior's ``M`` modes for as long as the agent stays away. Within about ``w`` of the
beacon the reading is ``z`` itself and one mode remains. The reward is ``−0.1 ‖x' − z'‖ − 0.1`` a
step; an episode ends when the agent is within ``success_radius`` of the goal.

What the knobs set:

- ``dim`` (``d``): the dimension of both the position and the goal, so the belief lives in ``2d``
  dimensions and its modes differ in ``d`` of them;
- ``modes`` (``M``): the number of candidate goals (at most ``2(d − 1)``: the last axis is the
  beacon's);
- ``beacon_distance`` (``β``) and ``beacon_width`` (``w``): how far the agent must travel before any
  action can break the symmetry, so how long the modes persist.

A controller that commits to the heaviest mode reaches the goal with probability about ``1/M`` (and
then waits at a wrong candidate, where nothing it sees tells it so); one that visits the beacon first
pays ``β`` steps and reaches the goal every time. The model's exact likelihood is a product of
Gaussians: the tests check it against a brute-force histogram of :meth:`HiddenGoal.observe` at low
dimension.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from escort_rl.config.errors import ConfigError
from escort_rl.config.params import HasParams, build_params, param
from escort_rl.models.gaussian import AdditiveGaussianTransition, GaussianNoise


@dataclass(frozen=True)
class HiddenGoalParams:
    """:class:`HiddenGoal`'s parameters (the module docstring gives the model they define).

    Attributes:
        dim: ``d``, the dimension of the agent's position and of the goal (the state has ``2d``).
        modes: ``M``, the number of candidate goals, ``2 ≤ M ≤ 2(d − 1)``.
        goal_distance: ``r``, the candidates' distance from the origin, where the agent starts.
        goal_spread: the standard deviation of each mode of the goal's prior.
        beacon_distance: ``β``, the beacon's distance from the origin along the last axis.
        beacon_width: ``w``, the length scale of the beacon's signal ``ℓ(x)``.
        step: the push of one action.
        position_noise_std: ``σ_x``, the process noise of the agent's position.
        goal_drift_std: ``σ_z'``, the goal's drift per step (small: the goal stays where it is).
        position_obs_std: ``σ_o``, the noise of the position reading.
        goal_obs_std: ``σ_g``, the noise of the goal reading.
        start_spread: the start is uniform in ``[−start_spread, start_spread]^d`` (and so is the
            prior belief's position).
        success_radius: the episode ends when ``‖x − z‖`` is below it.
    """

    dim: int = param(5, ge=2)
    modes: int = param(4, ge=2)
    goal_distance: float = param(3.0, gt=0)
    goal_spread: float = param(0.1, gt=0)
    beacon_distance: float = param(3.0, ge=0)
    beacon_width: float = param(1.0, gt=0)
    step: float = param(0.5, gt=0)
    position_noise_std: float = param(0.1, gt=0)
    goal_drift_std: float = param(0.01, gt=0)
    position_obs_std: float = param(0.2, gt=0)
    goal_obs_std: float = param(0.3, gt=0)
    start_spread: float = param(0.5, ge=0)
    success_radius: float = param(0.5, gt=0)


class HiddenGoal(AdditiveGaussianTransition, HasParams):
    """The hidden-goal family (module docstring). Takes :class:`HiddenGoalParams` (or its fields as
    keyword arguments) and ``device``. State ``[*S, 2d]`` (position, then goal), observation
    ``[*S, 2d]`` (position reading, then goal reading), actions int64 ``[*S]`` in ``[0, 2d)``.

    Example:
        >>> m = HiddenGoal(dim=5, modes=4)
        >>> m.state_dim, m.obs_dim, m.n_actions, tuple(m.candidate_goals.shape)
        (10, 10, 10, (4, 5))
    """

    Params = HiddenGoalParams

    def __init__(self, params: HiddenGoalParams | None = None, *, device: torch.device | str | None = None,
                 **kwargs) -> None:
        self.params = p = build_params(HiddenGoalParams, params, kwargs, owner=type(self).__name__)
        d = p.dim
        if p.modes > 2 * (d - 1):
            raise ConfigError(f"{type(self).__name__}.modes: at most 2·(dim − 1) = {2 * (d - 1)} candidate goals "
                              f"fit on the axes the beacon leaves free, got {p.modes}; raise dim or lower modes")
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        f32 = dict(dtype=torch.float32, device=self.device)
        self.dim = d
        self.state_dim, self.obs_dim, self.n_actions = 2 * d, 2 * d, 2 * d
        self.position_dims, self.goal_dims = tuple(range(d)), tuple(range(d, 2 * d))
        goals = torch.zeros(p.modes, d, **f32)
        for j in range(p.modes):
            goals[j, j // 2] = p.goal_distance if j % 2 == 0 else -p.goal_distance
        self.candidate_goals = goals  # [M, d]
        self.beacon = torch.zeros(d, **f32)
        self.beacon[d - 1] = -p.beacon_distance
        stds = torch.tensor([p.position_noise_std] * d + [p.goal_drift_std] * d, **f32)
        self._process = GaussianNoise(torch.diag(stds))
        self._pushes = torch.zeros(2 * d, 2 * d, **f32)  # [n_actions, 2d]: what each action adds to the state
        for a in range(2 * d):
            self._pushes[a, a // 2] = p.step if a % 2 == 0 else -p.step

    # ------------------------------------------------------------------ for the benchmarks
    @property
    def state_parts(self) -> dict[str, tuple[int, ...]]:
        """The parts the benchmarks compare beliefs on: the goal first (the multi-modal part), then the position."""
        return {"goal": self.goal_dims, "position": self.position_dims}

    behaviour_description = ("toward the beacon: each step, with probability 1/2, the push along the beacon's axis "
                             "toward it, else a uniform random action; the goal's modes fade as the agent nears it")

    def behaviour_action(self, s: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """The benchmarks' behaviour policy (:attr:`behaviour_description`) in state ``s`` ``[2d]`` -> int64
        ``[]``: the walk toward the beacon, slowed by random steps, so that a trajectory's posterior over the
        goal goes from the prior's ``M`` modes to one over some ``2β / step`` steps."""
        d = self.dim
        toward = 2 * (d - 1) + int(bool(s[d - 1] > self.beacon[d - 1]))  # push the last axis toward the beacon
        coin, draw = torch.rand(2, generator=generator, device=self.device)
        return torch.tensor(toward if coin < 0.5 else min(int(draw * self.n_actions), self.n_actions - 1),
                            dtype=torch.int64, device=self.device)

    # ------------------------------------------------------------------ Rao-Blackwellised posterior
    # Given the agent's path, the goal is a linear-Gaussian state (z' = z + noise, o_z = ℓ(x') z' + noise)
    # under a Gaussian-sum prior: its posterior is M Kalman filters with exact mode weights. A reference
    # then samples the position alone (escort_rl.metrics.rao_blackwell).
    @property
    def rao_blackwell_dims(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """``(position dims, goal dims)``: the sampled part and the part in closed form."""
        return self.position_dims, self.goal_dims

    def rao_blackwell_prior(self, batch: int, n: int, generator: torch.Generator | None = None):
        """``n`` prior positions per belief (uniform in the start box) ``[B, n, d]``, each with the goal's
        prior: ``M`` equally weighted modes at the candidates, variance ``goal_spread²``. float64."""
        p, d, m = self.params, self.dim, self.params.modes
        f64 = dict(dtype=torch.float64, device=self.device)
        x = p.start_spread * (2.0 * torch.rand(batch, n, d, generator=generator, **f64) - 1.0)
        means = self.candidate_goals.double().expand(batch, n, m, d).clone()
        log_w = torch.full((batch, n, m), -math.log(m), **f64)
        return x, log_w, means, torch.full((batch, n, d), p.goal_spread ** 2, **f64)

    def rao_blackwell_step(self, x: Tensor, log_w: Tensor, means: Tensor, var: Tensor, a: Tensor, o: Tensor,
                           generator: torch.Generator | None = None):
        """One exact step given each particle's path. The position moves by the optimal proposal given the
        position reading, ``x' ~ N(v (x̄/σ_x² + o_x/σ_o²), v I)``, ``x̄ = x + step·u_a``, ``v = (σ_x⁻² + σ_o⁻²)⁻¹``,
        with weight ``N(o_x; x̄, (σ_x² + σ_o²) I)``; then each goal mode's Kalman update with ``ℓ = ℓ(x')``
        (:meth:`_goal_update`), whose evidence joins the particle's weight.
        ``x`` ``[B, n, d]``, ``log_w`` ``[B, n, M]``, ``means`` ``[B, n, M, d]``, ``var`` ``[B, n, d]``,
        ``a`` ``[B]``, ``o`` ``[B, 2d]``; returns the same and the log incremental weight ``[B, n]``."""
        p, d = self.params, self.dim
        o = o.double()
        ox = o[..., :d].unsqueeze(-2)
        pred = x + self._pushes.double()[a.long()][..., :d].unsqueeze(-2)
        sx2, so2 = p.position_noise_std ** 2, p.position_obs_std ** 2
        log_inc = -0.5 * (((ox - pred) ** 2).sum(-1) / (sx2 + so2) + d * math.log(2 * math.pi * (sx2 + so2)))
        x_new = self._position_proposal(pred, ox, generator)
        log_w, means, var, evidence = self._goal_update(x_new, log_w, means, var, o[..., d:])
        return x_new, log_w, means, var, log_inc + evidence

    def rao_blackwell_first_step(self, batch: int, n: int, a: Tensor, o: Tensor,
                                 generator: torch.Generator | None = None):
        """The prior and the first step in one, fully adapted to the first position reading: each coordinate
        of the start ``x₀`` from its posterior given it (the start box's uniform prior times
        ``N(o_x; x₀ + step·u_a, σ_x² + σ_o²)``: a truncated Gaussian, by inverting its CDF), then
        :meth:`rao_blackwell_step`'s proposal and goal update. The position part of the weight is then the
        same for every particle, and only the goal's evidence weighs them: in ``d`` dimensions, prior draws
        weighted by the reading keep about ``0.7^d`` of their ESS. Same returns as :meth:`rao_blackwell_step`."""
        p, d = self.params, self.dim
        o = o.double()
        ox = o[..., :d].unsqueeze(-2)  # [B, 1, d]
        push = self._pushes.double()[a.long()][..., :d].unsqueeze(-2)
        sx2, so2 = p.position_noise_std ** 2, p.position_obs_std ** 2
        centre, scale = ox - push, math.sqrt(sx2 + so2)
        lo = torch.special.ndtr((-p.start_spread - centre) / scale)
        hi = torch.special.ndtr((p.start_spread - centre) / scale)
        u = torch.rand(batch, n, d, generator=generator, dtype=torch.float64, device=self.device)
        q = (lo + u * (hi - lo)).clamp(1e-300, 1 - 1e-16)
        x0 = (centre + scale * torch.special.ndtri(q)).clamp(-p.start_spread, p.start_spread)
        _, log_w, means, var = self.rao_blackwell_prior(batch, n, generator)
        x_new = self._position_proposal(x0 + push, ox, generator)
        return (x_new, *self._goal_update(x_new, log_w, means, var, o[..., d:]))

    def _position_proposal(self, pred: Tensor, ox: Tensor, generator: torch.Generator | None) -> Tensor:
        """``x' ~ N(v (x̄/σ_x² + o_x/σ_o²), v I)``: the position given its prediction ``x̄`` and reading ``o_x``."""
        p = self.params
        sx2, so2 = p.position_noise_std ** 2, p.position_obs_std ** 2
        v = 1.0 / (1.0 / sx2 + 1.0 / so2)
        eps = torch.randn(pred.shape, generator=generator, dtype=pred.dtype, device=pred.device)
        return v * (pred / sx2 + ox / so2) + math.sqrt(v) * eps

    def _goal_update(self, x_new: Tensor, log_w: Tensor, means: Tensor, var: Tensor, oz: Tensor):
        """Each goal mode's Kalman update given the position ``x'``, ``ℓ = ℓ(x')``: ``P = v_z + σ_z'²``,
        ``S = ℓ² P + σ_g²``, ``m' = m + (ℓP/S)(o_z − ℓm)``, ``v_z' = P σ_g² / S``; the modes reweighted by
        ``N(o_z; ℓ m, S I)``. Returns ``(log_w, means, var, log evidence [B, n])``."""
        p = self.params
        ell = self.signal(x_new)[..., None, None]  # [B, n, 1, 1]
        big_p = (var + p.goal_drift_std ** 2).unsqueeze(-2)  # [B, n, 1, d]
        s = ell * ell * big_p + p.goal_obs_std ** 2
        resid = oz[:, None, None, :] - ell * means  # [B, n, M, d]
        joint = log_w - 0.5 * (resid * resid / s + torch.log(2 * math.pi * s)).sum(-1)
        evidence = torch.logsumexp(joint, -1)
        gain = ell * big_p / s
        return (joint - evidence.unsqueeze(-1), means + gain * resid, (big_p * p.goal_obs_std ** 2 / s).squeeze(-2),
                evidence)

    # ------------------------------------------------------------------ the beacon
    def signal(self, x: Tensor) -> Tensor:
        """``ℓ(x) = exp(−‖x − b‖² / (2 w²))`` in ``(0, 1]``: how much of the goal the sensor sees at
        position ``x`` ``[*S, d]`` -> ``[*S]``."""
        diff = x - self.beacon.to(x.dtype)
        return torch.exp(-0.5 * (diff * diff).sum(-1) / self.params.beacon_width ** 2)

    def mode_of(self, goal: Tensor) -> Tensor:
        """The index of the candidate nearest each goal position ``[*S, d]`` -> int64 ``[*S]``."""
        sq = ((goal.unsqueeze(-2) - self.candidate_goals.to(goal.dtype)) ** 2).sum(-1)  # [*S, M]
        return sq.argmin(-1)

    # ------------------------------------------------------------------ protocol
    def _starts(self, shape: tuple[int, ...], generator: torch.Generator | None) -> Tensor:
        """``[*shape, 2d]`` draws of the start distribution: a position uniform in the start box and a
        goal from the prior mixture."""
        p, d = self.params, self.dim
        u = torch.rand(*shape, d, generator=generator, device=self.device)
        x = p.start_spread * (2.0 * u - 1.0)
        j = torch.randint(0, p.modes, shape, generator=generator, device=self.device)
        z = self.candidate_goals[j] + p.goal_spread * torch.randn(*shape, d, generator=generator, device=self.device)
        return torch.cat([x, z], dim=-1)

    def initial_state(self, shape: tuple[int, ...], generator: torch.Generator | None = None) -> Tensor:
        """``[*shape, 2d]``: the start position and the hidden goal."""
        return self._starts(tuple(shape), generator)

    def initial_belief(self, shape: tuple[int, ...], n: int, generator: torch.Generator | None = None) -> Tensor:
        """``[*shape, n, 2d]`` draws of the prior: the ``M`` goal modes, equally likely."""
        return self._starts((*shape, n), generator)

    def transition_mean(self, s: Tensor, a: Tensor) -> Tensor:
        """``s + step · u_a`` (the goal does not move on average). ``[*S, 2d]``."""
        return s + self._pushes.to(s.dtype)[a.long()]

    def observe(self, s_next: Tensor, a: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """``o = (x' + σ_o ε, ℓ(x') z' + σ_g ε')``: ``[*S, 2d]`` -> ``[*S, 2d]``."""
        p, d = self.params, self.dim
        x, z = s_next[..., :d], s_next[..., d:]
        eps = torch.randn(s_next.shape, generator=generator, device=s_next.device, dtype=s_next.dtype)
        return torch.cat([x + p.position_obs_std * eps[..., :d],
                          self.signal(x).unsqueeze(-1) * z + p.goal_obs_std * eps[..., d:]], dim=-1)

    def observation_log_prob(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor:
        """``log N(o_x; x', σ_o² I) + log N(o_z; ℓ(x') z', σ_g² I)``. Broadcasts; ``[*S]``."""
        p, d = self.params, self.dim
        x, z = s_next[..., :d], s_next[..., d:]
        ex, ez = o[..., :d] - x, o[..., d:] - self.signal(x).unsqueeze(-1) * z
        norm = -d * (math.log(p.position_obs_std) + math.log(p.goal_obs_std) + math.log(2 * math.pi))
        return norm - 0.5 * ((ex * ex).sum(-1) / p.position_obs_std ** 2 + (ez * ez).sum(-1) / p.goal_obs_std ** 2)

    def observation_score(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor:
        """``∇_{s'} log O(o | s')`` in closed form (what autograd gives :meth:`observation_log_prob`):

            ∇_x = (o_x − x)/σ_o² − ℓ (eᵀz / σ_g²) (x − b)/w²,     ∇_z = ℓ e / σ_g²,

        with ``e = o_z − ℓ z`` and ``∇ℓ = −ℓ (x − b)/w²``. ``[*S, 2d]``."""
        p, d = self.params, self.dim
        x, z = s_next[..., :d], s_next[..., d:]
        ell = self.signal(x).unsqueeze(-1)
        ez = (o[..., d:] - ell * z) / p.goal_obs_std ** 2
        grad_x = (o[..., :d] - x) / p.position_obs_std ** 2 \
            - ell * (ez * z).sum(-1, keepdim=True) * (x - self.beacon.to(x.dtype)) / p.beacon_width ** 2
        return torch.cat([grad_x, ell * ez], dim=-1)

    def distance_to_goal(self, s: Tensor) -> Tensor:
        """``‖x − z‖``: ``[*S, 2d]`` -> ``[*S]``."""
        return torch.linalg.vector_norm(s[..., : self.dim] - s[..., self.dim:], dim=-1)

    def reward(self, s: Tensor, a: Tensor, s_next: Tensor) -> Tensor:
        """``−0.1 ‖x' − z'‖ − 0.1``, as Light-Dark's."""
        return -0.1 * self.distance_to_goal(s_next) - 0.1

    def is_terminal(self, s: Tensor) -> Tensor:
        """Success: the agent within ``success_radius`` of the goal."""
        return self.distance_to_goal(s) < self.params.success_radius

    @property
    def action_coordinates(self) -> tuple[tuple[int, int], ...]:
        """``(x_i, z_i)`` for the pair of actions ``2i``, ``2i + 1`` that pushes coordinate ``i``: what a
        per-coordinate policy head reads for that pair (``actor.head=per_coordinate``)."""
        return tuple((i, self.dim + i) for i in range(self.dim))
