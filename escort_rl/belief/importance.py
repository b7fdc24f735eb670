"""Self-normalised importance weights, their effective sample size, and adaptive tempering.

Pure functions on log-weights ``[*B, N]`` (one row per belief), batched, with no host sync.

Samples ``y_j ~ q`` stand for the target ``p`` with the self-normalised weights

    w_j = exp(ℓ_j) / Σ_l exp(ℓ_l),      ℓ_j = log p(y_j) − log q(y_j)   (up to a constant),

whose effective sample size (Kong, 1992) is

    ESS = 1 / Σ_j w_j²   ∈ [1, N].

When the weights degenerate (ESS far below N, as in high dimension or under a sharp likelihood),
a statistic of the weighted set rests on a few samples. :func:`tempered_log_weights` then uses
``β ℓ`` with the largest ``β ∈ [0, 1]`` whose ESS reaches a floor (adaptive tempering, as in
sequential Monte Carlo samplers): the weighted set then stands for ``p^β q^(1−β)``, a distribution
between the proposal and the target, estimated from at least ``floor · N`` effective samples.
``ESS(β)`` is non-increasing in ``β`` (``d log ESS / dβ = 2 (E_β[ℓ] − E_{2β}[ℓ]) ≤ 0``, since the
tilted mean ``E_β[ℓ]`` grows with ``β``), so bisection finds ``β``.

Example:
    >>> import torch
    >>> effective_sample_size(torch.zeros(4))  # equal weights
    tensor(4.)
    >>> effective_sample_size(torch.tensor([0.0, -float("inf"), -float("inf")]))  # one sample
    tensor(1.)
"""

from __future__ import annotations

import torch
from torch import Tensor

TEMPER_BISECTIONS = 30  # halvings of [0, 1]: β to about 1e-9


def normalised_weights(log_weights: Tensor) -> Tensor:
    """``w_j = exp(ℓ_j) / Σ_l exp(ℓ_l)`` along the last dimension: ``[*B, N] -> [*B, N]``.

    Entries of ``−inf`` get weight 0; a row that is all ``−inf`` gets equal weights (nothing
    distinguishes its samples), never NaN.
    """
    all_impossible = torch.isneginf(log_weights).all(-1, keepdim=True)
    safe = torch.where(all_impossible, torch.zeros_like(log_weights), log_weights)
    return torch.softmax(safe, dim=-1)


def effective_sample_size(log_weights: Tensor) -> Tensor:
    """``ESS = 1 / Σ_j w_j²`` of the self-normalised weights of ``log_weights`` ``[*B, N]`` -> ``[*B]``.
    ``N`` for equal weights, 1 when one sample holds all the weight."""
    w = normalised_weights(log_weights)
    return 1.0 / (w * w).sum(-1)


def predictive_log_evidence(log_weights: Tensor, log_likelihood: Tensor) -> Tensor:
    """``log Σ_j w_j p(o | x_j)`` ``[*B]``: the log of the observation's predictive density estimated by
    weighted samples of the prediction (``log_weights`` ``[*B, N]``, normalised or not; the
    log-likelihoods ``[*B, N]``), the increment of a bootstrap filter's log-evidence.

    Example:
        >>> import math
        >>> round(float(predictive_log_evidence(torch.zeros(2), torch.log(torch.tensor([0.2, 0.4])))), 4)
        -1.204
        >>> round(math.log(0.3), 4)
        -1.204
    """
    return torch.logsumexp(log_weights + log_likelihood, -1) - torch.logsumexp(log_weights, -1)


def largest_step_keeping_ess(base: Tensor, direction: Tensor, upper: Tensor, target: float,
                             bisections: int = TEMPER_BISECTIONS) -> Tensor:
    """The largest ``δ ∈ [0, upper]`` with ``ESS(base + δ · direction) ≥ target``, per row, to
    ``upper · 2^−bisections``, by bisection (no host sync); 0 where no ``δ > 0`` reaches it.

    ``base``, ``direction`` ``[*B, N]`` (log-weights and log-likelihoods; ``−inf`` allowed, with
    ``0 · (−inf) = 0``), ``upper`` ``[*B]``, ``target`` a number of particles. It assumes what holds
    for tempering toward a likelihood: the ESS falls as ``δ`` grows, so the set that reaches the
    target is an interval from 0.

    Example:
        >>> base, ell = torch.zeros(1, 4), torch.tensor([[0.0, -10.0, -10.0, -10.0]])
        >>> d = largest_step_keeping_ess(base, ell, torch.ones(1), 2.0)
        >>> bool(0 < d < 1), round(float(effective_sample_size(base + d * ell)), 3)
        (True, 2.0)
    """
    lo, hi = torch.zeros_like(upper), upper.clone()
    for _ in range(bisections):
        mid = 0.5 * (lo + hi)
        ok = effective_sample_size(base + scaled_log_likelihood(direction, mid)) >= target
        lo, hi = torch.where(ok, mid, lo), torch.where(ok, hi, mid)
    return lo


def scaled_log_likelihood(log_lik: Tensor, delta: Tensor) -> Tensor:
    """``δ ℓ`` ``[*B, N]`` for ``δ`` ``[*B]``, with ``0 · (−inf) = 0`` (a particle of zero likelihood keeps
    its weight until some of the likelihood is taken in)."""
    scaled = delta.unsqueeze(-1) * log_lik
    return torch.where(torch.isneginf(log_lik) & (delta.unsqueeze(-1) == 0), torch.zeros_like(scaled), scaled)


def tempered_log_weights(log_weights: Tensor, ess_floor: float) -> tuple[Tensor, Tensor, Tensor]:
    """``β ℓ`` with the largest ``β ∈ [0, 1]`` such that ``ESS(β ℓ) ≥ ess_floor · N``, per row.

    ``log_weights`` ``[*B, N]``; ``ess_floor`` in ``[0, 1]`` (0 never tempers). A row whose ESS
    already reaches the floor keeps ``β = 1``. Returns the tempered log-weights ``[*B, N]``, ``β``
    ``[*B]`` and the untempered ESS ``[*B]``. ``−inf`` entries stay ``−inf`` (weight 0 at every
    ``β > 0``); ``β`` is found by :func:`largest_step_keeping_ess` (no host sync).

    Example:
        >>> ell = torch.tensor([[0.0, -10.0, -10.0, -10.0]])   # ESS ≈ 1.0
        >>> t, beta, ess = tempered_log_weights(ell, 0.5)
        >>> bool(effective_sample_size(t) >= 2.0 - 1e-4), bool(0 < beta < 1)
        (True, True)
    """
    if not (isinstance(ess_floor, (int, float)) and not isinstance(ess_floor, bool) and 0.0 <= ess_floor <= 1.0):
        raise ValueError(f"ess_floor: expected a number in [0, 1], got {ess_floor!r}")
    n = log_weights.shape[-1]
    ess = effective_sample_size(log_weights)
    finite = torch.isfinite(log_weights)
    # centre the finite values so that β ℓ stays well scaled; −inf stays −inf
    centred = torch.where(finite, log_weights - torch.where(finite, log_weights, torch.zeros_like(log_weights))
                          .amax(-1, keepdim=True), log_weights)
    target = ess_floor * n
    # β = 0 (equal weights on the finite entries) always reaches the target
    lo = largest_step_keeping_ess(torch.zeros_like(centred), centred, torch.ones_like(ess), target)
    beta = torch.where(ess >= target, torch.ones_like(ess), lo)
    # β = 0 with −inf entries: keep them impossible (0 · −inf would be NaN)
    tempered = torch.where(finite, beta.unsqueeze(-1) * centred, log_weights)
    return tempered, beta, ess


def weighted_quantile_points(y: Tensor, log_weights: Tensor) -> Tensor:
    """``N`` equally weighted points that stand for the weighted set ``(y_j, w_j)``: deterministic
    systematic resampling with offset ½, i.e. copy ``j`` appears once per level ``(i + ½)/N``,
    ``i = 0 … N−1``, that falls in ``(W_{j−1}, W_j]`` (``W`` the cumulative weights).

    Along any direction, their sorted projections are then the weighted set's quantiles at those
    levels, which is what a 1-D Wasserstein distance to an equally weighted set compares.
    ``y`` ``[*B, N, d]``, ``log_weights`` ``[*B, N]`` -> ``[*B, N, d]``.
    """
    n = y.shape[-2]
    w = normalised_weights(log_weights)
    cumulative = torch.cumsum(w, dim=-1)
    cumulative = cumulative / cumulative[..., -1:].clamp_min(1e-30)
    levels = (torch.arange(n, device=y.device, dtype=w.dtype) + 0.5) / n
    idx = torch.searchsorted(cumulative.contiguous(), levels.expand(*w.shape[:-1], n).contiguous())
    idx = idx.clamp_max(n - 1)
    return torch.gather(y, -2, idx.unsqueeze(-1).expand(*idx.shape, y.shape[-1]))
