"""The Rao-Blackwellised reference (escort_rl.metrics.rao_blackwell): its mixture's draws and moments, its
posterior against a large bootstrap filter, and what it asks of a model."""

from __future__ import annotations

import math

import pytest
import torch

from escort_rl.bench.trajectories import generate_trajectories
from escort_rl.metrics.rao_blackwell import RaoBlackwellisedSMC, has_rao_blackwell_form
from escort_rl.metrics.reference import reference_posterior
from escort_rl.models import HiddenGoal, LightDark10D


def _filtered(model, seeds, steps, n, generator):
    traj = generate_trajectories(model, steps, seeds)
    f = RaoBlackwellisedSMC()
    b = f.init(model, len(seeds), n, generator)
    for t in range(steps):
        b = f.update(model, b, traj["actions"][:, t], traj["observations"][:, t], generator)
    return f, b, traj


def test_the_draws_follow_the_mixtures_moments(per_test_generator):
    """The mean of ``m`` draws lies within 5 standard errors ``√(Σ_kk / ESS_draws)`` of the mixture's exact mean,
    on a belief whose goal is still spread over several modes (4 steps toward the beacon, d = 3). The
    draws pick particles by systematic resampling, which cannot add error beyond iid draws of them."""
    model = HiddenGoal(dim=3, modes=4)
    f, b, _ = _filtered(model, [0, 1], 4, 5000, per_test_generator)
    mean, cov = f.moments(model, b)
    m = 100_000
    y = f.draws(model, b, m, per_test_generator)
    se = (torch.diagonal(cov, dim1=-2, dim2=-1) / m).sqrt()
    assert ((y.mean(1) - mean).abs() < 5 * se).all()
    assert (torch.softmax(b.mode_log_weights, -1).amax(-1) < 0.99).any()  # the modes were still apart


def test_the_rao_blackwellised_posterior_agrees_with_a_large_bootstrap_filter():
    """At d = 2 (a 4-D state) a bootstrap filter of 400,000 particles is accurate: on 3 trajectories of 8 steps
    the two goal means agree within 0.1 at every step (the modes lie 6 apart, and both filters' Monte Carlo
    errors are a few hundredths there), and so do the goal variances within 0.1."""
    model = HiddenGoal(dim=2, modes=2)
    seeds = [0, 1, 2]
    traj = generate_trajectories(model, 8, seeds)
    rb = reference_posterior(model, traj, seeds, 20_000, sample=64, name="hg", method="rao_blackwell")
    sir = reference_posterior(model, traj, seeds, 400_000, sample=64, name="hg", method="sir")
    assert (rb["goal"]["mean"] - sir["goal"]["mean"]).abs().max() < 0.1
    var_rb = torch.diagonal(rb["goal"]["cov"], dim1=-2, dim2=-1)
    var_sir = torch.diagonal(sir["goal"]["cov"], dim1=-2, dim2=-1)
    assert (var_rb - var_sir).abs().max() < 0.1
    assert var_sir.max() > 1.0  # some step still held both modes


def test_it_gives_what_the_bootstrap_reference_gives(per_test_generator):
    """The same keys and shapes as ``method="sir"``, so that the frontier reads either."""
    model = HiddenGoal(dim=2, modes=2)
    seeds = [0, 1]
    traj = generate_trajectories(model, 3, seeds)
    rb = reference_posterior(model, traj, seeds, 500, sample=32, name="hg", method="rao_blackwell")
    sir = reference_posterior(model, traj, seeds, 500, sample=32, name="hg", method="sir")
    assert set(rb) == set(sir) - {"ess_fraction_of_stages"}
    for part in ("goal", "position"):
        assert {k: tuple(v.shape) for k, v in rb[part].items()} == {k: tuple(v.shape) for k, v in sir[part].items()}
    assert torch.isfinite(rb["goal"]["sample"]).all()


def test_a_model_without_the_form_is_refused_naming_what_it_lacks():
    assert has_rao_blackwell_form(HiddenGoal(dim=2, modes=2)) and not has_rao_blackwell_form(LightDark10D())
    with pytest.raises(ValueError, match=r"--reference-filter rao_blackwell: LightDark10D lacks rao_blackwell_dims, "
                                         r"rao_blackwell_prior, rao_blackwell_step"):
        RaoBlackwellisedSMC().init(LightDark10D(), 1, 10)


def test_resampling_keeps_each_particle_with_its_own_gaussian_sum(per_test_generator):
    """Every resampled row (a position with its goal's modes, weights and variance) is some row of the belief
    before, whole; the resampled belief is equally weighted, and a belief not chosen is left as it was."""
    model = HiddenGoal(dim=2, modes=2)
    _, b, _ = _filtered(model, [0, 1], 3, 50, per_test_generator)
    b = b._replace(log_weights=torch.log_softmax(3.0 * torch.randn(2, 50, generator=per_test_generator,
                                                                    dtype=torch.float64), -1))

    def rows(c):
        return torch.cat([c.x, c.mode_means.flatten(2), c.mode_log_weights, c.variance], -1)  # [B, n, ·]

    after = RaoBlackwellisedSMC.resample(b, torch.tensor([True, False]), per_test_generator)
    before_rows, after_rows = rows(b), rows(after)
    assert all(((before_rows[0] - r).abs().amax(-1) == 0).any() for r in after_rows[0])
    assert torch.allclose(after.log_weights[0], torch.full((50,), -math.log(50), dtype=torch.float64))
    assert torch.equal(after_rows[1], before_rows[1]) and torch.equal(after.log_weights[1], b.log_weights[1])
    assert len({tuple(r.tolist()) for r in after_rows[0]}) < 50  # it did resample (unequal weights before)


def test_each_belief_takes_the_fully_adapted_start_whatever_the_filter_did_before(per_test_generator):
    """The first update of a belief from ``init`` is the model's fully adapted start, even when the same filter
    initialised or updated another belief in between: far from the beacon its weights then stay equal (ESS/n 1),
    where a start from prior draws loses most of its ESS to the first reading in 10 dimensions."""
    model = HiddenGoal(dim=10, modes=2, beacon_distance=30.0)
    traj = generate_trajectories(model, 2, [0])
    f = RaoBlackwellisedSMC()
    first, second = f.init(model, 1, 2000, per_test_generator), f.init(model, 1, 2000, per_test_generator)
    a, o = traj["actions"][:, 0], traj["observations"][:, 0]
    f.update(model, first, a, o, per_test_generator)
    f.update(model, second, a, o, per_test_generator)
    assert float(f.last_ess_fraction.min()) > 0.999
    moved = f.update(model, f.update(model, first, a, o, per_test_generator), traj["actions"][:, 1],
                     traj["observations"][:, 1], per_test_generator)
    assert not moved.at_prior
