"""The predicted prior p̂ of a belief update, and its score (SPEC §4, step 2)."""

from __future__ import annotations

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


class SmoothedPrior:
    """``p̂(x) = Σ_j w_j N(x; μ_j, S)`` with ``S = Σ_T + h² Σ̂`` shared by all components.

    ``μ_j = transition_mean(X_t[j], a)`` ``[*B, N, d]``, ``Σ_T`` the process-noise covariance, ``Σ̂``
    the weighted covariance of the ``μ_j`` and ``h`` Silverman's factor. With ``L = chol(S)``,
    ``z = L⁻¹x`` and ``m_j = L⁻¹μ_j``:

        log p̂(x) = logsumexp_j(log w_j − ½‖z − m_j‖²) − Σ log L_ii − (d/2) log 2π
        ∇ log p̂(x) = −L⁻ᵀ (z − Σ_j r_j m_j),   r_j = softmax_j(log w_j − ½‖z − m_j‖²)

    The responsibilities come from one ``[N, N]`` matmul per belief; nothing of size ``[N, N, d]``.
    """

    def __init__(self, means: Tensor, process_scale_tril: Tensor, log_weights: Tensor | None = None,
                 bandwidth_factor: float | None = None, ridge: float = 1e-6) -> None:
        n, d = means.shape[-2], means.shape[-1]
        h = silverman_factor(n, d) if bandwidth_factor is None else bandwidth_factor
        process_cov = process_scale_tril @ process_scale_tril.transpose(-1, -2)
        cov = process_cov + h * h * weighted_covariance(means, log_weights)
        cov = cov + ridge * torch.eye(d, dtype=means.dtype, device=means.device)
        self.scale_tril = torch.linalg.cholesky(cov)  # [*B, d, d]
        self.means = means
        self.whitened_means = self._whiten(means)  # [*B, N, d]
        n_tensor = torch.tensor(float(n), dtype=means.dtype, device=means.device)
        self.log_weights = (torch.full(means.shape[:-1], 0.0, dtype=means.dtype, device=means.device) - torch.log(n_tensor)
                            if log_weights is None else torch.log_softmax(log_weights, dim=-1))
        self._m_sq = (self.whitened_means**2).sum(-1)  # [*B, N]

    def _whiten(self, x: Tensor) -> Tensor:
        """``L⁻¹ x`` for points ``[*B, M, d]``."""
        return torch.linalg.solve_triangular(self.scale_tril, x.transpose(-1, -2), upper=False).transpose(-1, -2)

    def _logits(self, z: Tensor) -> Tensor:
        z_sq = (z * z).sum(-1, keepdim=True)
        sq = z_sq + self._m_sq.unsqueeze(-2) - 2.0 * (z @ self.whitened_means.transpose(-1, -2))
        return self.log_weights.unsqueeze(-2) - 0.5 * sq.clamp_min(0.0)  # [*B, M, N]

    def log_prob(self, x: Tensor) -> Tensor:
        """``log p̂(x)`` for ``x`` ``[*B, M, d]`` -> ``[*B, M]``."""
        d = x.shape[-1]
        z = self._whiten(x)
        log_det = torch.log(torch.diagonal(self.scale_tril, dim1=-2, dim2=-1)).sum(-1)
        return (torch.logsumexp(self._logits(z), dim=-1) - log_det.unsqueeze(-1)
                - 0.5 * d * torch.log(torch.tensor(2 * torch.pi, dtype=x.dtype)))

    def score(self, x: Tensor) -> Tensor:
        """``∇ log p̂(x)`` for ``x`` ``[*B, M, d]`` -> ``[*B, M, d]``."""
        z = self._whiten(x)
        r = torch.softmax(self._logits(z), dim=-1)  # [*B, M, N]
        diff = z - r @ self.whitened_means  # [*B, M, d]
        return -torch.linalg.solve_triangular(self.scale_tril.transpose(-1, -2), diff.transpose(-1, -2),
                                              upper=True).transpose(-1, -2)
