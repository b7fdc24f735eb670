"""ESCORT and SVGD belief filters, batched over beliefs ``[*B, N, d]``.

One update, for particles ``X_t``, action ``a`` and the next observation ``o``:

1. Predict ``X̃ = transition(X_t, a)``.
2. Target ``log p(x) = log O(o | x, a) + log p̂(x)``, with ``p̂`` the smoothed predicted prior
   (:class:`escort_rl.belief.prior.SmoothedPrior`) or, optionally, the exact transition mixture.
   Its score takes ``∇ log O`` from the model's closed-form ``observation_score`` when the model has
   one, else from autograd (:func:`likelihood_score`).
3. From ``X = X̃``, ``K`` iterations of ``x_i ← x_i + ε · AdaGrad(φ_SVGD + F_corr + F_temp)``.
4. Add Gaussian jitter. No resampling anywhere.

``SVGDFilter`` is the same update with both regularisers off.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from escort_rl.belief.base import BeliefFilter
from escort_rl.belief.checks import (
    OFF,
    FiniteGuard,
)
from escort_rl.belief.compiling import CompiledFunctions, unaliased
from escort_rl.belief.denormals import flush_denormals
from escort_rl.belief.evolution import AdaptiveStop, IterationScalars, evolution_step, jittered
from escort_rl.belief.importance import effective_sample_size, predictive_log_evidence, tempered_log_weights
from escort_rl.belief.kernels import median_bandwidth, pairwise_sq_dists
from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.belief.prior import SmoothedPrior
from escort_rl.belief.projections import (
    RANK_COUNT_MAX,
    TemporalReference,
    correlation_projections,
    max_sliced_directions,
    permutation_ranks,
    projection_shape,
    projector,
    random_deflated_projections,
    random_directions,
)
from escort_rl.belief.scores import (
    MAX_SCORE,
    Channels,
    ScoreTerm,
    gaussian_fit_log_prob,
    likelihood_score,
    log_density_score,
    smoothed_prior_score,
    target_score,
)
from escort_rl.config.params import HasParams, build_params, param
from escort_rl.models.protocol import action_shape, per_particle


@dataclass(frozen=True)
class SVGDParams:
    """:class:`SVGDFilter`'s parameters, shared by :class:`ESCORTParams`.

    Attributes:
        num_steps: ``K``, particle-evolution iterations per update (default 50).
        step_size: ``ε`` of the AdaGrad-normalised step (default 0.1).
        step_decay: ``ε_k = ε / (1 + step_decay · k)`` (default 0: constant).
        adagrad_alpha: memory of the squared-gradient average (default 0.9, as the SVGD reference).
        repulsion: ``"plain"`` (default) or ``"enhanced"``, which scales the kernel-gradient term by
            ``1 + 0.1 d`` (the paper's enhanced repulsion). Enhanced repulsion inflates the
            posterior variance (a fixed point of SVGD with repulsion ``r`` is roughly ``p^(1/r)``),
            so it is an option, not the default.
        bandwidth_every: recompute the median-heuristic bandwidth every this many iterations
            (default 10; the median is a selection over N² distances).
        bandwidth_scale: multiplies the median-heuristic bandwidth (default 1). With well-separated
            modes the median pairwise distance is the distance between modes, so the kernel spans
            several modes and particles move together; a scale below 1 localises the kernel.
        prior: ``"smoothed"`` (default), ``"shrunk"`` (the smoothed prior with its centres shrunk
            toward their mean so that it keeps the predicted covariance instead of widening it by
            ``1 + h²``; :class:`~escort_rl.belief.prior.SmoothedPrior`) or ``"exact"`` (the transition
            mixture, for models that give only ``transition_log_prob``).
        jitter: std of the Gaussian jitter; ``None`` gives ``sqrt(0.01 (1 + 0.1 d))``, 0 turns it off.
        jitter_at: ``"end"`` (default): added to the evolved particles, so the belief
            carries it as spread. ``"start"``: added to the predicted particles the evolution starts
            from, where it still spreads the start but the K iterations then move the particles
            toward the target, so the belief the consumer reads is the evolution's.
        compile: run each iteration (:func:`evolution_step`) through ``torch.compile``, which fuses
            it into a few kernels. The first update of each shape compiles (tens of seconds on a CPU,
            cached on disk afterwards); later updates are several times faster. Default False.
        stop_tolerance: the adaptive stop (default 0: off, every update runs ``K`` iterations). Every
            ``stop_window`` iterations, each belief whose mean and per-coordinate spread both moved
            by less than ``stop_tolerance`` times its spread over the window (:func:`moment_change`)
            stops moving; the loop ends when every belief of the batch has stopped, or at ``K``.
            One host synchronisation per window. :meth:`mean_iterations` reports the iterations used.
        stop_window: iterations between two convergence checks (default 5).
        anneal_cycles: annealed SVGD (D'Angelo & Fortuin, 2021): the score in the SVGD direction is
            multiplied by ``γ_k = (k mod P) / P``, ``P = ceil(anneal_fraction K / anneal_cycles)``,
            for ``k < anneal_fraction K`` and by 1 afterwards, so each cycle starts from pure
            repulsion (the particles spread) and tempers the target back in. 0 (default) is off,
            1 a linear ramp, more a cyclical schedule.
        anneal_fraction: the share of the ``K`` iterations the annealing (and the bandwidth
            schedule) takes (default 0.5).
        bandwidth_start: the bandwidth schedule: the kernel's bandwidth starts at ``bandwidth_start``
            times the median heuristic and shrinks geometrically to it over the first
            ``anneal_fraction K`` iterations (a wider kernel early moves particles between modes).
            1 (default) is off.
    """

    num_steps: int = param(50, ge=0)
    step_size: float = param(0.1, gt=0)
    step_decay: float = param(0.0, ge=0)
    adagrad_alpha: float = param(0.9, ge=0, lt=1)
    repulsion: str = param("plain", choices=["plain", "enhanced"])
    bandwidth_every: int = param(10, ge=1)
    bandwidth_scale: float = param(1.0, gt=0)
    prior: str = param("smoothed", choices=["smoothed", "shrunk", "exact"])
    jitter: Optional[float] = param(None, ge=0)
    jitter_at: str = param("end", choices=["end", "start"])
    compile: bool = param(False)
    stop_tolerance: float = param(0.0, ge=0)
    stop_window: int = param(5, ge=1)
    anneal_cycles: int = param(0, ge=0)
    anneal_fraction: float = param(0.5, gt=0, le=1)
    bandwidth_start: float = param(1.0, gt=0)


@dataclass(frozen=True)
class ESCORTParams(SVGDParams):
    """:class:`ESCORTFilter`'s parameters: SVGD's and the two regularisers'.

    Attributes:
        lambda_corr: ``λ_corr`` (default 0.1; 0 gives ESCORT-NoCorr). With the velocity form the
            particles come to rest where SVGD's do for every ``λ_corr < 0.5`` (the term changes the
            path only); from 0.5 it can reverse the velocity along a projection and diverge, which a
            warning says.
        lambda_temp: ``λ_temp`` (default 0.1; 0 gives ESCORT-NoTemp).
        n_proj: number of correlation projections and of temporal directions (default 5).
        proj_dim: columns of each correlation projection ``A_k`` (default 2).
        projection: ``"learned"`` (eigenvectors of ΔC refined by ascent) or ``"random"``
            (ESCORT-NoProj).
        projection_every: recompute the correlation projections every this many iterations.
        corr_form: ``"velocity"`` (default, damps ``φ − φ̄``) or ``"position"`` (the paper's
            appendix form with ``x − x̄``; it contracts the belief).
        temp_schedule: ``"anneal"`` (default, ``λ_temp (1 − k/K)``) or ``"constant"``.
        temp_clip: elementwise clip of ``F_temp`` (default 10, as the paper).
        temporal_ascent_steps: gradient-ascent steps that refine the directions ``θ_j`` of ``F_temp``
            toward the maximal projected W1 (default 10; each step sorts both sets along every ``θ_j``,
            which at ``K = 15`` costs about as much as ten iterations of the loop).
        projection_ascent_steps: gradient-ascent steps that refine the learned correlation projections
            toward the maximal projected W1 between the particles and the weighted target samples
            (default 10, the same ascent as ``temporal_ascent_steps``).
        likelihood_pull: the paper's ``α w_i (μ_obs − x̃_i)`` pull, applied once after prediction
            when ``> 0`` (needs a model with ``position``-like observations: ``o`` compared with the
            first ``obs_dim`` coordinates). Default 0 (off).
        ess_floor: the correlation projections learn the target from importance samples (the
            predicted particles weighted by the likelihood in a filter update; the starting particles
            weighted by ``p/q`` in :meth:`fit`). When their effective sample size is below
            ``ess_floor · N``, the log-weights are tempered to ``β log w`` with the largest ``β`` that
            reaches it (:func:`~escort_rl.belief.importance.tempered_log_weights`), so the target's
            correlation is never read off one or two particles. Default 0.2; 0 never tempers.
            :meth:`importance_diagnostics` reports the ESS and ``β`` met.

    """

    lambda_corr: float = param(0.1, ge=0)
    lambda_temp: float = param(0.1, ge=0)
    n_proj: int = param(5, ge=1)
    proj_dim: int = param(2, ge=1)
    projection: str = param("learned", choices=["learned", "random"])
    projection_every: int = param(10, ge=1)
    corr_form: str = param("velocity", choices=["velocity", "position"])
    temp_schedule: str = param("anneal", choices=["anneal", "constant"])
    temp_clip: float = param(10.0, gt=0)
    temporal_ascent_steps: int = param(10, ge=0)
    projection_ascent_steps: int = param(10, ge=0)
    likelihood_pull: float = param(0.0, ge=0)
    ess_floor: float = param(0.2, ge=0, le=1)


class ESCORTFilter(HasParams, BeliefFilter):
    """ESCORT: SVGD with a correlation-aware regulariser and a temporal-consistency term.

    Takes :class:`ESCORTParams` (or its fields as keyword arguments: ``ESCORTFilter(num_steps=15)``).

    Attribute ``check_finite`` (default True; see :class:`BeliefFilter`): raise a ``ValueError``
    naming the culprit when the input belief, what the model's methods return (``transition``,
    ``transition_mean``, ``transition_scale_tril``, ``observation_log_prob``, and
    ``observation_score`` or ``transition_log_prob`` at any iteration) or the result holds a NaN or an
    inf (a ``-inf`` log-density is a zero density, and allowed). One host synchronisation per update,
    outside the compiled iteration; :meth:`fit` checks its target the same way.

    Zero likelihood: a particle whose log-likelihood is ``-inf`` has a zero likelihood score (the
    autograd path) and a negligible weight among the target samples of the correlation projections.
    If every particle of a belief has zero likelihood, those weights are equal and the particles
    follow the prior and the closed-form score, if any; nothing becomes NaN.
    """

    Params = ESCORTParams

    def __init__(self, params: ESCORTParams | None = None, **kwargs) -> None:
        self.params = build_params(ESCORTParams, params, kwargs, owner=type(self).__name__)
        if self.corr_form == "velocity" and self.lambda_corr >= 0.5:
            warnings.warn(f"{type(self).__name__}.lambda_corr={self.lambda_corr}: with the velocity form, a projection "
                          "of weight w_k > 1/(2 lambda_corr) reverses SVGD's velocity along it and the particles can "
                          "diverge (docs/DESIGN.md, the correlation term's fixed points); keep lambda_corr < 0.5",
                          stacklevel=2)
        self._compiled = CompiledFunctions(self.compile)
        self._iterations_used = [0.0, 0]  # Σ over updated beliefs of the iterations they ran, and their count

    def mean_iterations(self) -> float:
        """The mean number of iterations a belief ran per update since the filter was built (``K``
        without the adaptive stop; NaN before the first update)."""
        total, count = self._iterations_used
        return float(total) / count if count else float("nan")

    def _record_iterations(self, used: Tensor | int, beliefs: int) -> None:
        total = float(used.sum()) if isinstance(used, Tensor) else float(used) * beliefs
        self._iterations_used = [self._iterations_used[0] + total, self._iterations_used[1] + beliefs]

    def __repr__(self) -> str:
        keys = ("num_steps", "step_size", "repulsion", "lambda_corr", "lambda_temp", "n_proj", "projection",
                "corr_form", "temp_schedule", "prior", "compile")
        extra = "" if self.check_finite else ", check_finite=False"
        return f"{type(self).__name__}(" + ", ".join(f"{k}={getattr(self, k)!r}" for k in keys) + extra + ")"

    # ------------------------------------------------------------------ pieces
    def repulsion_scale(self, d: int) -> float:
        return 1.0 + 0.1 * d if self.repulsion == "enhanced" else 1.0

    def schedule(self, k: int, k_total: int) -> tuple[float, float]:
        """``(γ_k, b_k)`` of iteration ``k`` of ``k_total``: the annealing factor of the score and the
        bandwidth's multiplier (see ``anneal_cycles`` and ``bandwidth_start``); ``(1, 1)`` when both
        are off or after the first ``anneal_fraction`` of the iterations.

        Examples:
            >>> ESCORTFilter(anneal_cycles=2, anneal_fraction=0.5).schedule(3, 20)  # P = ceil(10 / 2) = 5
            (0.6, 1.0)
            >>> ESCORTFilter(bandwidth_start=4.0, anneal_fraction=0.5).schedule(5, 20)
            (1.0, 2.0)
        """
        span = self.anneal_fraction * k_total
        if k >= span:
            return 1.0, 1.0
        gamma = 1.0
        if self.anneal_cycles > 0:
            period = math.ceil(span / self.anneal_cycles)
            gamma = (k % period) / period
        return gamma, self.bandwidth_start ** (1.0 - k / span)

    def jitter_std(self, d: int) -> float:
        return math.sqrt(0.01 * (1.0 + 0.1 * d)) if self.jitter is None else float(self.jitter)

    def _target_score(self, model, observation: Tensor, action: Tensor,
                      prior: tuple[ScoreTerm, Channels]) -> tuple[Callable[[Tensor], tuple[Tensor, Tensor]], Channels]:
        """``x ↦ (∇ log O(o|x, a) + ∇ log p̂(x), counts)``; the likelihood part by :func:`likelihood_score`,
        the prior part a :data:`ScoreTerm`. ``counts`` ``[*B, C]`` counts the particles of each belief
        flagged by each of the ``C`` channels (returned with the function)."""
        return target_score(likelihood_score(model, observation.unsqueeze(-2), action), prior)

    def _exact_prior_score(self, model, particles: Tensor, log_weights: Tensor,
                           action: Tensor) -> tuple[ScoreTerm, Channels]:
        """``∇ log Σ_j w_j T(x | X_t[j], a)`` by autograd, with ``[*B, N, 1, d]`` against ``[*B, 1, N, d]``,
        as a :data:`ScoreTerm` (a NaN or +inf mixture means ``transition_log_prob`` gave one)."""
        src = particles.unsqueeze(-3)  # [*B, 1, N, d]
        a = action.unsqueeze(-2 - len(action_shape(model)))  # [*B, 1, N] ([*B, 1, N, action_dim])
        log_w = torch.log_softmax(log_weights, dim=-1).unsqueeze(-2)

        def mixture(z: Tensor) -> Tensor:
            lp = model.transition_log_prob(z.unsqueeze(-2), src, a)  # [*B, N, N]
            return torch.logsumexp(lp + log_w, dim=-1)

        return log_density_score(mixture, "model.transition_log_prob (in the exact prior's mixture)",
                                 "the model's transition_log_prob must be finite or -inf, with a finite gradient, "
                                 "wherever the particles move")

    # ------------------------------------------------------------------ evolution
    def iteration_scalars(self, k: int, k_total: int, like: Tensor) -> IterationScalars:
        """The numbers of iteration ``k`` of ``k_total`` (:class:`~escort_rl.belief.evolution.IterationScalars`):
        ``ε_k``, ``α_k``, ``λ_temp,k`` and the schedule ``(γ_k, b_k)`` of :meth:`schedule`, as one
        tensor of ``like``'s dtype and device."""
        lam_temp = self.lambda_temp * (1.0 - k / k_total) if self.temp_schedule == "anneal" else self.lambda_temp
        scheduled = self.anneal_cycles > 0 or self.bandwidth_start != 1.0
        values = torch.tensor([self.step_size / (1.0 + self.step_decay * k), 0.0 if k == 0 else self.adagrad_alpha,
                               lam_temp, *(self.schedule(k, k_total) if scheduled else (1.0, 1.0))],
                              dtype=like.dtype, device=like.device)
        return IterationScalars(values, scheduled)

    def _rank_fn(self, n: int) -> Callable[[Tensor], Tensor] | None:
        """The rank permutation the once-per-update ascents order projections of ``n`` points with: a
        compiled :func:`permutation_ranks` (counting, which beats ``torch.sort`` for short rows) when
        the filter compiles and ``n ≤`` :data:`RANK_COUNT_MAX`, else ``None`` (``torch.sort``)."""
        return self._compiled(permutation_ranks) if self.compile and n <= RANK_COUNT_MAX else None

    def _temporal_reference(self, x: Tensor, reference: Tensor, generator) -> TemporalReference:
        """``F_temp``'s sorted reference: the directions ``θ_j`` refined toward the maximal projected
        W1 between ``x`` and ``reference`` (both ``[*B, N, d]``). Once per update, eager apart from its
        ranks: compiling the whole ascent cost about 10 s per shape and saved nothing, but a compiled
        filter ranks by counting, which beats ``torch.sort`` for short rows, here and in the iterations."""
        theta0 = random_directions(x, self.n_proj, generator)
        rank_fn = self._rank_fn(x.shape[-2])
        theta, theta_w = max_sliced_directions(x, reference, theta0, ascent_steps=self.temporal_ascent_steps,
                                               rank_fn=rank_fn)
        return TemporalReference(reference, theta, theta_w, rank_fn=rank_fn)

    def _correlation_projector(self, x: Tensor, target_samples: Tensor, target_log_weights: Tensor, generator,
                               k_total: int) -> Tensor:
        """``Σ_k w_k A_k A_kᵀ`` ``[*B, d, d]`` of ``F_corr``: learned from the weighted target samples,
        or random deflated projections with equal weights (ESCORT-NoProj)."""
        d = x.shape[-1]
        if self.projection == "learned":
            # compiled only where it runs more than once per update: a compile costs about 10 s per
            # shape, and once per update eager is as fast
            refine = (self._compiled(correlation_projections) if self.projection_every < k_total
                      else correlation_projections)
            projections, proj_weights = refine(x, target_samples, target_log_weights, self.n_proj, self.proj_dim,
                                               ascent_steps=self.projection_ascent_steps,
                                               rank_fn=None if refine is not correlation_projections
                                               else self._rank_fn(x.shape[-2]))
        else:
            projections = random_deflated_projections(x.shape[:-2], d, self.n_proj, self.proj_dim, generator,
                                                      x.device, x.dtype)
            m = projection_shape(d, self.n_proj, self.proj_dim)[0]
            proj_weights = torch.full((*projections.shape[:-3], m), 1.0 / m, dtype=x.dtype, device=x.device)
        return projector(projections, proj_weights)

    def evolve(self, x: Tensor, score_fn: Callable[[Tensor], tuple[Tensor, Tensor | None]], *,
               target_samples: Tensor | None = None, target_log_weights: Tensor | None = None,
               reference: Tensor | None = None, generator: torch.Generator | None = None,
               num_steps: int | None = None) -> tuple[Tensor, Tensor | None]:
        """Run the particle evolution from ``x`` ``[*B, N, d]``.

        ``score_fn(x)`` gives the target score ``[*B, N, d]`` and integer counts ``[*B, C]`` of the
        particles at which its sources gave NaN or inf (or ``None``), as :meth:`_target_score`.
        Returns the particles ``[*B, N, d]`` and, per belief and channel, the largest count met at any
        iteration (``None`` without iterations or counts); checking it is the caller's business, so
        the loop never waits for the device.

        ``target_samples`` (with ``target_log_weights``) are weighted samples of the target used to
        build ``ΔC`` for the correlation projections; ``reference`` is the temporal reference set
        (``None`` turns ``F_temp`` off). Inside :meth:`timed_parts` its parts are timed (see
        :mod:`escort_rl.belief.timing`).
        """
        k_total = self.num_steps if num_steps is None else num_steps
        timer = self.part_timer(x.device)
        step = self._compiled(evolution_step)
        fused = self.compile  # a compiled iteration is one graph: timed whole, its parts not separable
        use_corr = self.lambda_corr > 0 and target_samples is not None
        if use_corr and self.projection == "learned":
            # the target samples' self-normalised weights, tempered where their ESS is below the floor
            target_log_weights, beta, ess = tempered_log_weights(target_log_weights.detach(), self.ess_floor)
            self._record_importance(ess / target_log_weights.shape[-1], beta)
        if self.compile:
            target_samples = unaliased(x, target_samples)
        with torch.no_grad():
            temporal = None
            if self.lambda_temp > 0 and reference is not None:
                with timer("temporal_reference"):
                    temporal = self._temporal_reference(x, reference, generator)
            hist, proj, counts = torch.zeros_like(x), None, None
            stop = AdaptiveStop(x, self.stop_tolerance, self.stop_window)
            for k in range(k_total):
                if k % self.bandwidth_every == 0:
                    with timer("bandwidth"):
                        bandwidth = median_bandwidth(pairwise_sq_dists(x)) * self.bandwidth_scale
                if use_corr and (proj is None or (self.projection == "learned" and k % self.projection_every == 0)):
                    with timer("projections"):
                        proj = self._correlation_projector(x, target_samples, target_log_weights, generator, k_total)
                with timer("iterations" if fused else None):
                    x, hist, flagged = step(x, hist, score_fn, bandwidth, self.iteration_scalars(k, k_total, x),
                                            repulsion=self.repulsion_scale(x.shape[-1]), proj=proj,
                                            lambda_corr=self.lambda_corr, corr_form=self.corr_form,
                                            temporal=temporal, temp_clip=self.temp_clip,
                                            timer=None if fused else timer, active=stop.active)
                if flagged is not None:
                    counts = flagged if counts is None else torch.maximum(counts, flagged)
                if stop.after(k, k_total, x):
                    break
        self._record_iterations(stop.iterations(k_total), math.prod(x.shape[:-2]))
        return x, counts

    # ------------------------------------------------------------------ filter interface
    times_own_parts = True

    def _update(self, model, belief, action, observation, generator, *, guard=None):
        guard = OFF if guard is None else guard
        x_t = belief.particles
        n, d = x_t.shape[-2], x_t.shape[-1]
        a = per_particle(model, action, x_t.shape[:-1])  # [*B, N] ([*B, N, action_dim])
        timer = self.part_timer(x_t.device)
        std = self.jitter_std(d)
        with timer("predict"):
            x_pred = model.transition(x_t, a, generator)
            guard.model_values("model.transition", x_pred)
            if std > 0 and self.jitter_at == "start":
                x_pred = jittered(x_pred, std, generator)
            means = model.transition_mean(x_t, a)
            guard.model_values("model.transition_mean", means)
            if self.prior in ("smoothed", "shrunk"):
                scale_tril = model.transition_scale_tril()
                guard.model_values("model.transition_scale_tril", scale_tril, per_particle=False)
                prior_score = smoothed_prior_score(SmoothedPrior(means, scale_tril, belief.log_weights,
                                                                 shrink=self.prior == "shrunk"))
            else:
                prior_score = self._exact_prior_score(model, x_t, belief.log_weights, a)
            score_fn, channels = self._target_score(model, observation, a, prior_score)
            log_lik = model.observation_log_prob(observation.unsqueeze(-2), x_pred, a).detach()
            guard.model_log_density("model.observation_log_prob", log_lik)
            # the predictive-particle estimate log Σᵢ wᵢ⁻ p(o_t | xᵢ⁻): an approximation (the predicted
            # particles are a sample of the prediction only where the transition was sampled exactly)
            increment = predictive_log_evidence(belief.log_weights, log_lik)
            ess = effective_sample_size(belief.log_weights + log_lik)
            # -inf (zero likelihood) -> -1e30: a belief whose particles are all impossible gets equal
            # target weights, not NaN. NaN and +inf were recorded above and fail the guard.
            log_lik = torch.where(torch.isfinite(log_lik), log_lik, torch.full_like(log_lik, -1e30))
        if self.likelihood_pull > 0:
            w = torch.softmax(log_lik, dim=-1).unsqueeze(-1) * n  # mean 1
            m = observation.shape[-1]
            pull = torch.zeros_like(x_pred)
            pull[..., :m] = observation.unsqueeze(-2) - x_pred[..., :m]
            x_pred = x_pred + self.likelihood_pull * w.clamp(max=10.0) * pull
        x, counts = self.evolve(x_pred, score_fn, target_samples=x_pred, target_log_weights=log_lik,
                                reference=means if self.lambda_temp > 0 else None, generator=generator)
        guard.counts(channels, counts, "during the particle evolution")
        if std > 0 and self.jitter_at == "end":
            with timer("jitter"):
                x = jittered(x, std, generator)
        return ParticleBelief.uniform(x.detach()).diagnosed(increment, ess, previous=belief)

    def fit(self, log_prob: Callable[[Tensor], Tensor], particles: Tensor, num_steps: int | None = None,
            generator: torch.Generator | None = None,
            proposal_log_prob: Callable[[Tensor], Tensor] | None = None) -> Tensor:
        """Fit particles ``[*B, N, d]`` to a fixed target ``log_prob: [*B, N, d] -> [*B, N]``.

        There is no time axis, so ``F_temp`` is off. The correlation projections take the starting
        particles as importance samples of the target, with self-normalised weights
        ``p/q`` (tempered below ``ess_floor``): ``q`` is ``proposal_log_prob``, the log-density the
        particles were drawn from, when given; otherwise the Gaussian with the particles' own mean and
        covariance (exact for a Gaussian start). Pass ``proposal_log_prob=log_prob`` for particles that
        already sample the target (equal weights).
        Returns ``[*B, N, d]``; no jitter is added. With ``check_finite``, non-finite ``particles``, a
        NaN or +inf ``log_prob`` (``-inf`` is a zero density) or a non-finite gradient of it raise a
        ``ValueError`` naming them, after one host synchronisation.
        """
        if particles.ndim < 2:
            raise ValueError(f"particles: expected [*B, N, d], got shape {tuple(particles.shape)}")
        guard = FiniteGuard(f"{type(self).__name__}.fit", particles.shape[:-2], enabled=self.check_finite)
        guard.values("particles:", particles, "the starting particles must be finite")
        fix = "the target's log_prob must be finite or -inf, with a finite gradient, wherever the particles move"
        term, channels = log_density_score(log_prob, "log_prob", fix)

        def score(x: Tensor) -> tuple[Tensor, Tensor]:
            grad, flags = term(x)
            return grad.clamp(-MAX_SCORE, MAX_SCORE), flags.sum(-2)

        with torch.no_grad():
            log_p = log_prob(particles).detach()
            log_q = (gaussian_fit_log_prob(particles) if proposal_log_prob is None
                     else proposal_log_prob(particles).detach())
        guard.log_density("log_prob returned", log_p, fix)
        guard.log_density("proposal_log_prob returned", log_q, "the proposal's log-density must be finite where "
                          "the starting particles lie")
        log_w = log_p - log_q
        log_w = torch.where(torch.isfinite(log_w), log_w, torch.full_like(log_w, -1e30))
        with guard.diagnosing(), flush_denormals():
            x, counts = self.evolve(particles.detach(), score, target_samples=particles.detach(),
                                    target_log_weights=log_w, reference=None, generator=generator, num_steps=num_steps)
        guard.counts(channels, counts, "while fitting")
        guard.values(f"{type(self).__name__}.fit: its result has", x,
                     "the inputs and the target were finite, so the arithmetic overflowed")
        guard.verify()
        return x.detach()


class SVGDFilter(ESCORTFilter):
    """Plain SVGD: :class:`ESCORTFilter` with ``lambda_corr = lambda_temp = 0`` and the
    median-heuristic bandwidth. The paper's SVGD baseline adds ``repulsion="enhanced"``.

    Takes :class:`SVGDParams` (or its fields as keyword arguments); ``self.params`` is then the
    :class:`ESCORTParams` it runs with, the regularisers off.
    """

    Params = SVGDParams

    def __init__(self, params: SVGDParams | None = None, **kwargs) -> None:
        svgd = build_params(SVGDParams, params, kwargs, owner=type(self).__name__)
        super().__init__(ESCORTParams(**dataclasses.asdict(svgd), lambda_corr=0.0, lambda_temp=0.0))


