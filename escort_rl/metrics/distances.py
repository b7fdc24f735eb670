"""Belief-approximation metrics of the synthetic benchmark (paper, appendix "Evaluation Metrics"),
as pure torch functions.

Conventions. ``x`` holds approximating particles, ``y`` reference samples (e.g. exact samples of
the target). Sample sets are ``[N, d]``; functions that say so also take leading batch dimensions
``[..., N, d]``. Inputs of different floating dtypes are promoted to the wider one; integer inputs
are converted to the default float dtype. Every function is differentiable wherever the formula is
(sorting and thresholding are piecewise). Bad shapes or values raise :class:`ValueError` naming the
argument.

Summary of the exact definitions (details in each docstring):

* :func:`mmd_squared` — MMD² with k(a, b) = exp(-γ‖a-b‖²), γ = 0.5; the biased V-statistic of the
  paper's formula by default, the unbiased U-statistic on request. It is the SQUARE (no root).
* :func:`wasserstein_1d` — exact W1 between two 1-D empirical distributions (any sizes).
* :func:`sliced_wasserstein` — mean over unit directions θ_l of W1(θ_l·x, θ_l·y) (p = 1), or
  (mean_l W2²)^{1/2} (p = 2); directions seeded (seed 0 unless a generator is given).
* :func:`weighted_wasserstein_1d`, :func:`weighted_sliced_wasserstein`, :func:`kernel_mean` and
  :func:`weighted_mmd_squared` — the same distances between *weighted* sample sets, batched over
  leading dimensions (protocol (a)'s comparison with a reference posterior).
* :func:`mode_coverage` — fraction of modes k with more than 0.05/K of the particles within τ = 1
  (the paper's ball; degenerate from about 20D, where exact samples lie far outside it).
* :func:`mode_coverage_mahalanobis` — the same count with each component's own ellipsoid: particles
  whose Mahalanobis distance to component k is within its χ²_d quantile (valid at every dimension).
* :func:`correlation_error` — ‖C_true − C_hat‖_F.
* :func:`rmse_of_mean` — ‖mean(x) − μ‖₂ / √d (root mean square over coordinates).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "mmd_squared",
    "wasserstein_1d",
    "sliced_wasserstein",
    "random_projections",
    "weighted_wasserstein_1d",
    "weighted_sliced_wasserstein",
    "kernel_mean",
    "weighted_mmd_squared",
    "mode_fractions",
    "mode_coverage",
    "mode_coverage_mahalanobis",
    "chi2_quantile",
    "correlation_matrix",
    "correlation_error",
    "mixture_mean_and_covariance",
    "mixture_correlation",
    "rmse_of_mean",
]

DEFAULT_PROJECTION_SEED = 0


# ----------------------------------------------------------------------------- input checks

def _as_float(name: str, t) -> Tensor:
    if not isinstance(t, Tensor):
        try:
            t = torch.as_tensor(t)
        except (TypeError, ValueError, RuntimeError) as err:
            raise ValueError(f"{name}: expected a tensor, got {type(t).__name__} ({err})") from None
    if not t.is_floating_point():
        if t.is_complex():
            raise ValueError(f"{name}: expected a real tensor, got dtype {t.dtype}")
        t = t.to(torch.get_default_dtype())
    return t


def _check_finite(name: str, t: Tensor) -> None:
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: contains NaN or Inf")


def _samples(name: str, t, min_n: int = 1, allow_batch: bool = True) -> Tensor:
    """A sample set ``[..., N, d]`` (``[N]`` is read as ``[N, 1]``)."""
    t = _as_float(name, t)
    if t.dim() == 1:
        t = t[:, None]
    if t.dim() < 2 or (not allow_batch and t.dim() != 2):
        want = "[N, d] or [..., N, d]" if allow_batch else "[N, d]"
        raise ValueError(f"{name}: expected {want}, got shape {list(t.shape)}")
    if t.shape[-2] < min_n:
        raise ValueError(f"{name}: expected at least {min_n} sample(s) along dim -2, got shape {list(t.shape)}")
    if t.shape[-1] < 1:
        raise ValueError(f"{name}: expected d >= 1, got shape {list(t.shape)}")
    _check_finite(name, t)
    return t


def _common(*ts: Tensor) -> list[Tensor]:
    dtype = ts[0].dtype
    for t in ts[1:]:
        dtype = torch.promote_types(dtype, t.dtype)
    device = ts[0].device
    return [t.to(device=device, dtype=dtype) for t in ts]


def _weights(name: str, w, batch_n: tuple[int, ...], like: Tensor) -> Tensor:
    """Normalised non-negative weights broadcast to ``batch_n`` = ``(..., N)``."""
    w = _as_float(name, w).to(device=like.device, dtype=like.dtype)
    try:
        w = torch.broadcast_to(w, batch_n)
    except RuntimeError:
        raise ValueError(f"{name}: expected shape {list(batch_n)} (or broadcastable), got {list(w.shape)}") from None
    _check_finite(name, w)
    if bool((w < 0).any()):
        raise ValueError(f"{name}: weights must be non-negative")
    total = w.sum(-1, keepdim=True)
    if bool((total <= 0).any()):
        raise ValueError(f"{name}: weights must not all be zero")
    return w / total


# ----------------------------------------------------------------------------- MMD

def _sq_dists(a: Tensor, b: Tensor) -> Tensor:
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
    """
    unbiased = bool(unbiased)
    min_n = 2 if unbiased else 1
    x = _samples("x", x, min_n)
    y = _samples("y", y, min_n)
    if x.shape[-1] != y.shape[-1]:
        raise ValueError(f"y: expected the same dimension d as x ({x.shape[-1]}), got shape {list(y.shape)}")
    gamma = float(gamma)
    if not (gamma > 0 and math.isfinite(gamma)):
        raise ValueError(f"gamma: expected a positive finite number, got {gamma}")
    x, y = _common(x, y)
    n, m = x.shape[-2], y.shape[-2]
    kxx = torch.exp(-gamma * _sq_dists(x, x))
    kyy = torch.exp(-gamma * _sq_dists(y, y))
    kxy = torch.exp(-gamma * _sq_dists(x, y))
    if unbiased:
        # k(a, a) = 1 exactly for the RBF kernel: remove it analytically.
        sxx = (kxx.sum((-1, -2)) - n) / (n * (n - 1))
        syy = (kyy.sum((-1, -2)) - m) / (m * (m - 1))
    else:
        sxx = kxx.mean((-1, -2))
        syy = kyy.mean((-1, -2))
    return sxx + syy - 2.0 * kxy.mean((-1, -2))


# ----------------------------------------------------------------------------- Wasserstein

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
    """
    x = _as_float("x", x)
    y = _as_float("y", y)
    tensors = []
    for name, t in (("x", x), ("y", y)):
        if t.dim() == 2 and t.shape[-1] == 1:
            t = t[:, 0]
        if t.dim() != 1:
            raise ValueError(f"{name}: expected 1-D samples [N] or [N, 1], got shape {list(t.shape)}")
        if t.shape[0] < 1:
            raise ValueError(f"{name}: expected at least one sample, got shape {list(t.shape)}")
        _check_finite(name, t)
        tensors.append(t)
    x, y = _common(*tensors)
    return _wasserstein_1d_power(x, y, 1)


def random_projections(num_projections: int, dim: int, generator: torch.Generator | None = None,
                       dtype: torch.dtype = torch.float64) -> Tensor:
    """``[L, d]`` directions uniform on the unit sphere S^{d−1}: normalised standard normal draws
    from ``generator`` (CPU; a fresh ``torch.Generator().manual_seed(0)`` if None)."""
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
    x = _samples("x", x, allow_batch=False)
    y = _samples("y", y, allow_batch=False)
    if x.shape[-1] != y.shape[-1]:
        raise ValueError(f"y: expected the same dimension d as x ({x.shape[-1]}), got shape {list(y.shape)}")
    if p not in (1, 2):
        raise ValueError(f"p: expected 1 or 2, got {p}")
    x, y = _common(x, y)
    d = x.shape[-1]
    if projections is None:
        theta = random_projections(num_projections, d, generator, dtype=x.dtype).to(x.device)
    else:
        theta = _as_float("projections", projections)
        if theta.dim() != 2 or theta.shape[-1] != d or theta.shape[0] < 1:
            raise ValueError(f"projections: expected [L, d] with d = {d}, got shape {list(theta.shape)}")
        _check_finite("projections", theta)
        theta = theta.to(device=x.device, dtype=x.dtype)
    px = theta @ x.T  # [L, N]
    py = theta @ y.T  # [L, M]
    per = _wasserstein_1d_power(px, py, p)  # [L]
    if p == 1:
        return per.mean()
    return per.mean().sqrt()


# ----------------------------------------------------------------------------- weighted, batched

def _normalised(name: str, w, like: Tensor) -> Tensor:
    """Weights ``w`` ``[..., N]`` normalised along the last dim (uniform when None); ``like``
    ``[..., N]`` gives N, the dtype and the device."""
    if w is None:
        return torch.full(like.shape, 1.0 / like.shape[-1], dtype=like.dtype, device=like.device)
    w = _as_float(name, w)
    try:
        shape = torch.broadcast_shapes(w.shape, like.shape)
    except RuntimeError:
        raise ValueError(f"{name}: expected shape {list(like.shape)} (or broadcastable), got {list(w.shape)}") from None
    return _weights(name, w, shape, like)


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
    u, v = _as_float("u", u), _as_float("v", v)
    _check_finite("u", u)
    _check_finite("v", v)
    if u.dim() < 1 or v.dim() < 1 or u.shape[-1] < 1 or v.shape[-1] < 1:
        raise ValueError(f"u, v: expected samples [..., N] with N >= 1, got {list(u.shape)} and {list(v.shape)}")
    u, v = _common(u, v)
    wu, wv = _normalised("u_weights", u_weights, u), _normalised("v_weights", v_weights, v)
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
    x, y = _samples("x", x), _samples("y", y)
    if x.shape[-1] != y.shape[-1]:
        raise ValueError(f"y: expected the same dimension d as x ({x.shape[-1]}), got shape {list(y.shape)}")
    theta = _as_float("projections", projections)
    if theta.dim() != 2 or theta.shape[-1] != x.shape[-1] or theta.shape[0] < 1:
        raise ValueError(f"projections: expected [L, d] with d = {x.shape[-1]}, got shape {list(theta.shape)}")
    x, y, theta = _common(x, y, theta.to(x.device))
    px = (x @ theta.T).transpose(-1, -2)  # [..., L, N]
    py = (y @ theta.T).transpose(-1, -2)  # [..., L, M]
    wx = None if x_weights is None else _normalised("x_weights", x_weights, x[..., 0])[..., None, :]
    wy = None if y_weights is None else _normalised("y_weights", y_weights, y[..., 0])[..., None, :]
    return weighted_wasserstein_1d(px, py, wx, wy).mean(-1)


def kernel_mean(x, y, gamma, x_weights=None, y_weights=None) -> Tensor:
    r"""``Σ_i Σ_j w_i v_j exp(−γ ‖x_i − y_j‖²)``, batched; ``gamma`` a positive number or a tensor
    ``[...]`` (one bandwidth per batch element). Shapes as :func:`weighted_mmd_squared`."""
    x, y = _samples("x", x), _samples("y", y)
    if x.shape[-1] != y.shape[-1]:
        raise ValueError(f"y: expected the same dimension d as x ({x.shape[-1]}), got shape {list(y.shape)}")
    x, y = _common(x, y)
    gamma = torch.as_tensor(gamma, dtype=x.dtype, device=x.device)
    if not bool(((gamma > 0) & torch.isfinite(gamma)).all()):
        raise ValueError("gamma: expected positive finite bandwidths")
    wx, wy = _normalised("x_weights", x_weights, x[..., 0]), _normalised("y_weights", y_weights, y[..., 0])
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


# ----------------------------------------------------------------------------- modes

def _means(name: str, means, d: int) -> Tensor:
    means = _as_float(name, means)
    if means.dim() == 1 and d == 1:
        means = means[:, None]
    if means.dim() != 2 or means.shape[-1] != d or means.shape[0] < 1:
        raise ValueError(f"{name}: expected [K, d] with d = {d}, got shape {list(means.shape)}")
    _check_finite(name, means)
    return means


def mode_fractions(particles, means, tau: float = 1.0, weights=None) -> Tensor:
    r"""Fraction of the particles within distance τ of each mode centre.

    ``f_k = (1/N) |{i : ‖x_i − μ_k‖₂ < τ}|`` (strict inequality), or ``Σ_i w_i 1[‖x_i − μ_k‖ < τ]``
    with normalised ``weights``. Shapes: ``particles`` [..., N, d], ``means`` [K, d],
    ``weights`` [..., N] or None. Returns [..., K].
    """
    x = _samples("particles", particles)
    mu = _means("means", means, x.shape[-1])
    tau = float(tau)
    if not (tau > 0 and math.isfinite(tau)):
        raise ValueError(f"tau: expected a positive finite number, got {tau}")
    x, mu = _common(x, mu)
    inside = (_sq_dists(x, mu) < tau * tau).to(x.dtype)  # [..., N, K]
    if weights is None:
        return inside.mean(-2)
    w = _weights("weights", weights, tuple(x.shape[:-1]), x)
    return (w[..., :, None] * inside).sum(-2)


def mode_coverage(particles, means, tau: float = 1.0, threshold: float | None = None,
                  weights=None) -> Tensor:
    r"""Mode coverage ratio (paper, appendix "Evaluation Metrics").

    Mode k is covered iff ``f_k > threshold`` where ``f_k`` is the fraction of particles with
    ``‖x_i − μ_k‖₂ < τ`` (see :func:`mode_fractions`) and ``threshold = 0.05 / K`` by default.
    Returns ``(1/K) Σ_k 1[f_k > threshold]`` in [0, 1]: a scalar, or [...] for batched particles.

    Shapes: ``particles`` [N, d] or [..., N, d], ``means`` [K, d], ``weights`` [..., N] or None.
    """
    f = mode_fractions(particles, means, tau, weights)
    k = f.shape[-1]
    thr = 0.05 / k if threshold is None else float(threshold)
    if not math.isfinite(thr):
        raise ValueError(f"threshold: expected a finite number, got {threshold}")
    return (f > thr).to(f.dtype).mean(-1)


def chi2_quantile(df: int, level: float) -> float:
    r"""The ``level`` quantile of the χ² distribution with ``df`` degrees of freedom: the ``x`` with
    ``P(χ²_df ≤ x) = γ(df/2, x/2) / Γ(df/2) = level``, by bisection on the regularised incomplete gamma
    function in float64 (to about 1e-10 relative). Closed form for ``df = 2``: ``−2 log(1 − level)``.

    Example:
        >>> round(chi2_quantile(2, 0.99), 6), round(-2 * math.log(0.01), 6)
        (9.21034, 9.21034)
    """
    if not (isinstance(df, int) and not isinstance(df, bool) and df >= 1):
        raise ValueError(f"df: expected an int >= 1, got {df!r}")
    if not (0.0 < float(level) < 1.0):
        raise ValueError(f"level: expected a number in (0, 1), got {level!r}")
    a = torch.tensor(df / 2.0, dtype=torch.float64)
    lo, hi = 0.0, float(df) + 10.0 * math.sqrt(2.0 * df) + 50.0  # the tail beyond hi is < 1e-12
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if float(torch.special.gammainc(a, torch.tensor(mid / 2.0, dtype=torch.float64))) < level:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-12 * hi:
            break
    return 0.5 * (lo + hi)


def mode_fractions_mahalanobis(particles, means, covariances, level: float = 0.99) -> Tensor:
    r"""Fraction of the particles inside each component's ``level`` ellipsoid:
    ``f_k = (1/N) |{i : (x_i − μ_k)ᵀ Σ_k⁻¹ (x_i − μ_k) ≤ χ²_{d, level}}|``.

    Exact samples of component ``k`` fall inside with probability ``level`` at every dimension (the
    squared Mahalanobis distance of a Gaussian sample is χ²_d), where a fixed ball of radius τ holds
    almost none of them once ``σ√d ≫ τ``. Shapes: ``particles`` [..., N, d], ``means`` [K, d],
    ``covariances`` [K, d, d] (symmetric positive definite). Returns [..., K].
    """
    x = _samples("particles", particles)
    d = x.shape[-1]
    mu = _means("means", means, d)
    cov = _as_float("covariances", covariances)
    if cov.shape != (mu.shape[0], d, d):
        raise ValueError(f"covariances: expected [K, d, d] = {[mu.shape[0], d, d]}, got shape {list(cov.shape)}")
    x, mu, cov = _common(x, mu, cov)
    tril, info = torch.linalg.cholesky_ex(cov)
    if bool((info != 0).any()):
        raise ValueError("covariances: every component's covariance must be positive definite")
    diff = x[..., None, :] - mu  # [..., N, K, d]
    z = torch.linalg.solve_triangular(tril, diff.unsqueeze(-1), upper=False).squeeze(-1)
    inside = ((z * z).sum(-1) <= chi2_quantile(d, level)).to(x.dtype)  # [..., N, K]
    return inside.mean(-2)


def mode_coverage_mahalanobis(particles, means, covariances, level: float = 0.99,
                              threshold: float | None = None) -> Tensor:
    r"""Mode coverage valid at every dimension: mode ``k`` is covered iff more than ``threshold``
    (default ``0.05 / K``, the paper's) of the particles lie inside its ``level`` ellipsoid
    (:func:`mode_fractions_mahalanobis`). Returns ``(1/K) Σ_k 1[f_k > threshold]`` in [0, 1], [...]
    for batched particles. Exact samples cover component ``k`` whenever ``level · w_k`` exceeds the
    threshold with margin (every target of the benchmark: ``w_k ≥ 0.08``, ``0.05/K ≤ 0.025``).
    """
    f = mode_fractions_mahalanobis(particles, means, covariances, level)
    k = f.shape[-1]
    thr = 0.05 / k if threshold is None else float(threshold)
    if not math.isfinite(thr):
        raise ValueError(f"threshold: expected a finite number, got {threshold}")
    return (f > thr).to(f.dtype).mean(-1)


# ----------------------------------------------------------------------------- correlations

def cov_to_corr(cov: Tensor) -> Tensor:
    """Correlation from covariance [..., d, d]; a zero-variance dimension gets correlation 0 with
    every other dimension and 1 with itself."""
    var = torch.diagonal(cov, dim1=-2, dim2=-1)
    ok = var > 0
    std = torch.where(ok, var, torch.ones_like(var)).sqrt()
    corr = cov / (std[..., :, None] * std[..., None, :])
    both = ok[..., :, None] & ok[..., None, :]
    corr = torch.where(both, corr, torch.zeros_like(corr))
    eye = torch.eye(cov.shape[-1], dtype=torch.bool, device=cov.device)
    corr = torch.where(eye, torch.ones_like(corr), corr)
    return corr.clamp(-1.0, 1.0)


def correlation_matrix(x, weights=None) -> Tensor:
    r"""Sample (Pearson) correlation matrix.

    With normalised weights w (uniform 1/N if None), m = Σ_i w_i x_i and
    ``S = Σ_i w_i (x_i − m)(x_i − m)ᵀ``: ``C_ab = S_ab / √(S_aa S_bb)``. (The N vs N−1 scaling of S
    cancels in C.) Entries are clamped to [−1, 1]; a dimension with zero sample variance is given
    correlation 0 with every other dimension and 1 on the diagonal (instead of NaN).

    Shapes: ``x`` [N, d] or [..., N, d], ``weights`` [..., N] or None. Returns [..., d, d].
    """
    x = _samples("x", x)
    if weights is None:
        m = x.mean(-2, keepdim=True)
        xc = x - m
        cov = xc.transpose(-1, -2) @ xc / x.shape[-2]
    else:
        w = _weights("weights", weights, tuple(x.shape[:-1]), x)
        m = (w[..., :, None] * x).sum(-2, keepdim=True)
        xc = x - m
        cov = (w[..., :, None] * xc).transpose(-1, -2) @ xc
    return cov_to_corr(cov)


def correlation_error(c_true, x, weights=None) -> Tensor:
    r"""Correlation error ``‖C_true − C_hat‖_F`` (Frobenius norm over all d² entries), with
    ``C_hat = correlation_matrix(x, weights)``.

    Shapes: ``c_true`` [d, d], ``x`` [N, d] or [..., N, d]. Returns a scalar or [...].
    """
    x = _samples("x", x)
    c = _as_float("c_true", c_true)
    d = x.shape[-1]
    if c.dim() != 2 or c.shape != (d, d):
        raise ValueError(f"c_true: expected [d, d] with d = {d} (the dimension of x), got shape {list(c.shape)}")
    _check_finite("c_true", c)
    c_hat = correlation_matrix(x, weights)
    c, c_hat = _common(c, c_hat)
    return torch.linalg.matrix_norm(c - c_hat, ord="fro")


def _mixture_args(weights, means, covs) -> tuple[Tensor, Tensor, Tensor]:
    w = _as_float("weights", weights)
    mu = _as_float("means", means)
    cov = _as_float("covs", covs)
    if w.dim() != 1 or w.shape[0] < 1:
        raise ValueError(f"weights: expected [K], got shape {list(w.shape)}")
    k = w.shape[0]
    if mu.dim() != 2 or mu.shape[0] != k:
        raise ValueError(f"means: expected [K, d] with K = {k}, got shape {list(mu.shape)}")
    d = mu.shape[1]
    if cov.shape != (k, d, d):
        raise ValueError(f"covs: expected [K, d, d] = {[k, d, d]}, got shape {list(cov.shape)}")
    for name, t in (("weights", w), ("means", mu), ("covs", cov)):
        _check_finite(name, t)
    if bool((w < 0).any()):
        raise ValueError("weights: must be non-negative")
    total = float(w.sum())
    if abs(total - 1.0) > 1e-6:
        raise ValueError(f"weights: must sum to 1, got {total}")
    return tuple(_common(w, mu, cov))  # type: ignore[return-value]


def mixture_mean_and_covariance(weights, means, covs) -> tuple[Tensor, Tensor]:
    r"""Exact mean and covariance of the Gaussian mixture Σ_k w_k N(μ_k, Σ_k).

    ``μ = Σ_k w_k μ_k`` and ``Σ = Σ_k w_k (Σ_k + μ_k μ_kᵀ) − μ μᵀ`` (law of total covariance,
    computed as ``Σ_k w_k Σ_k + Σ_k w_k (μ_k − μ)(μ_k − μ)ᵀ`` to avoid cancellation).

    Shapes: ``weights`` [K] (non-negative, summing to 1), ``means`` [K, d], ``covs`` [K, d, d].
    Returns (mean [d], covariance [d, d]).
    """
    w, mu, cov = _mixture_args(weights, means, covs)
    mean = w @ mu
    dev = mu - mean
    total = torch.einsum("k,kij->ij", w, cov) + torch.einsum("k,ki,kj->ij", w, dev, dev)
    return mean, 0.5 * (total + total.T)


def mixture_correlation(weights, means, covs) -> Tensor:
    r"""Exact correlation matrix of the whole mixture: ``C_ab = Σ_ab / √(Σ_aa Σ_bb)`` with Σ from
    :func:`mixture_mean_and_covariance`. Returns [d, d]."""
    _, cov = mixture_mean_and_covariance(weights, means, covs)
    return cov_to_corr(cov)


# ----------------------------------------------------------------------------- RMSE

def rmse_of_mean(x, true_mean, weights=None, per_coordinate: bool = True) -> Tensor:
    r"""Error of the particle mean.

    With ``x̄ = (1/N) Σ_i x_i`` (or ``Σ_i w_i x_i`` with normalised ``weights``)::

        per_coordinate=True (default):  RMSE = ‖x̄ − μ‖₂ / √d = √( (1/d) Σ_j (x̄_j − μ_j)² )
        per_coordinate=False:           ‖x̄ − μ‖₂

    i.e. by default the root mean square over the d coordinates of the error of the mean, which is
    comparable across dimensions. The paper's scalability table uses
    ``√((1/T) Σ_t ‖s_t − ŝ_t‖²)`` over T trials without the 1/d; average ``rmse_of_mean(...,
    per_coordinate=False) ** 2`` over trials and take the root to get that.

    Shapes: ``x`` [N, d] or [..., N, d], ``true_mean`` [d] (broadcasts to [..., d]),
    ``weights`` [..., N] or None. Returns a scalar or [...].
    """
    x = _samples("x", x)
    mu = _as_float("true_mean", true_mean)
    d = x.shape[-1]
    if mu.dim() == 0 and d == 1:
        mu = mu[None]
    if mu.dim() < 1 or mu.shape[-1] != d:
        raise ValueError(f"true_mean: expected [d] with d = {d}, got shape {list(mu.shape)}")
    _check_finite("true_mean", mu)
    if weights is None:
        xbar = x.mean(-2)
    else:
        w = _weights("weights", weights, tuple(x.shape[:-1]), x)
        xbar = (w[..., :, None] * x).sum(-2)
    xbar, mu = _common(xbar, mu)
    err = (xbar - mu).pow(2).sum(-1)
    if per_coordinate:
        err = err / d
    return err.sqrt()
