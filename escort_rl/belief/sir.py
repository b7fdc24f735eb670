"""SIR: the bootstrap particle filter (Gordon et al. 1993), batched over beliefs."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from escort_rl.belief.base import BeliefFilter, check_output_shape
from escort_rl.belief.checks import OFF
from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.config.params import HasParams, build_params, param


def systematic_resample_indices(log_weights: Tensor, generator: torch.Generator | None = None,
                                num_samples: int | None = None) -> Tensor:
    """Systematic resampling: one uniform offset per belief.

    With normalised weights ``w`` ``[*B, N]`` and ``u ~ U[0, 1)``, draw ``k`` of the new set is
    the index ``i`` with ``C_{i-1} ≤ (u + k)/M < C_i``, where ``C`` is the cumulative sum of ``w``
    and ``M`` = ``num_samples`` (default ``N``). Returns indices ``[*B, M]`` (int64).

    Examples:
        >>> g = torch.Generator().manual_seed(0)
        >>> systematic_resample_indices(torch.log(torch.tensor([0.5, 0.0, 0.5])), g, num_samples=4)
        tensor([0, 0, 2, 2])
    """
    n = log_weights.shape[-1]
    m = n if num_samples is None else int(num_samples)
    w = torch.softmax(log_weights, dim=-1)
    cdf = torch.cumsum(w, dim=-1)
    cdf = cdf / cdf[..., -1:]  # exactly 1 at the top, and flat after the last positive weight
    u = torch.rand((*log_weights.shape[:-1], 1), generator=generator, device=w.device, dtype=w.dtype)
    positions = (u + torch.arange(m, device=w.device, dtype=w.dtype)) / m
    # (u + M - 1)/M can round up to 1.0; keep positions strictly below 1 so that a trailing
    # zero-weight particle (whose cdf value equals 1) is never selected.
    one = torch.ones((), dtype=w.dtype, device=w.device)
    positions = positions.clamp_max(torch.nextafter(one, torch.zeros_like(one)))
    return torch.searchsorted(cdf.contiguous(), positions.contiguous(), right=True).clamp_max(n - 1)


@dataclass(frozen=True)
class SIRParams:
    """:class:`SIRFilter`'s parameters.

    Attributes:
        resample_threshold: resample a belief when ``ESS/N < resample_threshold``; ``1.0`` resamples
            every step, ``0.0`` never.
        roughening: if > 0, after resampling add ``N(0, (roughening·range·N^(-1/d))²)`` per dimension,
            where ``range`` is the per-dimension spread of the resampled particles (Gordon et al.).
            0 is off.
    """

    resample_threshold: float = param(0.5, ge=0, le=1)
    roughening: float = param(0.0, ge=0)


class SIRFilter(HasParams, BeliefFilter):
    """Bootstrap particle filter: propagate, weight by the likelihood, resample when ESS is low.

    Takes :class:`SIRParams` (or its fields as keyword arguments: ``SIRFilter(roughening=0.2)``).

    Attribute ``check_finite`` (default True; see :class:`BeliefFilter`): raise a ``ValueError``
    naming the culprit when the input belief, what the model's ``transition`` or
    ``observation_log_prob`` returns, or the result holds a NaN or an inf (a ``-inf``
    log-likelihood is a zero likelihood, and allowed). One host synchronisation per update.

    If every particle of a belief has zero likelihood (all ``-inf``), that belief keeps its prior
    weights (the propagated particles with the input log-weights) instead of becoming NaN.
    """

    Params = SIRParams

    def __init__(self, params: SIRParams | None = None, **kwargs) -> None:
        self.params = build_params(SIRParams, params, kwargs, owner=type(self).__name__)

    def __repr__(self) -> str:
        extra = "" if self.check_finite else ", check_finite=False"
        return f"SIRFilter(resample_threshold={self.resample_threshold}, roughening={self.roughening}{extra})"

    def _update(self, model, belief, action, observation, generator, *, guard=None):
        guard = OFF if guard is None else guard
        x = belief.particles
        n, d = x.shape[-2], x.shape[-1]
        x_next, a = self._predict(model, belief, action, generator, guard)
        log_lik = model.observation_log_prob(observation.unsqueeze(-2), x_next, a)  # [*B, N]
        check_output_shape("model.observation_log_prob", log_lik, x.shape[:-1], "one log-density per particle, [*B, N]")
        guard.model_log_density("model.observation_log_prob", log_lik)
        log_w = belief.log_weights + log_lik
        all_neg_inf = torch.isneginf(log_w).all(-1, keepdim=True)
        # If every particle has zero likelihood, keep the prior weights instead of producing NaN.
        log_w = torch.where(all_neg_inf, belief.log_weights, log_w)
        log_w = log_w - torch.logsumexp(log_w, dim=-1, keepdim=True)

        ess_ratio = 1.0 / (torch.exp(2 * log_w).sum(-1) * n)  # [*B]
        self._record_importance(ess_ratio, torch.ones_like(ess_ratio))
        resample = ess_ratio < self.resample_threshold
        if self.resample_threshold >= 1.0:
            resample = torch.ones_like(resample)
        if resample.any():
            idx = systematic_resample_indices(log_w, generator)
            x_res = torch.gather(x_next, -2, idx.unsqueeze(-1).expand(*idx.shape, d))
            if self.roughening > 0:
                spread = x_res.amax(-2, keepdim=True) - x_res.amin(-2, keepdim=True)
                scale = self.roughening * spread * n ** (-1.0 / d)
                eps = torch.randn(x_res.shape, generator=generator, device=x.device, dtype=x.dtype)
                x_res = x_res + scale * eps
            uniform = torch.full_like(log_w, -math.log(n))
            x_next = torch.where(resample[..., None, None], x_res, x_next)
            log_w = torch.where(resample[..., None], uniform, log_w)
        return ParticleBelief(x_next, log_w)
