"""Gaussian observation noise clipped to a box, as POPGym's noisy tasks add it.

POPGym's noisy control tasks observe ``o = clip(h(s') + σ·ε, low, high)`` with ``ε ~ N(0, I)`` per
coordinate (``numpy.clip`` to the observation box). The law of ``o`` is a *censored* Gaussian per
coordinate: inside the box it has the Gaussian density, and each bound carries a point mass, the
Gaussian tail beyond it:

    log O(o_i | m_i) = log N(o_i; m_i, σ²)          if low_i < o_i < high_i
                     = log Φ((m_i − high_i)/σ)       if o_i ≥ high_i   (P(m_i + σε ≥ high_i))
                     = log Φ((low_i − m_i)/σ)        if o_i ≤ low_i    (P(m_i + σε ≤ low_i))

summed over the coordinates. It is a density with respect to Lebesgue measure inside the box plus
a counting measure at the bounds, which is all a filter needs: every particle is weighed against the
same ``o``, so the same branch applies to all of them. ``log Φ`` is ``torch.special.log_ndtr``, finite
and differentiable in ``m`` for every finite argument (no ``log(1 − Φ)`` cancellation), so the
density stays finite and smooth at, and far beyond, the bounds.

Example:
    >>> import torch
    >>> low, high = torch.tensor([-1.0]), torch.tensor([1.0])
    >>> # an observation at the bound, from a mean on the bound: half the mass lies beyond it
    >>> clipped_gaussian_log_prob(torch.tensor([1.0]), torch.tensor([1.0]), 0.1, low, high).exp().item()
    0.5
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def clipped_gaussian_sample(mean: Tensor, std: float, low: Tensor, high: Tensor,
                            generator: torch.Generator | None = None) -> Tensor:
    """``clip(mean + std·ε, low, high)``, ``ε ~ N(0, I)``; ``mean`` itself (not clipped) when
    ``std == 0``, as POPGym's noiseless tasks observe. ``mean`` ``[*S, k]``, ``low``, ``high`` ``[k]``
    -> ``[*S, k]`` in ``mean``'s dtype."""
    if std == 0:
        return mean
    eps = torch.randn(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype)
    return torch.minimum(torch.maximum(mean + std * eps, low.to(mean)), high.to(mean))


def clipped_gaussian_log_prob(o: Tensor, mean: Tensor, std: float, low: Tensor, high: Tensor) -> Tensor:
    """The censored Gaussian log-density above, summed over the last dimension.

    ``o`` ``[*S, k]`` and ``mean`` ``[*S, k]`` broadcast; ``std > 0``; ``low``, ``high`` ``[k]``.
    Returns ``[*S]``. Differentiable in ``mean``: the branch taken depends on ``o`` only, and every
    branch is finite, so ``torch.where`` passes finite gradients everywhere."""
    low, high = low.to(mean), high.to(mean)
    z = (o - mean) / std
    inside = -0.5 * z * z - (math.log(std) + _HALF_LOG_2PI)
    above = torch.special.log_ndtr((mean - high) / std)
    below = torch.special.log_ndtr((low - mean) / std)
    per_coordinate = torch.where(o >= high, above, torch.where(o <= low, below, inside))
    return per_coordinate.sum(-1)


class ClippedGaussianObservation:
    """The observation part of the model protocol for ``o = clip(m(s') + σ ε, low, high)``, POPGym's
    noisy observations: a model mixes it in and defines ``observation_mean(s')`` ``[*S, obs_dim]``,
    ``obs_noise`` (the σ it draws with; 0: the noiseless ``m(s')``, unclipped), ``observation_std`` (the
    density's σ, floored) and the box ``obs_low``, ``obs_high`` ``[obs_dim]``."""

    obs_noise: float
    observation_std: float
    obs_low: Tensor
    obs_high: Tensor

    def observe(self, s_next: Tensor, a: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """``clip(m(s') + obs_noise·ε, low, high)``, and ``m(s')`` when ``obs_noise = 0``, as POPGym.
        ``[*S, d]`` -> ``[*S, obs_dim]``."""
        return clipped_gaussian_sample(self.observation_mean(s_next), self.obs_noise, self.obs_low, self.obs_high,
                                       generator)

    def observation_log_prob(self, o: Tensor, s_next: Tensor, a: Tensor) -> Tensor:
        """The censored Gaussian log-density of ``o`` with std ``observation_std``
        (:func:`clipped_gaussian_log_prob`). ``o`` ``[*S, obs_dim]``, ``s_next`` ``[*S, d]`` (broadcast)
        -> ``[*S]``, differentiable in ``s_next``."""
        if self.observation_std == 0:
            raise ValueError(f"{type(self).__name__}.obs_noise_floor: is 0 on a noiseless task, so the observation "
                             "has no density; a filter needs obs_noise_floor > 0 (e.g. the default 0.01)")
        return clipped_gaussian_log_prob(o, self.observation_mean(s_next), self.observation_std, self.obs_low,
                                         self.obs_high)
