"""Distances between particle sets, as pure torch functions.

Conventions. ``x`` holds approximating particles, ``y`` reference samples (e.g. exact samples of
the target). Sample sets are ``[N, d]``; functions that say so also take leading batch dimensions
``[..., N, d]``. Inputs of different floating dtypes are promoted to the wider one; integer inputs
are converted to the default float dtype. Every function is differentiable wherever the formula is
(sorting is piecewise). Bad shapes or values raise :class:`ValueError` naming the argument.

Summary of the exact definitions (details in each docstring):

* :func:`mmd_squared` — MMD² with k(a, b) = exp(-γ‖a-b‖²), γ = 0.5; the biased V-statistic of the
  paper's formula by default, the unbiased U-statistic on request. It is the SQUARE (no root).
* :func:`wasserstein_1d` — exact W1 between two 1-D empirical distributions (any sizes).
* :func:`sliced_wasserstein` — mean over unit directions θ_l of W1(θ_l·x, θ_l·y) (p = 1), or
  (mean_l W2²)^{1/2} (p = 2); directions seeded (seed 0 unless a generator is given,
  :func:`sphere_directions`).
* :func:`weighted_wasserstein_1d`, :func:`weighted_sliced_wasserstein`, :func:`kernel_mean` and
  :func:`weighted_mmd_squared` — the same distances between *weighted* sample sets, batched over
  leading dimensions (the comparison with a reference posterior).
* :func:`median_gamma` — the median-heuristic bandwidth of the RBF kernel.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from escort_rl.metrics.checks import as_float, check_finite, promoted, sample_set, weights_or_uniform

__all__ = [
    "squared_distances",
    "mmd_squared",
    "wasserstein_1d",
    "sliced_wasserstein",
    "sphere_directions",
    "weighted_wasserstein_1d",
    "weighted_sliced_wasserstein",
    "kernel_mean",
    "weighted_mmd_squared",
    "median_gamma",
]

DEFAULT_PROJECTION_SEED = 0


def squared_distances(a: Tensor, b: Tensor) -> Tensor:
    """‖a_i − b_j‖² for ``a`` [..., N, d], ``b`` [..., M, d] -> [..., N, M] (clamped at 0)."""
    aa = (a * a).sum(-1)[..., :, None]
    bb = (b * b).sum(-1)[..., None, :]
    return (aa + bb - 2.0 * a @ b.transpose(-1, -2)).clamp_min(0.0)


def mmd_squared(x, y, gamma: float = 0.5, unbiased: bool = False) -> Tensor:
    r"""Squared maximum mean discrepancy with the RBF kernel k(a, b) = exp(−γ‖a − b‖²).

    Returns MMD² itself, NOT its square root.

    Biased V-statistic (default; the paper's formula)::

        MMD²_b = 1/N² Σ_{i,j} k(x_i, x_j) + 1/M² Σ_{i,j} k(y_i, y_j) − 2/(NM) Σ_{i,j} k(x_i, y_j)

    It is ≥ 0 and exactly 0 when the two sample sets are equal as multisets.

    Unbiased U-statistic (``unbiased=True``, needs N, M ≥ 2): the diagonal terms i = j are dropped
    from the first two sums, which are divided by N(N−1) and M(M−1). Its expectation is the
    population MMD², so it can be negative.

    Shapes: ``x`` [N, d] or [..., N, d], ``y`` [M, d] or [..., M, d] (batch dims broadcast; a 1-D
    tensor [N] is read as [N, 1]). Returns a scalar, or [...] for batched input.

    Examples:
        >>> x = torch.tensor([[0.0], [1.0]])
        >>> float(mmd_squared(x, x))
        0.0
        >>> round(float(mmd_squared(torch.tensor([[0.0]]), torch.tensor([[1.0]]))), 6)  # 2 − 2e^{−1/2}
        0.786939
    """
    unbiased = bool(unbiased)
    min_n = 2 if unbiased else 1
    x = sample_set("x", x, min_n)
    y = sample_set("y", y, min_n)
    if x.shape[-1] != y.shape[-1]:
        raise ValueError(f"y: expected the same dimension d as x ({x.shape[-1]}), got shape {list(y.shape)}")
    gamma = float(gamma)
    if not (gamma > 0 and math.isfinite(gamma)):
        raise ValueError(f"gamma: expected a positive finite number, got {gamma}")
    x, y = promoted(x, y)
    n, m = x.shape[-2], y.shape[-2]
    kxx = torch.exp(-gamma * squared_distances(x, x))
    kyy = torch.exp(-gamma * squared_distances(y, y))
    kxy = torch.exp(-gamma * squared_distances(x, y))
    if unbiased:
        # k(a, a) = 1 exactly for the RBF kernel: remove it analytically.
        sxx = (kxx.sum((-1, -2)) - n) / (n * (n - 1))
        syy = (kyy.sum((-1, -2)) - m) / (m * (m - 1))
    else:
        sxx = kxx.mean((-1, -2))
        syy = kyy.mean((-1, -2))
    return sxx + syy - 2.0 * kxy.mean((-1, -2))


def _wasserstein_1d_power(u: Tensor, v: Tensor, p: float) -> Tensor:
    r"""∫₀¹ |F_u⁻¹(t) − F_v⁻¹(t)|^p dt for empirical samples along the last dim.

    ``u`` [..., N], ``v`` [..., M] with broadcastable batch dims -> [...]. The quantile functions
    are step functions with jumps at t = i/N and t = j/M; on each interval between consecutive
    jump points both are constant, so the integral is an exact finite sum (this is W_p^p).
    """
    n, m = u.shape[-1], v.shape[-1]
    us = torch.sort(u, dim=-1).values
    vs = torch.sort(v, dim=-1).values
    dtype, device = us.dtype, us.device
    # Jump points of both quantile functions, computed in float64 (they only index and weight).
    t = torch.cat([torch.arange(1, n + 1, dtype=torch.float64) / n,
                   torch.arange(1, m + 1, dtype=torch.float64) / m])
    t = torch.sort(t).values
    t_prev = torch.cat([torch.zeros(1, dtype=torch.float64), t[:-1]])
    width = (t - t_prev).clamp_min(0.0)
    mid = 0.5 * (t + t_prev)  # strictly inside each interval of positive width
    iu = torch.clamp(torch.floor(mid * n).long(), max=n - 1).to(device)
    iv = torch.clamp(torch.floor(mid * m).long(), max=m - 1).to(device)
    qu = us.index_select(-1, iu)
    qv = vs.index_select(-1, iv)
    diff = (qu - qv).abs()
    if p != 1:
        diff = diff ** p
    return (diff * width.to(device=device, dtype=dtype)).sum(-1)


def wasserstein_1d(x, y) -> Tensor:
    r"""Exact 1-Wasserstein distance between two 1-D empirical distributions.

    ``W1(x, y) = ∫₀¹ |F_x⁻¹(t) − F_y⁻¹(t)| dt = ∫ |F_x(s) − F_y(s)| ds``, with F the empirical CDFs
    of equally weighted samples; N and M may differ. This is what
    ``scipy.stats.wasserstein_distance(x, y)`` computes. For N = M it is
    ``mean(|sort(x) − sort(y)|)``.

    Shapes: ``x`` [N] (or [N, 1]), ``y`` [M] (or [M, 1]). Returns a scalar tensor.

    Examples:
        >>> float(wasserstein_1d(torch.tensor([0.0, 1.0]), torch.tensor([2.0, 3.0])))  # a shift by 2
        2.0
        >>> float(wasserstein_1d(torch.tensor([0.0]), torch.tensor([0.0, 1.0])))
        0.5
    """
    x = as_float("x", x)
    y = as_float("y", y)
    tensors = []
    for name, t in (("x", x), ("y", y)):
        if t.dim() == 2 and t.shape[-1] == 1:
            t = t[:, 0]
        if t.dim() != 1:
            raise ValueError(f"{name}: expected 1-D samples [N] or [N, 1], got shape {list(t.shape)}")
        if t.shape[0] < 1:
            raise ValueError(f"{name}: expected at least one sample, got shape {list(t.shape)}")
        check_finite(name, t)
        tensors.append(t)
    x, y = promoted(*tensors)
    return _wasserstein_1d_power(x, y, 1)


def sphere_directions(num_projections: int, dim: int, generator: torch.Generator | None = None,
                       dtype: torch.dtype = torch.float64) -> Tensor:
    """``[L, d]`` directions uniform on the unit sphere S^{d−1}: ``θ_l = g_l / ‖g_l‖₂`` for standard
    normal draws ``g_l`` from ``generator`` (CPU; a fresh ``torch.Generator().manual_seed(0)`` if
    None). (Not :func:`escort_rl.belief.projections.random_directions`, which draws per belief.)

    Examples:
        >>> theta = sphere_directions(3, 4)
        >>> theta.shape, bool(torch.allclose(theta.norm(dim=-1), torch.ones(3, dtype=torch.float64)))
        (torch.Size([3, 4]), True)
        >>> torch.equal(theta, sphere_directions(3, 4))  # seeded: the same directions every call
        True
    """
    if int(num_projections) < 1:
        raise ValueError(f"num_projections: expected >= 1, got {num_projections}")
    if generator is None:
        generator = torch.Generator().manual_seed(DEFAULT_PROJECTION_SEED)
    g = torch.randn(int(num_projections), int(dim), generator=generator, dtype=torch.float64)
    g = g / g.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    return g.to(dtype)


def sliced_wasserstein(x, y, num_projections: int = 100, generator: torch.Generator | None = None,
                       p: int = 1, projections=None) -> Tensor:
    r"""Sliced Wasserstein distance with a Monte-Carlo set of L unit directions θ_1..θ_L.

    With the projected samples ⟨θ_l, x_i⟩ and ⟨θ_l, y_j⟩ and the exact 1-D W_p between them::

        p = 1 (default):  SW1 = (1/L) Σ_l W1(θ_l·x, θ_l·y)
        p = 2:            SW2 = ( (1/L) Σ_l W2²(θ_l·x, θ_l·y) )^{1/2}

    i.e. in general ``((1/L) Σ_l W_p^p)^{1/p}``, the same convention as POT's
    ``ot.sliced_wasserstein_distance(x, y, projections=θ.T, p=p)``.

    Directions: ``projections`` [L, d] used as given (not renormalised), else ``num_projections``
    directions uniform on the sphere drawn from ``generator`` — from a generator seeded with 0 when
    None, so the default is deterministic. Shapes: ``x`` [N, d], ``y`` [M, d] (1-D [N] read as
    [N, 1]). Returns a scalar tensor.
    """
    x = sample_set("x", x, allow_batch=False)
    y = sample_set("y", y, allow_batch=False)
    if x.shape[-1] != y.shape[-1]:
        raise ValueError(f"y: expected the same dimension d as x ({x.shape[-1]}), got shape {list(y.shape)}")
    if p not in (1, 2):
        raise ValueError(f"p: expected 1 or 2, got {p}")
    x, y = promoted(x, y)
    d = x.shape[-1]
    if projections is None:
        theta = sphere_directions(num_projections, d, generator, dtype=x.dtype).to(x.device)
    else:
        theta = as_float("projections", projections)
        if theta.dim() != 2 or theta.shape[-1] != d or theta.shape[0] < 1:
            raise ValueError(f"projections: expected [L, d] with d = {d}, got shape {list(theta.shape)}")
        check_finite("projections", theta)
        theta = theta.to(device=x.device, dtype=x.dtype)
    px = theta @ x.T  # [L, N]
    py = theta @ y.T  # [L, M]
    per = _wasserstein_1d_power(px, py, p)  # [L]
    if p == 1:
        return per.mean()
    return per.mean().sqrt()


def weighted_wasserstein_1d(u, v, u_weights=None, v_weights=None) -> Tensor:
    r"""Exact W1 between two weighted 1-D empirical distributions, batched.

    ``W1 = ∫ |F_u(s) − F_v(s)| ds`` with ``F_u(s) = Σ_{i: u_i ≤ s} w_i`` (weights normalised to 1).
    Both CDFs are steps at the pooled points ``z`` (sorted), so the integral is the exact sum
    ``Σ_k |C_k| (z_{k+1} − z_k)``, where ``C_k`` is the cumulative sum of the signed weights
    ``(+w_u, −w_v)`` in the pooled order. This is ``scipy.stats.wasserstein_distance(u, v, u_weights,
    v_weights)``.

    Shapes: ``u`` ``[..., N]``, ``v`` ``[..., M]`` (batch dims broadcast), weights the same shapes or
    None (uniform). Returns ``[...]``.

    Examples:
        >>> float(weighted_wasserstein_1d(torch.tensor([0.0, 1.0]), torch.tensor([0.0, 1.0]),
        ...                               torch.tensor([0.5, 0.5]), torch.tensor([1.0, 0.0])))
        0.5
    """
    u, v = as_float("u", u), as_float("v", v)
    check_finite("u", u)
    check_finite("v", v)
    if u.dim() < 1 or v.dim() < 1 or u.shape[-1] < 1 or v.shape[-1] < 1:
        raise ValueError(f"u, v: expected samples [..., N] with N >= 1, got {list(u.shape)} and {list(v.shape)}")
    u, v = promoted(u, v)
    wu, wv = weights_or_uniform("u_weights", u_weights, u), weights_or_uniform("v_weights", v_weights, v)
    batch = torch.broadcast_shapes(u.shape[:-1], v.shape[:-1], wu.shape[:-1], wv.shape[:-1])
    u, wu = u.expand(*batch, u.shape[-1]), wu.expand(*batch, u.shape[-1])
    v, wv = v.expand(*batch, v.shape[-1]), wv.expand(*batch, v.shape[-1])
    z = torch.cat([u, v], -1)
    signed = torch.cat([wu, -wv], -1)
    z, order = torch.sort(z, dim=-1)
    c = torch.cumsum(signed.gather(-1, order), -1)[..., :-1]
    return (c.abs() * z.diff(dim=-1)).sum(-1)


def weighted_sliced_wasserstein(x, y, projections, x_weights=None, y_weights=None) -> Tensor:
    r"""Sliced W1 between weighted sample sets, batched: ``(1/L) Σ_l W1(θ_l·x, θ_l·y)`` with the
    weighted 1-D W1 of :func:`weighted_wasserstein_1d` and the given directions ``projections``
    ``[L, d]`` (used as given). With uniform weights it equals :func:`sliced_wasserstein`.

    Shapes: ``x`` ``[..., N, d]``, ``y`` ``[..., M, d]``, weights ``[..., N]``, ``[..., M]`` or None.
    Returns ``[...]``.
    """
    x, y = sample_set("x", x), sample_set("y", y)
    if x.shape[-1] != y.shape[-1]:
        raise ValueError(f"y: expected the same dimension d as x ({x.shape[-1]}), got shape {list(y.shape)}")
    theta = as_float("projections", projections)
    if theta.dim() != 2 or theta.shape[-1] != x.shape[-1] or theta.shape[0] < 1:
        raise ValueError(f"projections: expected [L, d] with d = {x.shape[-1]}, got shape {list(theta.shape)}")
    x, y, theta = promoted(x, y, theta.to(x.device))
    px = (x @ theta.T).transpose(-1, -2)  # [..., L, N]
    py = (y @ theta.T).transpose(-1, -2)  # [..., L, M]
    wx = None if x_weights is None else weights_or_uniform("x_weights", x_weights, x[..., 0])[..., None, :]
    wy = None if y_weights is None else weights_or_uniform("y_weights", y_weights, y[..., 0])[..., None, :]
    return weighted_wasserstein_1d(px, py, wx, wy).mean(-1)


def kernel_mean(x, y, gamma, x_weights=None, y_weights=None) -> Tensor:
    r"""``Σ_i Σ_j w_i v_j exp(−γ ‖x_i − y_j‖²)``, batched; ``gamma`` a positive number or a tensor
    ``[...]`` (one bandwidth per batch element). Shapes as :func:`weighted_mmd_squared`."""
    x, y = sample_set("x", x), sample_set("y", y)
    if x.shape[-1] != y.shape[-1]:
        raise ValueError(f"y: expected the same dimension d as x ({x.shape[-1]}), got shape {list(y.shape)}")
    x, y = promoted(x, y)
    gamma = torch.as_tensor(gamma, dtype=x.dtype, device=x.device)
    if not bool(((gamma > 0) & torch.isfinite(gamma)).all()):
        raise ValueError("gamma: expected positive finite bandwidths")
    wx, wy = (weights_or_uniform("x_weights", x_weights, x[..., 0]),
              weights_or_uniform("y_weights", y_weights, y[..., 0]))
    g = gamma[..., None, None]
    # −γ‖x_i − y_j‖² = 2γ x_i·y_j − γ‖x_i‖² − γ‖y_j‖², built in place in one [..., N, M] buffer
    k = (x @ y.transpose(-1, -2)).mul_(2.0 * g)
    k.sub_(g * (x * x).sum(-1)[..., :, None]).sub_(g * (y * y).sum(-1)[..., None, :])
    k.clamp_max_(0.0).exp_()
    return (wx[..., None, :] @ k @ wy[..., :, None])[..., 0, 0]


def weighted_mmd_squared(x, y, gamma, x_weights=None, y_weights=None, yy: Tensor | None = None) -> Tensor:
    r"""MMD² between weighted sample sets with ``k(a, b) = exp(−γ‖a − b‖²)``, batched (the biased
    V-statistic; with uniform weights it equals :func:`mmd_squared`)::

        MMD² = Σ_ij w_i w_j k(x_i, x_j) + Σ_ij v_i v_j k(y_i, y_j) − 2 Σ_ij w_i v_j k(x_i, y_j)

    ``yy``: the second term, when the caller has it already (a fixed reference set). Shapes: ``x``
    ``[..., N, d]``, ``y`` ``[..., M, d]``, weights ``[..., N]``/``[..., M]`` or None (uniform),
    ``gamma`` a number or ``[...]``. Returns ``[...]`` (≥ 0 up to rounding).
    """
    if yy is None:
        yy = kernel_mean(y, y, gamma, y_weights, y_weights)
    return (kernel_mean(x, x, gamma, x_weights, x_weights) + yy
            - 2.0 * kernel_mean(x, y, gamma, x_weights, y_weights))


def median_gamma(y: Tensor) -> Tensor:
    """``γ = 1 / (2 med²)`` for ``k(a, b) = exp(−γ‖a − b‖²)``, with ``med`` the median of the
    pairwise distances ``‖y_i − y_j‖``, ``i < j``, of ``y`` ``[..., M, d]`` (floored at 1e-12)."""
    m = y.shape[-2]
    i, j = torch.triu_indices(m, m, 1)
    sq = ((y[..., i, :] - y[..., j, :]) ** 2).sum(-1)
    med2 = sq.median(-1).values.clamp_min(1e-12)
    return 0.5 / med2

