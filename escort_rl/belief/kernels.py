"""RBF kernels and the SVGD direction, batched over beliefs ``[*B, N, d]``."""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor


def pairwise_sq_dists(x: Tensor) -> Tensor:
    """``D_ij = ‖x_i − x_j‖²`` via ``‖x_i‖² + ‖x_j‖² − 2 x_i·x_j`` (one matmul). ``[*B, N, d] -> [*B, N, N]``."""
    sq = (x * x).sum(-1)
    lead, (n, dim) = x.shape[:-2], x.shape[-2:]
    x3 = x.reshape(-1, n, dim)
    d = torch.baddbmm((sq.unsqueeze(-1) + sq.unsqueeze(-2)).reshape(-1, n, n), x3, x3.transpose(-1, -2), alpha=-2.0)
    return d.clamp_min_(0.0).reshape(*lead, n, n)


def median_bandwidth(sq_dists: Tensor, min_bandwidth: float = 1e-6, max_points: int = 256) -> Tensor:
    """The median heuristic of Liu & Wang (2016): ``h = med / log N``, where ``med`` is the median
    of the squared pairwise distances ``‖x_i − x_j‖²`` over the pairs ``i ≠ j``, for the kernel
    ``k(x, y) = exp(−‖x − y‖² / h)``.

    The median is taken by selection (``kthvalue``), not a full sort, over the ``N(N − 1)/2`` pairs
    ``i < j`` (the matrix is symmetric, so this is the median over ``i ≠ j`` at half the cost). For
    ``N > max_points`` it is taken over the pairs among the first ``max_points`` particles
    (particles are exchangeable, so this is an unbiased estimate of the median over all pairs, at
    O(max_points²) instead of O(N²) cost). ``h`` is floored at ``min_bandwidth`` so that coincident
    particles give a finite kernel; ``log N`` uses the full ``N``. ``[*B, N, N] -> [*B]``.
    """
    n_all = sq_dists.shape[-1]
    if n_all > max_points:
        sq_dists = sq_dists[..., :max_points, :max_points]
    n = sq_dists.shape[-1]
    if n < 2:
        return torch.ones(sq_dists.shape[:-2], dtype=sq_dists.dtype, device=sq_dists.device)
    pairs = sq_dists.reshape(*sq_dists.shape[:-2], n * n)[..., _upper_pairs(n, sq_dists.device)]  # [*B, N(N-1)/2]
    # the median of the N(N-1) off-diagonal values, which come in equal pairs: the ceil(M/2)-th of
    # the M = N(N-1)/2 pairs
    med = pairs.kthvalue((pairs.shape[-1] + 1) // 2, dim=-1).values
    return (med / math.log(max(n_all, 2))).clamp_min(min_bandwidth)


@functools.lru_cache(maxsize=16)
def _upper_pairs(n: int, device: torch.device) -> Tensor:
    """The flat indices ``i·N + j`` of the pairs ``i < j`` of an ``N × N`` matrix (cached per ``N``)."""
    rows, cols = torch.triu_indices(n, n, 1, device=device)
    return rows * n + cols


def svgd_direction(x: Tensor, score: Tensor, bandwidth: Tensor, repulsion: float = 1.0,
                   sq_dists: Tensor | None = None) -> Tensor:
    """The SVGD velocity with the RBF kernel ``k(x, y) = exp(−‖x − y‖²/h)``:

        φ(x_i) = (1/N) Σ_j [ k(x_j, x_i) ∇log p(x_j) + r · ∇_{x_j} k(x_j, x_i) ],
        ∇_{x_j} k(x_j, x_i) = (2/h) (x_i − x_j) k(x_j, x_i),

    where ``r`` is the repulsion scale (the paper's enhanced repulsion uses ``1 + 0.1 d``).
    ``x``, ``score``: ``[*B, N, d]``; ``bandwidth``: ``[*B]``. Returns ``[*B, N, d]``.
    Cost O(N² d) time and O(N²) memory: no ``[N, N, d]`` tensor is built.
    """
    n, d = x.shape[-2], x.shape[-1]
    if sq_dists is None:
        sq_dists = pairwise_sq_dists(x)
    h = bandwidth[..., None, None]
    k = torch.div(sq_dists, -h).exp_()  # [*B, N, N], symmetric; one N×N temporary
    # K·[score, x] as ([score, x]ᵀ Kᵀ)ᵀ: reads K once for K·score and K·x, and a batched matmul with
    # 2d rows runs faster than one with 2d columns (at B = 64, N = 100, d = 10: 0.16 against 0.20 ms)
    both = (torch.cat([score, x], dim=-1).transpose(-1, -2) @ k.transpose(-1, -2)).transpose(-1, -2)
    drive, kx = both[..., :d], both[..., d:]
    repulse = (2.0 / h) * (x * k.sum(-1, keepdim=True) - kx)
    return (drive + repulsion * repulse) / n
