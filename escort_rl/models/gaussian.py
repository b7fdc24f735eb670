"""Small Gaussian helpers shared by the models (pure functions, batched)."""

from __future__ import annotations

import math

import torch
from torch import Tensor


class GaussianNoise:
    """A zero-mean Gaussian ``N(0, L Lᵀ)`` with its factor and precision factor precomputed.

    ``scale_tril``: ``[d, d]`` lower-triangular ``L``. :meth:`log_prob` evaluates
    ``-½‖L⁻¹ε‖² - Σ log L_ii - (d/2) log 2π`` with one matmul by the stored ``L⁻¹`` (cheaper
    under autograd than a triangular solve per call).
    """

    def __init__(self, scale_tril: Tensor) -> None:
        self.scale_tril = scale_tril
        eye = torch.eye(scale_tril.shape[-1], dtype=scale_tril.dtype, device=scale_tril.device)
        self.inv_tril_t = torch.linalg.solve_triangular(scale_tril, eye, upper=False).T.contiguous()  # L⁻ᵀ
        d = scale_tril.shape[-1]
        self.log_norm = -torch.log(torch.diagonal(scale_tril)).sum() - 0.5 * d * math.log(2 * math.pi)

    def log_prob(self, eps: Tensor) -> Tensor:
        """``log N(ε; 0, L Lᵀ)`` for ``ε`` ``[*S, d]`` -> ``[*S]`` (in ``ε``'s dtype)."""
        z = eps @ self.inv_tril_t.to(eps.dtype)
        return self.log_norm.to(eps.dtype) - 0.5 * (z * z).sum(-1)

    def sample(self, shape, generator=None) -> Tensor:
        """``[*shape, d]`` draws."""
        d = self.scale_tril.shape[-1]
        e = torch.randn(*shape, d, generator=generator, device=self.scale_tril.device, dtype=self.scale_tril.dtype)
        return e @ self.scale_tril.T


class AdditiveGaussianTransition:
    """The transition part of the model protocol for ``s' = transition_mean(s, a) + ε``,
    ``ε ~ N(0, L Lᵀ)``. A model mixes it in, defines ``transition_mean`` and sets
    ``self._process = GaussianNoise(L)`` in its constructor."""

    _process: GaussianNoise

    def transition_scale_tril(self) -> Tensor:
        """``[d, d]`` Cholesky factor ``L`` of the process-noise covariance."""
        return self._process.scale_tril

    def transition(self, s: Tensor, a: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """``s' = transition_mean(s, a) + L ε``, ``ε ~ N(0, I)``. ``[*S, d]``."""
        mean = self.transition_mean(s, a)
        eps = torch.randn(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype)
        return mean + eps @ self._process.scale_tril.to(mean.dtype).T

    def transition_log_prob(self, s_next: Tensor, s: Tensor, a: Tensor) -> Tensor:
        """``log N(s' − transition_mean(s, a); 0, L Lᵀ)``. Broadcasts; returns ``[*S]``."""
        return self._process.log_prob(s_next - self.transition_mean(s, a))


class FilterNoiseTransition:
    """The transition part of the model protocol for deterministic dynamics under a filter-side
    Gaussian process noise: ``s' = transition_mean(s, a) + diag(σ) ε`` with ``σ = self.process_std``
    ``[d]``. At ``σ = 0`` the step is the deterministic one exactly and has no density, so
    :meth:`transition_log_prob` raises, naming ``process_noise``. A model mixes it in, defines
    ``transition_mean`` and sets ``self.process_std`` (and ``self.process_noise``, its scale)."""

    process_std: Tensor
    process_noise: float

    def transition_scale_tril(self) -> Tensor:
        """``diag(σ)`` ``[d, d]`` (all zeros at ``process_noise = 0``)."""
        return torch.diag(self.process_std)

    def transition(self, s: Tensor, a: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """``transition_mean(s, a) + σ ε``, ``ε ~ N(0, I)``; the deterministic step at ``σ = 0``. ``[*S, d]``."""
        mean = self.transition_mean(s, a)
        if self.process_noise == 0:
            return mean
        eps = torch.randn(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype)
        return mean + eps * self.process_std.to(mean)

    def transition_log_prob(self, s_next: Tensor, s: Tensor, a: Tensor) -> Tensor:
        """``log N(s'; transition_mean(s, a), diag(σ²))`` ``[*S]``; raises at ``process_noise = 0``."""
        if self.process_noise == 0:
            raise ValueError(f"{type(self).__name__}.process_noise: is 0, so the dynamics are deterministic and "
                             "have no density; a filter needs process_noise > 0 (e.g. the default 0.05)")
        std = self.process_std.to(s_next)
        z = (s_next - self.transition_mean(s, a)) / std
        return -0.5 * (z * z).sum(-1) - torch.log(std).sum() - 0.5 * std.shape[-1] * math.log(2 * math.pi)


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


def pair_rows(paper: Tensor, used: Tensor, names: list[str]) -> list[tuple[str, str, str]]:
    """``(label, paper, used)`` table rows, one per pair ``i < j`` the paper's correlation matrix sets
    (non-zero), the values as text."""
    d = paper.shape[0]
    return [(f"rho({names[i]}, {names[j]})", f"{paper[i, j]:.2f}", f"{used[i, j]:.3f}")
            for i in range(d) for j in range(i + 1, d) if paper[i, j] != 0]


def correlation_report(title: str, paper: Tensor, used: Tensor, rows: list[tuple[str, str, str]],
                       column: str = "pair") -> str:
    """A Markdown report of a paper's process-noise correlation matrix ``paper`` and the matrix a model
    uses instead (``used``, the nearest correlation matrix when the paper's is not PSD): the smallest
    eigenvalues, a table of ``rows`` (:func:`pair_rows`) and the largest correlation ``used`` adds
    where the paper has none."""
    paper_min = torch.linalg.eigvalsh(paper).min().item()
    lines = [
        title,
        "",
        f"smallest eigenvalue: paper {paper_min:.4f} ({'not PSD' if paper_min < 0 else 'PSD'}), "
        f"used {torch.linalg.eigvalsh(used).min().item():.4f}",
        "",
        f"| {column} | paper | used |",
        "| --- | --- | --- |",
        *(f"| {label} | {p} | {u} |" for label, p, u in rows),
    ]
    off = (used * (paper == 0)).abs().max().item()
    lines += ["", f"largest |correlation| the used matrix adds where the paper has none: {off:.3f}"]
    return "\n".join(lines)
