"""ClippedNormal (escort_rl.modules.clipped_normal), the ``actor.distribution=clipped_normal`` head: its
log-probability against the censored Gaussian's closed form, its atoms' mass against sampled frequencies,
its entropy, its deterministic action, and both policies' heads (the kickstart on it:
tests/trainers/test_kickstart.py)."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from torch.distributions import Normal
from torchrl.envs.utils import ExplorationType, set_exploration_type

from conftest import hoeffding
from escort_rl.config import compose
from escort_rl.models import LightDark10DContinuous
from escort_rl.modules import DeepSetsActor, make_deepsets_policy
from escort_rl.modules.clipped_normal import ClippedNormal

LOW, HIGH = torch.tensor([-1.0, 0.0, 2.0]), torch.tensor([1.0, 0.5, 3.0])  # centres 0, 0.25, 2.5


def _dist(loc, scale):
    return ClippedNormal(torch.as_tensor(loc, dtype=torch.float64), torch.as_tensor(scale, dtype=torch.float64),
                         LOW.double(), HIGH.double())


def test_log_prob_is_the_gaussian_density_inside_and_the_tail_mass_on_each_face():
    loc, scale = torch.tensor([[0.3, -0.5, 1.5]]), torch.tensor([[0.7, 2.0, 0.4]])
    d = _dist(loc, scale)
    mu = (LOW + HIGH).double() / 2 + (HIGH - LOW).double() / 2 * loc.double()
    sigma = (HIGH - LOW).double() / 2 * scale.double()
    gauss = Normal(mu, sigma)
    inside = torch.tensor([[0.2, 0.1, 2.9]], dtype=torch.float64)
    torch.testing.assert_close(d.log_prob(inside), gauss.log_prob(inside).sum(-1))
    # the low face in dimension 0, the high face in dimensions 1 and 2: P(u ≤ low) and P(u ≥ high)
    edges = torch.tensor([[-1.0, 0.5, 3.0]], dtype=torch.float64)
    by_hand = (math.log(float(gauss.cdf(edges)[0, 0])) + math.log(1 - float(gauss.cdf(edges)[0, 1]))
               + math.log(1 - float(gauss.cdf(edges)[0, 2])))
    assert float(d.log_prob(edges)) == pytest.approx(by_hand, rel=1e-12)


def test_the_atoms_and_the_density_make_one_probability():
    """The face masses plus the integral of the density inside (trapezoid rule) is 1, per dimension."""
    d = _dist([[0.8, -1.2, 0.1]], [[0.5, 1.5, 2.0]])
    total = torch.zeros(3, dtype=torch.float64)
    for j in range(3):
        grid = torch.linspace(float(LOW[j]), float(HIGH[j]), 20001, dtype=torch.float64)
        density = torch.exp(Normal(d.gaussian.loc[0, j], d.gaussian.scale[0, j]).log_prob(grid))
        atoms = sum(math.exp(float(torch.special.log_ndtr(z)))
                    for z in ((LOW[j] - d.gaussian.loc[0, j]) / d.gaussian.scale[0, j],
                              (d.gaussian.loc[0, j] - HIGH[j]) / d.gaussian.scale[0, j]))
        total[j] = torch.trapezoid(density, grid) + atoms
    torch.testing.assert_close(total, torch.ones(3, dtype=torch.float64), atol=1e-6, rtol=0)


def test_samples_lie_in_the_box_and_hit_each_face_as_often_as_its_mass(per_test_generator):
    d = _dist([[0.9, 0.0, -0.6]], [[0.5, 0.3, 1.0]])
    n = 40_000
    torch.manual_seed(int(torch.randint(0, 2**31 - 1, (1,), generator=per_test_generator)))
    a = d.sample((n,))[:, 0]
    assert a.shape == (n, 3) and bool(((a >= LOW.double()) & (a <= HIGH.double())).all())
    for j in range(3):
        for face, z in ((LOW[j], (LOW[j] - d.gaussian.loc[0, j]) / d.gaussian.scale[0, j]),
                        (HIGH[j], (d.gaussian.loc[0, j] - HIGH[j]) / d.gaussian.scale[0, j])):
            freq = float((a[:, j] == face.double()).double().mean())
            assert abs(freq - math.exp(float(torch.special.log_ndtr(z)))) < hoeffding(n)


def test_far_past_a_face_the_log_prob_of_the_face_tends_to_zero_and_stays_finite():
    d = _dist([[40.0, -40.0, 0.0]], [[0.01, 0.01, 1e-3]])
    lp = d.log_prob(torch.tensor([[1.0, 0.0, 2.5]], dtype=torch.float64))
    assert bool(torch.isfinite(lp).all())
    # the two faces contribute ~0; dimension 2 is a narrow Gaussian at its centre
    assert float(lp) == pytest.approx(float(Normal(2.5, 0.5e-3).log_prob(torch.tensor(2.5))), rel=1e-9)
    # the face's log-mass one scale inside the face is log Φ(1), and its gradient in the mean is finite
    loc = torch.tensor([[0.99, 0.0, 0.0]], requires_grad=True)
    lp = ClippedNormal(loc, torch.tensor([[0.01, 1.0, 1.0]]), LOW, HIGH).log_prob(torch.tensor([[1.0, 0.25, 2.5]]))
    lp.backward()
    assert bool(torch.isfinite(loc.grad).all())


def test_entropy_is_the_gaussians_and_the_deterministic_action_the_clipped_mean():
    d = _dist([[0.3, 2.0, -5.0]], [[0.7, 2.0, 0.4]])
    torch.testing.assert_close(d.entropy(), d.gaussian.entropy().sum(-1))
    torch.testing.assert_close(d.deterministic_sample, torch.tensor([[0.3, 0.5, 2.0]], dtype=torch.float64))
    assert d.batch_shape == (1,) and d.event_shape == (3,)


def _policy_and_beliefs():
    torch.manual_seed(0)
    box = (LightDark10DContinuous().action_low, LightDark10DContinuous().action_high)
    policy = make_deepsets_policy(DeepSetsActor(10, 10, hidden=16), action_box=box, distribution="clipped_normal")
    td = TensorDict({"particles": torch.randn(64, 6, 10), "particle_log_weights": torch.zeros(64, 6)}, [64])
    return policy, td, box


def test_the_policy_writes_actions_in_the_box_and_their_log_prob():
    policy, td, (low, high) = _policy_and_beliefs()
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        out = policy(td)
    assert out["action"].shape == (64, 5) and bool(((out["action"] >= low) & (out["action"] <= high)).all())
    assert bool((out["action"] == high).any())  # the initial scale (1 half-width) reaches the faces
    with torch.no_grad():
        again = policy.get_dist(out).log_prob(out["action"])
    torch.testing.assert_close(out["action_log_prob"], again)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        greedy = policy(td.clone())
    torch.testing.assert_close(greedy["action"], (0.1 * greedy["loc"]).clamp(-0.1, 0.1))


def test_an_unknown_distribution_is_refused_by_name():
    with pytest.raises(ValueError, match="distribution"):
        make_deepsets_policy(DeepSetsActor(10, 10, hidden=8), action_box=_policy_and_beliefs()[2], distribution="beta")
    with pytest.raises(Exception, match="actor.distribution"):
        compose(["env=lightdark10d_continuous", "actor.distribution=beta"])


@pytest.mark.parametrize("distribution,law", [("clipped_normal", "ClippedNormal"), ("tanh_normal", "TanhNormal")])
def test_both_continuous_policies_take_actor_distribution(distribution, law):
    """The belief policy and the GRU on raw observations read the same ``actor.distribution``, so that a
    comparison between them is one of inputs, not of action laws."""
    from escort_rl.trainers.builders import build_model, build_policy
    from escort_rl.trainers.recurrent_ppo import build_recurrent_actor_critic

    overrides = ["env=lightdark10d_continuous", f"actor.distribution={distribution}", "actor.min_scale=0.2"]
    cfg = compose(overrides)
    model = build_model(cfg.env)
    _, belief_policy = build_policy(cfg, model)
    td = TensorDict({"particles": torch.randn(4, 6, 10), "particle_log_weights": torch.zeros(4, 6)}, [4])
    assert type(belief_policy.get_dist(belief_policy(td))).__name__ == law
    gru_policy, _, primer = build_recurrent_actor_critic(compose([*overrides, "trainer=recurrent_ppo"]), model)
    obs = TensorDict({"observation": torch.randn(4, model.obs_dim), "is_init": torch.ones(4, 1, dtype=torch.bool),
                      "recurrent_state": torch.zeros(4, 1, primer.primers["recurrent_state"].shape[-1])}, [4])
    out = gru_policy(obs)
    assert type(gru_policy.get_dist(out)).__name__ == law
    assert bool((out["scale"] >= 0.2).all()) and out["action"].shape == (4, 5)

