"""The DVRL-style parametric row of the synthetic benchmark: the IW-ELBO fit of a diagonal Gaussian."""

from __future__ import annotations

import math

import pytest
import torch
from torch.distributions import Independent, Normal

from escort_rl.bench.parametric import fit_parametric, iw_elbo
from escort_rl.bench.targets import GaussianMixture

MEAN = torch.tensor([1.0, -2.0])
STD = torch.tensor([0.5, 2.0])


def _gaussian_target():
    return GaussianMixture([1.0], MEAN.unsqueeze(0), torch.diag(STD**2).unsqueeze(0))


def test_iw_elbo_is_log_z_exactly_when_q_is_the_target():
    q = Independent(Normal(MEAN, STD), 1)
    log_z = math.log(3.0)  # an unnormalised target: 3 × the density
    values = [float(iw_elbo(lambda z: q.log_prob(z) + log_z, q, 7, torch.Generator().manual_seed(s)))
              for s in range(5)]
    assert values == pytest.approx([log_z] * 5, abs=1e-5)


def test_iw_elbo_is_below_log_z_for_a_wrong_q_and_tightens_with_k():
    target = Independent(Normal(MEAN, STD), 1)
    q = Independent(Normal(MEAN + 1.0, STD * 2), 1)

    def mean_bound(k):
        g = torch.Generator().manual_seed(0)
        return sum(float(iw_elbo(target.log_prob, q, k, g)) for _ in range(400)) / 400

    b1, b100 = mean_bound(1), mean_bound(100)
    assert b1 < b100 < 0.0  # log Z = 0


def test_fit_recovers_a_gaussian_target_in_the_family():
    target = _gaussian_target()
    x = fit_parametric(lambda z: target.log_prob(z), 2, seeds=[0, 1], n=4000, num_steps=400, init_std=3.0)
    assert x.shape == (2, 4000, 2) and x.dtype == torch.float32
    for s in range(2):
        assert torch.allclose(x[s].mean(0), MEAN, atol=0.15)
        assert torch.allclose(x[s].std(0), STD, rtol=0.12)
    with pytest.raises(ValueError, match="k >= 1"):
        fit_parametric(lambda z: target.log_prob(z), 2, seeds=[0], n=10, k=0)


def test_dreg_surrogate_gradient_matches_the_iw_elbo_gradient_on_average():
    from escort_rl.bench.parametric import dreg_surrogate

    target = Independent(Normal(MEAN, STD), 1)
    mu = torch.tensor([0.3, -1.0], requires_grad=True)
    log_sigma = torch.tensor([0.2, 0.4], requires_grad=True)

    def mean_grad(fn, reps=1200):
        g = torch.Generator().manual_seed(1)
        total = torch.zeros(4)
        for _ in range(reps):
            q = Independent(Normal(mu, log_sigma.exp()), 1)
            out = fn(target.log_prob, q, 8, g)
            value = out[0] if isinstance(out, tuple) else out
            grads = torch.autograd.grad(value, (mu, log_sigma))
            total += torch.cat(grads)
        return total / reps

    plain, dreg = mean_grad(iw_elbo), mean_grad(dreg_surrogate)
    assert torch.allclose(plain, dreg, atol=0.05, rtol=0.1)  # both unbiased for ∇ L_K
