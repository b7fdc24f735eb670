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
distribution, goal, action set, horizon) lives in ``configs/env/mtt20d.yaml`` with its reason; the
constructor defaults equal the yaml.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from types import MappingProxyType

import torch
import torch.nn.functional as F
from torch import Tensor

from escort_rl.models.gaussian import (
    AdditiveGaussianTransition,
    GaussianNoise,
    make_positive_definite,
    nearest_correlation_matrix,
)

N_TARGETS = 4
ENTITY_DIM = 4  # [x, y, vx, vy]
LOG_2PI = math.log(2 * math.pi)

# Defaults: identical to configs/env/mtt20d.yaml (tests/test_multi_target.py checks it).
DEFAULT_ACTIONS = ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))
DEFAULT_ZONE_GRID = (("clear", "limited"), ("confusion", "blind"))
DEFAULT_ZONE_VISIBILITY = MappingProxyType({"clear": 1.0, "limited": 0.3, "confusion": 0.7, "blind": 0.0})
DEFAULT_ZONE_NOISE_STD = MappingProxyType({"clear": 0.1, "limited": 0.5, "confusion": 0.2, "blind": 0.5})
DEFAULT_ZONE_SWAP_PROB = MappingProxyType({"clear": 0.0, "limited": 0.0, "confusion": 0.3, "blind": 0.0})
DEFAULT_TARGET_START_CENTERS = ((2.5, 2.5), (7.5, 2.5), (7.5, 7.5), (2.5, 7.5))


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


def _log_cosh(z: Tensor) -> Tensor:
    """``log cosh z``, stable for any ``z`` (gradient ``tanh z``)."""
    return F.softplus(2 * z) - z - math.log(2.0)


def _softmax_and_logsumexp(x: Tensor) -> tuple[Tensor, Tensor]:
    """``softmax`` and ``logsumexp`` over a short last dimension in one pass: ``[*S, n]`` ->
    ``[*S, n]`` and ``[*S]``. Each row needs a finite entry (``-inf`` entries get weight 0). On a CPU
    these few elementwise ops are several times faster than ATen's kernels on rows of a few entries."""
    top = x.amax(-1, keepdim=True)
    e = torch.exp(x - top)
    total = e.sum(-1, keepdim=True)
    return e / total, (top + torch.log(total)).squeeze(-1)


def _log_sinh(k: float) -> float:
    """``log sinh k`` for a constant ``k > 0``, without overflow."""
    return k + math.log(-math.expm1(-2 * k)) - math.log(2.0)


class MultiTargetTracking20D(AdditiveGaussianTransition):
    """The 20-D Multi-Target Tracking POMDP. All tensors are float32 on ``device``.

    Args (paper values marked; the rest are the choices documented in ``configs/env/mtt20d.yaml``):
        map_size: side of the square map ``[0, map_size]²`` (paper: 10).
        dt: time step Δt. damping: velocity damping λ (paper: 0.1). accel: acceleration per action.
        actions: unit-ish 2-D acceleration directions, one per action (paper: +x, -x, +y, -y); the
            normalised direction is also the heading of the field of view.
        flow_center, flow_rate, flow_radius, flow_attraction: the circular current
            ``F(p) = ω·(-r_y, r_x) + 2κ·(1 - u)/(1 + u)·r``, ``r = p - c``, ``u = ‖r‖²/R²`` (ω in rad
            per unit time),
            that targets are dragged toward.
        flocking_alignment: gain pulling each target's velocity toward the mean target velocity.
        repulsion_radius (paper: 1.0), repulsion_gain: collision repulsion between targets.
        wall_gain: restoring force per unit distance outside the map.
        position_noise_std, velocity_noise_std: process-noise stds (same for agent and targets).
        agent_obs_noise_std: std of the agent's own position measurement.
        zone_x_edges, zone_y_edges: strictly increasing cell edges of the zone grid.
        zone_grid: zone names per cell, rows = y bins from the bottom, columns = x bins from the left.
        zone_visibility (paper: clear 1, limited 0.3, confusion 0.7, blind 0), zone_noise_std,
            zone_swap_prob (paper: confusion 0.3): per-zone observation parameters; same keys.
        zone_softness: width of the sigmoid zone boundaries.
        fov_degrees: field of view (paper: 60). fov_softness: width of its edge in ``cos θ`` units.
        swap_length_scale: ℓ of the proximity weights of the swap partner.
        goal, success_radius (paper: 0.5), distance_weight α (paper: 0.1), step_penalty β (paper:
            0.05), collision_radius δ (paper: 0.5), collision_penalty (paper: 1): the reward.
        agent_start_center, agent_start_halfwidth, target_start_centers, target_start_halfwidth:
            start positions uniform in these boxes; start velocities zero.
        device: where the model's constant tensors live.
    """

    state_dim = 20
    obs_dim = 2 + 3 * N_TARGETS
    n_targets = N_TARGETS
    agent_position_dims = (0, 1)
    position_dims = tuple(d for i in range(1, N_TARGETS + 1) for d in (4 * i, 4 * i + 1))
    velocity_dims = tuple(d for i in range(1, N_TARGETS + 1) for d in (4 * i + 2, 4 * i + 3))  # the targets'
    obs_mask_dims = tuple(2 + 3 * i for i in range(N_TARGETS))

    def __init__(
        self,
        map_size: float = 10.0,
        dt: float = 0.1,
        damping: float = 0.1,
        accel: float = 0.2,
        actions: Sequence[Sequence[float]] = DEFAULT_ACTIONS,
        flow_center: Sequence[float] = (5.0, 5.0),
        flow_rate: float = 0.3,
        flow_radius: float = 3.5,
        flow_attraction: float = 0.2,
        flocking_alignment: float = 0.05,
        repulsion_radius: float = 1.0,
        repulsion_gain: float = 0.1,
        wall_gain: float = 0.1,
        position_noise_std: float = 0.05,
        velocity_noise_std: float = 0.05,
        agent_obs_noise_std: float = 0.1,
        zone_x_edges: Sequence[float] = (5.0,),
        zone_y_edges: Sequence[float] = (5.0,),
        zone_grid: Sequence[Sequence[str]] = DEFAULT_ZONE_GRID,
        zone_visibility: Mapping[str, float] = DEFAULT_ZONE_VISIBILITY,
        zone_noise_std: Mapping[str, float] = DEFAULT_ZONE_NOISE_STD,
        zone_swap_prob: Mapping[str, float] = DEFAULT_ZONE_SWAP_PROB,
        zone_softness: float = 0.1,
        fov_degrees: float = 60.0,
        fov_softness: float = 0.02,
        swap_length_scale: float = 2.0,
        goal: Sequence[float] = (9.0, 9.0),
        success_radius: float = 0.5,
        distance_weight: float = 0.1,
        step_penalty: float = 0.05,
        collision_radius: float = 0.5,
        collision_penalty: float = 1.0,
        agent_start_center: Sequence[float] = (1.0, 1.0),
        agent_start_halfwidth: float = 0.5,
        target_start_centers: Sequence[Sequence[float]] = DEFAULT_TARGET_START_CENTERS,
        target_start_halfwidth: float = 0.5,
        device: torch.device | str | None = None,
    ) -> None:
        cls = type(self).__name__

        def fail(name: str, msg: str) -> None:
            raise ValueError(f"{cls}.{name}: {msg}")

        for name, value in (
            ("map_size", map_size), ("dt", dt), ("accel", accel), ("flow_radius", flow_radius),
            ("repulsion_radius", repulsion_radius), ("position_noise_std", position_noise_std),
            ("velocity_noise_std", velocity_noise_std), ("agent_obs_noise_std", agent_obs_noise_std),
            ("zone_softness", zone_softness), ("fov_softness", fov_softness),
            ("swap_length_scale", swap_length_scale), ("success_radius", success_radius),
        ):
            if not (_is_number(value) and value > 0):
                fail(name, f"must be a finite number > 0, got {value!r}")
        for name, value in (
            ("flow_attraction", flow_attraction), ("flocking_alignment", flocking_alignment),
            ("repulsion_gain", repulsion_gain), ("wall_gain", wall_gain),
            ("distance_weight", distance_weight), ("step_penalty", step_penalty),
            ("collision_radius", collision_radius), ("collision_penalty", collision_penalty),
            ("agent_start_halfwidth", agent_start_halfwidth), ("target_start_halfwidth", target_start_halfwidth),
        ):
            if not (_is_number(value) and value >= 0):
                fail(name, f"must be a finite number >= 0, got {value!r}")
        if not (_is_number(damping) and 0.0 <= damping <= 1.0):
            fail("damping", f"must be in [0, 1], got {damping!r}")
        if not _is_number(flow_rate):
            fail("flow_rate", f"must be a finite number, got {flow_rate!r}")
        if not (_is_number(fov_degrees) and 0.0 < fov_degrees < 360.0):
            fail("fov_degrees", f"must be in (0, 360), got {fov_degrees!r}")

        def vec2(name: str, value) -> Tensor:
            t = torch.as_tensor(value, dtype=torch.float64) if _is_numeric_seq(value) else None
            if t is None or t.shape != (2,) or not torch.isfinite(t).all():
                fail(name, f"must be two finite numbers, got {value!r}")
            return t

        def edges(name: str, value) -> Tensor:
            t = torch.as_tensor(list(value), dtype=torch.float64) if _is_numeric_seq(value) else None
            if (t is None or t.dim() != 1 or not torch.isfinite(t).all()
                    or (t.numel() > 1 and not bool((t.diff() > 0).all()))):
                fail(name, f"must be a strictly increasing list of finite numbers, got {value!r}")
            return t

        act = torch.as_tensor(actions, dtype=torch.float64) if _is_numeric_seq(actions) else None
        if (act is None or act.dim() != 2 or act.shape[0] < 1 or act.shape[1] != 2
                or not bool(torch.isfinite(act).all())):
            fail("actions", f"must be a non-empty list of [ax, ay] pairs, got {actions!r}")
        if not bool((torch.linalg.vector_norm(act, dim=-1) > 0).all()):
            fail("actions", "every action needs a non-zero direction (it also sets the camera heading)")
        flow_c, goal_t = vec2("flow_center", flow_center), vec2("goal", goal)
        agent_c = vec2("agent_start_center", agent_start_center)
        tsc = (torch.as_tensor(target_start_centers, dtype=torch.float64)
               if _is_numeric_seq(target_start_centers) else None)
        if tsc is None or tsc.shape != (N_TARGETS, 2) or not torch.isfinite(tsc).all():
            fail("target_start_centers", f"must be {N_TARGETS} pairs [x, y], got {target_start_centers!r}")
        x_edges, y_edges = edges("zone_x_edges", zone_x_edges), edges("zone_y_edges", zone_y_edges)

        # zone tables
        for name, table in (("zone_visibility", zone_visibility), ("zone_noise_std", zone_noise_std),
                            ("zone_swap_prob", zone_swap_prob)):
            if not isinstance(table, Mapping) or not table:
                fail(name, f"must be a non-empty mapping zone name -> number, got {table!r}")
        names = set(zone_visibility)
        for name, table in (("zone_noise_std", zone_noise_std), ("zone_swap_prob", zone_swap_prob)):
            if set(table) != names:
                fail(name, f"must have the same zones as zone_visibility {sorted(names)}, got {sorted(table)}")
        for z in names:
            if not (_is_number(zone_visibility[z]) and 0.0 <= zone_visibility[z] <= 1.0):
                fail("zone_visibility", f"zone '{z}' must be in [0, 1], got {zone_visibility[z]!r}")
            if not (_is_number(zone_noise_std[z]) and zone_noise_std[z] > 0):
                fail("zone_noise_std", f"zone '{z}' must be > 0, got {zone_noise_std[z]!r}")
            if not (_is_number(zone_swap_prob[z]) and 0.0 <= zone_swap_prob[z] < 1.0):
                fail("zone_swap_prob", f"zone '{z}' must be in [0, 1), got {zone_swap_prob[z]!r}")
        is_grid = isinstance(zone_grid, Sequence) and not isinstance(zone_grid, str)
        rows = ([list(r) for r in zone_grid if isinstance(r, Sequence) and not isinstance(r, str)]
                if is_grid else None)
        if (rows is None or len(rows) != len(zone_grid) or len(rows) != y_edges.numel() + 1
                or any(isinstance(r, str) or len(r) != x_edges.numel() + 1 for r in rows)):
            fail("zone_grid", f"must be {y_edges.numel() + 1} rows (y bins) of {x_edges.numel() + 1} zone names "
                 f"(x bins), got {zone_grid!r}")
        for r in rows:
            for z in r:
                if z not in names:
                    fail("zone_grid", f"unknown zone '{z}'; zones are {sorted(names)}")
        if not any(zone_visibility[z] > 0 for r in rows for z in r):
            fail("zone_visibility", "every zone in zone_grid is blind; no target could ever be observed")

        self.device = torch.device(device) if device is not None else torch.device("cpu")
        dev = self.device

        def to(x: Tensor) -> Tensor:
            return x.to(dtype=torch.float32, device=dev)

        for name, value in (
            ("map_size", map_size), ("dt", dt), ("damping", damping), ("accel", accel), ("flow_rate", flow_rate),
            ("flow_radius", flow_radius), ("flow_attraction", flow_attraction),
            ("flocking_alignment", flocking_alignment), ("repulsion_radius", repulsion_radius),
            ("repulsion_gain", repulsion_gain), ("wall_gain", wall_gain), ("agent_obs_noise_std", agent_obs_noise_std),
            ("zone_softness", zone_softness), ("fov_degrees", fov_degrees), ("fov_softness", fov_softness),
            ("swap_length_scale", swap_length_scale), ("success_radius", success_radius),
            ("distance_weight", distance_weight), ("step_penalty", step_penalty),
            ("collision_radius", collision_radius), ("collision_penalty", collision_penalty),
            ("agent_start_halfwidth", agent_start_halfwidth), ("target_start_halfwidth", target_start_halfwidth),
        ):
            setattr(self, name, float(value))
        self._cos_half_fov = math.cos(math.radians(fov_degrees) / 2)
        self.n_actions = int(act.shape[0])
        self.action_directions = to(act)  # [n_actions, 2]
        self.headings = to(act / torch.linalg.vector_norm(act, dim=-1, keepdim=True))  # camera heading per action
        self.flow_center, self.goal = to(flow_c), to(goal_t)
        self.agent_start_center, self.target_start_centers = to(agent_c), to(tsc)

        # ---- zones: a grid of cells with soft edges; per-cell observation constants
        self.zone_x_edges, self.zone_y_edges = to(x_edges), to(y_edges)
        self.zone_names = tuple(z for r in rows for z in r)  # cell c = by * n_xbins + bx
        self.zone_visibility = dict(zone_visibility)
        self.zone_noise_std = dict(zone_noise_std)
        self.zone_swap_prob = dict(zone_swap_prob)
        nu = torch.tensor([float(zone_visibility[z]) for z in self.zone_names], dtype=torch.float64)
        sig = torch.tensor([float(zone_noise_std[z]) for z in self.zone_names], dtype=torch.float64)
        q = torch.tensor([float(zone_swap_prob[z]) for z in self.zone_names], dtype=torch.float64)
        self.cell_visibility, self.cell_noise_std, self.cell_swap_prob = to(nu), to(sig), to(q)
        self._vis_cells = torch.nonzero(nu > 0).flatten().to(dev)  # cells where a detection can happen
        self._miss_cells = torch.nonzero(nu < 1).flatten().to(dev)  # cells where a miss can happen
        self._log_nu_vis = to(torch.log(nu[nu > 0]))
        self._log_1m_nu_miss = to(torch.log1p(-nu[nu < 1]))
        self._log_sig = to(torch.log(sig))
        self._inv_var = to(1.0 / sig**2)
        # [C] log(1 - q) for the identity component, log q for the swap components (-inf when q = 0)
        self._log_keep = to(torch.log1p(-q))
        self._log_swap = to(torch.log(q))
        self._eye = torch.eye(N_TARGETS, dtype=torch.bool, device=dev)
        # observation_score splits the visible cells: "plain" ones (q = 0) report their own target,
        # "swapping" ones (q > 0) mix over the source; cells in the order plain, then swapping. The
        # constants are the ones above, indexed (not recombined), so both methods round alike.
        plain, swapping = (nu > 0) & (q == 0), (nu > 0) & (q > 0)
        score_cells = torch.cat([torch.nonzero(plain).flatten(), torch.nonzero(swapping).flatten()])
        self._score_cells, self._score_log_nu = score_cells.to(dev), to(torch.log(nu[score_cells]))
        plain, swapping = plain.to(dev), swapping.to(dev)
        self._plain_inv_var, self._plain_log_sig = self._inv_var[plain], self._log_sig[plain]
        self._swap_inv_var, self._swap_log_sig = self._inv_var[swapping], self._log_sig[swapping]
        self._swap_log_keep, self._swap_log_swap = self._log_keep[swapping], self._log_swap[swapping]
        self._x_bin_logsinh = [_log_sinh(float(w) / (2 * zone_softness)) for w in x_edges.diff()]
        self._y_bin_logsinh = [_log_sinh(float(w) / (2 * zone_softness)) for w in y_edges.diff()]

        # ---- process noise
        self.paper_correlation = paper_correlations()
        self.correlation = _used_correlations().clone()
        stds = torch.tensor([position_noise_std, position_noise_std, velocity_noise_std, velocity_noise_std]
                            * (N_TARGETS + 1), dtype=torch.float64)
        cov = self.correlation * stds[:, None] * stds[None, :]
        self.noise_covariance = to(cov)
        self._process = GaussianNoise(to(torch.linalg.cholesky(cov)))

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
        """Soft 1-D bins: ``x`` ``[*S]`` -> ``[*S, n_edges + 1]`` log-probabilities summing to 1.

        Bin 0 is ``σ(-(x - e_0)/τ)``, the last ``σ((x - e_last)/τ)``, and bin ``b`` in between
        ``σ((x - e_{b-1})/τ) - σ((x - e_b)/τ) = sinh(w/2τ) / (2 cosh(a/2) cosh(c/2))``, evaluated
        in log space (no cancellation, finite gradients)."""
        if edges.numel() == 0:
            return torch.zeros(*x.shape, 1, dtype=x.dtype, device=x.device)
        a = (x.unsqueeze(-1) - edges) / self.zone_softness  # [*S, E]
        parts = [F.logsigmoid(-a[..., 0])]
        for b in range(1, edges.numel()):
            parts.append(logsinh[b - 1] - math.log(2.0) - _log_cosh(a[..., b - 1] / 2) - _log_cosh(a[..., b] / 2))
        parts.append(F.logsigmoid(a[..., -1]))
        return torch.stack(parts, dim=-1)

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
        # the detection mixture per visible cell v: a plain cell's report comes from its own target
        # (κ_ivj = δ_ij); a swapping cell's mixes over the source j, laid out [*S, slot i, cell v, target j]
        # so that the sums over j run along the last, contiguous dimension
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
        """``d/dx`` of :meth:`_bin_log_probs`: ``x`` ``[*S]`` -> ``[*S, n_edges + 1]``. With
        ``a_e = (x − e)/τ``: ``−σ(a_0)/τ`` for bin 0, ``σ(−a_last)/τ`` for the last bin, and
        ``−(tanh(a_{b−1}/2) + tanh(a_b/2))/(2τ)`` in between (``d log cosh z/dz = tanh z``; autograd
        through :func:`_log_cosh` differs by under ``1e-8/τ``, as softplus turns linear past 20)."""
        if edges.numel() == 0:
            return torch.zeros(*x.shape, 1, dtype=x.dtype, device=x.device)
        a = (x.unsqueeze(-1) - edges) / self.zone_softness  # [*S, E]
        tau = self.zone_softness
        parts = [-torch.sigmoid(a[..., 0]) / tau]
        for b in range(1, edges.numel()):
            parts.append(-(torch.tanh(a[..., b - 1] / 2) + torch.tanh(a[..., b] / 2)) / (2 * tau))
        parts.append(torch.sigmoid(-a[..., -1]) / tau)
        return torch.stack(parts, dim=-1)

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


def _is_number(value) -> bool:
    """A finite real number (bools excluded)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _is_numeric_seq(value) -> bool:
    """True for (nested) lists/tuples/tensors of numbers that torch can read."""
    if isinstance(value, (str, bytes, Mapping)):
        return False
    try:
        t = torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        return False
    return t.numel() > 0 or t.dim() == 1


def describe_correlations() -> str:
    """A Markdown report of the paper's process-noise correlations for Multi-Target Tracking 20D
    and the nearest correlation matrix (Higham 2002) that :class:`MultiTargetTracking20D` uses."""
    paper = paper_correlations()
    used = MultiTargetTracking20D().correlation
    names = _state_names()
    lines = [
        "Multi-Target Tracking 20D process-noise correlations",
        "",
        f"smallest eigenvalue: paper {torch.linalg.eigvalsh(paper).min().item():.4f} (not PSD), "
        f"used {torch.linalg.eigvalsh(used).min().item():.4f}",
        "",
        "| pair | paper | used |",
        "| --- | --- | --- |",
    ]
    d = paper.shape[0]
    for i in range(d):
        for j in range(i + 1, d):
            if paper[i, j] != 0:
                lines.append(f"| rho({names[i]}, {names[j]}) | {paper[i, j]:.2f} | {used[i, j]:.3f} |")
    off = (used * (paper == 0)).abs().max().item()
    lines += ["", f"largest |correlation| the used matrix adds where the paper has none: {off:.3f}"]
    return "\n".join(lines)
