"""Moments of particle sets and of Gaussian mixtures, and the errors of a particle set's moments.

* :func:`weighted_moments` — weighted mean and covariance of particles.
* :func:`safe_correlation` — correlation from a covariance, defined for zero-variance dimensions.
* :func:`correlation_matrix`, :func:`correlation_error` — ``‖C_true − C_hat‖_F``.
* :func:`mixture_mean_and_covariance`, :func:`mixture_correlation` — exact moments of a mixture.
* :func:`rmse_of_mean` — ‖mean(x) − μ‖₂ / √d (root mean square over coordinates).
"""

from __future__ import annotations

import torch
from torch import Tensor

from escort_rl.belief.projections import correlation_from_covariance
from escort_rl.metrics.checks import as_float, check_finite, normalised_weights, promoted, sample_set

__all__ = [
    "weighted_moments",
    "safe_correlation",
    "correlation_matrix",
    "correlation_error",
    "mixture_mean_and_covariance",
    "mixture_correlation",
    "rmse_of_mean",
]


def weighted_moments(x: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """Mean ``Σ w_i x_i`` ``[..., d]`` and covariance ``Σ w_i (x_i − m)(x_i − m)ᵀ`` ``[..., d, d]`` of
    particles ``x`` ``[..., N, d]`` with normalised weights ``w`` ``[..., N]`` (accumulated in float64)."""
    x64, w64 = x.double(), w.double()
    m = (w64[..., None] * x64).sum(-2)
    xc = x64 - m[..., None, :]
    return m, (w64[..., None] * xc).transpose(-1, -2) @ xc


def safe_correlation(cov: Tensor) -> Tensor:
    r"""Correlation from a covariance ``[..., d, d]``: ``C_ab = Σ_ab / √(Σ_aa Σ_bb)``
    (:func:`~escort_rl.belief.projections.correlation_from_covariance`), with entries clamped to
    [−1, 1]; a zero-variance dimension gets correlation 0 with every other dimension and 1 with
    itself (instead of NaN), and its gradient stays finite.

    Examples:
        >>> safe_correlation(torch.tensor([[4.0, 2.0, 0.0], [2.0, 4.0, 0.0], [0.0, 0.0, 0.0]]))
        tensor([[1.0000, 0.5000, 0.0000],
                [0.5000, 1.0000, 0.0000],
                [0.0000, 0.0000, 1.0000]])
    """
    var = torch.diagonal(cov, dim1=-2, dim2=-1)
    ok = var > 0
    # a zero variance reads as 1 inside the division, so no 0/0 reaches the values or the gradient
    filled = torch.where(ok, var, torch.ones_like(var))
    corr = correlation_from_covariance(cov.diagonal_scatter(filled, dim1=-2, dim2=-1), eps=0.0)
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
    x = sample_set("x", x)
    if weights is None:
        m = x.mean(-2, keepdim=True)
        xc = x - m
        cov = xc.transpose(-1, -2) @ xc / x.shape[-2]
    else:
        w = normalised_weights("weights", weights, tuple(x.shape[:-1]), x)
        m = (w[..., :, None] * x).sum(-2, keepdim=True)
        xc = x - m
        cov = (w[..., :, None] * xc).transpose(-1, -2) @ xc
    return safe_correlation(cov)


def correlation_error(c_true, x, weights=None) -> Tensor:
    r"""Correlation error ``‖C_true − C_hat‖_F`` (Frobenius norm over all d² entries), with
    ``C_hat = correlation_matrix(x, weights)``.

    Shapes: ``c_true`` [d, d], ``x`` [N, d] or [..., N, d]. Returns a scalar or [...].
    """
    x = sample_set("x", x)
    c = as_float("c_true", c_true)
    d = x.shape[-1]
    if c.dim() != 2 or c.shape != (d, d):
        raise ValueError(f"c_true: expected [d, d] with d = {d} (the dimension of x), got shape {list(c.shape)}")
    check_finite("c_true", c)
    c_hat = correlation_matrix(x, weights)
    c, c_hat = promoted(c, c_hat)
    return torch.linalg.matrix_norm(c - c_hat, ord="fro")


def _mixture_args(weights, means, covs) -> tuple[Tensor, Tensor, Tensor]:
    w = as_float("weights", weights)
    mu = as_float("means", means)
    cov = as_float("covs", covs)
    if w.dim() != 1 or w.shape[0] < 1:
        raise ValueError(f"weights: expected [K], got shape {list(w.shape)}")
    k = w.shape[0]
    if mu.dim() != 2 or mu.shape[0] != k:
        raise ValueError(f"means: expected [K, d] with K = {k}, got shape {list(mu.shape)}")
    d = mu.shape[1]
    if cov.shape != (k, d, d):
        raise ValueError(f"covs: expected [K, d, d] = {[k, d, d]}, got shape {list(cov.shape)}")
    for name, t in (("weights", w), ("means", mu), ("covs", cov)):
        check_finite(name, t)
    if bool((w < 0).any()):
        raise ValueError("weights: must be non-negative")
    total = float(w.sum())
    if abs(total - 1.0) > 1e-6:
        raise ValueError(f"weights: must sum to 1, got {total}")
    return tuple(promoted(w, mu, cov))  # type: ignore[return-value]


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
    return safe_correlation(cov)


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

    Examples:
        >>> x = torch.tensor([[1.0, 3.0], [3.0, 5.0]])  # mean (2, 4)
        >>> float(rmse_of_mean(x, torch.tensor([2.0, 1.0])))  # √((0² + 3²) / 2)
        2.1213202476501465
        >>> float(rmse_of_mean(x, torch.tensor([2.0, 1.0]), per_coordinate=False))
        3.0
    """
    x = sample_set("x", x)
    mu = as_float("true_mean", true_mean)
    d = x.shape[-1]
    if mu.dim() == 0 and d == 1:
        mu = mu[None]
    if mu.dim() < 1 or mu.shape[-1] != d:
        raise ValueError(f"true_mean: expected [d] with d = {d}, got shape {list(mu.shape)}")
    check_finite("true_mean", mu)
    if weights is None:
        xbar = x.mean(-2)
    else:
        w = normalised_weights("weights", weights, tuple(x.shape[:-1]), x)
        xbar = (w[..., :, None] * x).sum(-2)
    xbar, mu = promoted(xbar, mu)
    err = (xbar - mu).pow(2).sum(-1)
    if per_coordinate:
        err = err / d
    return err.sqrt()

