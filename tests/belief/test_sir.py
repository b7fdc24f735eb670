"""Tests of the SIR (bootstrap) particle filter, its resampling and the update-input validation."""

from __future__ import annotations

import math

import pytest
import torch

from escort_rl.belief import ParticleBelief, SIRFilter, validate_update_inputs
from escort_rl.models import LightDark10D, LinearGaussian


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _assert_normalised(belief: ParticleBelief, atol: float = 1e-5) -> None:
    lse = torch.logsumexp(belief.log_weights.double(), dim=-1)
    torch.testing.assert_close(lse, torch.zeros_like(lse), rtol=0, atol=atol)


# ---------------------------------------------------------------------------------------------
# Tracking the exact posterior
# ---------------------------------------------------------------------------------------------


def test_sir_tracks_the_kalman_posterior():
    """SIR with N = 20000 against the Kalman filter on a 4-D linear-Gaussian model, 10 steps, 2 beliefs.

    Tolerance. The Monte-Carlo error of a weighted mean is about sqrt(Var/ESS). In a bootstrap filter
    the error made at the most degenerate weighting step propagates to the later steps (resampling
    does not undo it), so we use, per belief, the smallest *pre-resampling* ESS seen so far (the ESS
    of the weights before resampling, recovered by re-running the same update with
    ``resample_threshold=0`` on a copy of the generator: the transition draws come first, so the
    propagated particles are the same). With SE_i = sqrt(P_ii / ESS_min):

    - each posterior-mean coordinate is within 6 SE of the Kalman mean;
    - each covariance entry is within 7 SE of P_ij, with SE = sqrt((P_ii P_jj + P_ij²) / ESS_min),
      the standard error of a Gaussian sample covariance;
    - the root-mean-square of all 80 standardised mean errors is below 2 (it is ≈ 1 or less when
      the filter is unbiased: the SE above is conservative).

    Calibration: over 40 seeds (800 belief-steps) the largest standardised errors were 4.8 (mean)
    and 5.4 (covariance). A filter that skips the weighting, weights by the previous observation,
    or resamples with the wrong weights is off by tens of SE (the prior-to-posterior shift is
    ~sqrt(ESS) SE).
    """
    model = LinearGaussian(state_dim=4)
    n, steps, b = 20_000, 10, 2
    g = gen(0)
    sir = SIRFilter()  # resample when ESS/N < 0.5
    state = model.initial_state((b,), g)
    belief = sir.init(model, (b,), n, g)
    mean = model.m0.double().expand(b, 4)
    cov = model.P0.double().expand(b, 4, 4)
    min_ess = torch.full((b,), float(n), dtype=torch.float64)
    z_all = []
    resampled_any = False
    for t in range(steps):
        action = (torch.arange(b) + t) % model.n_actions
        state = model.transition(state, action, g)
        obs = model.observe(state, action, g)
        probe = torch.Generator()
        probe.set_state(g.get_state())
        unresampled = SIRFilter(resample_threshold=0.0).update(model, belief, action, obs, probe)
        belief = sir.update(model, belief, action, obs, g)
        mean, cov = model.kalman_step(mean, cov, action, obs)

        assert belief.particles.shape == (b, n, 4)
        _assert_normalised(belief)
        ess = unresampled.effective_sample_size().double()
        resampled_any |= bool((ess < 0.5 * n).any())
        min_ess = torch.minimum(min_ess, ess)
        var = torch.diagonal(cov, dim1=-2, dim2=-1)
        z = (belief.mean().double() - mean) / torch.sqrt(var / min_ess[:, None])
        assert z.abs().max() < 6, f"step {t}: standardised mean errors {z}"
        se_cov = torch.sqrt((var[:, :, None] * var[:, None, :] + cov**2) / min_ess[:, None, None])
        z_cov = (belief.covariance().double() - cov) / se_cov
        assert z_cov.abs().max() < 7, f"step {t}: standardised covariance errors {z_cov}"
        z_all.append(z)
    rms = torch.stack(z_all).pow(2).mean().sqrt()
    assert rms < 2.0
    assert resampled_any  # the resampling path was exercised


# ---------------------------------------------------------------------------------------------
# Systematic resampling
# ---------------------------------------------------------------------------------------------


# ---------------------------------------------------------------------------------------------
# Resampling policy, normalisation, degenerate likelihoods
# ---------------------------------------------------------------------------------------------


def _one_update(model, threshold: float, seed: int = 3, b: int = 3, n: int = 500):
    g = gen(seed)
    sir = SIRFilter(resample_threshold=threshold)
    belief = sir.init(model, (b,), n, g)
    state = model.initial_state((b,), g)
    action = torch.arange(b) % model.n_actions
    state = model.transition(state, action, g)
    obs = model.observe(state, action, g)
    return belief, sir.update(model, belief, action, obs, g), action, obs


def test_threshold_zero_never_resamples():
    model = LinearGaussian(state_dim=4)
    g = gen(4)
    sir = SIRFilter(resample_threshold=0.0)
    belief = sir.init(model, (3,), 500, g)
    state = model.initial_state((3,), g)
    for t in range(6):
        action = torch.full((3,), t % model.n_actions)
        state = model.transition(state, action, g)
        obs = model.observe(state, action, g)
        belief = sir.update(model, belief, action, obs, g)
        _assert_normalised(belief)
        # the weights degenerate instead of being reset to uniform
        assert bool((belief.log_weights.amax(-1) - belief.log_weights.amin(-1) > 1.0).all())
        assert bool((belief.effective_sample_size() < 0.5 * 500).all())
        # no particle was duplicated (propagation adds continuous noise to distinct particles)
        for row in belief.particles:
            assert torch.unique(row, dim=0).shape[0] == 500


def test_threshold_one_always_resamples():
    model = LinearGaussian(state_dim=4, observation_cov=25.0 * torch.eye(4))  # weak likelihood: ESS ≈ N
    prior, post, _, _ = _one_update(model, 1.0)
    torch.testing.assert_close(post.log_weights, torch.full_like(post.log_weights, -math.log(500)))
    # resampling duplicates the heavier particles and drops the lighter ones
    for row in post.particles:
        assert torch.unique(row, dim=0).shape[0] < 500
    # the default threshold (0.5) does not resample this weak update
    _, kept, _, _ = _one_update(model, 0.5)
    assert bool((kept.effective_sample_size() > 0.5 * 500).all())
    assert not torch.allclose(kept.log_weights, torch.full_like(kept.log_weights, -math.log(500)))
    for row in kept.particles:
        assert torch.unique(row, dim=0).shape[0] == 500


def test_roughening_breaks_ties_after_resampling():
    model = LinearGaussian(state_dim=4)
    g = gen(5)
    sir = SIRFilter(resample_threshold=1.0, roughening=0.2)
    belief = sir.init(model, (2,), 300, g)
    obs = torch.zeros(2, 4)
    post = sir.update(model, belief, torch.zeros(2, dtype=torch.long), obs, g)
    for row in post.particles:
        assert torch.unique(row, dim=0).shape[0] == 300
    _assert_normalised(post)


@pytest.mark.parametrize("threshold", [0.0, 0.5, 1.0])
def test_log_weights_stay_normalised_on_light_dark(threshold):
    model = LightDark10D()
    g = gen(6)
    sir = SIRFilter(resample_threshold=threshold)
    belief = sir.init(model, (4,), 200, g)
    state = model.initial_state((4,), g)
    for t in range(8):
        action = torch.tensor([0, 2, 4, 6]) + (t % 2)
        state = model.transition(state, action, g)
        obs = model.observe(state, action, g)
        belief = sir.update(model, belief, action, obs, g)
        _assert_normalised(belief)
        assert bool(torch.isfinite(belief.particles).all())
        assert not bool(torch.isnan(belief.log_weights).any())


def test_all_particles_impossible_gives_no_nan():
    """An observation so far away that every particle's log-likelihood is -inf keeps the prior weights."""
    model = LinearGaussian(state_dim=4)
    g = gen(7)
    sir = SIRFilter()
    belief = sir.init(model, (2,), 100, g)
    obs = torch.stack([torch.full((4,), 1e20), torch.zeros(4)])  # finite, but (1e20/0.5)² overflows
    action = torch.zeros(2, dtype=torch.long)
    x_next = model.transition(belief.particles, action.unsqueeze(-1).expand(2, 100), gen(0))
    lik = model.observation_log_prob(obs.unsqueeze(-2), x_next, action.unsqueeze(-1).expand(2, 100))
    assert bool(torch.isneginf(lik[0]).all())  # the premise: all -inf for belief 0
    assert bool(torch.isfinite(lik[1]).all())
    post = sir.update(model, belief, action, obs, g)
    assert not bool(torch.isnan(post.particles).any())
    assert not bool(torch.isnan(post.log_weights).any())
    assert bool(torch.isfinite(post.log_weights).all())
    _assert_normalised(post)
    # belief 0 kept the prior (uniform) weights; belief 1 was updated normally
    torch.testing.assert_close(post.log_weights[0], torch.full((100,), -math.log(100)))
    # several impossible steps in a row stay finite
    for _ in range(3):
        post = sir.update(model, post, action, obs, g)
    assert bool(torch.isfinite(post.particles).all())
    assert bool(torch.isfinite(post.log_weights).all())


def test_batch_rows_do_not_interact():
    """Separate updates of each belief are not comparable draw for draw (the generator's stream is
    shared across the batch), but with the same generator seed, changing one belief's inputs must
    leave the other beliefs' results bit-identical."""
    model = LinearGaussian(state_dim=4)
    g = gen(8)
    sir = SIRFilter(resample_threshold=0.5, roughening=0.1)
    belief = sir.init(model, (3,), 400, g)
    action = torch.tensor([0, 3, 5])
    obs = torch.randn(3, 4, generator=g)
    ref = sir.update(model, belief, action, obs, gen(9))
    obs2 = obs.clone()
    obs2[1] += 3.0  # belief 1 now resamples differently
    action2 = action.clone()
    action2[1] = 6
    other = sir.update(model, belief, action2, obs2, gen(9))
    for i in (0, 2):
        assert torch.equal(ref.particles[i], other.particles[i])
        assert torch.equal(ref.log_weights[i], other.log_weights[i])
    assert not torch.equal(ref.particles[1], other.particles[1])
    # the same inputs and seed reproduce the update exactly
    again = sir.update(model, belief, action, obs, gen(9))
    assert torch.equal(ref.particles, again.particles) and torch.equal(ref.log_weights, again.log_weights)


def test_update_keeps_arbitrary_batch_shapes():
    model = LinearGaussian(state_dim=4)
    g = gen(10)
    sir = SIRFilter()
    belief = sir.init(model, (2, 3), 50, g)
    assert belief.particles.shape == (2, 3, 50, 4)
    post = sir.update(model, belief, torch.zeros(2, 3, dtype=torch.long), torch.zeros(2, 3, 4), g)
    assert post.particles.shape == (2, 3, 50, 4) and post.log_weights.shape == (2, 3, 50)
    _assert_normalised(post)
    unbatched = sir.init(model, (), 50, g)
    post0 = sir.update(model, unbatched, torch.tensor(1), torch.zeros(4), g)
    assert post0.particles.shape == (50, 4)


def test_sir_rejects_bad_configuration():
    with pytest.raises(ValueError, match="resample_threshold"):
        SIRFilter(resample_threshold=1.5)
    with pytest.raises(ValueError, match="roughening"):
        SIRFilter(roughening=-0.1)
    with pytest.raises(ValueError, match="num_particles"):
        SIRFilter().init(LinearGaussian(), (2,), 0)


# ---------------------------------------------------------------------------------------------
# Input validation
# ---------------------------------------------------------------------------------------------


@pytest.fixture
def valid_inputs():
    model = LinearGaussian(state_dim=4, obs_dim=2)
    belief = SIRFilter().init(model, (3,), 10, gen(11))
    return model, belief, torch.zeros(3, dtype=torch.long), torch.zeros(3, 2)


def test_validate_accepts_valid_inputs(valid_inputs):
    validate_update_inputs(*valid_inputs)  # no error
    model, belief, action, obs = valid_inputs
    validate_update_inputs(model, belief, action.to(torch.int32), obs)  # any integer dtype


def _bad(valid_inputs, **change):
    model, belief, action, obs = valid_inputs
    args = dict(model=model, belief=belief, action=action, observation=obs)
    args.update(change)
    return args


BAD_CASES = {
    "action_shape_long": (dict(action=torch.zeros(4, dtype=torch.long)), "action:"),
    "action_shape_onehot": (dict(action=torch.zeros(3, 8, dtype=torch.long)), "action:"),
    "action_float": (dict(action=torch.zeros(3)), "action:"),
    "action_bool": (dict(action=torch.zeros(3, dtype=torch.bool)), "action:"),
    "action_not_tensor": (dict(action=[0, 0, 0]), "action:"),
    "observation_shape": (dict(observation=torch.zeros(3, 4)), "observation:"),
    "observation_batch": (dict(observation=torch.zeros(2, 2)), "observation:"),
    "observation_nan": (dict(observation=torch.tensor([[0.0, 0.0], [float("nan"), 0.0], [0.0, 0.0]])),
                        "observation:"),
    "observation_inf": (dict(observation=torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.0, -float("inf")]])),
                        "observation:"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_validate_rejects_bad_inputs(valid_inputs, case):
    change, prefix = BAD_CASES[case]
    args = _bad(valid_inputs, **change)
    with pytest.raises(ValueError) as info:
        validate_update_inputs(**args)
    assert str(info.value).startswith(prefix), str(info.value)
    # the filter's update runs the same validation
    with pytest.raises(ValueError) as info:
        SIRFilter().update(args["model"], args["belief"], args["action"], args["observation"], gen(0))
    assert str(info.value).startswith(prefix), str(info.value)


def test_validate_rejects_state_dim_mismatch(valid_inputs):
    model, _, action, obs = valid_inputs
    belief = SIRFilter().init(LinearGaussian(state_dim=3, obs_dim=2), (3,), 10, gen(12))
    with pytest.raises(ValueError) as info:
        validate_update_inputs(model, belief, action, obs)
    assert str(info.value).startswith("belief.particles:"), str(info.value)
    with pytest.raises(ValueError) as info:
        SIRFilter().update(model, belief, action, obs)
    assert str(info.value).startswith("belief.particles:")


def test_validate_reports_the_bad_rows(valid_inputs):
    model, belief, action, _ = valid_inputs
    obs = torch.zeros(3, 2)
    obs[2, 1] = float("nan")
    with pytest.raises(ValueError, match=r"indices \[2\]"):
        validate_update_inputs(model, belief, action, obs)


@pytest.mark.parametrize("bad_value", [-1, 8], ids=["negative", "too_large"])
def test_validate_rejects_out_of_range_actions(valid_inputs, bad_value):
    model, belief, action, obs = valid_inputs
    assert model.n_actions == 8
    action = action.clone()
    action[1] = bad_value
    with pytest.raises(ValueError) as info:
        SIRFilter().update(model, belief, action, obs, gen(0))
    assert str(info.value).startswith("action:")


def test_non_finite_roughening_is_refused():
    import math as _math

    for bad in (float("inf"), float("nan"), -1.0):
        with pytest.raises(ValueError, match="^SIRFilter.roughening: must be (a finite number|>= 0)"):
            SIRFilter(roughening=bad)
    assert _math.isfinite(SIRFilter(roughening=0.2).roughening)
