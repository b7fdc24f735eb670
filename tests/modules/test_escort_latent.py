"""ESCORT-latent's options: the bootstrap ELBO against its closed form on a linear-Gaussian model, the
likelihood of the observation's encoding, and the frame networks for 10×10 grids."""

from __future__ import annotations

import math

import pytest
import torch
from linear_gaussian_parts import CarryLatent, LinearEmission, LinearPrior
from torch import nn
from torch.distributions import Normal

from escort_rl.belief import ESCORTFilter
from escort_rl.modules import DVRL, ESCORTLatent, FrameGRU
from escort_rl.modules.dvrl_networks import FeatureEmission, MinAtarDecoder, MinAtarEncoder

torch.set_num_threads(1)


# z_1 ~ N(0, 1) (h_0 = 0), o ~ N(z, σ²): p(o) = N(o; 0, 1 + σ²), the posterior N(o/(1 + σ²), σ²/(1 + σ²)).
SIGMA, OBS = 0.5, 1.5
LOG_P = float(Normal(0.0, math.sqrt(1 + SIGMA**2)).log_prob(torch.tensor(OBS)))
POST_MEAN, POST_STD = OBS / (1 + SIGMA**2), math.sqrt(SIGMA**2 / (1 + SIGMA**2))


def bootstrap_latent(k: int) -> ESCORTLatent:
    return ESCORTLatent(1, n_actions=2, latent_dim=1, hidden=1, num_particles=k, encoding_dim=2, summary="deepsets",
                        summary_dim=2, observation_encoder=nn.Identity(), prior=LinearPrior(),
                        emission=LinearEmission(SIGMA), recurrence=CarryLatent(), elbo="prior",
                        escort=ESCORTFilter(num_steps=2, jitter=0.0))


def first_step_elbo(model: ESCORTLatent, batch: int, seed: int) -> torch.Tensor:
    with torch.no_grad():
        _, elbo, _ = model.step(model.initial_state(batch), torch.zeros(batch, dtype=torch.long),
                                torch.full((batch, 1), OBS), torch.ones(batch, dtype=torch.bool),
                                generator=torch.Generator().manual_seed(seed))
    return elbo


def test_the_bootstrap_elbo_is_the_prior_proposal_bound_and_unbiased_in_p():
    # K = 1: E[ELBO] = E_prior[log p(o|z)] = log p(o) - KL(prior || posterior), exactly.
    elbo_1 = first_step_elbo(bootstrap_latent(1), 20000, seed=0)
    kl = math.log(POST_STD) + (1 + POST_MEAN**2) / (2 * POST_STD**2) - 0.5
    assert abs(float(elbo_1.mean()) - (LOG_P - kl)) < 4 * float(elbo_1.std()) / math.sqrt(20000)
    # K = 50: exp(ELBO) is the bootstrap filter's unbiased estimate of p(o): E[p̂ / p] = 1
    ratio = torch.exp(first_step_elbo(bootstrap_latent(50), 4000, seed=1).double() - LOG_P)
    assert abs(float(ratio.mean()) - 1.0) < 4 * float(ratio.std()) / math.sqrt(4000) + 1e-3
    assert bootstrap_latent(3).proposal is None  # the bootstrap ELBO needs no proposal network


def test_the_elbo_is_read_at_the_predicted_particles_the_evolution_starts_from():
    model = bootstrap_latent(6)
    h, a = torch.zeros(3, 6, 1), model.encode_action(torch.zeros(3, dtype=torch.long), torch.ones(3, dtype=torch.bool))
    obs = torch.full((3, 1), OBS)
    pred = model.predict(h, a.unsqueeze(1).expand(3, 6, -1), obs, obs.unsqueeze(1).expand(3, 6, 1),
                         torch.Generator().manual_seed(7))
    elbo = first_step_elbo(model, 3, seed=7)
    torch.testing.assert_close(elbo, torch.logsumexp(pred.log_lik, -1) - math.log(6))


def small_latent(likelihood: str, elbo: str, obs_shape=(4, 10, 10)) -> ESCORTLatent:
    torch.manual_seed(0)
    return ESCORTLatent(obs_shape, 3, 4, hidden=8, num_particles=5, encoding_dim=8, likelihood=likelihood, elbo=elbo,
                        escort=ESCORTFilter(num_steps=2, jitter=0.0))


def test_the_feature_likelihood_has_no_decoder_and_leaves_the_encoder_to_the_policy():
    model = small_latent("features", "prior")
    assert isinstance(model.emission, FeatureEmission)
    assert not any("decoder" in name for name, _ in model.named_parameters())
    obs = (torch.rand(2, 4, 10, 10) < 0.2).float()
    state, elbo, summary = model.step(model.initial_state(2), torch.zeros(2, dtype=torch.long), obs,
                                      torch.ones(2, dtype=torch.bool), torch.Generator().manual_seed(0))
    assert elbo.shape == (2,) and torch.isfinite(elbo).all() and summary.shape == (2, 8)
    elbo.sum().backward()
    for net in (model.emission, model.prior):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())
    # the encoding is the ELBO's target, detached: a first step's ELBO does not reach the encoder
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.observation_encoder.parameters())


@pytest.mark.parametrize("likelihood, elbo", [("pixels", "proposal"), ("pixels", "prior"), ("features", "proposal")])
def test_every_option_gives_a_finite_elbo_that_trains_the_model(likelihood, elbo):
    model = small_latent(likelihood, elbo)
    obs = (torch.rand(2, 4, 10, 10) < 0.2).float()
    _, value, _ = model.step(model.initial_state(2), torch.zeros(2, dtype=torch.long), obs,
                             torch.ones(2, dtype=torch.bool), torch.Generator().manual_seed(0))
    assert torch.isfinite(value).all()
    value.sum().backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.emission.parameters())
    assert (model.proposal is None) == (elbo == "prior")


def test_bad_options_name_the_argument():
    with pytest.raises(ValueError, match="likelihood: expected one of"):
        small_latent("voxels", "prior")
    with pytest.raises(ValueError, match="elbo: expected one of"):
        small_latent("features", "posterior")
    with pytest.raises(ValueError, match="emission: likelihood='features' builds its own"):
        ESCORTLatent(1, 2, 1, likelihood="features", emission=LinearEmission(SIGMA))


def test_minatar_frame_networks_shapes():
    encoder, decoder = MinAtarEncoder(6, 32), MinAtarDecoder(20, 6)
    assert encoder(torch.rand(3, 5, 6, 10, 10)).shape == (3, 5, 32)
    assert decoder(torch.rand(3, 5, 20)).shape == (3, 5, 6, 10, 10)
    dvrl = DVRL((6, 10, 10), n_actions=4, latent_dim=4, hidden=8, num_particles=3, encoding_dim=8)
    assert isinstance(dvrl.observation_encoder, MinAtarEncoder)
    with torch.no_grad():
        _, elbo, _ = dvrl.step(dvrl.initial_state(2), torch.zeros(2, dtype=torch.long), torch.rand(2, 6, 10, 10),
                               torch.ones(2, dtype=torch.bool))
    assert torch.isfinite(elbo).all()
    h, logits, value = FrameGRU(6, 4, hidden=8, frame_size=10).step(
        torch.zeros(2, 8), torch.zeros(2, dtype=torch.long), torch.rand(2, 6, 10, 10), torch.ones(2, dtype=torch.bool))
    assert h.shape == (2, 8) and logits.shape == (2, 4) and value.shape == (2,)
    with pytest.raises(ValueError, match=r"frames must be one of \(C, 84, 84\), \(C, 10, 10\)"):
        DVRL((3, 64, 64), n_actions=6, latent_dim=4)
