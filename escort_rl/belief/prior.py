"""The predicted prior p̂ of a belief update, and its score."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def silverman_factor(n: int, d: int) -> float:
    """Silverman's rule ``h = (4 / (N (d + 2)))^(1/(d + 4))``."""
    return (4.0 / (n * (d + 2))) ** (1.0 / (d + 4))


def weighted_covariance(x: Tensor, log_weights: Tensor | None = None) -> Tensor:
    """``Σ_i w_i (x_i − x̄)(x_i − x̄)ᵀ`` with normalised weights (equal if ``None``). ``[*B, N, d] -> [*B, d, d]``."""
    if log_weights is None:
        w = torch.full(x.shape[:-1], 1.0 / x.shape[-2], dtype=x.dtype, device=x.device)
    else:
        w = torch.softmax(log_weights, dim=-1)
    mean = (w.unsqueeze(-1) * x).sum(-2, keepdim=True)
    c = x - mean
    return (w.unsqueeze(-1) * c).transpose(-1, -2) @ c


class PriorCovarianceError(ValueError):
    """The smoothed prior's covariance cannot be factored: the belief has diverged (particles so far
    apart that the covariance is not positive definite in float, even with a ridge)."""


def robust_cholesky(cov: Tensor, ridge: float = 1e-6, tries: int = 8) -> Tensor:
    """Cholesky factor of a symmetric PSD ``cov`` ``[*B, d, d]``. Where float round-off makes a batch
    element fail (e.g. a spread-out belief whose covariance spans many orders of magnitude), adds
    ``ridge · 10^k · mean(diag)`` to its diagonal, ``k = 0, 1, …``, until it factors."""
    cov = 0.5 * (cov + cov.transpose(-1, -2))
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    scale = torch.diagonal(cov, dim1=-2, dim2=-1).mean(-1).abs().clamp_min(1e-12)[..., None, None]
    factor, info = torch.linalg.cholesky_ex(cov)
    jitter = ridge
    for _ in range(tries):
        failed = (info > 0)[..., None, None]
        if not bool(failed.any()):
            return factor
        cov = torch.where(failed, cov + jitter * scale * eye, cov)
        factor, info = torch.linalg.cholesky_ex(cov)
        jitter *= 10.0
    if bool((info > 0).any()):
        raise PriorCovarianceError("SmoothedPrior: the prior covariance is not positive definite even with a ridge of "
                         f"{jitter:.0e} × its mean variance; are the particles finite?")
    return factor


class SmoothedPrior:
    """``p̂(x) = Σ_j w_j N(x; μ_j, S)`` with ``S = Σ_T + h² Σ̂`` shared by all components.

    ``μ_j = transition_mean(X_t[j], a)`` ``[*B, N, d]``, ``Σ_T`` the process-noise covariance, ``Σ̂``
    the weighted covariance of the ``μ_j`` and ``h`` Silverman's factor. With the precision
    ``P = S⁻¹``:

    The kernel adds ``h² Σ̂`` to the covariance of the predicted prior, whose exact value is
    ``Σ̂ + Σ_T``: every update widens the target by ``1 + h²`` in the directions the observation does
    not inform (``h² ≈ 0.44`` at ``N = 100``, ``d = 10``). ``shrink=True`` moves each centre toward the
    weighted mean first, ``μ_j ← a μ_j + (1 − a) μ̄`` with ``a = sqrt(1 − h²)`` (Liu & West 2001), so
    that the mixture keeps the predicted mean and covariance exactly (``a² Σ̂ + h² Σ̂ + Σ_T``).

        log p̂(x) = logsumexp_j(ℓ_j(x)) − ½ log det(2π S),  ℓ_j(x) = log w_j − ½ (x − μ_j)ᵀ P (x − μ_j)
        ∇ log p̂(x) = −P (x − Σ_j r_j μ_j),   r_j = softmax_j ℓ_j(x)

    Expanding ``ℓ_j = log w_j − ½ xᵀPx + xᵀPμ_j − ½ μ_jᵀPμ_j`` gives the responsibilities from one
    ``[M, N]`` matmul per belief: nothing of size ``[M, N, d]`` is built.
    """

    def __init__(self, means: Tensor, process_scale_tril: Tensor, log_weights: Tensor | None = None,
                 bandwidth_factor: float | None = None, ridge: float = 1e-6, shrink: bool = False) -> None:
        n, d = means.shape[-2], means.shape[-1]
        h = silverman_factor(n, d) if bandwidth_factor is None else bandwidth_factor
        if shrink and not 0 < h < 1:
            raise ValueError(f"SmoothedPrior.shrink: needs a bandwidth factor in (0, 1), got {h}")
        process_cov = process_scale_tril @ process_scale_tril.transpose(-1, -2)
        cov = process_cov + h * h * weighted_covariance(means, log_weights)
        if shrink:
            w = (torch.full(means.shape[:-1], 1.0 / n, dtype=means.dtype, device=means.device) if log_weights is None
                 else torch.softmax(log_weights, dim=-1))
            centre = (w.unsqueeze(-1) * means).sum(-2, keepdim=True)
            a = math.sqrt(1.0 - h * h)
            means = a * means + (1.0 - a) * centre
        cov = cov + ridge * torch.eye(d, dtype=means.dtype, device=means.device)
        self.scale_tril = robust_cholesky(cov)  # [*B, d, d]
        # P = L⁻ᵀ L⁻¹ by a triangular solve (cholesky_inverse checks its input on the host: a sync)
        inv_tril = torch.linalg.solve_triangular(
            self.scale_tril, torch.eye(d, dtype=means.dtype, device=means.device).expand_as(self.scale_tril),
            upper=False)
        self.precision = inv_tril.transpose(-1, -2) @ inv_tril  # [*B, d, d], symmetric
        self.means = means
        self.means_p = means @ self.precision  # μ_j P  [*B, N, d]
        if log_weights is None:
            log_w = torch.full(means.shape[:-1], -math.log(n), dtype=means.dtype, device=means.device)
        else:
            log_w = torch.log_softmax(log_weights, dim=-1)
        self.offset = (log_w - 0.5 * (self.means_p * means).sum(-1)).unsqueeze(-2)  # [*B, 1, N]
        self.means_t = means.transpose(-1, -2).contiguous()  # [*B, d, N]
        log_det = 2 * torch.log(torch.diagonal(self.scale_tril, dim1=-2, dim2=-1)).sum(-1)
        self.log_norm = -0.5 * (log_det + d * math.log(2 * math.pi))  # [*B]

    def log_prob(self, x: Tensor) -> Tensor:
        """``log p̂(x)`` for ``x`` ``[*B, M, d]`` -> ``[*B, M]``."""
        xp = x @ self.precision
        logits = self.offset + xp @ self.means_t - 0.5 * (xp * x).sum(-1, keepdim=True)
        return torch.logsumexp(logits, dim=-1) + self.log_norm.unsqueeze(-1)

    def score(self, x: Tensor) -> Tensor:
        """``∇ log p̂(x)`` for ``x`` ``[*B, M, d]`` -> ``[*B, M, d]``. (The softmax drops the
        ``−½ xᵀPx`` term of ``ℓ_j``: it is the same for every ``j``.)"""
        xp = x @ self.precision  # [*B, M, d]
        r = torch.softmax(self.offset + xp @ self.means_t, dim=-1)  # [*B, M, N]
        # r·μP as ((μP)ᵀ rᵀ)ᵀ: a batched matmul with d rows runs about 3× faster than one with d
        # columns (at B = 64, M = N = 100, d = 10: 0.10 against 0.30 ms)
        return (self.means_p.transpose(-1, -2) @ r.transpose(-1, -2)).transpose(-1, -2) - xp
