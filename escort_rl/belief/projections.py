"""Projections for ESCORT's regularisers: correlation-aware subspaces and 1-D optimal transport
matchings (SPEC §4, step 3). Batched over beliefs ``[*B, N, d]``."""

from __future__ import annotations

import torch
from torch import Tensor

from escort_rl.belief.prior import weighted_covariance


def correlation_from_covariance(cov: Tensor, eps: float = 1e-12) -> Tensor:
    """``C_ij = Σ_ij / sqrt(Σ_ii Σ_jj)``. ``[*B, d, d] -> [*B, d, d]``."""
    s = torch.sqrt(torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(eps))
    return cov / s.unsqueeze(-1) / s.unsqueeze(-2)


def orthonormalise(a: Tensor) -> Tensor:
    """Orthonormal columns by QR, with signs fixed so the result is unique. ``[*B, d, k]``."""
    q, r = torch.linalg.qr(a)
    sign = torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    return q * sign.unsqueeze(-2)


def random_projections(batch_shape, d: int, n_proj: int, proj_dim: int, generator=None,
                       device=None, dtype=torch.float32) -> Tensor:
    """``n_proj`` random orthonormal ``d × proj_dim`` matrices per belief: ``[*B, n_proj, d, proj_dim]``."""
    g = torch.randn(*batch_shape, n_proj, d, proj_dim, generator=generator, device=device, dtype=dtype)
    return orthonormalise(g)


def pair_second_moment(x: Tensor, y: Tensor, y_log_weights: Tensor) -> Tensor:
    """``M = E[(x − y)(x − y)ᵀ]`` for independent ``x`` uniform over ``x_i`` and ``y`` drawn from ``y_j``
    with weights ``w_j``: ``M = Cov(x) + Cov_w(y) + (x̄ − ȳ)(x̄ − ȳ)ᵀ``. Returns ``[*B, d, d]``."""
    w = torch.softmax(y_log_weights, dim=-1).unsqueeze(-1)
    delta = x.mean(-2) - (w * y).sum(-2)
    return weighted_covariance(x) + weighted_covariance(y, y_log_weights) + delta.unsqueeze(-1) * delta.unsqueeze(-2)


def correlation_projections(x: Tensor, y: Tensor, y_log_weights: Tensor, n_proj: int, proj_dim: int,
                            ascent_steps: int = 5, ascent_lr: float = 0.1,
                            generator: torch.Generator | None = None,
                            fill: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """ESCORT's correlation projections ``A_k`` and their weights ``w_k``.

    1. Start from the eigenvectors of ``ΔC = corr(x) − corr_w(y)``, in order of ``|eigenvalue|``:
       ``A_k`` takes eigenvectors ``k·p … k·p + p − 1`` (``p = proj_dim``); when ``n_proj · p > d``
       the projections that do not fit start from seeded random orthonormal matrices (drawn with
       ``generator``, or taken from ``fill`` ``[*B, n_proj, d, p]`` if given).
    2. Refine each ``A_k`` by ``ascent_steps`` steps of gradient ascent on
       ``D_k = E‖A_kᵀ(x − y)‖² = tr(A_kᵀ M A_k)`` (``M`` from :func:`pair_second_moment`; exact for
       independent draws), with the exact gradient ``∇_A D = 2 M A`` (what autograd computes; a test
       checks it) and a step ``ascent_lr / ‖M‖_F``, re-orthonormalising by QR after each step.
    3. ``w_k = sqrt(D_k) / Σ_l sqrt(D_l)``.

    ``x`` ``[*B, N, d]`` (current particles), ``y`` ``[*B, N, d]`` with ``y_log_weights`` ``[*B, N]``
    (weighted samples of the target). Returns ``A`` ``[*B, n_proj, d, proj_dim]`` and ``w``
    ``[*B, n_proj]``. Everything is computed without gradient tracking of ``x`` and ``y``.
    """
    d = x.shape[-1]
    p = max(1, min(proj_dim, d))
    x, y, y_log_weights = x.detach(), y.detach(), y_log_weights.detach()
    delta_c = correlation_from_covariance(weighted_covariance(x)) - correlation_from_covariance(
        weighted_covariance(y, y_log_weights))
    evals, evecs = torch.linalg.eigh(delta_c)  # ascending
    order = torch.argsort(evals.abs(), dim=-1, descending=True)
    evecs = torch.gather(evecs, -1, order.unsqueeze(-2).expand_as(evecs))
    n_eig = min(n_proj, d // p)  # blocks of eigenvectors that fit; the rest start at random
    a = evecs[..., : n_eig * p].reshape(*evecs.shape[:-1], n_eig, p).movedim(-2, -3)  # [*B, n_eig, d, p]
    if n_eig < n_proj:
        extra = (random_projections(x.shape[:-2], d, n_proj - n_eig, p, generator, x.device, x.dtype)
                 if fill is None else fill[..., n_eig:, :, :p])
        a = torch.cat([a, extra], dim=-3)
    a = orthonormalise(a)
    m = pair_second_moment(x, y, y_log_weights).unsqueeze(-3)  # [*B, 1, d, d]
    scale = torch.linalg.matrix_norm(m).clamp_min(1e-12)[..., None, None]
    for _ in range(ascent_steps):
        # ∇_A tr(Aᵀ M A) = 2 M A (M symmetric): the gradient autograd gives, without a graph
        a = orthonormalise(a + ascent_lr * 2.0 * (m @ a) / scale)
    a = a.detach()
    dist = torch.diagonal(a.transpose(-1, -2) @ m @ a, dim1=-2, dim2=-1).sum(-1).clamp_min(0.0).sqrt()
    w = dist / dist.sum(-1, keepdim=True).clamp_min(1e-12)
    return a, w


def projector(projections: Tensor, weights: Tensor) -> Tensor:
    """``Σ_k w_k A_k A_kᵀ``: ``[*B, K, d, p]``, ``[*B, K]`` -> ``[*B, d, d]`` (symmetric)."""
    return (weights[..., None, None] * (projections @ projections.transpose(-1, -2))).sum(-3)


def correlation_force(phi: Tensor, projections: Tensor, weights: Tensor, strength: float,
                      form: str = "velocity", x: Tensor | None = None, proj: Tensor | None = None) -> Tensor:
    """``F_corr = −λ Σ_k w_k A_k A_kᵀ (φ(x_i) − φ̄)`` (``form="velocity"``, the gradient of R_corr in φ),
    or the paper's appendix form with ``(x_i − x̄)`` in place of ``(φ(x_i) − φ̄)`` (``form="position"``).

    ``phi`` ``[*B, N, d]``, ``projections`` ``[*B, K, d, p]``, ``weights`` ``[*B, K]``; ``proj`` may
    pass a precomputed :func:`projector`. Returns ``[*B, N, d]``.
    """
    if form == "velocity":
        v = phi - phi.mean(-2, keepdim=True)
    elif form == "position":
        if x is None:
            raise ValueError("x: the position form needs the particles")
        v = x - x.mean(-2, keepdim=True)
    else:
        raise ValueError(f"corr_form: must be 'velocity' or 'position', got '{form}'")
    if proj is None:
        proj = projector(projections, weights)
    return (-strength) * (v @ proj)  # proj is symmetric


def random_directions(x: Tensor, n_dirs: int, generator=None) -> Tensor:
    """``n_dirs`` seeded random unit vectors per belief of ``x`` ``[*B, N, d]``: ``[*B, n_dirs, d]``."""
    theta = torch.randn(*x.shape[:-2], n_dirs, x.shape[-1], generator=generator, device=x.device, dtype=x.dtype)
    return theta / torch.linalg.vector_norm(theta, dim=-1, keepdim=True).clamp_min(1e-12)


def max_sliced_directions(x: Tensor, r: Tensor, theta: Tensor, ascent_steps: int = 10,
                          ascent_lr: float = 0.5) -> tuple[Tensor, Tensor]:
    """Directions ``θ_j`` that maximise the projected W1 between ``x`` and ``r`` (equal weights).

    Starts from the unit vectors ``theta`` ``[*B, J, d]`` (e.g. :func:`random_directions`) and takes
    ``ascent_steps`` gradient ascent steps on ``W1_θ = (1/N) Σ_k |sort(x θ)_k − sort(r θ)_k|``
    (:func:`projected_w1_grad`), renormalising θ after each step.
    ``x``, ``r`` ``[*B, N, d]``. Returns ``θ`` ``[*B, J, d]`` and weights ``w_j ∝ W1_θj`` ``[*B, J]``.
    """
    x, r = x.detach(), r.detach()

    def projected_w1(t: Tensor) -> Tensor:
        px = torch.sort(x @ t.transpose(-1, -2), dim=-2).values  # [*B, N, J]
        pr = torch.sort(r @ t.transpose(-1, -2), dim=-2).values
        return (px - pr).abs().mean(-2)  # [*B, J]

    for _ in range(ascent_steps):
        theta = theta + ascent_lr * projected_w1_grad(x, r, theta)
        theta = theta / torch.linalg.vector_norm(theta, dim=-1, keepdim=True).clamp_min(1e-12)
    theta = theta.detach()
    w1 = projected_w1(theta)
    weights = w1 / w1.sum(-1, keepdim=True).clamp_min(1e-12)
    return theta, weights


def projected_w1_grad(x: Tensor, r: Tensor, theta: Tensor) -> Tensor:
    """``∇_θ W1_θ`` for ``W1_θ = (1/N) Σ_k |θ·x_(k) − θ·r_(k)|``, where ``x_(k)`` and ``r_(k)`` are
    the points of rank ``k`` along ``θ``: ``(1/N) Σ_k sign(θ·x_(k) − θ·r_(k)) (x_(k) − r_(k))``
    (the gradient autograd gives through the sort; a test checks it).
    ``x``, ``r`` ``[*B, N, d]``, ``theta`` ``[*B, J, d]``. Returns ``[*B, J, d]``."""
    n = x.shape[-2]
    px, ix = torch.sort(theta @ x.transpose(-1, -2), dim=-1)  # [*B, J, N]
    pr, ir = torch.sort(theta @ r.transpose(-1, -2), dim=-1)
    sign = torch.sign(px - pr)  # [*B, J, N]
    # Σ_k s_k x_(k) = Σ_i s_{rank(i)} x_i: scatter the signs back to particle order, then one matmul
    sx = torch.zeros_like(sign).scatter_(-1, ix, sign)
    sr = torch.zeros_like(sign).scatter_(-1, ir, sign)
    return (sx @ x - sr @ r) / n


def sorted_matching(x: Tensor, r: Tensor, theta: Tensor) -> Tensor:
    """The 1-D optimal transport matching along each direction: ``σ_j(i)`` is the index of the
    reference point with the same rank along ``θ_j`` as ``x_i``.

    ``x``, ``r`` ``[*B, N, d]``, ``theta`` ``[*B, J, d]``. Returns indices ``[*B, J, N]``.
    """
    ix = torch.argsort((x @ theta.transpose(-1, -2)).transpose(-1, -2), dim=-1)  # [*B, J, N]: rank -> i
    ir = torch.argsort((r @ theta.transpose(-1, -2)).transpose(-1, -2), dim=-1)  # rank -> reference
    sigma = torch.empty_like(ix)
    sigma.scatter_(-1, ix, ir)
    return sigma


class TemporalReference:
    """The reference set ``r`` ``[*B, N, d]`` sorted once along each direction ``θ_j`` ``[*B, J, d]``,
    so that each :meth:`force` call sorts only the moving particles."""

    def __init__(self, r: Tensor, theta: Tensor, weights: Tensor) -> None:
        d = r.shape[-1]
        self.theta = theta  # [*B, J, d]
        order = torch.argsort(theta @ r.transpose(-1, -2), dim=-1)  # [*B, J, N]: rank -> index
        self.sorted_ref = torch.gather(r.unsqueeze(-3).expand(*order.shape, d), -2,
                                       order.unsqueeze(-1).expand(*order.shape, d))  # [*B, J, N, d]
        # the weights are folded in: the pull is Σ_j w_j r_{σ_j(i)} − x_i (Σ_j w_j = 1)
        self.weighted_sorted_ref = weights[..., None, None] * self.sorted_ref
        self.weights = weights

    def force(self, x: Tensor, strength: float, clip: float = 10.0) -> Tensor:
        """``F_temp(x_i) = λ Σ_j w_j (r_{σ_j(i)} − x_i)``, clipped elementwise to ``±clip``. ``[*B, N, d]``."""
        rank_to_i = torch.argsort(self.theta @ x.transpose(-1, -2), dim=-1)  # [*B, J, N], sorted contiguously
        idx = rank_to_i.unsqueeze(-1).expand(self.sorted_ref.shape)
        matched = torch.zeros_like(self.weighted_sorted_ref).scatter_(-2, idx, self.weighted_sorted_ref)
        pull = matched.sum(-3) - self.weights.sum(-1)[..., None, None] * x
        return (strength * pull).clamp(-clip, clip)


def temporal_force(x: Tensor, r: Tensor, theta: Tensor, weights: Tensor, strength: float,
                   clip: float = 10.0) -> Tensor:
    """``F_temp(x_i) = λ Σ_j w_j (r_{σ_j(i)} − x_i)``, clipped elementwise to ``±clip``, where ``σ_j``
    is the sorted 1-D OT matching along ``θ_j`` (:func:`sorted_matching`).

    ``x``, ``r`` ``[*B, N, d]``; ``theta`` ``[*B, J, d]``; ``weights`` ``[*B, J]``. Returns ``[*B, N, d]``.
    """
    return TemporalReference(r, theta, weights).force(x, strength, clip)
