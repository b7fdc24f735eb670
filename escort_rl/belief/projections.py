"""Projections for ESCORT's regularisers: correlation-aware subspaces and 1-D optimal transport
matchings. Batched over beliefs ``[*B, N, d]``."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from escort_rl.belief.importance import weighted_quantile_points
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


def projection_shape(d: int, n_proj: int, proj_dim: int) -> tuple[int, int]:
    """The ``(m, p)`` of the correlation projections in ``d`` dimensions: ``p = min(proj_dim, d)``
    columns each and ``m = min(n_proj, ⌊d / p⌋)`` projections, so that all ``m · p`` directions can be
    orthonormal (the deflation). More projections would repeat directions already held.

    Examples:
        >>> projection_shape(20, 5, 2), projection_shape(5, 5, 2), projection_shape(1, 5, 2)
        ((5, 2), (2, 2), (1, 1))
    """
    p = max(1, min(proj_dim, d))
    return max(1, min(n_proj, d // p)), p


def split_directions(theta: Tensor, m: int, p: int) -> Tensor:
    """Rows ``θ_1 … θ_{m·p}`` ``[*B, m·p, d]`` as ``m`` projection matrices ``A_k = [θ_{kp+1} … θ_{kp+p}]``:
    ``[*B, m, d, p]``."""
    return theta.reshape(*theta.shape[:-2], m, p, theta.shape[-1]).transpose(-1, -2)


def random_deflated_projections(batch_shape, d: int, n_proj: int, proj_dim: int, generator=None,
                                device=None, dtype=torch.float32) -> Tensor:
    """ESCORT-NoProj's projections: ``m`` random ``d × p`` matrices (:func:`projection_shape`) whose
    ``m · p`` columns are jointly orthonormal (a uniformly random orthonormal frame, by QR):
    ``[*B, m, d, p]``."""
    m, p = projection_shape(d, n_proj, proj_dim)
    g = torch.randn(*batch_shape, d, m * p, generator=generator, device=device, dtype=dtype)
    return split_directions(orthonormalise(g).transpose(-1, -2), m, p)


def correlation_projections(x: Tensor, y: Tensor, y_log_weights: Tensor, n_proj: int, proj_dim: int,
                            ascent_steps: int = 10, ascent_lr: float = 0.5,
                            rank_fn: Callable[[Tensor], Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """ESCORT's correlation projections ``A_k`` and their weights ``w_k`` (paper Eq. 4 and its
    appendix: ascent on the projected Wasserstein distance between the particles and the target).

    ``x`` ``[*B, N, d]`` are the particles (``q``); ``y`` ``[*B, M, d]`` with ``y_log_weights``
    ``[*B, M]`` are self-normalised importance samples of the target ``p`` (log of ``p/q_y`` up to a
    constant, where ``q_y`` is what ``y`` was drawn from; :mod:`escort_rl.belief.importance`).

    1. ``ΔC = corr(x) − corr_w(y)``; its eigenvectors in order of ``|eigenvalue|`` give the
       starting directions ``θ_1 … θ_J``, ``J = m · p`` (:func:`projection_shape`), orthonormal.
    2. The weighted set is turned into ``N`` equally weighted quantile points ``ỹ``
       (:func:`~escort_rl.belief.importance.weighted_quantile_points`), and each ``θ_j`` takes
       ``ascent_steps`` steps of gradient ascent on the max-sliced distance
       ``W1_θ = (1/N) Σ_k |θ·x_(k) − θ·ỹ_(k)|`` (:func:`max_sliced_directions` with ``deflate``):
       after each step the directions are re-orthonormalised in order (QR), so ``θ_j`` ascends in
       the orthogonal complement of ``θ_1 … θ_{j−1}`` and the projections do not collapse onto
       one direction.
    3. ``A_k = [θ_{kp+1} … θ_{kp+p}]`` and ``w_k = Σ_{j ∈ A_k} W1_θj / Σ_j W1_θj``.

    Returns ``A`` ``[*B, m, d, p]`` (all ``m · p`` columns orthonormal) and ``w`` ``[*B, m]``,
    computed without gradient tracking of the inputs. ``rank_fn``: as in :func:`max_sliced_directions`.
    """
    d = x.shape[-1]
    m, p = projection_shape(d, n_proj, proj_dim)
    x, y, y_log_weights = x.detach(), y.detach(), y_log_weights.detach()
    delta_c = correlation_from_covariance(weighted_covariance(x)) - correlation_from_covariance(
        weighted_covariance(y, y_log_weights))
    evals, evecs = torch.linalg.eigh(delta_c)  # ascending
    order = torch.argsort(evals.abs(), dim=-1, descending=True)
    evecs = torch.gather(evecs, -1, order.unsqueeze(-2).expand_as(evecs))
    theta0 = evecs[..., : m * p].transpose(-1, -2)  # [*B, J, d], orthonormal rows
    y_points = weighted_quantile_points(y, y_log_weights)
    if y_points.shape[-2] != x.shape[-2]:
        raise ValueError(f"y: expected as many target samples as particles ({x.shape[-2]}), got {y.shape[-2]}")
    theta, weights = max_sliced_directions(x, y_points, theta0, ascent_steps=ascent_steps, ascent_lr=ascent_lr,
                                           rank_fn=rank_fn, deflate=True)
    return split_directions(theta, m, p), weights.reshape(*weights.shape[:-1], m, p).sum(-1)


def projector(projections: Tensor, weights: Tensor) -> Tensor:
    """``Σ_k w_k A_k A_kᵀ``: ``[*B, K, d, p]``, ``[*B, K]`` -> ``[*B, d, d]`` (symmetric)."""
    return (weights[..., None, None] * (projections @ projections.transpose(-1, -2))).sum(-3)


def correlation_force(phi: Tensor, projections: Tensor, weights: Tensor, strength: float,
                      form: str = "velocity", x: Tensor | None = None, proj: Tensor | None = None) -> Tensor:
    """``F_corr = −2λ Σ_k w_k A_k A_kᵀ (φ(x_i) − φ̄)`` (``form="velocity"``): ``−λ`` times the gradient
    of ``R_corr(φ) = E_x Σ_k w_k |A_kᵀ(φ(x) − φ̄)|²`` (paper Eq. 3) with respect to ``φ(x_i)``, per
    particle (the ``1/N`` of the expectation is the functional gradient's measure). It sums to zero over
    the particles and vanishes with ``φ``, so it cannot move a fixed point of SVGD (``docs/DESIGN.md``).
    ``form="position"`` is the appendix's practical form, ``(x_i − x̄)`` in place of ``(φ(x_i) − φ̄)``
    (with the same factor 2: the gradient of ``E_x Σ_k w_k |A_kᵀ(x − x̄)|²``); it does not vanish at
    SVGD's fixed point and contracts the belief along the projections.

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
    return (-2.0 * strength) * (v @ proj)  # proj is symmetric


def random_directions(x: Tensor, n_dirs: int, generator=None) -> Tensor:
    """``n_dirs`` seeded random unit vectors per belief of ``x`` ``[*B, N, d]``: ``[*B, n_dirs, d]``."""
    theta = torch.randn(*x.shape[:-2], n_dirs, x.shape[-1], generator=generator, device=x.device, dtype=x.dtype)
    return theta / torch.linalg.vector_norm(theta, dim=-1, keepdim=True).clamp_min(1e-12)


def max_sliced_directions(x: Tensor, r: Tensor, theta: Tensor, ascent_steps: int = 10,
                          ascent_lr: float = 0.5, rank_fn: Callable[[Tensor], Tensor] | None = None,
                          deflate: bool = False) -> tuple[Tensor, Tensor]:
    """Directions ``θ_j`` that maximise the projected W1 between ``x`` and ``r`` (equal weights).

    Starts from the unit vectors ``theta`` ``[*B, J, d]`` (e.g. :func:`random_directions`) and takes
    ``ascent_steps`` gradient ascent steps on ``W1_θ = (1/N) Σ_k |sort(x θ)_k − sort(r θ)_k|``
    (:func:`projected_w1_grad`), renormalising θ after each step; with ``deflate`` (``J ≤ d``), the
    directions are instead re-orthonormalised in order after each step (QR), so ``θ_j`` ascends in
    the orthogonal complement of ``θ_1 … θ_{j−1}`` and the result is an orthonormal frame.
    ``x``, ``r`` ``[*B, N, d]``. Returns ``θ`` ``[*B, J, d]`` and weights ``w_j ∝ W1_θj`` ``[*B, J]``.
    ``rank_fn`` (e.g. a compiled :func:`permutation_ranks`) orders the projections instead of
    ``torch.sort``: the same result, faster where it is compiled (see :func:`ranks`).
    """
    x, r = x.detach(), r.detach()

    def projected_w1(t: Tensor) -> Tensor:
        if rank_fn is None:
            px = torch.sort(x @ t.transpose(-1, -2), dim=-2).values  # [*B, N, J]
            pr = torch.sort(r @ t.transpose(-1, -2), dim=-2).values
            return (px - pr).abs().mean(-2)  # [*B, J]
        px, pr = t @ x.transpose(-1, -2), t @ r.transpose(-1, -2)  # [*B, J, N]
        return (sort_by_ranks(px, rank_fn(px)) - sort_by_ranks(pr, rank_fn(pr))).abs().mean(-1)

    if deflate and theta.shape[-2] > theta.shape[-1]:
        raise ValueError(f"theta: deflation needs at most d = {theta.shape[-1]} directions, got {theta.shape[-2]}")

    def normalise(t: Tensor) -> Tensor:
        if deflate:
            return orthonormalise(t.transpose(-1, -2)).transpose(-1, -2)
        return t / torch.linalg.vector_norm(t, dim=-1, keepdim=True).clamp_min(1e-12)

    for _ in range(ascent_steps):
        theta = normalise(theta + ascent_lr * projected_w1_grad(x, r, theta, rank_fn))
    theta = theta.detach()
    w1 = projected_w1(theta)
    weights = w1 / w1.sum(-1, keepdim=True).clamp_min(1e-12)
    return theta, weights


def projected_w1_grad(x: Tensor, r: Tensor, theta: Tensor,
                      rank_fn: Callable[[Tensor], Tensor] | None = None) -> Tensor:
    """``∇_θ W1_θ`` for ``W1_θ = (1/N) Σ_k |θ·x_(k) − θ·r_(k)|``, where ``x_(k)`` and ``r_(k)`` are
    the points of rank ``k`` along ``θ``: ``(1/N) Σ_k sign(θ·x_(k) − θ·r_(k)) (x_(k) − r_(k))``
    (the gradient autograd gives through the sort; a test checks it).
    ``x``, ``r`` ``[*B, N, d]``, ``theta`` ``[*B, J, d]``. Returns ``[*B, J, d]``. ``rank_fn``: as in
    :func:`max_sliced_directions`."""
    n = x.shape[-2]
    px, pr = theta @ x.transpose(-1, -2), theta @ r.transpose(-1, -2)  # [*B, J, N]
    # Σ_k s_k x_(k) = Σ_i s_{rank(i)} x_i: the signs in particle order, then one matmul
    if rank_fn is None:
        px, ix = torch.sort(px, dim=-1)
        pr, ir = torch.sort(pr, dim=-1)
        sign = torch.sign(px - pr)  # [*B, J, N], by rank
        sx = torch.zeros_like(sign).scatter_(-1, ix, sign)
        sr = torch.zeros_like(sign).scatter_(-1, ir, sign)
    else:
        rx, rr = rank_fn(px), rank_fn(pr)
        sign = torch.sign(sort_by_ranks(px, rx) - sort_by_ranks(pr, rr))
        sx, sr = torch.gather(sign, -1, rx), torch.gather(sign, -1, rr)
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


RANK_COUNT_MAX = 256  # ranks by counting (O(N²) compares, fused) up to this N; a sort beyond it


def ranks(values: Tensor, break_ties: bool = False) -> Tensor:
    """The rank of each entry along the last dimension, 0 for the smallest:

        rank_i = #{j : v_j < v_i}                      (tied values share the lowest of their ranks),
        rank_i = #{j : v_j < v_i} + #{j < i : v_j = v_i}   with ``break_ties`` (a permutation),

    so distinct values get a permutation of ``0 … N − 1`` either way. ``[*B, N] -> [*B, N]`` (int64).

    It counts with ``O(N²)`` comparisons instead of sorting. Compiled (:func:`torch.compile` fuses
    the comparisons and the sum into one pass) it is several times faster than ``torch.sort`` on a
    CPU for short rows: at ``[64, 5, 100]`` about 0.2 ms (0.37 ms with ``break_ties``) against 1 ms.
    Eager, the ``[*B, N, N]`` comparison tensor makes it slower than a sort, so the uncompiled paths
    sort.

    Example:
        >>> ranks(torch.tensor([0.3, -1.0, 2.0, 0.3]))
        tensor([1, 0, 3, 1])
        >>> ranks(torch.tensor([0.3, -1.0, 2.0, 0.3]), break_ties=True)
        tensor([1, 0, 3, 2])
    """
    mine, other = values.unsqueeze(-1), values.unsqueeze(-2)  # [*B, N, 1] (i), [*B, 1, N] (j)
    below = other < mine
    if break_ties:
        idx = torch.arange(values.shape[-1], device=values.device, dtype=values.dtype)
        below = below | ((other == mine) & (idx < idx.unsqueeze(-1)))
    # float32 counts are exact up to 2^24 and vectorise; int64 sums do not
    return below.to(torch.float32).sum(-1).to(torch.int64)


def permutation_ranks(values: Tensor) -> Tensor:
    """:func:`ranks` with ``break_ties=True``: the rank permutation of every row. ``[*B, N] -> [*B, N]``."""
    return ranks(values, break_ties=True)


def sort_by_ranks(values: Tensor, rank: Tensor) -> Tensor:
    """``values`` ``[*B, N]`` in ascending order, given their rank permutation ``rank`` ``[*B, N]``
    (:func:`permutation_ranks`): what ``torch.sort(values).values`` gives."""
    return torch.empty_like(values).scatter_(-1, rank, values)


class TemporalReference:
    """The reference set ``r`` ``[*B, N, d]`` sorted once along each direction ``θ_j`` ``[*B, J, d]``,
    so that each :meth:`force` call ranks only the moving particles.

    With ``rank_fn`` (a rank permutation such as a compiled :func:`permutation_ranks`) everything
    ranks by counting instead of sorting: the reference is ordered with ``rank_fn`` once, and each
    :meth:`force` counts the particles' ranks (:func:`ranks`). That is the same matching for distinct
    projections, and faster inside a compiled iteration for ``N ≤`` :data:`RANK_COUNT_MAX`
    (particles tied along ``θ_j``, which must coincide along it, are then pulled toward the same
    reference point instead of neighbouring ones)."""

    def __init__(self, r: Tensor, theta: Tensor, weights: Tensor,
                 rank_fn: Callable[[Tensor], Tensor] | None = None) -> None:
        d = r.shape[-1]
        self.count_ranks = rank_fn is not None
        self.theta = theta  # [*B, J, d]
        along = theta @ r.transpose(-1, -2)  # [*B, J, N]
        shape = (*along.shape, d)
        if rank_fn is None:
            order = torch.argsort(along, dim=-1)  # [*B, J, N]: rank -> index
            self.sorted_ref = torch.gather(r.unsqueeze(-3).expand(shape), -2, order.unsqueeze(-1).expand(shape))
        else:  # the same from the rank permutation
            rank = rank_fn(along).unsqueeze(-1).expand(shape)
            self.sorted_ref = torch.empty(shape, dtype=r.dtype, device=r.device).scatter_(
                -2, rank, r.unsqueeze(-3).expand(shape))  # [*B, J, N, d]
        # the weights are folded in: the pull is Σ_j w_j r_{σ_j(i)} − x_i (Σ_j w_j = 1)
        self.weighted_sorted_ref = weights[..., None, None] * self.sorted_ref
        self.weights = weights

    def force(self, x: Tensor, strength: float, clip: float = 10.0) -> Tensor:
        """``F_temp(x_i) = λ Σ_j w_j (r_{σ_j(i)} − x_i)``, clipped elementwise to ``±clip``. ``[*B, N, d]``."""
        along = self.theta @ x.transpose(-1, -2)  # [*B, J, N]
        if self.count_ranks:  # matched[j, i] = w_j r_(rank_j(i)): a gather
            idx = ranks(along).unsqueeze(-1).expand(self.sorted_ref.shape)
            matched = torch.gather(self.weighted_sorted_ref, -2, idx)
        else:  # the same by scattering the sorted reference to the particles' order
            rank_to_i = torch.argsort(along, dim=-1)  # [*B, J, N]
            idx = rank_to_i.unsqueeze(-1).expand(self.sorted_ref.shape)
            matched = torch.zeros_like(self.weighted_sorted_ref).scatter_(-2, idx, self.weighted_sorted_ref)
        pull = matched.sum(-3) - self.weights.sum(-1)[..., None, None] * x
        return (strength * pull).clamp(-clip, clip)


def temporal_force(x: Tensor, r: Tensor, theta: Tensor, weights: Tensor, strength: float,
                   clip: float = 10.0, rank_fn: Callable[[Tensor], Tensor] | None = None) -> Tensor:
    """``F_temp(x_i) = λ Σ_j w_j (r_{σ_j(i)} − x_i)``, clipped elementwise to ``±clip``, where ``σ_j``
    is the sorted 1-D OT matching along ``θ_j`` (:func:`sorted_matching`).

    ``x``, ``r`` ``[*B, N, d]``; ``theta`` ``[*B, J, d]``; ``weights`` ``[*B, J]``. Returns ``[*B, N, d]``.
    """
    return TemporalReference(r, theta, weights, rank_fn).force(x, strength, clip)
