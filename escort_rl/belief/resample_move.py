"""Resample-move SMC with adaptive tempering: a particle filter that does not collapse when the
likelihood is sharp, for references and for models whose posteriors SIR represents by a handful of
particles.

One update from the belief ``{x_{t−1}^i, w^i}`` with action ``a`` and observation ``o``:

1. **Propagate**: ``x^i ~ T(· | x_{t−1}^i, a)``, each particle keeping its parent ``p^i = x_{t−1}^i``; the
   log-likelihoods ``ℓ^i = log p(o | x^i)``.
2. **Bridge the likelihood in stages** (Del Moral, Doucet & Jasra 2006; Jasra et al. 2011): from
   ``β = 0``, each stage takes the largest increment ``δ ∈ (0, 1 − β]`` that keeps the effective sample
   size of the weights ``w^i exp(δ ℓ^i)`` at ``ess_target · N`` or above (found by bisection), so that no
   stage puts its weight on a few particles. The weights become ``w^i exp(δ ℓ^i)`` and ``β ← β + δ``.
3. **Resample, then move** after every stage: resample (``resampling``'s scheme), then ``mcmc_steps``
   random-walk Metropolis moves per particle that leave the stage's target invariant,

       π_β(x | p) ∝ T(x | p, a) · p(o | x)^β,

   proposing ``x* = x + (proposal_scale / √d) · σ ⊙ ε`` with ``ε ~ N(0, I)`` and ``σ`` per coordinate the
   smaller of the belief's standard deviation and that of the particles' moves ``x − p`` (the target is
   no wider than the transition from the parent), accepted with probability
   ``min(1, π_β(x* | p) / π_β(x | p))``. The moves give back the diversity that resampling removes,
   inside each mode.

It ends at ``β = 1`` with equally weighted particles (after ``max_stages`` stages the last increment is
whatever remains). The log-evidence increment is the product over the stages of the mean incremental
weight, ``log p̂(o_t | o_<t) = Σ_s log Σ_i W_s^i exp(δ_s ℓ^i)`` (``W_s`` the stage's normalised
weights), an unbiased estimate of ``p(o_t | o_<t)`` as SIR's is.

The moves act on ``x`` given its parent, so a coordinate that the transition barely moves (a goal that
stays put, a static parameter) keeps its parents' diversity only: after a sharp reading of it the moves
cannot spread it again, as they can the coordinates the transition stirs. Tempering still keeps each
stage's weights on many particles.

It needs the model's ``transition_log_prob`` (the moves' target). Each move calls it and
``observation_log_prob`` once on every particle, so an update costs about ``1 + stages · mcmc_steps``
times a SIR update's likelihood evaluations. With ``ess_target = 0`` and ``mcmc_steps = 0`` it is SIR
resampling every step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from escort_rl.belief.base import BeliefFilter, check_output_shape
from escort_rl.belief.checks import OFF
from escort_rl.belief.importance import effective_sample_size, largest_step_keeping_ess, scaled_log_likelihood
from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.belief.resampling import SCHEMES, resample_indices
from escort_rl.config.params import HasParams, build_params, param

INCREMENT_BISECTIONS = 30
"""Bisections that find each stage's tempering increment (its relative precision is ``2^−30``)."""


@dataclass(frozen=True)
class ResampleMoveParams:
    """:class:`ResampleMoveFilter`'s parameters.

    Attributes:
        ess_target: each stage's increment keeps ``ESS / N`` at this fraction or above.
        mcmc_steps: random-walk Metropolis moves per particle after each stage's resampling.
        proposal_scale: the random walk's step is ``proposal_scale / √d`` times a per-coordinate spread
            (the module docstring; 2.38: the optimal scaling for Gaussian targets).
        max_stages: the most tempering stages an update takes; the last takes all that remains.
        resampling: the scheme (:mod:`escort_rl.belief.resampling`).
    """

    ess_target: float = param(0.5, ge=0, lt=1)
    mcmc_steps: int = param(3, ge=0)
    proposal_scale: float = param(2.38, gt=0)
    max_stages: int = param(20, ge=1)
    resampling: str = param("systematic", choices=sorted(SCHEMES))


def tempering_increment(log_weights: Tensor, log_lik: Tensor, remaining: Tensor, ess_target: float) -> Tensor:
    """The largest ``δ ∈ [0, remaining]`` with ``ESS(log w + δ ℓ) ≥ ess_target · N``, per belief ``[*B]``:
    ``remaining`` where that holds at ``δ = remaining``, and also where no ``δ > 0`` reaches the target
    (the particles of zero likelihood outnumber it: waiting would not help). ``log_weights``, ``log_lik``
    ``[*B, N]``; :func:`~escort_rl.belief.importance.largest_step_keeping_ess` with :data:`INCREMENT_BISECTIONS`
    bisections, no host sync.

    Example:
        >>> lw, ll = torch.zeros(1, 4), torch.tensor([[0.0, -10.0, -10.0, -10.0]])
        >>> d = tempering_increment(lw, ll, torch.ones(1), 0.5)
        >>> bool(0 < d < 1), round(float(effective_sample_size(lw + d * ll)), 3)
        (True, 2.0)
    """
    target = ess_target * log_lik.shape[-1]
    full_ok = effective_sample_size(log_weights + scaled_log_likelihood(log_lik, remaining)) >= target
    lo = largest_step_keeping_ess(log_weights, log_lik, remaining, target, INCREMENT_BISECTIONS)
    return torch.where(full_ok | (lo <= 0), remaining, lo)


class ResampleMoveFilter(HasParams, BeliefFilter):
    """Resample-move SMC with adaptive tempering (see the module docstring). Takes
    :class:`ResampleMoveParams` (or its fields as keyword arguments).

    ``mean_stages`` is the mean number of tempering stages per belief update since the filter was built.
    :meth:`importance_diagnostics` adds ``mean_stage_ess_fraction`` and ``min_stage_ess_fraction``: per
    belief update, the smallest ESS / N among the weights its stages resampled (at least ``ess_target``
    unless the last of ``max_stages`` stages took what remained), its mean and minimum over the updates.
    Its ``mean_ess_fraction`` is SIR's, before any tempering.

    Example:
        >>> from escort_rl.models import LinearGaussian
        >>> model, g = LinearGaussian(state_dim=2, obs_dim=1), torch.Generator().manual_seed(0)
        >>> filt = ResampleMoveFilter(mcmc_steps=2)
        >>> b = filt.init(model, (3,), 200, g)
        >>> b = filt.update(model, b, torch.zeros(3, dtype=torch.long), torch.zeros(3, 1), g)
        >>> tuple(b.particles.shape), bool(torch.isfinite(b.log_evidence).all())
        ((3, 200, 2), True)
    """

    Params = ResampleMoveParams

    def __init__(self, params: ResampleMoveParams | None = None, **kwargs) -> None:
        self.params = build_params(ResampleMoveParams, params, kwargs, owner=type(self).__name__)
        self._stages = (0.0, 0)  # stages summed over beliefs, beliefs
        self._stage_ess = (0.0, 1.0)  # Σ over beliefs of the smallest stage ESS / N of an update, and its minimum

    @property
    def mean_stages(self) -> float:
        total, count = self._stages
        return total / count if count else float("nan")

    def importance_diagnostics(self) -> dict:
        out = super().importance_diagnostics()
        if out:
            total, low = self._stage_ess
            out.update(mean_stage_ess_fraction=total / out["count"], min_stage_ess_fraction=low)
        return out

    def __repr__(self) -> str:
        p = self.params
        return (f"ResampleMoveFilter(ess_target={p.ess_target}, mcmc_steps={p.mcmc_steps}, "
                f"proposal_scale={p.proposal_scale}, max_stages={p.max_stages})")

    def _target(self, model, x: Tensor, parents: Tensor, a: Tensor, observation: Tensor,
                beta: Tensor) -> tuple[Tensor, Tensor]:
        """``(log T(x | parent, a) + β log p(o | x), log p(o | x))``, each ``[*B, N]``."""
        try:
            log_t = model.transition_log_prob(x, parents, a)
        except NotImplementedError as err:
            raise ValueError(f"ResampleMoveFilter: its moves need model.transition_log_prob, which "
                             f"{type(model).__name__} does not give ({err}); use SIRFilter") from None
        check_output_shape("model.transition_log_prob", log_t, x.shape[:-1], "one log-density per particle, [*B, N]")
        log_lik = model.observation_log_prob(observation.unsqueeze(-2), x, a)
        return log_t + scaled_log_likelihood(log_lik, beta), log_lik

    def _move(self, model, x, parents, a, observation, beta, log_lik, moving, generator) -> tuple[Tensor, Tensor]:
        """``mcmc_steps`` random-walk Metropolis moves of the particles of the ``moving`` beliefs ``[*B]``;
        returns ``(x, log_lik)``."""
        d = x.shape[-1]
        if self.params.mcmc_steps == 0:
            return x, log_lik
        spread = torch.minimum(x.std(-2, keepdim=True), (x - parents).std(-2, keepdim=True))
        step = (self.params.proposal_scale / math.sqrt(d)) * spread.clamp_min(1e-12)
        current, _ = self._target(model, x, parents, a, observation, beta)
        for _ in range(self.params.mcmc_steps):
            eps = torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
            proposal = x + step * eps
            proposed, proposal_lik = self._target(model, proposal, parents, a, observation, beta)
            u = torch.rand(current.shape, generator=generator, device=x.device, dtype=x.dtype)
            accept = (torch.log(u) < proposed - current) & moving.unsqueeze(-1)  # NaN (−inf − −inf): rejected
            x = torch.where(accept.unsqueeze(-1), proposal, x)
            current = torch.where(accept, proposed, current)
            log_lik = torch.where(accept, proposal_lik, log_lik)
        return x, log_lik

    def _update(self, model, belief, action, observation, generator, *, guard=None):
        guard = OFF if guard is None else guard
        p = self.params
        parents, n, d = belief.particles, belief.particles.shape[-2], belief.particles.shape[-1]
        x, a = self._predict(model, belief, action, generator, guard)
        log_lik = model.observation_log_prob(observation.unsqueeze(-2), x, a)
        check_output_shape("model.observation_log_prob", log_lik, x.shape[:-1], "one log-density per particle, [*B, N]")
        guard.model_log_density("model.observation_log_prob", log_lik)
        log_w = belief.log_weights - torch.logsumexp(belief.log_weights, -1, keepdim=True)
        ess = effective_sample_size(log_w + log_lik)  # [*B]: SIR's, before any tempering
        beta = torch.zeros_like(ess)
        increment = torch.zeros_like(ess)
        first = None
        stages = torch.zeros_like(ess)
        stage_ess = torch.full_like(ess, float(n))  # the smallest ESS among the weights the stages resample
        for stage in range(p.max_stages):
            remaining = 1.0 - beta
            moving = remaining > 0
            delta = remaining if stage == p.max_stages - 1 else tempering_increment(log_w, log_lik, remaining,
                                                                                    p.ess_target)
            delta = torch.where(moving, delta, torch.zeros_like(delta))
            first = delta if first is None else first
            tilted = log_w + scaled_log_likelihood(log_lik, delta)
            step_evidence = torch.logsumexp(tilted, -1)  # log Σ W exp(δ ℓ), W normalised
            increment = increment + torch.where(moving & torch.isfinite(step_evidence), step_evidence,
                                                torch.zeros_like(step_evidence))
            tilted = torch.where(torch.isneginf(tilted).all(-1, keepdim=True), log_w, tilted)  # all impossible
            log_w = tilted - torch.logsumexp(tilted, -1, keepdim=True)
            stage_ess = torch.where(moving, torch.minimum(stage_ess, effective_sample_size(log_w)), stage_ess)
            beta = torch.where(moving, beta + delta, beta)
            beta = torch.where(beta > 1.0 - 1e-6, torch.ones_like(beta), beta)
            stages = stages + moving.to(stages.dtype)
            idx = resample_indices(log_w, p.resampling, generator)
            take = idx.unsqueeze(-1).expand(*idx.shape, d)  # the action is the belief's, the same for every particle
            resampled = (torch.gather(x, -2, take), torch.gather(parents, -2, take), torch.gather(log_lik, -1, idx))
            keep = moving.unsqueeze(-1)
            x = torch.where(keep.unsqueeze(-1), resampled[0], x)
            parents = torch.where(keep.unsqueeze(-1), resampled[1], parents)
            log_lik = torch.where(keep, resampled[2], log_lik)
            log_w = torch.where(keep, torch.full_like(log_w, -math.log(n)), log_w)
            x, log_lik = self._move(model, x, parents, a, observation, beta, log_lik, moving, generator)
            if not bool((beta < 1.0).any()):
                break
        total, count = self._stages
        self._stages = (total + float(stages.sum()), count + stages.numel())
        self._stage_ess = (self._stage_ess[0] + float(stage_ess.sum()) / n, min(self._stage_ess[1],
                                                                              float(stage_ess.min()) / n))
        self._record_importance(ess / n, first)
        return ParticleBelief(x, log_w).diagnosed(increment, ess, torch.ones_like(ess, dtype=torch.bool),
                                                  previous=belief)
