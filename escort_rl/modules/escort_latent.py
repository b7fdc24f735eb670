"""ESCORT-latent: ESCORT's particle evolution over the latent state of DVRL's learned VRNN.

There is no known model on Atari, so the model is DVRL's: the transition ``p(z_t | h_{t-1}, a_{t-1})``
(the VRNN prior), the emission ``p(o_t | h_{t-1}, z_t, a_{t-1})`` and the recurrence
``h_t = GRU([φ(z_t), φ(o_t), φ(a_{t-1})], h_{t-1})``, learned by the same ELBO. Each env keeps ``K``
equally weighted particles ``(h_k, z_k)``. One step, given ``a_{t-1}`` and ``o_t``:

1. **Predict** ``z̃_k ~ p(z | h_k, a_{t-1})`` through the learned transition.
2. **Target** ``log π_k(z) = log p(o_t | h_k, z, a_{t-1}) + log p̂(z)``, with ``p̂`` the smoothed
   predicted prior (:class:`escort_rl.belief.prior.SmoothedPrior`) over the transition
   means ``μ_k``, its process covariance ``diag(mean_k σ_k²)`` (the transition's variances averaged
   over the particles: the smoothed prior shares one covariance). Each particle's likelihood is read
   at its own ``h_k`` (the deterministic part of its history).
3. **Evolve** the ``z`` by :meth:`escort_rl.belief.ESCORTFilter.evolve`: ``K`` iterations of SVGD +
   the correlation force + the temporal force (reference: the ``μ_k``), no resampling. The
   particles are moved without gradients: the policy's loss reaches the networks through ``h`` and
   the summary, not through the SVGD moves.
4. **Learn** the model by DVRL's ELBO term of the step, with the evolved belief as the ancestors:
   ``ELBO_t = log (1/K) Σ_k exp(Δ_k)``, ``Δ_k`` of a proposal sample ``z_k^q ~ q(z | h_k, a, o)``
   (:meth:`DVRL.importance_step`). This is DVRL's estimator with uniform weights, a lower bound
   (in expectation) of ``log p(o_t | belief_{t-1}, a_{t-1})``.
5. ``h_k ← GRU([φ(z_k), φ(o_t), φ(a_{t-1})], h_k)`` with the evolved ``z_k``; the weights stay uniform.

The class is a :class:`~escort_rl.modules.dvrl.DVRL` with another :meth:`step`, so
:class:`~escort_rl.modules.dvrl_torchrl.DVRLPolicy`, its primer and DVRL's trainer take it as it is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from escort_rl.belief import ESCORTFilter
from escort_rl.belief.prior import SmoothedPrior
from escort_rl.belief.scores import log_density_score, smoothed_prior_score, target_score
from escort_rl.modules.dvrl import DVRL, DVRLState


class ESCORTLatent(DVRL):
    """DVRL's VRNN whose belief is evolved by ESCORT in the latent space (see the module docstring).

    Args:
        obs_shape, n_actions, latent_dim, and the keyword arguments of :class:`DVRL` (``resample`` is
        always False: ESCORT does not resample).
        escort: the :class:`~escort_rl.belief.ESCORTFilter` whose ``evolve`` moves the particles
            (its ``num_steps``, ``step_size``, ``lambda_corr``, ``lambda_temp``, projections, and
            ``jitter``: the std of Gaussian noise added after the evolution; ``None`` there means the
            filter's default ``sqrt(0.01 (1 + 0.1 d))``). Default: ``ESCORTFilter(num_steps=5,
            jitter=0.0)``.
    """

    def __init__(self, obs_shape: int | Sequence[int], n_actions: int, latent_dim: int,
                 escort: ESCORTFilter | None = None, **dvrl_kwargs) -> None:
        if dvrl_kwargs.pop("resample", False):
            raise ValueError("resample: ESCORT-latent does not resample, as ESCORT does not; "
                             "leave it out or set it False")
        super().__init__(obs_shape, n_actions, latent_dim, resample=False, **dvrl_kwargs)
        if escort is None:
            escort = ESCORTFilter(num_steps=5, jitter=0.0)
        if not isinstance(escort, ESCORTFilter):
            raise TypeError(f"escort: expected an ESCORTFilter, got {type(escort).__name__}")
        self.escort = escort

    def step(self, state: DVRLState | tuple[Tensor, Tensor, Tensor], action_prev: Tensor, observation: Tensor,
             reset_mask: Tensor | None = None,
             generator: torch.Generator | None = None) -> tuple[DVRLState, Tensor, Tensor]:
        """One ESCORT-latent update; the arguments and returns of :meth:`DVRL.step` (``elbo [B]`` is
        the model's ELBO term of step 4 of the module docstring; the returned ``log_w`` is uniform)."""
        state, action_prev, reset_mask = self.prepare_step(state, action_prev, observation, reset_mask)
        b, k = state.log_w.shape
        obs_k = self.observation_encoder(observation).unsqueeze(1).expand(b, k, -1)
        action_k = self.encode_action(action_prev, reset_mask).unsqueeze(1).expand(b, k, -1)

        z = self.evolve(state.h, action_k, observation, generator)
        _, increment = self.importance_step(state.h, obs_k, action_k, observation, generator)
        elbo = torch.logsumexp(increment, dim=-1) - math.log(k)
        h = self.recurrence(state.h, z, obs_k, action_k)
        new_state = DVRLState(h, z, torch.full_like(state.log_w, -math.log(k)))
        return new_state, elbo, self.summarize(new_state)

    def evolve(self, h: Tensor, action_k: Tensor, observation: Tensor,
               generator: torch.Generator | None = None) -> Tensor:
        """Steps 1–3 of the module docstring, without gradients: ``h [B, K, H]``, ``action_k [B, K, E]``,
        ``observation [B, *obs_shape]`` -> the evolved particles ``z [B, K, Z]`` (detached)."""
        b, k = h.shape[:2]
        h, action_k, observation = h.detach(), action_k.detach(), observation.detach()
        obs_rep = observation.unsqueeze(1).expand(b, k, *observation.shape[1:])

        def log_likelihood(z: Tensor) -> Tensor:  # [B, K, Z] -> [B, K]
            return self.emission(h, z, action_k).log_prob(obs_rep)

        with torch.no_grad():
            transition = self.prior(h, action_k)
            means = transition.mean
            noise = torch.randn(b, k, self.latent_dim, generator=generator, device=h.device)
            z_pred = means + transition.stddev * noise
            process_tril = torch.diag_embed(transition.variance.mean(1).sqrt())  # [B, Z, Z]
            log_lik = log_likelihood(z_pred)
        fix = "lower the learning rate: the learned emission gave a non-finite log-likelihood or gradient"
        score_fn, channels = target_score(log_density_score(log_likelihood, "emission log p(o|h,z,a)", fix),
                                          smoothed_prior_score(SmoothedPrior(means, process_tril)))
        temporal_reference = means if self.escort.lambda_temp > 0 else None
        z, counts = self.escort.evolve(z_pred, score_fn, target_samples=z_pred, target_log_weights=log_lik,
                                       reference=temporal_reference, generator=generator)
        if counts is not None and bool((counts > 0).any()):
            lead, hint = channels[int((counts > 0).any(0).nonzero()[0])]
            raise FloatingPointError(f"ESCORT-latent: {lead}; {hint}")
        std = self.escort.jitter_std(self.latent_dim)
        if std > 0:
            z = z + std * torch.randn(z.shape, generator=generator, device=z.device)
        if not bool(torch.isfinite(z).all()):
            raise FloatingPointError("ESCORT-latent: the evolved particles are not finite; lower the learning rate "
                                     "or escort.step_size")
        return z.detach()
