"""Small Gaussian helpers shared by the models (pure functions, batched)."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def mvn_log_prob_tril(x: Tensor, mean: Tensor, scale_tril: Tensor) -> Tensor:
    """log N(x; mean, L Lᵀ) for a shared lower-triangular factor ``L``.

    Shapes: ``x`` and ``mean`` broadcast to ``[*S, d]``; ``scale_tril`` is ``[d, d]``.
    Returns ``[*S]``:  -½‖L⁻¹(x-μ)‖² - Σ log L_ii - (d/2) log 2π.
    """
    diff = x - mean
    d = diff.shape[-1]
    flat = diff.reshape(-1, d).T  # [d, M]
    z = torch.linalg.solve_triangular(scale_tril, flat, upper=False)  # [d, M]
    maha = (z * z).sum(0).reshape(diff.shape[:-1])
    half_log_det = torch.log(torch.diagonal(scale_tril)).sum()
    return -0.5 * maha - half_log_det - 0.5 * d * math.log(2 * math.pi)


def diag_normal_log_prob(x: Tensor, mean: Tensor, std: Tensor) -> Tensor:
    """Σ_k log N(x_k; mean_k, std_k²) over the last dimension; ``std`` broadcasts. Returns ``[*S]``."""
    z = (x - mean) / std
    return (-0.5 * z * z - torch.log(std) - 0.5 * math.log(2 * math.pi)).sum(-1)


def nearest_correlation_matrix(a: Tensor, max_iter: int = 1000, tol: float = 1e-10) -> Tensor:
    """The nearest correlation matrix in the Frobenius norm (Higham 2002, alternating projections
    with Dykstra's correction).

    Alternates the projection onto the PSD cone (clip negative eigenvalues) and onto the unit-diagonal
    set. ``a``: ``[d, d]`` symmetric. Returns a symmetric PSD matrix with unit diagonal, in float64.
    """
    y = a.to(torch.float64).clone()
    ds = torch.zeros_like(y)
    x = y
    for _ in range(max_iter):
        r = y - ds
        evals, evecs = torch.linalg.eigh(r)
        x = (evecs * evals.clamp_min(0.0)) @ evecs.T
        ds = x - r
        y_new = x.clone()
        y_new.fill_diagonal_(1.0)
        if torch.linalg.norm(y_new - y) <= tol * torch.linalg.norm(y):
            y = y_new
            break
        y = y_new
    return (y + y.T) / 2


def make_positive_definite(c: Tensor, min_eig: float = 1e-3) -> Tensor:
    """Raise the spectrum of a PSD correlation matrix to ``min_eig`` and renormalise the diagonal,
    so its Cholesky factor exists. ``c``: ``[d, d]``; returns ``[d, d]`` float64."""
    evals, evecs = torch.linalg.eigh(c.to(torch.float64))
    c = (evecs * evals.clamp_min(min_eig)) @ evecs.T
    s = torch.sqrt(torch.diagonal(c))
    return c / s[:, None] / s[None, :]
