"""ParticleBelief: a batch of weighted particle sets."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class ParticleBelief:
    """Weighted particles for a batch of beliefs.

    Attributes:
        particles: ``[*B, N, d]``.
        log_weights: ``[*B, N]``, normalised so that ``logsumexp(log_weights, -1) == 0``.
            Equal weights (``-log N``) for SVGD and ESCORT.
    """

    particles: Tensor
    log_weights: Tensor

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
        """ESS = 1 / Σ_i w_i²: ``[*B]``."""
        return 1.0 / (self.weights() ** 2).sum(-1)
