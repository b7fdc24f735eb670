"""Light-Dark 10D (paper, Appendix "Domains: Light Dark 10D"), and its family in more dimensions.

State ``s = (x, v)``: 5-D position ``x`` and 5-D velocity ``v`` (``state_dim = 10``).
Actions ``a ∈ {0..9}``: ``a = 2i`` pushes dimension ``i`` with force ``+f``, ``a = 2i+1`` with ``-f``.

**More dimensions** (``n_pos > 5``, ``state_dim = 2·n_pos``): the light field is the paper's, a
function of the first five position coordinates; every coordinate is observed with the noise that
light sets; the process-noise correlations follow the paper's pattern along the chain; and the dark
swaps become the ``⌊n_pos/2⌋`` pairs ``(2i, 2i+1)``, each with probability
``confusion_prob / ⌊n_pos/2⌋``. At ``n_pos = 5`` that is the paper's (1, 2) and (3, 4) with
``confusion_prob / 2`` each; above, the dark likelihood is a mixture of more components, so the
belief keeps its multi-modal structure as the dimension grows.

Dynamics (additive correlated Gaussian noise ``η ~ N(0, Σ)``):

    x' = x + Δt·v + η_x
    v' = v + f_a - γ·v + η_v

Observation: a noisy copy of the next position, ``o = P·x' + σ(x')·ε`` with
``σ²(x) = σ_base²·(1 - L(x)) + σ_min²`` and ``L`` the light field below. In very dark places
(``L(x) < 0.1``) the permutation ``P`` swaps dimensions (1, 2) or (3, 4), each with probability
``confusion_prob / 2``; elsewhere ``P = I``. ``observation_log_prob`` is the exact mixture over these
events, computed with log-sum-exp.

Light field: ``L(x) = max(0.05, max_j I_j·(1 - (d_j/r_j)²)·[d_j < r_j])`` over seven regions.

Choices the paper leaves open (documented in ``docs/DESIGN.md`` and ``configs/env/lightdark10d.yaml``):
the process-noise scale (the paper gives correlations only), the radii of the goal beacon and the
ambiguous region, and the start velocity (zero).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from escort_rl.config.errors import ConfigError
from escort_rl.config.params import HasParams, build_params, param
from escort_rl.models.gaussian import (
    AdditiveGaussianTransition,
    GaussianNoise,
    correlation_report,
    make_positive_definite,
    nearest_correlation_matrix,
    pair_rows,
)

LIGHT_DIM = 5
"""The light field's dimension: it is a function of the first five position coordinates."""

# (centre, radius, intensity); centres in 5-D position space.
LIGHT_REGIONS: tuple[tuple[tuple[float, ...], float, float], ...] = (
    ((5.0, 0.0, 0.0, 0.0, 0.0), 2.0, 0.9),  # primary corridor
    ((0.0, 5.0, 0.0, 0.0, 0.0), 2.0, 0.9),  # mirror corridor
    ((0.0, 0.0, 2.5, 2.5, 0.0), 1.5, 0.8),  # Z-path start
    ((0.0, 0.0, 5.0, 5.0, 0.0), 1.5, 0.8),  # Z-path middle
    ((0.0, 0.0, 7.5, 7.5, 0.0), 1.5, 0.8),  # Z-path end
    ((0.0, 0.0, 0.0, 0.0, 7.0), 2.0, 1.0),  # goal beacon (radius not given by the paper)
    ((3.33, 3.33, 3.33, 0.0, 0.0), 2.0, 0.4),  # ambiguous region (radius not given by the paper)
)


def paper_correlations(n_pos: int = 5) -> Tensor:
    """The process-noise correlation matrix exactly as the paper lists it at ``n_pos = 5``
    (``[2·n_pos, 2·n_pos]`` float64; beyond five, the chain pattern continues).

    ρ(x_i, v_i) = 0.8, ρ(x_i, x_{i+1}) = 0.5, ρ(v_i, v_{i+1}) = 0.6, ρ(x1, x3) = ρ(x2, x4) = 0.4,
    ρ(v1, v2) = 0.7, ρ(v1, v3) = 0.5 (the later entries override the adjacent-velocity value).
    This matrix is not positive semi-definite (smallest eigenvalue ≈ -0.66).
    """
    d = 2 * n_pos
    c = torch.eye(d, dtype=torch.float64)

    def put(i: int, j: int, r: float) -> None:
        c[i, j] = c[j, i] = r

    for i in range(n_pos):
        put(i, n_pos + i, 0.8)
    for i in range(n_pos - 1):
        put(i, i + 1, 0.5)
        put(n_pos + i, n_pos + i + 1, 0.6)
    put(0, 2, 0.4)
    put(1, 3, 0.4)
    put(n_pos + 0, n_pos + 1, 0.7)
    put(n_pos + 0, n_pos + 2, 0.5)
    return c


PAPER_START_BOX = (0.0, 2.0)
"""The paper's start box of every position coordinate (and the evaluation's)."""


@dataclass(frozen=True)
class LightDark10DParams:
    """:class:`LightDark10D`'s parameters (paper, Appendix "Domains"). Values the paper gives are
    marked (paper); the others are choices it leaves open, with the reason.

    Attributes:
        position_noise_std, velocity_noise_std: std of the process noise per step in position and in
            velocity. The paper gives the noise's correlations but not its scale: 0.05 keeps the
            noise small next to the 0.1 force.
        force: force magnitude per action (paper: 0.1).
        damping: velocity damping γ (paper: 0.1).
        dt: time step Δt (paper: 0.1).
        sigma_base, sigma_min: observation noise law (paper: 0.5, 0.01).
        confusion_prob: probability of a dimension swap when ``L < dark_threshold`` (paper: 0.2).
        dark_threshold: light level under which swaps happen (paper: 0.1).
        goal: every coordinate of the goal position (paper: (8, 8, 8, 8, 8)).
        success_radius: (paper: 0.5).
        start_low, start_high: the start box for positions (paper: [0, 2]^5); start velocity 0
            (our choice).
        prior_width: ``None``: the belief's prior is the start distribution. A number (exploring
            starts, where the start box is wider than the paper's): the prior is a box of this side
            placed around the start (:meth:`LightDark10D.initial_belief_around`).
        paper_start_share: the share of starts drawn from the paper's box ``[0, 2]^n_pos`` instead of
            ``[start_low, start_high]^n_pos`` (default 0). Under exploring starts it keeps the
            evaluation's long trajectories in training: a start uniform in ``[0, 10]^5`` is on average
            half as far from the goal as one in the paper's box, and almost never as far.
        n_pos: the position dimension (paper: 5; at least 5); ``state_dim = 2·n_pos``,
            ``obs_dim = n_pos``, ``n_actions = 2·n_pos``. More gives the family in more dimensions:
            the same light field of the first five coordinates, and ``⌊n_pos/2⌋`` dark swaps.
    """

    position_noise_std: float = param(0.05, gt=0)
    velocity_noise_std: float = param(0.05, gt=0)
    force: float = param(0.1)
    damping: float = param(0.1)
    dt: float = param(0.1, gt=0)
    sigma_base: float = param(0.5, gt=0)
    sigma_min: float = param(0.01, gt=0)
    confusion_prob: float = param(0.2, ge=0, lt=1)
    dark_threshold: float = param(0.1)
    goal: float = param(8.0)
    success_radius: float = param(0.5)
    start_low: float = param(0.0)
    start_high: float = param(2.0)
    prior_width: Optional[float] = param(None, gt=0)
    paper_start_share: float = param(0.0, ge=0, le=1)
    n_pos: int = param(5, ge=LIGHT_DIM)


class LightDark10D(HasParams, AdditiveGaussianTransition):
    """The 10-D Light-Dark navigation POMDP. All tensors are float32 on ``device``.

    Takes :class:`LightDark10DParams` (or its fields as keyword arguments) and ``device``, where the
    model's constant tensors live.
    """

    Params = LightDark10DParams

    # the paper's sizes; another n_pos sets its own on the instance (so that at n_pos = 5 a subclass
    # or a caller may still change one)
    n_pos = 5
    position_dims = (0, 1, 2, 3, 4)
    velocity_dims = (5, 6, 7, 8, 9)
    state_dim = 10
    obs_dim = 5
    n_actions = 10

    def __init__(self, params: LightDark10DParams | None = None, *, device: torch.device | str | None = None,
                 **kwargs) -> None:
        self.params = p = build_params(LightDark10DParams, params, kwargs, owner=type(self).__name__)
        if not p.start_low < p.start_high:
            raise ConfigError(f"{type(self).__name__}.start_low: must be < start_high (the start box is "
                              f"[start_low, start_high]^n_pos), got {p.start_low} >= {p.start_high}")
        n, confusion_prob, force = p.n_pos, p.confusion_prob, p.force
        if n != type(self).n_pos:
            self.n_pos, self.position_dims, self.velocity_dims = n, tuple(range(n)), tuple(range(n, 2 * n))
            self.state_dim, self.obs_dim, self.n_actions = 2 * n, n, 2 * n
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.goal = torch.full((self.n_pos,), float(p.goal), device=self.device)

        self.correlation = make_positive_definite(nearest_correlation_matrix(paper_correlations(n)))
        stds = torch.tensor([p.position_noise_std] * n + [p.velocity_noise_std] * n, dtype=torch.float64)
        cov = self.correlation * stds[:, None] * stds[None, :]
        self.noise_covariance = cov.to(torch.float32).to(self.device)
        self._process = GaussianNoise(torch.linalg.cholesky(cov).to(torch.float32).to(self.device))

        self.light_centres = torch.tensor([c for c, _, _ in LIGHT_REGIONS], device=self.device)
        self.light_radii = torch.tensor([r for _, r, _ in LIGHT_REGIONS], device=self.device)
        self.light_intensities = torch.tensor([i for _, _, i in LIGHT_REGIONS], device=self.device)
        self._centre_sq = (self.light_centres**2).sum(-1)
        self._radius_sq = self.light_radii**2
        n_pairs = n // 2
        share = confusion_prob / n_pairs
        # log-probabilities of {no swap, swap(1,2), swap(3,4), ...} in the dark
        self._log_event_probs = torch.log(torch.tensor([1 - confusion_prob] + [share] * n_pairs, device=self.device))
        self._set_actions(force)
        self._swap_i = torch.arange(0, 2 * n_pairs, 2, device=self.device)  # [n_pairs]: pair k swaps
        self._swap_j = self._swap_i + 1  # coordinates 2k and 2k + 1
        perms = torch.arange(n).repeat(n_pairs + 1, 1)
        perms[1 + torch.arange(n_pairs), 2 * torch.arange(n_pairs)] += 1
        perms[1 + torch.arange(n_pairs), 2 * torch.arange(n_pairs) + 1] -= 1
        self._swap_perms = perms.to(self.device)  # [1 + n_pairs, n_pos]: identity, then each swap
        self._no_swap = torch.zeros(n_pairs + 1, device=self.device)  # event weights in the light
        self._no_swap[0] = 1.0

    def _set_actions(self, force: float) -> None:
        """The action set: ``a = 2i`` pushes velocity ``i`` by ``+force``, ``a = 2i + 1`` by ``−force``."""
        forces = torch.zeros(self.n_actions, self.state_dim, device=self.device)
        for a in range(self.n_actions):
            forces[a, self.n_pos + a // 2] = force if a % 2 == 0 else -force
        self._velocity_force = forces  # [n_actions, d]: the force added to v' per action

    # ------------------------------------------------------------------ light and noise
    def _light_levels(self, pos: Tensor) -> tuple[Tensor, Tensor]:
        """Squared distances ``d_j²`` to the region centres and the levels ``I_j(1 - (d_j/r_j)²)``.
        ``pos``: ``[*S, 5]`` (the first five coordinates) -> two ``[*S, 7]`` tensors."""
        # squared distances to the centres by ‖x‖² - 2x·c + ‖c‖² (one matmul, no [*S, 7, 5] tensor)
        sq = (pos * pos).sum(-1, keepdim=True) - 2 * pos @ self.light_centres.T + self._centre_sq
        ratio = sq.clamp_min(0.0) / self._radius_sq  # (d_j / r_j)²
        return sq, self.light_intensities * (1.0 - ratio)  # a level is negative exactly when d_j > r_j

    def light(self, pos: Tensor) -> Tensor:
        """Light intensity ``L(x)`` in [0.05, 1], of the first five coordinates. ``pos``: ``[*S, n_pos]``
        -> ``[*S]``."""
        return self._light_levels(pos[..., :LIGHT_DIM])[1].amax(-1).clamp_min(0.05)

    def light_and_gradient(self, pos: Tensor) -> tuple[Tensor, Tensor]:
        """``L(x)`` ``[*S]`` and the gradient autograd gives it, ``∇L(x)`` ``[*S, n_pos]``.

        ``∇L = Σ_j w_j·(-2 I_j/r_j²)·[d_j² ≥ 0]·(x - c_j)``: ``w`` shares 1 evenly among the regions
        that attain the max (the gradient of ``amax``) and is 0 where the max is clamped up to 0.05
        (outside every radius, or nearly so), so ``∇L = 0`` there. ``pos``: ``[*S, n_pos]``; the gradient
        is 0 beyond the first five coordinates."""
        full, pos = pos, pos[..., :LIGHT_DIM]
        sq, level = self._light_levels(pos)
        top = level.amax(-1, keepdim=True)
        at_top = (level == top).to(pos.dtype)
        share = at_top / at_top.sum(-1, keepdim=True) * (top >= 0.05)
        coef = share * (sq >= 0) * (-2.0 * self.light_intensities / self._radius_sq)  # [*S, 7]
        grad = coef.sum(-1, keepdim=True) * pos - coef @ self.light_centres
        if full.shape[-1] > LIGHT_DIM:
            grad = torch.cat([grad, grad.new_zeros(*grad.shape[:-1], full.shape[-1] - LIGHT_DIM)], dim=-1)
        return top.squeeze(-1).clamp_min(0.05), grad

    def observation_std_from_light(self, light: Tensor) -> Tensor:
        """σ = sqrt(σ_base²(1 - L) + σ_min²), elementwise."""
        return torch.sqrt(self.sigma_base**2 * (1.0 - light) + self.sigma_min**2)

    def observation_std(self, pos: Tensor) -> Tensor:
        """σ(x) for positions ``[*S, n_pos]`` -> ``[*S]``."""
        return self.observation_std_from_light(self.light(pos))

    # ------------------------------------------------------------------ protocol
    def initial_state(self, shape: tuple[int, ...], generator: torch.Generator | None = None) -> Tensor:
        """Position uniform in the start box (or, with probability ``paper_start_share``, in the
        paper's ``[0, 2]^n_pos``), velocity zero. Returns ``[*shape, 2·n_pos]``."""
        u = torch.rand(*shape, self.n_pos, generator=generator, device=self.device)
        pos = self.start_low + (self.start_high - self.start_low) * u
        if self.paper_start_share > 0:
            low, high = PAPER_START_BOX
            paper = low + (high - low) * torch.rand(*shape, self.n_pos, generator=generator, device=self.device)
            pick = torch.rand(*shape, 1, generator=generator, device=self.device) < self.paper_start_share
            pos = torch.where(pick, paper, pos)
        return torch.cat([pos, torch.zeros_like(pos)], dim=-1)

    def initial_belief(
        self, shape: tuple[int, ...], n: int, generator: torch.Generator | None = None
    ) -> Tensor:
        """``n`` draws of the start distribution per batch element: ``[*shape, n, 2·n_pos]``."""
        return self.initial_state((*shape, n), generator)

    def initial_belief_around(self, state: Tensor, n: int, generator: torch.Generator | None = None) -> Tensor:
        """The prior of an episode that starts at ``state`` under exploring starts: as informative as
        the paper's start box, wherever the start. Positions uniform in a box of side
        ``prior_width`` whose corner is ``x₀ − prior_width·u``, ``u ~ U[0, 1]^5``, so that ``x₀`` is
        uniform in the box, as a start is in the paper's; velocity zero, as every start's.
        ``state`` ``[*S, 2·n_pos]`` -> ``[*S, n, 2·n_pos]``."""
        if self.prior_width is None:
            raise ValueError("LightDark10D.prior_width: is None; set it to place the prior around the start")
        pos = state[..., : self.n_pos]
        corner = pos - self.prior_width * torch.rand(pos.shape, generator=generator, device=pos.device, dtype=pos.dtype)
        u = torch.rand(*pos.shape[:-1], n, self.n_pos, generator=generator, device=pos.device, dtype=pos.dtype)
        particles = corner.unsqueeze(-2) + self.prior_width * u
        return torch.cat([particles, torch.zeros_like(particles)], dim=-1)

    def transition_mean(self, s: Tensor, a: Tensor) -> Tensor:
        """Noise-free dynamics. ``s``: ``[*S, 2·n_pos]``, ``a``: ``[*S]`` -> ``[*S, 2·n_pos]``."""
        pos, vel = s[..., : self.n_pos], s[..., self.n_pos :]
        new_pos = pos + self.dt * vel
        new_vel = (1.0 - self.damping) * vel
        return torch.cat([new_pos, new_vel], dim=-1) + self._velocity_force[a.long()]

    def observe(self, s_next: Tensor, a: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """``o = P·x' + σ(x')·ε``. ``s_next``: ``[*S, 2·n_pos]`` -> ``[*S, n_pos]``."""
        pos = s_next[..., : self.n_pos]
        u = torch.rand(pos.shape[:-1], generator=generator, device=pos.device)
        n_pairs = len(self._swap_i)
        pair = (u / (self.confusion_prob / n_pairs)).long().clamp_max(n_pairs - 1) if self.confusion_prob > 0 else 0
        event = torch.where(u < self.confusion_prob, 1 + pair, 0)
        event = torch.where(self.light(pos) < self.dark_threshold, event, torch.zeros_like(event))
        perm = self._swap_perms[event]  # [*S, n_pos]
        seen = torch.gather(pos, -1, perm)
        eps = torch.randn(pos.shape, generator=generator, device=pos.device, dtype=pos.dtype)
        return seen + self.observation_std(pos).unsqueeze(-1) * eps

    def _pair_coordinates(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """The coordinates the swaps exchange, as strided views: ``(t_0, t_2, …)`` and ``(t_1, t_3, …)``
        ``[*S, n_pairs]`` of ``t`` ``[*S, n_pos]`` (pair ``k`` swaps coordinates ``2k`` and ``2k + 1``).
        Slices, not index tensors: compiled, the score's arithmetic then runs vectorised."""
        end = 2 * len(self._swap_i)
        return t[..., 0:end:2], t[..., 1:end:2]

    def _swap_errors(self, o: Tensor, pos: Tensor) -> Tensor:
        """Squared errors ``‖o - P_k x‖²`` for the events {no swap, swap(1,2), swap(3,4), ...}: a
        swapped one differs from the unswapped one only in its two swapped coordinates.
        ``o``, ``pos``: ``[*S, n_pos]`` (broadcast) -> ``[*S, 1 + n_pairs]``."""
        diff = o - pos  # [*S, n_pos]
        sq = diff * diff
        sq_id = sq.sum(-1, keepdim=True)
        (o_i, o_j), (x_i, x_j), (sq_i, sq_j) = self._pair_coordinates(o), self._pair_coordinates(pos), \
            self._pair_coordinates(sq)
        cross = (o_i - x_j) ** 2 + (o_j - x_i) ** 2  # [*S, n_pairs]
        return torch.cat([sq_id, sq_id - sq_i - sq_j + cross], dim=-1)

    def observation_log_prob(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor:
        """``log O(o | s')``: in the dark, the mixture over {no swap, swap(1,2), swap(3,4)}.

        ``o``: ``[*S, n_pos]``, ``s_next``: ``[*S, 2·n_pos]`` (broadcast) -> ``[*S]``. With isotropic noise σ,
        each component is ``-‖o - P x‖²/(2σ²) - 5 log σ - (5/2) log 2π``; the swapped squared errors
        differ from the unswapped one only in the two swapped coordinates.
        """
        pos = s_next[..., : self.n_pos]
        light = self.light(pos)
        var = self.sigma_base**2 * (1.0 - light) + self.sigma_min**2  # [*S]
        errs = self._swap_errors(o, pos)  # [*S, 3]
        log_norm = -0.5 * self.n_pos * (torch.log(var) + math.log(2 * math.pi))
        comp = -0.5 * errs / var.unsqueeze(-1)
        dark = light < self.dark_threshold
        mixed = torch.logsumexp(comp + self._log_event_probs, dim=-1)
        return log_norm + torch.where(dark, mixed, comp[..., 0])

    def observation_score(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor:
        """``∇_{s'} log O(o | s')`` in closed form (the gradient autograd gives
        :meth:`observation_log_prob`). ``o``: ``[*S, n_pos]``, ``s_next``: ``[*S, 2·n_pos]``
        (broadcast) -> ``[*S, 2·n_pos]``.

        With ``v = σ²(x)``, errors ``e_k = ‖o - P_k x‖²`` and event weights ``w_k`` (the posterior
        ``softmax_k(log π_k - e_k/2v)`` in the dark, ``(1, 0, 0)`` in the light):

            ∇_x log O = (ō - x)/v + (ē/(2v²) - 5/(2v))·∇v,    ∇v = -σ_base²·∇L(x),

        with ``ō = Σ_k w_k P_k o`` (each ``P_k`` is its own inverse) and ``ē = Σ_k w_k e_k``; ``∇L``
        from :meth:`light_and_gradient`. The velocity part is 0."""
        pos = s_next[..., : self.n_pos]
        light, d_light = self.light_and_gradient(pos)
        var = self.sigma_base**2 * (1.0 - light) + self.sigma_min**2  # [*S]
        errs = self._swap_errors(o, pos)  # [*S, 3]
        logits = -0.5 * errs / var.unsqueeze(-1) + self._log_event_probs
        dark = (light < self.dark_threshold).unsqueeze(-1)
        posterior = torch.exp(logits - logits.amax(-1, keepdim=True))  # softmax by hand: on a CPU,
        posterior = posterior / posterior.sum(-1, keepdim=True)  # faster than ATen's on rows of 3
        w = torch.where(dark, posterior, self._no_swap)  # [*S, 3]
        # ō = Σ_k w_k P_k o: swap k moves w_k·(o_j - o_i) into coordinate i and its opposite into j
        o_i, o_j = self._pair_coordinates(o)
        shift = w[..., 1:] * (o_j - o_i)  # [*S, n_pairs]
        pairs = torch.stack([o_i + shift, o_j - shift], dim=-1).flatten(-2)  # [*S, 2·n_pairs]
        rest = o[..., pairs.shape[-1]:]
        seen = torch.cat([pairs, rest.expand(*pairs.shape[:-1], rest.shape[-1])], dim=-1)
        mean_err = (w * errs).sum(-1)
        d_var_coef = 0.5 * mean_err / var**2 - 0.5 * self.n_pos / var  # ∂ log O / ∂v
        grad_pos = (seen - pos) / var.unsqueeze(-1) - (self.sigma_base**2 * d_var_coef).unsqueeze(-1) * d_light
        return torch.cat([grad_pos, torch.zeros_like(grad_pos)], dim=-1)

    @property
    def action_coordinates(self) -> tuple[tuple[int, int], ...]:
        """The state coordinates each action group acts on: ``(x_i, v_i)`` for the pair of actions ``2i``,
        ``2i+1`` that pushes dimension ``i`` (for continuous actions, action coordinate ``i``). A policy may
        share one network across the groups (``actor.head=per_coordinate``)."""
        return tuple((i, self.n_pos + i) for i in range(self.n_pos))

    def distance_to_goal(self, s: Tensor) -> Tensor:
        """‖x - x_goal‖₂. ``s``: ``[*S, 2·n_pos]`` -> ``[*S]``."""
        return torch.linalg.vector_norm(s[..., : self.n_pos] - self.goal, dim=-1)

    def reward(self, s: Tensor, a: Tensor, s_next: Tensor) -> Tensor:
        """``r = -0.1·‖x' - x_goal‖ - 0.1`` (paper; evaluated at the next state)."""
        return -0.1 * self.distance_to_goal(s_next) - 0.1

    def is_terminal(self, s: Tensor) -> Tensor:
        """Success: within ``success_radius`` of the goal."""
        return self.distance_to_goal(s) < self.success_radius

    def position(self, s: Tensor) -> Tensor:
        """The position part of a state: ``[*S, 2·n_pos]`` -> ``[*S, n_pos]``."""
        return s[..., : self.n_pos]


def describe_correlations() -> str:
    """A Markdown report of the paper's process-noise correlations and the nearest correlation
    matrix (Higham 2002) that :class:`LightDark10D` uses instead."""
    paper = paper_correlations()
    used = LightDark10D().correlation
    names = [f"x{i + 1}" for i in range(5)] + [f"v{i + 1}" for i in range(5)]
    return correlation_report("Light-Dark 10D process-noise correlations", paper, used, pair_rows(paper, used, names))
