"""Multi-Target Tracking 20D (paper, Appendix "Domains: Multiple Target Tracking").

State ``s ∈ R^20`` (``state_dim = 20``), five entities of ``[x, y, vx, vy]`` each:

    s = [agent | target 1 | target 2 | target 3 | target 4],   entity e at indices 4e .. 4e+3

so the target positions are the indices :attr:`MultiTargetTracking20D.position_dims`
``(4, 5, 8, 9, 12, 13, 16, 17)`` and the agent position is ``(0, 1)``.

Actions ``a ∈ {0..n_actions-1}``: an acceleration of size ``accel`` along ``actions[a]``; the paper's
set (the default) is ``{+x, -x, +y, -y}``. The agent's camera faces the direction of the chosen
acceleration, so the action also sets the heading of the 60° field of view.

Dynamics (additive correlated Gaussian noise ``η ~ N(0, Σ)``, semi-explicit Euler as in Light-Dark):

    agent:    p' = p + Δt·v                 v' = (1 - λ)·v + accel·u_a + W(p)
    target i: p' = p + Δt·v                 v' = v + λ·(F(p) - v) + k_align·(v̄ - v) + R_i + W(p)

``λ`` is the damping (paper: 0.1). Targets are dragged toward the flow field ``F``, a circular
current about ``flow_center``: ``F(p) = ω·(-r_y, r_x) + 2κ·(1 - u)/(1 + u)·r`` with ``r = p - c``,
``u = ‖r‖²/R²`` (rotation plus a pull onto the ring of radius ``R``, of slope ``-2κ`` across the ring
and linear, ``-2κ·r``, far out); in still flow the drag is plain damping. The pull is kept linear far
out on purpose: a cubic pull ``κ(1 - u)·r`` makes the explicit step unstable beyond ``‖r‖ ≈ 14`` (a
particle that strays there, e.g. an unseen target's belief, is flung further out each step).
``v̄`` is the mean target velocity (flocking alignment). ``R_i = k_rep Σ_j relu(1 - d_ij/r)²·(p_i -
p_j)/d_ij`` is the collision repulsion between targets closer than ``r`` (paper: 1.0).
``W(p) = k_wall·(relu(-p) - relu(p - map_size))`` pushes entities back into the ``10×10`` map
(positions are never clipped, so the transition stays Gaussian).

Observation (``obs_dim = 14``, fixed size):

    o = [ox_a, oy_a,  m_1, ox_1, oy_1,  m_2, ox_2, oy_2,  m_3, ...,  m_4, ox_4, oy_4]

``(ox_a, oy_a) = p_a + σ_a·ε`` always (the paper observes the agent's own position). For slot ``i``:

1. the zone ``z`` of target ``i`` is drawn from a *soft* partition of the map, ``π_z(p_i)`` (a grid
   of cells whose edges are sigmoids of width ``zone_softness``; see :meth:`cell_log_probs`);
2. the target is detected (``m_i = 1``) with probability ``φ_i·ν_z``: ``ν_z`` is the zone's
   visibility (clear 1.0, limited 0.3, confusion 0.7, blind 0.0) and ``φ_i`` a smooth indicator that
   target ``i`` lies inside the 60° field of view (a sigmoid of ``cos θ - cos 30°`` of width
   ``fov_softness``);
3. when detected, with probability ``q_z`` (confusion 0.3, else 0) the slot reports the position of
   another target ``j ≠ i`` (an identity swap), ``j`` drawn with weights
   ``w_ij ∝ exp(-‖p_i - p_j‖²/(2ℓ²))`` (nearby targets get confused); otherwise ``j = i``;
4. ``(ox_i, oy_i) = p_j + σ_z·ε``, and ``(0, 0, 0)`` for ``(m_i, ox_i, oy_i)`` when not detected.

Slots are independent given ``s'``, as in the paper's ``P(o|s) = Π_i P(o_i | s_i, zone(s_i))``.
:meth:`observation_log_prob` is the exact density of this process: for each slot the mixture over
zones and (in zones with ``q_z > 0``) identity swaps, computed with log-sum-exp,

    m_i = 1:  log φ_i + log Σ_z π_z ν_z [(1 - q_z) N(o_i; p_i, σ_z²) + q_z Σ_{j≠i} w_ij N(o_i; p_j, σ_z²)]
    m_i = 0:  log(1 - φ_i Σ_z π_z ν_z) = log[(1 - φ_i) + φ_i Σ_z π_z (1 - ν_z)]

Choice (documented): detection is part of the likelihood through the smooth visibility ``φ_i·ν_z``,
so a missed detection is evidence too (a target not seen while in view is probably in the blind
zone). Every term is a log-sum-exp of finite numbers, so the density and its score in the state are
finite everywhere, including deep inside the blind zone and at zone boundaries; zones with
``ν_z = 0`` (resp. ``ν_z = 1``) are left out of the detected (resp. missed) sum instead of adding
``log 0``.

Reward (paper): ``r = -α‖p_a' - goal‖ - β - c·Σ_i 1[‖p_a' - p_i'‖ < δ]`` with ``α = 0.1``,
``β = 0.05``, ``δ = 0.5``, ``c = 1``; success (terminal) when ``‖p_a - goal‖ < 0.5``.

Process-noise correlations (paper): ``ρ(x, vx) = ρ(y, vy) = 0.8`` within every entity,
``ρ = 0.4`` between the same position coordinate of two targets and ``0.6`` between the same velocity
coordinate. That matrix is not PSD (smallest eigenvalue ≈ -0.306), so the model uses its nearest
correlation matrix (Higham 2002) with eigenvalues floored at 1e-3; :func:`describe_correlations`
prints both.

Every choice the paper leaves open (zone geometry, flow field, dt, acceleration, noise scales, start
distribution, goal, action set) is a parameter with its reason in
:class:`~escort_rl.models.multi_target_params.MultiTargetTracking20DParams`; the episode length is
``max_steps`` in ``configs/env/mtt20d.yaml``.
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F
from torch import Tensor

from escort_rl.config.params import HasParams, build_params
from escort_rl.models.gaussian import (
    AdditiveGaussianTransition,
    GaussianNoise,
    correlation_report,
    make_positive_definite,
    nearest_correlation_matrix,
    pair_rows,
)
from escort_rl.models.multi_target_params import (
    N_TARGETS,
    MultiTargetTracking20DParams,
    check_actions,
    check_edges,
    check_pair,
    check_target_start_centers,
    check_zone_grid,
    check_zone_tables,
)
from escort_rl.models.zone_grid import (
    bin_log_prob_grads,
    bin_log_probs,
    bin_log_sinh,
    cell_constants,
)

ENTITY_DIM = 4  # [x, y, vx, vy]
LOG_2PI = math.log(2 * math.pi)

# The scalar parameters, kept on the model as floats.
_FLOAT_FIELDS = (
    "map_size", "dt", "damping", "accel", "flow_rate", "flow_radius", "flow_attraction", "flocking_alignment",
    "repulsion_radius", "repulsion_gain", "wall_gain", "agent_obs_noise_std", "zone_softness", "fov_degrees",
    "fov_softness", "swap_length_scale", "success_radius", "distance_weight", "step_penalty", "collision_radius",
    "collision_penalty", "agent_start_halfwidth", "target_start_halfwidth",
)


def paper_correlations() -> Tensor:
    """The process-noise correlation matrix as the paper states it (``[20, 20]`` float64).

    Within each of the five entities ``ρ(x, vx) = ρ(y, vy) = 0.8``; between two different targets
    ``ρ(x_i, x_j) = ρ(y_i, y_j) = 0.4`` (positions) and ``ρ(vx_i, vx_j) = ρ(vy_i, vy_j) = 0.6``
    (velocities), read as same-axis pairs; everything else 0. Not PSD: on each axis the
    between-target contrasts have the block ``[[0.6, 0.8], [0.8, 0.4]]``, smallest eigenvalue
    ``0.5 - sqrt(0.65) ≈ -0.306``.
    """
    d = ENTITY_DIM * (N_TARGETS + 1)
    c = torch.eye(d, dtype=torch.float64)

    def put(i: int, j: int, r: float) -> None:
        c[i, j] = c[j, i] = r

    for e in range(N_TARGETS + 1):
        put(4 * e, 4 * e + 2, 0.8)
        put(4 * e + 1, 4 * e + 3, 0.8)
    for i in range(1, N_TARGETS + 1):
        for j in range(i + 1, N_TARGETS + 1):
            for k, r in ((0, 0.4), (1, 0.4), (2, 0.6), (3, 0.6)):
                put(4 * i + k, 4 * j + k, r)
    return c


@functools.lru_cache(maxsize=1)
def _used_correlations() -> Tensor:
    """The nearest correlation matrix of :func:`paper_correlations`, eigenvalues floored at 1e-3
    (computed once: Higham's iteration takes a few tenths of a second)."""
    return make_positive_definite(nearest_correlation_matrix(paper_correlations()))


def _state_names() -> list[str]:
    names = ["x_a", "y_a", "vx_a", "vy_a"]
    for i in range(1, N_TARGETS + 1):
        names += [f"x_t{i}", f"y_t{i}", f"vx_t{i}", f"vy_t{i}"]
    return names


def _softmax_and_logsumexp(x: Tensor) -> tuple[Tensor, Tensor]:
    """``softmax`` and ``logsumexp`` over a short last dimension in one pass: ``[*S, n]`` ->
    ``[*S, n]`` and ``[*S]``. Each row needs a finite entry (``-inf`` entries get weight 0). On a CPU
    these few elementwise ops are several times faster than ATen's kernels on rows of a few entries."""
    top = x.amax(-1, keepdim=True)
    e = torch.exp(x - top)
    total = e.sum(-1, keepdim=True)
    return e / total, (top + torch.log(total)).squeeze(-1)


class MultiTargetTracking20D(HasParams, AdditiveGaussianTransition):
    """The 20-D Multi-Target Tracking POMDP. All tensors are float32 on ``device``.

    Takes :class:`~escort_rl.models.multi_target_params.MultiTargetTracking20DParams` (or its
    fields as keyword arguments; lists may be tuples, tensors or OmegaConf lists) and ``device``,
    where the model's constant tensors live.
    """

    Params = MultiTargetTracking20DParams

    state_dim = 20
    obs_dim = 2 + 3 * N_TARGETS
    n_targets = N_TARGETS
    agent_position_dims = (0, 1)
    position_dims = tuple(d for i in range(1, N_TARGETS + 1) for d in (4 * i, 4 * i + 1))
    velocity_dims = tuple(d for i in range(1, N_TARGETS + 1) for d in (4 * i + 2, 4 * i + 3))  # the targets'
    obs_mask_dims = tuple(2 + 3 * i for i in range(N_TARGETS))

    def __init__(self, params: MultiTargetTracking20DParams | None = None, *,
                 device: torch.device | str | None = None, **kwargs) -> None:
        self.params = p = build_params(MultiTargetTracking20DParams, params, kwargs,
                                       owner=type(self).__name__)
        act = check_actions(p.actions)
        flow_c, goal_t = check_pair("flow_center", p.flow_center), check_pair("goal", p.goal)
        agent_c = check_pair("agent_start_center", p.agent_start_center)
        tsc = check_target_start_centers(p.target_start_centers)
        x_edges, y_edges = check_edges("zone_x_edges", p.zone_x_edges), check_edges("zone_y_edges", p.zone_y_edges)
        check_zone_tables(p)
        rows = check_zone_grid(p, x_edges, y_edges)

        self.device = torch.device(device) if device is not None else torch.device("cpu")
        to = self._to
        for name in _FLOAT_FIELDS:  # as floats: an int in a config reads as the float it stands for
            setattr(self, name, float(getattr(p, name)))
        self._cos_half_fov = math.cos(math.radians(p.fov_degrees) / 2)
        self.n_actions = int(act.shape[0])
        self.action_directions = to(act)  # [n_actions, 2]
        self.headings = to(act / torch.linalg.vector_norm(act, dim=-1, keepdim=True))  # camera heading per action
        self.flow_center, self.goal = to(flow_c), to(goal_t)
        self.agent_start_center, self.target_start_centers = to(agent_c), to(tsc)
        self._build_zones(p, rows, x_edges, y_edges)
        self._build_process_noise(p)

    def _to(self, x: Tensor) -> Tensor:
        return x.to(dtype=torch.float32, device=self.device)

    def _build_zones(self, p: MultiTargetTracking20DParams, rows: list[list[str]], x_edges: Tensor,
                     y_edges: Tensor) -> None:
        """The zone grid: cells with soft edges (cell ``c = by·n_xbins + bx``) and the observation
        constants of each cell (:func:`~escort_rl.models.zone_grid.cell_constants`)."""
        self.zone_x_edges, self.zone_y_edges = self._to(x_edges), self._to(y_edges)
        self.zone_names = tuple(z for r in rows for z in r)
        for name, value in cell_constants(self.zone_names, p.zone_visibility, p.zone_noise_std,
                                          p.zone_swap_prob, self.device).items():
            setattr(self, name, value)
        self._eye = torch.eye(N_TARGETS, dtype=torch.bool, device=self.device)
        self._x_bin_logsinh = bin_log_sinh(x_edges, p.zone_softness)
        self._y_bin_logsinh = bin_log_sinh(y_edges, p.zone_softness)

    def _build_process_noise(self, p: MultiTargetTracking20DParams) -> None:
        """The paper's correlations, the nearest correlation matrix used instead, and ``Σ``."""
        self.paper_correlation = paper_correlations()
        self.correlation = _used_correlations().clone()
        stds = torch.tensor([p.position_noise_std, p.position_noise_std, p.velocity_noise_std, p.velocity_noise_std]
                            * (N_TARGETS + 1), dtype=torch.float64)
        cov = self.correlation * stds[:, None] * stds[None, :]
        self.noise_covariance = self._to(cov)
        self._process = GaussianNoise(self._to(torch.linalg.cholesky(cov)))

    # ------------------------------------------------------------------ state access
    @staticmethod
    def agent_position(s: Tensor) -> Tensor:
        """``[*S, 20]`` -> ``[*S, 2]``."""
        return s[..., 0:2]

    @staticmethod
    def target_positions(s: Tensor) -> Tensor:
        """``[*S, 20]`` -> ``[*S, 4, 2]`` (target ``i`` at row ``i``)."""
        return s[..., ENTITY_DIM:].unflatten(-1, (N_TARGETS, ENTITY_DIM))[..., 0:2]

    @staticmethod
    def target_velocities(s: Tensor) -> Tensor:
        """``[*S, 20]`` -> ``[*S, 4, 2]``."""
        return s[..., ENTITY_DIM:].unflatten(-1, (N_TARGETS, ENTITY_DIM))[..., 2:4]

    def position_error(self, estimate: Tensor, truth: Tensor) -> Tensor:
        """The domain's position error (the protocol's optional hook): :meth:`target_position_error`."""
        return self.target_position_error(estimate, truth)

    def target_position_error(self, mean_state: Tensor, true_state: Tensor) -> Tensor:
        """The benchmark's tracking error: ``(1/4) Σ_i ‖p̂_i - p_i‖₂`` over the four targets, with
        ``p̂_i`` the target positions of ``mean_state`` (e.g. the belief mean). Shapes broadcast:
        ``[*S, 20]`` and ``[*S, 20]`` -> ``[*S]``."""
        diff = self.target_positions(mean_state) - self.target_positions(true_state)
        return torch.linalg.vector_norm(diff, dim=-1).mean(-1)

    def agent_position_error(self, mean_state: Tensor, true_state: Tensor) -> Tensor:
        """``‖p̂_a - p_a‖₂`` (the error the paper's appendix states). ``[*S, 20]`` -> ``[*S]``."""
        return torch.linalg.vector_norm(self.agent_position(mean_state) - self.agent_position(true_state), dim=-1)

    def distance_to_goal(self, s: Tensor) -> Tensor:
        """``‖p_a - goal‖₂``. ``[*S, 20]`` -> ``[*S]``."""
        return torch.linalg.vector_norm(self.agent_position(s) - self.goal, dim=-1)

    # ------------------------------------------------------------------ zones and field of view
    def _bin_log_probs(self, x: Tensor, edges: Tensor, logsinh: list[float]) -> Tensor:
        """Soft 1-D bins (:func:`~escort_rl.models.zone_grid.bin_log_probs`): ``x`` ``[*S]`` ->
        ``[*S, n_edges + 1]`` log-probabilities summing to 1."""
        return bin_log_probs(x, edges, self.zone_softness, logsinh)

    def cell_log_probs(self, pos: Tensor) -> Tensor:
        """Soft zone-cell membership ``log π_c(p)``: ``[*S, 2]`` -> ``[*S, C]`` (cells in
        ``zone_names`` order, row-major from the bottom-left); ``logsumexp`` over cells is 0."""
        lx = self._bin_log_probs(pos[..., 0], self.zone_x_edges, self._x_bin_logsinh)  # [*S, Bx]
        ly = self._bin_log_probs(pos[..., 1], self.zone_y_edges, self._y_bin_logsinh)  # [*S, By]
        return (ly.unsqueeze(-1) + lx.unsqueeze(-2)).flatten(-2)

    def zone_probs(self, pos: Tensor) -> dict[str, Tensor]:
        """Probability of each named zone at ``pos`` ``[*S, 2]`` -> ``{zone: [*S]}``."""
        p = self.cell_log_probs(pos).exp()
        out: dict[str, Tensor] = {}
        for c, z in enumerate(self.zone_names):
            out[z] = out[z] + p[..., c] if z in out else p[..., c]
        return out

    def _fov_margin(self, agent_pos: Tensor, target_pos: Tensor, a: Tensor) -> Tensor:
        """``(cos θ_i - cos(fov/2)) / fov_softness`` for targets ``[*S, 4, 2]`` -> ``[*S, 4]``;
        ``θ_i`` is the angle between the heading of action ``a`` and the agent→target direction."""
        h = self.headings[a.long()].unsqueeze(-2)  # [*A, 1, 2]
        d = target_pos - agent_pos.unsqueeze(-2)
        cos = (d * h).sum(-1) / torch.sqrt((d * d).sum(-1) + 1e-6)
        return (cos - self._cos_half_fov) / self.fov_softness

    def in_view_prob(self, s: Tensor, a: Tensor) -> Tensor:
        """``φ_i``: the smooth probability that target ``i`` is in the field of view. ``[*S, 4]``."""
        return torch.sigmoid(self._fov_margin(self.agent_position(s), self.target_positions(s), a))

    def detection_prob(self, s: Tensor, a: Tensor) -> Tensor:
        """``P(m_i = 1 | s, a) = φ_i Σ_z π_z(p_i) ν_z``. ``[*S, 20]`` -> ``[*S, 4]``."""
        pi = self.cell_log_probs(self.target_positions(s)).exp()
        return self.in_view_prob(s, a) * (pi * self.cell_visibility).sum(-1)

    def swap_log_weights(self, target_pos: Tensor) -> Tensor:
        """``log w_ij``: the swap partner law, ``[*S, 4, 2]`` -> ``[*S, 4, 4]`` (diagonal ``-inf``)."""
        diff = target_pos.unsqueeze(-2) - target_pos.unsqueeze(-3)
        logits = -(diff * diff).sum(-1) / (2 * self.swap_length_scale**2)
        return torch.log_softmax(logits.masked_fill(self._eye, float("-inf")), dim=-1)

    # ------------------------------------------------------------------ protocol: start
    def initial_state(self, shape: tuple[int, ...], generator: torch.Generator | None = None) -> Tensor:
        """Agent and targets uniform in their start boxes, velocities zero. ``[*shape, 20]``."""
        u = torch.rand(*shape, N_TARGETS + 1, 2, generator=generator, device=self.device)
        centres = torch.cat([self.agent_start_center.unsqueeze(0), self.target_start_centers], 0)
        half = torch.tensor([self.agent_start_halfwidth] + [self.target_start_halfwidth] * N_TARGETS,
                            device=self.device).unsqueeze(-1)
        pos = centres + half * (2 * u - 1)
        return torch.cat([pos, torch.zeros_like(pos)], dim=-1).flatten(-2)

    def initial_belief(self, shape: tuple[int, ...], n: int, generator: torch.Generator | None = None) -> Tensor:
        """``n`` draws of the start distribution per batch element: ``[*shape, n, 20]``."""
        return self.initial_state((*shape, n), generator)

    # ------------------------------------------------------------------ protocol: dynamics
    def flow(self, pos: Tensor) -> Tensor:
        """The circular current ``F(p) = ω·(-r_y, r_x) + 2κ·(1 - u)/(1 + u)·r`` with ``r = p - c``,
        ``u = ‖r‖²/R²``: a rotation at ω rad per unit time plus a pull onto the ring of radius ``R``
        (rational, so smooth everywhere; slope ``-2κ`` across the ring, ``-2κ·r`` far out, so the
        dynamics stay stable for any state). ``[*S, 2]`` -> ``[*S, 2]``."""
        r = pos - self.flow_center
        rot = torch.stack([-r[..., 1], r[..., 0]], dim=-1)
        u = (r * r).sum(-1, keepdim=True) / self.flow_radius**2
        radial = 2.0 * self.flow_attraction * (1.0 - u) / (1.0 + u)
        return self.flow_rate * rot + radial * r

    def _wall(self, pos: Tensor) -> Tensor:
        return self.wall_gain * (torch.relu(-pos) - torch.relu(pos - self.map_size))

    def _repulsion(self, tp: Tensor) -> Tensor:
        """``R_i = k Σ_{j≠i} relu(1 - d_ij/r)² (p_i - p_j)/d_ij``: ``[*S, 4, 2]`` -> ``[*S, 4, 2]``."""
        diff = tp.unsqueeze(-2) - tp.unsqueeze(-3)  # [*S, i, j, 2] = p_i - p_j
        dist = torch.sqrt((diff * diff).sum(-1) + 1e-6)
        strength = torch.relu(1.0 - dist / self.repulsion_radius) ** 2
        strength = strength.masked_fill(self._eye, 0.0)
        return self.repulsion_gain * ((strength / dist).unsqueeze(-1) * diff).sum(-2)

    def transition_mean(self, s: Tensor, a: Tensor) -> Tensor:
        """Noise-free dynamics (see the module docstring). ``s``: ``[*S, 20]``, ``a``: ``[*S]`` ->
        ``[*S, 20]`` (``s`` and ``a`` broadcast)."""
        batch = torch.broadcast_shapes(s.shape[:-1], a.shape)
        s, a = s.expand(*batch, self.state_dim), a.expand(batch)
        ent = s.unflatten(-1, (N_TARGETS + 1, ENTITY_DIM))
        pos, vel = ent[..., 0:2], ent[..., 2:4]  # [*S, 5, 2]
        new_pos = pos + self.dt * vel
        pa, va = pos[..., 0, :], vel[..., 0, :]
        tp, tv = pos[..., 1:, :], vel[..., 1:, :]
        push = self.accel * self.action_directions[a.long()]  # [*A, 2]
        new_va = (1.0 - self.damping) * va + push + self._wall(pa)
        new_tv = (tv + self.damping * (self.flow(tp) - tv)
                  + self.flocking_alignment * (tv.mean(-2, keepdim=True) - tv)
                  + self._repulsion(tp) + self._wall(tp))
        new_vel = torch.cat([new_va.unsqueeze(-2), new_tv], -2)
        return torch.cat([new_pos, new_vel], dim=-1).flatten(-2)

    # ------------------------------------------------------------------ protocol: observations
    def observe(self, s_next: Tensor, a: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Sample ``o ~ O(.|s', a)`` by the generative process of the module docstring.
        ``s_next``: ``[*S, 20]``, ``a``: ``[*S]`` -> ``[*S, 14]``."""
        batch = torch.broadcast_shapes(s_next.shape[:-1], a.shape)
        s = s_next.expand(*batch, self.state_dim)
        a = a.expand(batch)
        dev, dt = s.device, s.dtype

        def rand(*shape: int) -> Tensor:
            return torch.rand(*batch, *shape, generator=generator, device=dev, dtype=dt)

        def categorical(logits: Tensor) -> Tensor:
            """Gumbel-max draw over the last dim; a ``-inf`` logit is never drawn."""
            return (logits - torch.log(-torch.log(rand(*logits.shape[len(batch):])))).argmax(-1)

        pa, tp = self.agent_position(s), self.target_positions(s)
        cell = categorical(self.cell_log_probs(tp))  # [*S, 4]: the zone cell of each target
        in_view = rand(N_TARGETS) < torch.sigmoid(self._fov_margin(pa, tp, a))
        detected = in_view & (rand(N_TARGETS) < self.cell_visibility[cell])
        swap = rand(N_TARGETS) < self.cell_swap_prob[cell]
        partner = categorical(self.swap_log_weights(tp))  # [*S, 4], never the slot's own target
        source = torch.where(swap, partner, torch.arange(N_TARGETS, device=dev).expand_as(partner))
        seen = torch.gather(tp, -2, source.unsqueeze(-1).expand(*source.shape, 2))
        eps = torch.randn(*batch, N_TARGETS, 2, generator=generator, device=dev, dtype=dt)
        seen = seen + self.cell_noise_std[cell].unsqueeze(-1) * eps
        m = detected.to(dt)
        slots = torch.cat([m.unsqueeze(-1), seen * m.unsqueeze(-1)], dim=-1)  # [*S, 4, 3]
        eps_a = torch.randn(*batch, 2, generator=generator, device=dev, dtype=dt)
        return torch.cat([pa + self.agent_obs_noise_std * eps_a, slots.flatten(-2)], dim=-1)

    def observation_log_prob(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor:
        """``log O(o | s', a)``: the agent's Gaussian term plus, per slot, the exact mixture over
        zones and identity swaps (formula in the module docstring). A slot counts as detected when
        its mask entry is > 0.5. ``o``: ``[*S, 14]``, ``s_next``: ``[*S, 20]``, ``a``: ``[*S]``
        (all broadcast) -> ``[*S]``. Finite, with a finite score in ``s_next``, everywhere."""
        pa, tp = self.agent_position(s_next), self.target_positions(s_next)
        slots = o[..., 2:].unflatten(-1, (N_TARGETS, 3))
        m, oxy = slots[..., 0], slots[..., 1:3]
        # agent's own position
        za = (o[..., 0:2] - pa) / self.agent_obs_noise_std
        lp_agent = -0.5 * (za * za).sum(-1) - 2 * math.log(self.agent_obs_noise_std) - LOG_2PI
        # zones, field of view
        log_pi = self.cell_log_probs(tp)  # [*S, 4, C]
        margin = self._fov_margin(pa, tp, a)  # [*S, 4]
        log_phi, log_1m_phi = F.logsigmoid(margin), F.logsigmoid(-margin)
        # detected: Gaussian of slot i's report around every target j, in every cell's noise
        diff = oxy.unsqueeze(-2) - tp.unsqueeze(-3)  # [*S, slot i, target j, 2]
        sq = (diff * diff).sum(-1, keepdim=True)  # [*S, 4, 4, 1]
        log_n = -0.5 * sq * self._inv_var - 2 * self._log_sig - LOG_2PI  # [*S, 4, 4, C]
        lw = self.swap_log_weights(tp).unsqueeze(-1)  # [*S, 4, 4, 1]
        comp = torch.where(self._eye.unsqueeze(-1), self._log_keep, self._log_swap + lw)
        mix = torch.logsumexp(comp + log_n, dim=-2)  # [*S, 4, C]
        vis = self._vis_cells
        det = log_phi + torch.logsumexp(log_pi[..., vis] + self._log_nu_vis + mix[..., vis], dim=-1)
        # missed: (1 - φ) + φ Σ_z π_z (1 - ν_z)
        if self._miss_cells.numel() > 0:
            inner = torch.logsumexp(log_pi[..., self._miss_cells] + self._log_1m_nu_miss, dim=-1)
            miss = torch.logaddexp(log_1m_phi, log_phi + inner)
        else:
            miss = log_1m_phi
        per_slot = torch.where(m > 0.5, det, miss)
        return lp_agent + per_slot.sum(-1)

    def observation_score(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor:
        """``∇_{s'} log O(o | s', a)`` in closed form (the gradient autograd gives
        :meth:`observation_log_prob`). ``o``: ``[*S, 14]``, ``s_next``: ``[*S, 20]``, ``a``: ``[*S]``
        (all broadcast) -> ``[*S, 20]``; velocities get 0.

        Backward through the mixture by hand. For a detected slot ``i`` let ``ρ_iz`` be the zone
        posterior ``softmax_z(log π_iz + log ν_z + mix_iz)`` over the visible cells and ``κ_ijz`` the
        source posterior ``softmax_j(comp_ijz + log N_ijz)`` (``δ_ij`` in cells without swaps, which the
        code evaluates without the sum over ``j``); for a missed slot ``ψ_i = σ(log φ_i + inner_i − log(1 − φ_i))``
        (the weight of "in view but not seen") and ``ζ_iz = softmax_z(log π_iz + log(1 − ν_z))``. Then

            detected: ∂/∂ log π_iz = ρ_iz,   ∂/∂ log φ_i = 1,   ∂/∂ p_j += Σ_z ρ_iz κ_ijz (o_i − p_j)/σ_z²,
                      ∂/∂ log w_ij = γ_ij = Σ_z ρ_iz κ_ijz  (j ≠ i)
            missed:   ∂/∂ log π_iz = ψ_i ζ_iz,   ∂/∂ log φ_i = ψ_i,   ∂/∂ log(1 − φ_i) = 1 − ψ_i
            agent:    ∂/∂ p_a += (o_a − p_a)/σ_a²

        and the chain rule through the pieces: ``log w = log_softmax_j(−‖p_i − p_j‖²/2ℓ²)`` gives the
        logits the adjoint ``Λ_ij = γ_ij − w_ij Σ_k γ_ik``, so ``∂/∂p_n += −Σ_k (Λ_nk + Λ_kn)(p_n − p_k)/ℓ²``;
        ``log φ = logσ(μ)``, ``log(1 − φ) = logσ(−μ)`` with the margin ``μ_i = (cos θ_i − cos(fov/2))/τ``,
        ``cos θ_i = d_i·h/‖d_i‖_ε``, ``d_i = p_i − p_a`` and ``∂ cos θ_i/∂d_i = (h − cos θ_i d_i/‖d_i‖_ε)/‖d_i‖_ε``;
        and the soft bins through :meth:`_bin_log_prob_grads`."""
        dt = s_next.dtype
        pa, tp = self.agent_position(s_next), self.target_positions(s_next)
        slots = o[..., 2:].unflatten(-1, (N_TARGETS, 3))
        detected, oxy = (slots[..., 0] > 0.5).unsqueeze(-1), slots[..., 1:3]  # [*S, 4, 1], [*S, 4, 2]
        zero = torch.zeros((), dtype=dt, device=s_next.device)
        # ---- forward pieces (as observation_log_prob)
        log_pi = self.cell_log_probs(tp)  # [*S, 4, C]
        h = self.headings[a.long()].unsqueeze(-2)  # [*A, 1, 2]
        d = tp - pa.unsqueeze(-2)  # [*S, 4, 2]
        inv_norm = torch.rsqrt((d * d).sum(-1) + 1e-6)
        cos = (d * h).sum(-1) * inv_norm
        margin = (cos - self._cos_half_fov) / self.fov_softness  # [*S, 4]
        log_phi, log_1m_phi = F.logsigmoid(margin), F.logsigmoid(-margin)
        diff, weights, kappa, mix_plain, mix_swap = self._detection_mixture(oxy, tp)
        mix = torch.cat([mix_plain.expand(*mix_swap.shape[:-1], -1), mix_swap], dim=-1)  # [*S, i, V]
        rho_vis, _ = _softmax_and_logsumexp(log_pi[..., self._score_cells] + self._score_log_nu + mix)
        rho_plain, rho_swap = rho_vis.split([self._plain_inv_var.numel(), self._swap_inv_var.numel()], dim=-1)
        rho = torch.zeros(*rho_vis.shape[:-1], log_pi.shape[-1], dtype=dt, device=rho_vis.device)
        rho = rho.index_copy(-1, self._score_cells, rho_vis)  # [*S, i, C], 0 in blind cells
        if self._miss_cells.numel() > 0:
            zeta_miss, inner = _softmax_and_logsumexp(log_pi[..., self._miss_cells] + self._log_1m_nu_miss)
            psi = torch.sigmoid(log_phi + inner - log_1m_phi)  # [*S, 4]
            zeta = torch.zeros(*zeta_miss.shape[:-1], log_pi.shape[-1], dtype=dt, device=rho_vis.device)
            zeta = zeta.index_copy(-1, self._miss_cells, zeta_miss)
        else:
            psi, zeta = torch.zeros_like(log_phi), torch.zeros_like(log_pi)
        # ---- adjoints of the pieces
        g_pi = torch.where(detected, rho, psi.unsqueeze(-1) * zeta)  # ∂/∂ log π  [*S, 4, C]
        sig_pos, sig_neg = torch.sigmoid(margin), torch.sigmoid(-margin)
        g_margin = torch.where(detected[..., 0], sig_neg, psi * sig_neg - (1.0 - psi) * sig_pos)  # [*S, 4]
        # β_ij = Σ_v ρ_iv κ_ivj / σ_v² and γ_ij = Σ_v ρ_iv κ_ivj (swapping cells in one batched matmul)
        both = torch.stack([rho_swap * self._swap_inv_var, rho_swap], dim=-2) @ kappa  # [*S, i, 2, j]
        own = torch.diag_embed((rho_plain * self._plain_inv_var).sum(-1))  # plain cells: [*S, i, i]
        beta = torch.where(detected, both[..., 0, :] + own, zero)  # [*S, i, j]
        gamma = torch.where(detected & ~self._eye, both[..., 1, :], zero)
        lam = gamma - weights * gamma.sum(-1, keepdim=True)  # adjoint of the swap logits
        sym = lam + lam.transpose(-1, -2)
        # ---- target positions
        d_tp = (beta.unsqueeze(-1) * diff).sum(-3)  # detection Gaussians, summed over slots i
        d_tp = d_tp - (sym.sum(-1, keepdim=True) * tp - sym @ tp) / self.swap_length_scale**2
        d_tp = d_tp + self._cell_log_prob_grad(tp, g_pi)
        d_cos = (g_margin / self.fov_softness * inv_norm).unsqueeze(-1) * (h - (cos * inv_norm).unsqueeze(-1) * d)
        d_tp = d_tp + d_cos
        # ---- agent position
        d_pa = (o[..., 0:2] - pa) / self.agent_obs_noise_std**2 - d_cos.sum(-2)
        entities = torch.cat([d_pa.unsqueeze(-2), d_tp], dim=-2)  # [*S, 5, 2]
        return torch.cat([entities, torch.zeros_like(entities)], dim=-1).flatten(-2)

    def _detection_mixture(self, oxy: Tensor, tp: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """The detection mixture per visible cell ``v``, for :meth:`observation_score`: a plain
        cell's report comes from its own target (``κ_ivj = δ_ij``); a swapping cell's mixes over the
        source ``j``, laid out ``[*S, slot i, cell v, target j]`` so that the sums over ``j`` run
        along the last, contiguous dimension. ``oxy`` (the reports) and ``tp``: ``[*S, 4, 2]`` ->
        ``o_i − p_j`` ``[*S, i, j, 2]``, the swap weights ``w_ij`` ``[*S, i, j]``, the source
        posterior ``κ_ivj`` ``[*S, i, Vs, j]`` and the per-cell log-mixtures of the plain and
        swapping cells, ``[*S, i, Vp]`` and ``[*S, i, Vs]``."""
        diff = oxy.unsqueeze(-2) - tp.unsqueeze(-3)  # [*S, slot i, target j, 2]
        sq = (diff * diff).sum(-1)  # [*S, i, j]
        sq_own = torch.diagonal(sq, dim1=-2, dim2=-1).unsqueeze(-1)  # [*S, i, 1]
        mix_plain = -0.5 * sq_own * self._plain_inv_var - (2 * self._plain_log_sig + LOG_2PI)  # [*S, i, Vp]
        # swap_log_weights, as softmax and log-softmax
        tdiff = tp.unsqueeze(-2) - tp.unsqueeze(-3)
        logits = (-(tdiff * tdiff).sum(-1) / (2 * self.swap_length_scale**2)).masked_fill(self._eye, float("-inf"))
        weights, log_total = _softmax_and_logsumexp(logits)  # w_ij [*S, i, j], 0 on the diagonal
        lw = logits - log_total.unsqueeze(-1)
        norm = -(2 * self._swap_log_sig + LOG_2PI)  # log-normaliser of N(o; p, σ²I₂) [Vs]
        comp = torch.where(self._eye.unsqueeze(-2), (self._swap_log_keep + norm).unsqueeze(-1),
                           (self._swap_log_swap + norm).unsqueeze(-1) + lw.unsqueeze(-2))  # [*S, i, Vs, j]
        joint = comp - 0.5 * sq.unsqueeze(-2) * self._swap_inv_var.unsqueeze(-1)
        kappa, mix_swap = _softmax_and_logsumexp(joint)  # κ_ivj: the source j of slot i's report; [*S, i, Vs]
        return diff, weights, kappa, mix_plain, mix_swap

    def _cell_log_prob_grad(self, pos: Tensor, g_cells: Tensor) -> Tensor:
        """``Σ_c g_c ∇_p log π_c(p)`` for positions ``[*S, 2]`` and adjoints ``g_cells`` ``[*S, C]`` of
        :meth:`cell_log_probs` (cell ``c = by·n_x + bx``, ``log π_c = log π^y_by + log π^x_bx``)
        -> ``[*S, 2]``."""
        n_x = self.zone_x_edges.numel() + 1
        g = g_cells.unflatten(-1, (-1, n_x))  # [*S, By, Bx]
        gx = (g.sum(-2) * self._bin_log_prob_grads(pos[..., 0], self.zone_x_edges)).sum(-1)
        gy = (g.sum(-1) * self._bin_log_prob_grads(pos[..., 1], self.zone_y_edges)).sum(-1)
        return torch.stack(torch.broadcast_tensors(gx, gy), dim=-1)

    def _bin_log_prob_grads(self, x: Tensor, edges: Tensor) -> Tensor:
        """``d/dx`` of :meth:`_bin_log_probs` (:func:`~escort_rl.models.zone_grid.bin_log_prob_grads`)."""
        return bin_log_prob_grads(x, edges, self.zone_softness)

    # ------------------------------------------------------------------ protocol: reward
    def reward(self, s: Tensor, a: Tensor, s_next: Tensor) -> Tensor:
        """``-α‖p_a' - goal‖ - β - c·Σ_i 1[‖p_a' - p_i'‖ < δ]`` at the next state. ``[*S]``."""
        gap = self.target_positions(s_next) - self.agent_position(s_next).unsqueeze(-2)
        collisions = (torch.linalg.vector_norm(gap, dim=-1) < self.collision_radius).to(s_next.dtype).sum(-1)
        distance = self.distance_to_goal(s_next)
        return -self.distance_weight * distance - self.step_penalty - self.collision_penalty * collisions

    def is_terminal(self, s: Tensor) -> Tensor:
        """Success: the agent within ``success_radius`` of the goal. ``[*S]`` bool."""
        return self.distance_to_goal(s) < self.success_radius


def describe_correlations() -> str:
    """A Markdown report of the paper's process-noise correlations for Multi-Target Tracking 20D
    and the nearest correlation matrix (Higham 2002) that :class:`MultiTargetTracking20D` uses."""
    paper = paper_correlations()
    used = MultiTargetTracking20D().correlation
    names = _state_names()
    return correlation_report("Multi-Target Tracking 20D process-noise correlations", paper, used,
                              pair_rows(paper, used, names))
