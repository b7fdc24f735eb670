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

**Where the likelihood is read** (``likelihood``): ``"pixels"`` is DVRL's emission, a decoder pass per
particle, which steps 2–4 evaluate ``2 + num_steps`` times per step (and differentiate ``num_steps``
times); ``"features"`` replaces it everywhere by :class:`~escort_rl.modules.dvrl_networks.FeatureEmission`,
a Gaussian over the (detached) encoding ``φ(o_t)`` whose mean is an MLP of ``[h, φ(z), φ(a)]``: no
decoder at all, so an update costs less than DVRL's. The ELBO is then that of the features, not of the
pixels (the two are not comparable).

The class is a :class:`~escort_rl.modules.dvrl.DVRL` with another :meth:`step`, so
:class:`~escort_rl.modules.dvrl_torchrl.DVRLPolicy`, its primer and DVRL's trainer take it as it is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from escort_rl.belief import ESCORTFilter
from escort_rl.belief.prior import SmoothedPrior
from escort_rl.belief.scores import log_density_score, smoothed_prior_score, target_score
from escort_rl.modules.dvrl import DVRL, DVRLState
from escort_rl.modules.dvrl_networks import FeatureEmission


class Prediction(NamedTuple):
    """Step 1 of an update: the predicted particles ``z [B, K, Z]``, the transition's ``means`` and
    ``variance`` ``[B, K, Z]``, and the emission's ``log_lik [B, K]`` at ``z``."""

    z: Tensor
    means: Tensor
    variance: Tensor
    log_lik: Tensor


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
        likelihood: ``"pixels"`` (DVRL's emission) or ``"features"`` (a Gaussian over the
            observation's encoding; see the module docstring).
        elbo: the model's ELBO term from ``"proposal"`` samples (DVRL's learned ``q(z | h, a, o)``) or
            from the ``"prior"``'s predicted particles (the bootstrap filter's estimate
            ``log (1/K) Σ_k p(o_t | h_k, z̃_k, a)``, which step 2 computes anyway: no proposal network,
            and one likelihood pass per step instead of two).
    """

    LIKELIHOODS = ("pixels", "features")
    ELBOS = ("proposal", "prior")

    def __init__(self, obs_shape: int | Sequence[int], n_actions: int, latent_dim: int,
                 escort: ESCORTFilter | None = None, likelihood: str = "pixels", elbo: str = "proposal",
                 **dvrl_kwargs) -> None:
        if dvrl_kwargs.pop("resample", False):
            raise ValueError("resample: ESCORT-latent does not resample, as ESCORT does not; "
                             "leave it out or set it False")
        if likelihood not in self.LIKELIHOODS:
            raise ValueError(f"likelihood: expected one of {list(self.LIKELIHOODS)}, got {likelihood!r}")
        if elbo not in self.ELBOS:
            raise ValueError(f"elbo: expected one of {list(self.ELBOS)}, got {elbo!r}")
        if likelihood == "features" and dvrl_kwargs.get("emission") is not None:
            raise ValueError("emission: likelihood='features' builds its own emission; leave emission out")
        super().__init__(obs_shape, n_actions, latent_dim, resample=False, **dvrl_kwargs)
        if escort is None:
            escort = ESCORTFilter(num_steps=5, jitter=0.0)
        if not isinstance(escort, ESCORTFilter):
            raise TypeError(f"escort: expected an ESCORTFilter, got {type(escort).__name__}")
        self.escort = escort
        self.likelihood, self.elbo = likelihood, elbo
        if elbo == "prior":
            self.proposal = None  # unused: the predicted particles are the ELBO's samples
        if likelihood == "features":
            e = self.encoding_dim
            self.emission = FeatureEmission(self.latent_encoder, self.hidden + 2 * e, e, self.hidden,
                                            min_std=self.emission_min_std)

    def step(self, state: DVRLState | tuple[Tensor, Tensor, Tensor], action_prev: Tensor, observation: Tensor,
             reset_mask: Tensor | None = None,
             generator: torch.Generator | None = None) -> tuple[DVRLState, Tensor, Tensor]:
        """One ESCORT-latent update; the arguments and returns of :meth:`DVRL.step` (``elbo [B]`` is
        the model's ELBO term of step 4 of the module docstring; the returned ``log_w`` is uniform)."""
        state, action_prev, reset_mask = self.prepare_step(state, action_prev, observation, reset_mask)
        b, k = state.log_w.shape
        obs_k = self.observation_encoder(observation).unsqueeze(1).expand(b, k, -1)
        action_k = self.encode_action(action_prev, reset_mask).unsqueeze(1).expand(b, k, -1)

        with torch.set_grad_enabled(torch.is_grad_enabled() and self.elbo == "prior"):
            prediction = self.predict(state.h, action_k, observation, obs_k, generator)
        z = self.evolve(state.h, action_k, observation, generator, obs_k=obs_k, prediction=prediction)
        if self.elbo == "prior":  # the bootstrap filter's estimate, from the predicted particles
            elbo = torch.logsumexp(prediction.log_lik, dim=-1) - math.log(k)
        else:
            _, increment = self.importance_step(state.h, obs_k, action_k, observation, generator)
            elbo = torch.logsumexp(increment, dim=-1) - math.log(k)
        h = self.recurrence(state.h, z, obs_k, action_k)
        new_state = DVRLState(h, z, torch.full_like(state.log_w, -math.log(k)))
        return new_state, elbo, self.summarize(new_state)

    def observation_log_prob(self, h: Tensor, z: Tensor, action_k: Tensor, observation: Tensor,
                             obs_k: Tensor) -> Tensor:
        """``log p(o | h, z, a)`` ``[B, K]``: DVRL's on pixels, or the Gaussian over the detached encoding
        ``obs_k [B, K, E]`` (``likelihood="features"``)."""
        if self.likelihood == "features":
            return self.emission(h, z, action_k).log_prob(obs_k.detach())
        return super().observation_log_prob(h, z, action_k, observation, obs_k)

    def predict(self, h: Tensor, action_k: Tensor, observation: Tensor, obs_k: Tensor,
                generator: torch.Generator | None = None) -> Prediction:
        """Step 1 and the likelihood of its particles: ``z̃_k ~ p(z | h_k, a)`` (reparameterised) and
        ``log p(o | h_k, z̃_k, a)``, differentiable in the networks where gradients are enabled."""
        b, k = h.shape[:2]
        transition = self.prior(h, action_k)
        noise = torch.randn(b, k, self.latent_dim, generator=generator, device=h.device)
        z = transition.mean + transition.stddev * noise
        log_lik = self.observation_log_prob(h, z, action_k, observation, obs_k)
        return Prediction(z, transition.mean, transition.variance, log_lik)

    def evolve(self, h: Tensor, action_k: Tensor, observation: Tensor,
               generator: torch.Generator | None = None, obs_k: Tensor | None = None,
               prediction: Prediction | None = None) -> Tensor:
        """Steps 1–3 of the module docstring, without gradients: ``h [B, K, H]``, ``action_k [B, K, E]``,
        ``observation [B, *obs_shape]`` (and its encoding ``obs_k [B, K, E]``, computed here when
        ``None``; and step 1's :meth:`predict`, made here when ``None``) -> the evolved particles
        ``z [B, K, Z]`` (detached)."""
        b, k = h.shape[:2]
        if obs_k is None:
            obs_k = self.observation_encoder(observation).unsqueeze(1).expand(b, k, -1)
        h, action_k, observation, obs_k = h.detach(), action_k.detach(), observation.detach(), obs_k.detach()

        def log_likelihood(z: Tensor) -> Tensor:  # [B, K, Z] -> [B, K]
            return self.observation_log_prob(h, z, action_k, observation, obs_k)

        with torch.no_grad():
            if prediction is None:
                prediction = self.predict(h, action_k, observation, obs_k, generator)
            z_pred, means, variance, log_lik = (x.detach() for x in prediction)
            process_tril = torch.diag_embed(variance.mean(1).sqrt())  # [B, Z, Z]
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
