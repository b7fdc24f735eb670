"""SVGD and ESCORT: closed-form pieces, calibration against the Kalman filter, numerical safety."""

import math
import pickle

import pytest
import torch

from escort_rl.belief import ESCORTFilter, ParticleBelief, SVGDFilter
from escort_rl.belief.checks import is_finite, is_inf, is_nan
from escort_rl.belief.kernels import median_bandwidth, pairwise_sq_dists, svgd_direction
from escort_rl.belief.prior import SmoothedPrior, silverman_factor
from escort_rl.belief.projections import (
    TemporalReference,
    correlation_force,
    correlation_projections,
    max_sliced_directions,
    permutation_ranks,
    projected_w1_grad,
    random_directions,
    ranks,
    sort_by_ranks,
    sorted_matching,
    temporal_force,
)
from escort_rl.bench.calibration import kalman_calibration
from escort_rl.models import LightDark10D, LinearGaussian


def test_pairwise_and_median_match_direct_computation():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 25, 4, generator=g)
    sq = pairwise_sq_dists(x)
    direct = ((x.unsqueeze(-2) - x.unsqueeze(-3)) ** 2).sum(-1)
    torch.testing.assert_close(sq, direct, atol=1e-4, rtol=1e-4)
    off = ~torch.eye(25, dtype=torch.bool)
    for b in range(3):
        vals = torch.sort(direct[b][off]).values
        expected = vals[(vals.numel() - 1) // 2] / math.log(25)  # lower median over ordered pairs
        torch.testing.assert_close(median_bandwidth(sq)[b], expected, atol=1e-4, rtol=1e-4)


def test_svgd_direction_matches_the_naive_sum():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2, 15, 3, generator=g)
    score = torch.randn(2, 15, 3, generator=g)
    h = torch.tensor([0.7, 1.3])
    out = svgd_direction(x, score, h, repulsion=1.5)
    diff = x.unsqueeze(-2) - x.unsqueeze(-3)  # [B, i, j, d] = x_i - x_j
    k = torch.exp(-(diff**2).sum(-1) / h[:, None, None])
    grad_k = 2.0 / h[:, None, None, None] * diff * k.unsqueeze(-1)  # ∇_{x_j} k(x_j, x_i)
    naive = ((k.unsqueeze(-1) * score.unsqueeze(-3)).sum(-2) + 1.5 * grad_k.sum(-2)) / 15
    torch.testing.assert_close(out, naive, atol=1e-5, rtol=1e-4)


def test_smoothed_prior_matches_the_mixture_and_its_autograd_score():
    g = torch.Generator().manual_seed(2)
    means = torch.randn(2, 30, 3, generator=g, dtype=torch.float64)
    tril = torch.tensor([[0.5, 0, 0], [0.1, 0.4, 0], [0.0, -0.2, 0.3]], dtype=torch.float64)
    prior = SmoothedPrior(means, tril)
    h = silverman_factor(30, 3)
    x = torch.randn(2, 7, 3, generator=g, dtype=torch.float64)
    for b in range(2):
        cov = tril @ tril.T + h * h * torch.cov(means[b].T, correction=0) + 1e-6 * torch.eye(3, dtype=torch.float64)
        comp = torch.distributions.MultivariateNormal(means[b], covariance_matrix=cov)
        ref = torch.logsumexp(comp.log_prob(x[b].unsqueeze(-2)), -1) - math.log(30)
        torch.testing.assert_close(prior.log_prob(x)[b], ref)
    xg = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(prior.log_prob(xg).sum(), xg)
    torch.testing.assert_close(prior.score(x), grad)


def test_shrunk_prior_keeps_the_predicted_mean_and_covariance():
    """``shrink=True``: the mixture's mean and covariance are those of the predicted prior,
    ``μ̄`` and ``Σ̂ + Σ_T``; without it the covariance is ``(1 + h²) Σ̂ + Σ_T``."""
    g = torch.Generator().manual_seed(5)
    means = 3.0 * torch.randn(2, 40, 3, generator=g, dtype=torch.float64)
    log_w = torch.randn(2, 40, generator=g, dtype=torch.float64)
    tril = torch.tensor([[0.5, 0, 0], [0.1, 0.4, 0], [0.0, -0.2, 0.3]], dtype=torch.float64)
    w = torch.softmax(log_w, -1).unsqueeze(-1)
    mean = (w * means).sum(-2)
    spread = ((w * (means - mean.unsqueeze(-2))).transpose(-1, -2) @ (means - mean.unsqueeze(-2)))
    h2 = silverman_factor(40, 3) ** 2
    for shrink, expected in ((True, spread), (False, (1 + h2) * spread)):
        prior = SmoothedPrior(means, tril, log_w, shrink=shrink, ridge=0.0)
        centred = prior.means - mean.unsqueeze(-2)
        mixture_cov = (w * centred).transpose(-1, -2) @ centred + prior.scale_tril @ prior.scale_tril.transpose(-1, -2)
        torch.testing.assert_close((w * prior.means).sum(-2), mean)
        torch.testing.assert_close(mixture_cov, expected + tril @ tril.T)


def test_shrunk_prior_narrows_the_unobserved_velocity_of_light_dark():
    """On Light-Dark the velocity is observed only through the position, so the smoothed prior's
    ``1 + h²`` widening compounds there from update to update; the shrunk prior keeps the velocity
    marginal narrower on the same seeded steps."""
    model = LightDark10D()
    spreads = {}
    for prior in ("smoothed", "shrunk"):
        filt = ESCORTFilter(num_steps=15, step_size=0.15, prior=prior)
        g = torch.Generator().manual_seed(0)
        belief = filt.init(model, (4,), 100, g)
        s = model.initial_state((4,), g)
        for _ in range(30):
            a = torch.randint(0, model.n_actions, (4,), generator=g)
            s = model.transition(s, a, g)
            belief = filt.update(model, belief, a, model.observe(s, a, g), g)
        spreads[prior] = belief.particles[..., 5:].std(-2).mean()
    assert spreads["shrunk"] < 0.8 * spreads["smoothed"]


def test_sorted_matching_is_the_monotone_permutation():
    g = torch.Generator().manual_seed(3)
    x = torch.randn(1, 12, 2, generator=g)
    r = torch.randn(1, 12, 2, generator=g)
    theta = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]])
    sigma = sorted_matching(x, r, theta)
    for j in range(2):
        assert sorted(sigma[0, j].tolist()) == list(range(12))
        px, pr = x[0, :, j], r[0, sigma[0, j], j]
        order = torch.argsort(px)
        assert torch.all(pr[order][1:] >= pr[order][:-1])  # monotone: the 1-D OT plan


def test_temporal_force_pulls_toward_the_matched_reference_and_clips():
    x = torch.zeros(1, 4, 2)
    r = torch.full((1, 4, 2), 100.0)
    theta = torch.tensor([[[1.0, 0.0]]])
    force = temporal_force(x, r, theta, torch.ones(1, 1), strength=0.5, clip=10.0)
    assert torch.all(force == 10.0)


def test_correlation_force_vanishes_for_a_uniform_velocity():
    g = torch.Generator().manual_seed(4)
    x = torch.randn(2, 50, 5, generator=g)
    y = torch.randn(2, 50, 5, generator=g) @ torch.diag(torch.tensor([1.0, 2, 1, 1, 3]))
    a, w = correlation_projections(x, y, torch.zeros(2, 50), n_proj=3, proj_dim=2)
    assert a.shape == (2, 2, 5, 2)  # ⌊5 / 2⌋ = 2 projections: 4 orthonormal directions fit in 5D
    eye = torch.eye(2)
    torch.testing.assert_close(a.transpose(-1, -2) @ a, eye.expand_as(a.transpose(-1, -2) @ a), atol=1e-5, rtol=0)
    torch.testing.assert_close(w.sum(-1), torch.ones(2))
    phi = torch.ones(2, 50, 5) * torch.tensor([1.0, -2, 0.5, 0, 3])
    assert correlation_force(phi, a, w, 0.1).abs().max() < 1e-6
    assert correlation_force(phi, a, w, 0.1, form="position", x=x).abs().max() > 1e-3


def _episode_errors(filt, steps=12, n=300, batch=4, seed=0):
    return kalman_calibration(filt, steps=steps, n=n, batch=batch, seed=seed)


@pytest.mark.parametrize("filt", [SVGDFilter(), ESCORTFilter(), ESCORTFilter(prior="shrunk"),
                                  ESCORTFilter(num_steps=15, step_size=0.15, prior="shrunk")],
                         ids=["svgd", "escort", "escort-shrunk", "escort-train-shrunk"])
def test_calibrated_against_the_kalman_filter(filt):
    """Calibration: over a 12-step episode with N=300, mean within 0.6 Mahalanobis units of the Kalman
    mean on average, and total variance within [0.6, 1.6]× the Kalman variance."""
    maha, ratio = _episode_errors(filt)
    assert maha < 0.6, maha
    assert 0.6 <= ratio <= 1.6, ratio


def test_position_form_contracts_the_belief():
    """The appendix's position-form correlation term shrinks the variance below the velocity form's."""
    _, ratio_velocity = _episode_errors(ESCORTFilter(), steps=6, batch=2)
    _, ratio_position = _episode_errors(ESCORTFilter(corr_form="position"), steps=6, batch=2)
    assert ratio_position < ratio_velocity


def test_variants_are_configurations():
    model = LightDark10D()
    g = torch.Generator().manual_seed(5)
    for filt in (ESCORTFilter(lambda_corr=0.0), ESCORTFilter(lambda_temp=0.0), ESCORTFilter(projection="random"),
                 ESCORTFilter(prior="exact", num_steps=5), ESCORTFilter(likelihood_pull=0.1, num_steps=5),
                 ESCORTFilter(temp_schedule="constant", num_steps=5)):
        b = filt.init(model, (2,), 40, g)
        a = torch.tensor([0, 3])
        out = filt.update(model, b, a, torch.ones(2, 5), g)
        assert out.particles.shape == (2, 40, 10) and torch.isfinite(out.particles).all()
    with pytest.raises(ValueError, match="^SVGDFilter: unknown parameter .lambda_corr.; SVGDFilter takes num_steps"):
        SVGDFilter(lambda_corr=0.1)
    with pytest.raises(ValueError, match="^ESCORTFilter.corr_form"):
        ESCORTFilter(corr_form="other")


def test_coincident_particles_do_not_give_nan():
    model = LinearGaussian(state_dim=3)
    filt = ESCORTFilter(num_steps=10, jitter=0.0)
    belief = ParticleBelief.uniform(torch.zeros(2, 20, 3))
    model_q0 = LinearGaussian(state_dim=3, process_cov=1e-8 * torch.eye(3))
    for m in (model, model_q0):
        out = filt.update(m, belief, torch.zeros(2, dtype=torch.long), torch.zeros(2, 3))
        assert torch.isfinite(out.particles).all()
    x = filt.fit(lambda z: -(z**2).sum(-1), torch.zeros(1, 10, 3), num_steps=5)
    assert torch.isfinite(x).all()


class _ImpossibleObservation(LinearGaussian):
    def observation_log_prob(self, o, s_next, a):
        lp = super().observation_log_prob(o, s_next, a)
        return torch.where(s_next[..., 0] > 0, torch.full_like(lp, -float("inf")), lp * 1e8)


def test_infinite_and_huge_log_densities_do_not_give_nan():
    model = _ImpossibleObservation(state_dim=2)
    g = torch.Generator().manual_seed(6)
    for filt in (SVGDFilter(num_steps=10), ESCORTFilter(num_steps=10)):
        b = filt.init(model, (3,), 30, g)
        out = filt.update(model, b, torch.zeros(3, dtype=torch.long), torch.full((3, 2), 5.0), g)
        assert torch.isfinite(out.particles).all()
        assert torch.isfinite(out.mean()).all()


def test_fit_static_gaussian_target():
    g = torch.Generator().manual_seed(7)
    target = torch.distributions.MultivariateNormal(torch.tensor([1.0, -2.0]),
                                                    covariance_matrix=torch.tensor([[1.0, 0.8], [0.8, 1.0]]))
    x0 = 3.0 * torch.randn(1, 200, 2, generator=g)
    for filt in (SVGDFilter(), ESCORTFilter()):
        x = filt.fit(target.log_prob, x0, num_steps=300, generator=g)
        torch.testing.assert_close(x.mean(-2)[0], target.mean, atol=0.15, rtol=0)
        corr = torch.corrcoef(x[0].T)[0, 1]
        assert abs(float(corr) - 0.8) < 0.1, float(corr)


def test_subsampled_median_is_close_to_the_full_median():
    g = torch.Generator().manual_seed(8)
    x = torch.randn(2, 600, 3, generator=g)
    sq = pairwise_sq_dists(x)
    off = ~torch.eye(600, dtype=torch.bool)
    for b in range(2):
        full = sq[b][off].median() / math.log(600)
        est = median_bandwidth(sq)[b]
        assert abs(float(est / full) - 1) < 0.1
    torch.testing.assert_close(median_bandwidth(sq, max_points=600),
                               median_bandwidth(sq[:, :600, :600], max_points=10**6))


def test_projected_w1_gradient_matches_autograd_through_the_sort():
    g = torch.Generator().manual_seed(7)
    x, r = torch.randn(2, 30, 5, generator=g), torch.randn(2, 30, 5, generator=g) + 0.5
    theta = torch.nn.functional.normalize(torch.randn(2, 3, 5, generator=g), dim=-1).requires_grad_(True)
    px = torch.sort(theta @ x.transpose(-1, -2), dim=-1).values
    pr = torch.sort(theta @ r.transpose(-1, -2), dim=-1).values
    (expected,) = torch.autograd.grad((px - pr).abs().mean(-1).sum(), theta)
    torch.testing.assert_close(projected_w1_grad(x, r, theta.detach()), expected, atol=1e-5, rtol=1e-5)


def test_ranks_by_counting_match_the_sort():
    g = torch.Generator().manual_seed(11)
    v = torch.randn(3, 4, 40, generator=g)
    expected = torch.argsort(torch.argsort(v, dim=-1), dim=-1)
    assert torch.equal(ranks(v), expected)
    assert torch.equal(permutation_ranks(v), expected)
    assert torch.equal(sort_by_ranks(v, permutation_ranks(v)), torch.sort(v, dim=-1).values)
    # ties: shared lowest rank, or broken by position into a permutation
    tied = torch.tensor([2.0, 1.0, 2.0, 2.0, 0.0])
    assert ranks(tied).tolist() == [2, 1, 2, 2, 0]
    assert permutation_ranks(tied).tolist() == [2, 1, 3, 4, 0]
    assert torch.equal(sort_by_ranks(tied, permutation_ranks(tied)), torch.sort(tied).values)


def test_rank_paths_of_the_temporal_term_equal_the_sort_paths():
    """Counting ranks (what the compiled filter uses) gives the same directions, weights, sorted
    reference and force as sorting, for distinct projections."""
    g = torch.Generator().manual_seed(12)
    x, r = torch.randn(3, 50, 6, generator=g), torch.randn(3, 50, 6, generator=g) + 0.3
    theta0 = random_directions(x, 5, g)
    theta, w = max_sliced_directions(x, r, theta0, ascent_steps=3)
    theta_c, w_c = max_sliced_directions(x, r, theta0, ascent_steps=3, rank_fn=permutation_ranks)
    torch.testing.assert_close(theta_c, theta, atol=1e-6, rtol=0)
    torch.testing.assert_close(w_c, w, atol=1e-6, rtol=0)
    torch.testing.assert_close(projected_w1_grad(x, r, theta0, permutation_ranks), projected_w1_grad(x, r, theta0))
    by_sort = TemporalReference(r, theta, w)
    by_count = TemporalReference(r, theta, w, rank_fn=permutation_ranks)
    assert torch.equal(by_count.sorted_ref, by_sort.sorted_ref)
    torch.testing.assert_close(by_count.force(x, 0.3), by_sort.force(x, 0.3))


def test_finite_checks_match_torch():
    t = torch.tensor([0.0, -1.5, float("nan"), float("inf"), -float("inf"), 3e38])
    assert torch.equal(is_nan(t), torch.isnan(t))
    assert torch.equal(is_inf(t), torch.isinf(t))
    assert torch.equal(is_finite(t), torch.isfinite(t))


def test_max_sliced_directions_find_the_shift():
    """Two clouds that differ by a shift along e_0: the best direction is ±e_0."""
    g = torch.Generator().manual_seed(8)
    x = torch.randn(1, 200, 6, generator=g) * 0.3
    r = x + torch.tensor([3.0, 0, 0, 0, 0, 0])
    theta, w = max_sliced_directions(x, r, random_directions(x, 4, g))
    assert torch.all(theta[0, :, 0].abs() > 0.99)
    torch.testing.assert_close(w.sum(-1), torch.ones(1))


@pytest.mark.parametrize("cls", [ESCORTFilter, SVGDFilter])
def test_compiled_update_matches_eager(cls):
    """``compile=True`` runs the same iteration through torch.compile: same particles up to float error."""
    model = LinearGaussian(state_dim=4, obs_dim=2)
    beliefs = []
    for compile_ in (False, True):
        g = torch.Generator().manual_seed(3)
        filt = cls(num_steps=6, compile=compile_)
        belief = filt.init(model, (2,), 24, g)
        for t in range(2):
            a = torch.tensor([t, 1])
            o = model.observe(model.transition(model.initial_state((2,), g), a, g), a, g)
            belief = filt.update(model, belief, a, o, g)
        beliefs.append(belief.particles)
    torch.testing.assert_close(beliefs[1], beliefs[0], atol=1e-4, rtol=1e-4)
    assert pickle.loads(pickle.dumps(filt)).compile  # workers receive a pickled filter


def test_smoothed_prior_survives_an_ill_conditioned_spread():
    """A belief spread over 1e4 in one direction and 1e-3 in others: float32 Cholesky of
    Σ_T + h²Σ̂ can fail; the prior adds a ridge where needed and stays finite."""
    from escort_rl.belief.prior import robust_cholesky

    g = torch.Generator().manual_seed(0)
    means = torch.randn(2, 100, 14, generator=g) * torch.tensor([1e4] + [1e-3] * 13)
    tiny = torch.eye(14) * 1e-4
    prior = SmoothedPrior(means, tiny)
    assert torch.isfinite(prior.scale_tril).all()
    assert torch.isfinite(prior.score(means[:, :5])).all()
    bad = torch.ones(1, 3, 3)  # rank 1: needs the ridge
    factor = robust_cholesky(bad)
    assert torch.isfinite(factor).all()
    torch.testing.assert_close(factor @ factor.transpose(-1, -2), bad, atol=1e-3, rtol=1e-3)


@pytest.mark.parametrize("kwargs, name", [
    ({"step_size": float("inf")}, "step_size"), ({"step_size": float("nan")}, "step_size"),
    ({"lambda_temp": float("inf")}, "lambda_temp"), ({"jitter": float("nan")}, "jitter"),
    ({"temp_clip": -1.0}, "temp_clip"), ({"temp_clip": float("inf")}, "temp_clip"),
    ({"temporal_ascent_steps": -1}, "temporal_ascent_steps"), ({"temporal_ascent_steps": 2.5}, "temporal_ascent_steps"),
])
def test_non_finite_or_out_of_range_arguments_are_refused(kwargs, name):
    with pytest.raises(ValueError, match=f"^ESCORTFilter.{name}: (must be|expected an int)"):
        ESCORTFilter(**kwargs)


@pytest.mark.parametrize("filt", [ESCORTFilter(num_steps=2), SVGDFilter(num_steps=2)], ids=["escort", "svgd"])
def test_float64_observations_update_a_float32_belief(filt):
    from escort_rl.models import LightDark10D

    model = LightDark10D()
    belief = filt.init(model, (2,), 8, torch.Generator().manual_seed(0))
    action = torch.zeros(2, dtype=torch.long)
    obs = model.observe(model.transition(model.initial_state((2,)), action), action)
    g = torch.Generator().manual_seed(1)
    out64 = filt.update(model, belief, action, obs.double(), g)
    out32 = filt.update(model, belief, action, obs, torch.Generator().manual_seed(1))
    assert out64.particles.dtype == torch.float32
    torch.testing.assert_close(out64.particles, out32.particles)


def test_moment_change_is_the_shift_over_the_spread():
    from escort_rl.belief.evolution import belief_moments, moment_change

    x = torch.tensor([[[0.0, 0.0], [2.0, 0.0], [0.0, 2.0], [2.0, 2.0]]])  # mean (1, 1), std (1, 1)
    mean, std = belief_moments(x)
    torch.testing.assert_close(mean, torch.tensor([[1.0, 1.0]]))
    torch.testing.assert_close(std, torch.tensor([[1.0, 1.0]]))
    shifted = x + torch.tensor([0.3, 0.4])  # ‖Δμ‖ = 0.5, spread ‖σ‖ = √2
    torch.testing.assert_close(moment_change((mean, std), belief_moments(shifted)), torch.tensor([0.5 / math.sqrt(2)]))
    wider = 1.0 + 3.0 * (x - 1.0)  # σ 1 -> 3 in both coordinates: ‖Δσ‖ = 2√2
    torch.testing.assert_close(moment_change((mean, std), belief_moments(wider)), torch.tensor([2.0]))


def test_adaptive_stop_at_the_first_window_equals_running_that_many_iterations():
    target = torch.distributions.MultivariateNormal(torch.tensor([1.0, -2.0]), covariance_matrix=torch.eye(2))
    x0 = 3.0 * torch.randn(2, 50, 2, generator=torch.Generator().manual_seed(3))
    stopped = ESCORTFilter(num_steps=40, stop_tolerance=1e9, stop_window=5)
    short = ESCORTFilter(num_steps=5)
    a = stopped.fit(target.log_prob, x0, generator=torch.Generator().manual_seed(4))
    b = short.fit(target.log_prob, x0, generator=torch.Generator().manual_seed(4))
    torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert stopped.mean_iterations() == 5.0 and short.mean_iterations() == 5.0
    assert math.isnan(ESCORTFilter().mean_iterations())


def test_adaptive_stop_saves_iterations_and_stays_calibrated():
    """On the Kalman calibration episode a tolerance of 0.05 runs well under K = 50 iterations per
    update, with the mean and variance still within the calibration bounds."""
    filt = ESCORTFilter(stop_tolerance=0.05)
    maha, ratio = _episode_errors(filt)
    assert filt.mean_iterations() < 40, filt.mean_iterations()
    assert maha < 0.6, maha
    assert 0.6 <= ratio <= 1.6, ratio


def test_adaptive_stop_arguments_are_checked():
    with pytest.raises(ValueError, match="^ESCORTFilter.stop_tolerance: must be"):
        ESCORTFilter(stop_tolerance=-0.1)
    with pytest.raises(ValueError, match="^ESCORTFilter.stop_window: must be"):
        ESCORTFilter(stop_window=0)


def test_a_flat_log_density_has_a_zero_score():
    """A log-density that does not depend on the state (no autograd graph) has score 0, eager."""
    from escort_rl.belief.scores import autograd_score

    x = torch.randn(2, 5, 3)
    torch.testing.assert_close(autograd_score(lambda z: torch.zeros(z.shape[:-1]), x), torch.zeros_like(x))


@pytest.mark.parametrize("cls", [ESCORTFilter, SVGDFilter])
def test_a_model_with_a_flat_likelihood_updates(cls):
    class Flat(LinearGaussian):
        observation_score = None  # the autograd path

        def observation_log_prob(self, o, s_next, a):
            return torch.zeros(torch.broadcast_shapes(o.shape[:-1], s_next.shape[:-1]))

    model, g = Flat(state_dim=2), torch.Generator().manual_seed(0)
    filt = cls(num_steps=3)
    belief = filt.init(model, (2,), 10, g)
    out = filt.update(model, belief, torch.zeros(2, dtype=torch.long), torch.zeros(2, model.obs_dim), g)
    assert torch.isfinite(out.particles).all()


def test_a_non_number_argument_is_named():
    with pytest.raises(ValueError, match="^ESCORTFilter.step_size: expected a number, got '0.1'"):
        ESCORTFilter(step_size="0.1")
    with pytest.raises(ValueError, match="^SVGDFilter.jitter: expected a number or null, got 'x'"):
        SVGDFilter(jitter="x")


# ---------------------------------------------------------------------------------------- annealing
def test_schedule_closed_form():
    """γ_k = (k mod P)/P with P = ceil(fraction·K / cycles) over the first fraction·K iterations,
    then 1; the bandwidth multiplier start^(1 − k/(fraction·K)), then 1."""
    filt = ESCORTFilter(anneal_cycles=2, anneal_fraction=0.5, bandwidth_start=4.0)
    got = [filt.schedule(k, 20) for k in range(12)]
    gammas = [0.0, 0.2, 0.4, 0.6, 0.8, 0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.0]
    assert [g for g, _ in got] == pytest.approx(gammas)
    assert [b for _, b in got] == pytest.approx([4.0 ** (1 - k / 10) for k in range(10)] + [1.0, 1.0])
    assert ESCORTFilter().schedule(0, 20) == (1.0, 1.0)
    assert ESCORTFilter(anneal_cycles=1, anneal_fraction=1.0).schedule(5, 10) == (0.5, 1.0)


@pytest.mark.parametrize("kwargs, field", [({"anneal_cycles": -1}, "anneal_cycles"),
                                           ({"anneal_cycles": 1.5}, "anneal_cycles"),
                                           ({"anneal_fraction": 0.0}, "anneal_fraction"),
                                           ({"bandwidth_start": 0.0}, "bandwidth_start")])
def test_schedule_arguments_are_checked(kwargs, field):
    with pytest.raises(ValueError, match=f"^ESCORTFilter.{field}: (must be|expected an int)"):
        ESCORTFilter(**kwargs)


@pytest.mark.parametrize("kwargs", [{"anneal_cycles": 1}, {"anneal_cycles": 4}, {"bandwidth_start": 4.0},
                                    {"anneal_cycles": 4, "bandwidth_start": 4.0}])
def test_annealed_fit_still_reaches_the_target(kwargs):
    """The schedules act on the first half of the iterations; the fit then converges as without them."""
    g = torch.Generator().manual_seed(7)
    target = torch.distributions.MultivariateNormal(torch.tensor([1.0, -2.0]),
                                                    covariance_matrix=torch.tensor([[1.0, 0.8], [0.8, 1.0]]))
    x0 = 3.0 * torch.randn(1, 200, 2, generator=g)
    x = ESCORTFilter(**kwargs).fit(target.log_prob, x0, num_steps=300, generator=g)
    torch.testing.assert_close(x.mean(-2)[0], target.mean, atol=0.15, rtol=0)
    assert abs(float(torch.corrcoef(x[0].T)[0, 1]) - 0.8) < 0.1


def test_pure_repulsion_spreads_the_particles():
    """At γ = 0 (the first iteration of an annealing cycle) the score is off: the particles only
    repel each other, so their spread grows whatever the target."""
    g = torch.Generator().manual_seed(3)
    x0 = 0.1 * torch.randn(1, 100, 2, generator=g)
    target = torch.distributions.MultivariateNormal(torch.zeros(2), covariance_matrix=0.01 * torch.eye(2))
    # fraction 1, one cycle of P = K = 2 iterations: γ = 0 then 0.5; compare with γ = 1 throughout
    annealed = ESCORTFilter(anneal_cycles=1, anneal_fraction=1.0, lambda_corr=0.0).fit(target.log_prob, x0, num_steps=1)
    plain = ESCORTFilter(lambda_corr=0.0).fit(target.log_prob, x0, num_steps=1)
    assert float(annealed.std()) > float(x0.std())
    assert float(annealed.std()) > float(plain.std())


def test_jitter_at_start_is_evolved_away_and_at_end_stays_in_the_belief():
    # a large jitter (std 0.5 against a posterior std of about 0.5) on the calibration model: added at
    # the end it widens the belief by its variance; added to the start, the K iterations take the
    # particles back to the target, so calibration holds
    from escort_rl.bench.calibration import kalman_calibration

    end = kalman_calibration(ESCORTFilter(jitter=0.5))
    start = kalman_calibration(ESCORTFilter(jitter=0.5, jitter_at="start"))
    assert end[1] > 2.0
    assert start[0] < 0.6 and 0.6 < start[1] < 1.6
    with pytest.raises(ValueError, match="^ESCORTFilter.jitter_at: must be one of end, start; got 'middle'"):
        ESCORTFilter(jitter_at="middle")


def test_an_update_flushes_subnormals_and_leaves_the_mode_as_it_was():
    from escort_rl.belief.denormals import flush_denormals, flushing_denormals
    from escort_rl.models import LinearGaussian

    model = LinearGaussian(state_dim=3)
    filt = SVGDFilter(num_steps=2)
    b = filt.init(model, (2,), 20, torch.Generator().manual_seed(0))
    a = torch.zeros(2, dtype=torch.long)
    assert not flushing_denormals()
    filt.update(model, b, a, torch.zeros(2, 3))
    assert not flushing_denormals()  # restored
    supported = torch.set_flush_denormal(True)  # False on a CPU without flushing
    torch.set_flush_denormal(False)
    with flush_denormals():
        assert flushing_denormals() == supported
        with flush_denormals():
            pass
        assert flushing_denormals() == supported  # the inner block left the outer one's mode
    assert not flushing_denormals()
