"""ParticleBelief: a batch of weighted particle sets."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from escort_rl.belief.importance import effective_sample_size


@dataclass(frozen=True)
class ParticleBelief:
    """Weighted particles for a batch of beliefs, with the diagnostics of the update that made them.

    Attributes:
        particles: ``[*B, N, d]``.
        log_weights: ``[*B, N]``, normalised so that ``logsumexp(log_weights, -1) == 0``.
            Equal weights (``-log N``) for SVGD and ESCORT.
        log_evidence: ``[*B]``, the running sum of ``log p̂(o_t | o_<t)`` over the updates since the
            filter's ``init`` (0 there): an estimate of ``log p(o_1:t)``. Each filter says what its
            increment is (SIR: the standard unbiased estimate of ``p(o_t | o_<t)``; EnKF: its
            ensemble's Gaussian predictive density; SVGD and ESCORT: ``log Σᵢ wᵢ p(o_t | xᵢ⁻)`` over
            the predicted particles, a heuristic with no guarantee: never use it to rank filters or
            models). Default: zeros.
        ess: ``[*B]``, the effective sample size (in particles) of the update's weights before any
            resampling: ``1 / Σᵢ wᵢ²`` with ``wᵢ ∝ wᵢ⁻ p(o_t | xᵢ⁻)`` (what a bootstrap step would weigh
            the predicted particles with). Low means the observation surprised the predicted cloud.
            Default: that of ``log_weights``.
        resampled: bool ``[*B]``, whether the update resampled. Default: all False.
    """

    particles: Tensor
    log_weights: Tensor
    log_evidence: Tensor | None = None
    ess: Tensor | None = None
    resampled: Tensor | None = None

    def __post_init__(self) -> None:
        shape, device = self.log_weights.shape[:-1], self.log_weights.device
        if self.log_evidence is None:
            object.__setattr__(self, "log_evidence", torch.zeros(shape, dtype=self.log_weights.dtype, device=device))
        if self.ess is None:
            object.__setattr__(self, "ess", effective_sample_size(self.log_weights))
        if self.resampled is None:
            object.__setattr__(self, "resampled", torch.zeros(shape, dtype=torch.bool, device=device))

    def diagnosed(self, log_evidence_increment: Tensor, ess: Tensor, resampled: Tensor | None = None,
                  previous: ParticleBelief | None = None) -> ParticleBelief:
        """This belief with the diagnostics of the update that made it: ``previous``'s log-evidence
        (0 without) plus ``log_evidence_increment`` ``[*B]``, ``ess`` ``[*B]`` and ``resampled``
        (default: none)."""
        base = 0.0 if previous is None else previous.log_evidence
        return ParticleBelief(self.particles, self.log_weights, base + log_evidence_increment, ess,
                              resampled)

    @classmethod
    def uniform(cls, particles: Tensor) -> ParticleBelief:
        """Equal weights for ``particles`` ``[*B, N, d]``."""
        if not isinstance(particles, Tensor) or particles.ndim < 2 or not particles.dtype.is_floating_point:
            got = (f"shape {tuple(particles.shape)}, dtype {particles.dtype}" if isinstance(particles, Tensor)
                   else type(particles).__name__)
            raise ValueError(f"particles: expected a floating-point tensor [*B, N, d] (N particles of dimension d), "
                             f"got {got}; reshape it, e.g. particles.unsqueeze(-1) for N particles of one dimension")
        n = particles.shape[-2]
        log_w = torch.full(particles.shape[:-1], -math.log(n), dtype=particles.dtype, device=particles.device)
        return cls(particles, log_w)

    @property
    def batch_shape(self) -> torch.Size:
        return self.particles.shape[:-2]

    @property
    def num_particles(self) -> int:
        return self.particles.shape[-2]

    @property
    def state_dim(self) -> int:
        return self.particles.shape[-1]

    def weights(self) -> Tensor:
        """Normalised weights ``[*B, N]``."""
        return torch.softmax(self.log_weights, dim=-1)

    def mean(self) -> Tensor:
        """Weighted mean ``Σ_i w_i x_i``: ``[*B, d]``."""
        return (self.weights().unsqueeze(-1) * self.particles).sum(-2)

    def covariance(self) -> Tensor:
        """Weighted covariance ``Σ_i w_i (x_i - x̄)(x_i - x̄)ᵀ``: ``[*B, d, d]``."""
        w = self.weights().unsqueeze(-1)
        centred = self.particles - self.mean().unsqueeze(-2)
        return (w * centred).transpose(-1, -2) @ centred

    def effective_sample_size(self) -> Tensor:
        """ESS = 1 / Σ_i w_i² of the belief's own weights: ``[*B]`` (``ess`` is that of the update's
        weights before resampling)."""
        return effective_sample_size(self.log_weights)
