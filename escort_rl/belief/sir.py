"""SIR: the bootstrap particle filter (Gordon et al. 1993), batched over beliefs."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from escort_rl.belief.base import BeliefFilter, check_output_shape
from escort_rl.belief.checks import OFF
from escort_rl.belief.importance import predictive_log_evidence
from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.belief.resampling import SCHEMES, effective_sample_size, resample_indices
from escort_rl.config.params import HasParams, build_params, param


@dataclass(frozen=True)
class SIRParams:
    """:class:`SIRFilter`'s parameters.

    Attributes:
        resample_threshold: resample a belief when ``ESS/N < resample_threshold``; ``1.0`` resamples
            every step, ``0.0`` never.
        roughening: if > 0, after resampling add ``N(0, (roughening·range·N^(-1/d))²)`` per dimension,
            where ``range`` is the per-dimension spread of the resampled particles (Gordon et al.).
            0 is off.
        resampling: the scheme (:mod:`escort_rl.belief.resampling`): ``systematic`` (the default: the
            least variance in practice, and the cheapest), ``stratified``, ``residual`` or
            ``multinomial``.
        differentiable: keep the autograd graph through the log-weights, resampling with
            stop-gradient weights (Ścibior & Wood 2021, *Differentiable particle filtering without
            modifying the forward pass*): a resampled particle's log-weight is
            ``log wₐ − stop_grad(log wₐ) − log N`` for its ancestor ``a``, equal in value to the usual
            ``−log N`` but carrying ``∇ log wₐ``. Then ``belief.log_evidence.sum().backward()``
            estimates ``∇θ log p(o_1:T)`` for the parameters θ of the model's observation density (and
            of its transition, where ``model.transition`` is reparameterised). The forward pass is the
            same as without it (every value equal up to rounding).
    """

    resample_threshold: float = param(0.5, ge=0, le=1)
    roughening: float = param(0.0, ge=0)
    resampling: str = param("systematic", choices=sorted(SCHEMES))
    differentiable: bool = param(False)


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
        scheme = "" if self.resampling == "systematic" else f", resampling={self.resampling!r}"
        return (f"SIRFilter(resample_threshold={self.resample_threshold}, roughening={self.roughening}{scheme}"
                f"{extra})")

    def _update(self, model, belief, action, observation, generator, *, guard=None):
        guard = OFF if guard is None else guard
        x = belief.particles
        n, d = x.shape[-2], x.shape[-1]
        x_next, a = self._predict(model, belief, action, generator, guard)
        log_lik = model.observation_log_prob(observation.unsqueeze(-2), x_next, a)  # [*B, N]
        check_output_shape("model.observation_log_prob", log_lik, x.shape[:-1], "one log-density per particle, [*B, N]")
        guard.model_log_density("model.observation_log_prob", log_lik)
        log_w = belief.log_weights + log_lik
        # log p̂(o_t | o_<t) = log Σᵢ wᵢ⁻ p(o_t | xᵢ⁻), the standard unbiased estimate (of p, not of log p)
        increment = predictive_log_evidence(belief.log_weights, log_lik)
        all_neg_inf = torch.isneginf(log_w).all(-1, keepdim=True)
        # If every particle has zero likelihood, keep the prior weights instead of producing NaN.
        log_w = torch.where(all_neg_inf, belief.log_weights, log_w)
        log_w = log_w - torch.logsumexp(log_w, dim=-1, keepdim=True)

        ess = effective_sample_size(log_w)  # [*B], before any resampling
        ess_ratio = ess / n
        self._record_importance(ess_ratio, torch.ones_like(ess_ratio))
        resample = ess_ratio < self.resample_threshold
        if self.resample_threshold >= 1.0:
            resample = torch.ones_like(resample)
        if resample.any():
            idx = resample_indices(log_w, self.resampling, generator)
            x_res = torch.gather(x_next, -2, idx.unsqueeze(-1).expand(*idx.shape, d))
            if self.roughening > 0:
                spread = x_res.amax(-2, keepdim=True) - x_res.amin(-2, keepdim=True)
                scale = self.roughening * spread * n ** (-1.0 / d)
                eps = torch.randn(x_res.shape, generator=generator, device=x.device, dtype=x.dtype)
                x_res = x_res + scale * eps
            uniform = torch.full_like(log_w, -math.log(n))
            if self.differentiable:  # the ancestor's log-weight minus itself: -log N, with its gradient
                ancestor = log_w.gather(-1, idx)
                uniform = uniform + ancestor - ancestor.detach()
            x_next = torch.where(resample[..., None, None], x_res, x_next)
            log_w = torch.where(resample[..., None], uniform, log_w)
        return ParticleBelief(x_next, log_w).diagnosed(increment, ess, resample, previous=belief)
