"""Tests of the POMDP models: Light-Dark 10D and the linear-Gaussian calibration model."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import gen
from escort_rl.models import LightDark10D, LinearGaussian, POMDPModel, check_model
from escort_rl.models.gaussian import make_positive_definite, nearest_correlation_matrix
from escort_rl.models.light_dark import LIGHT_REGIONS, paper_correlations


@pytest.fixture(scope="module")
def model() -> LightDark10D:
    return LightDark10D()


def _is_correlation_matrix(c: torch.Tensor, tol: float = 1e-8) -> bool:
    return (
        torch.allclose(c, c.T, atol=tol)
        and torch.allclose(torch.diagonal(c), torch.ones(c.shape[0], dtype=c.dtype), atol=tol)
        and bool(torch.linalg.eigvalsh(c).min() >= -tol)
    )


def _random_correlation(d: int, g: torch.Generator) -> torch.Tensor:
    """A random (full-rank) correlation matrix: a normalised Wishart draw."""
    a = torch.randn(d, 2 * d, generator=g, dtype=torch.float64)
    c = a @ a.T
    s = torch.sqrt(torch.diagonal(c))
    return c / s[:, None] / s[None, :]


# ---------------------------------------------------------------------------------------------
# Light-Dark 10D: protocol and the process-noise correlation
# ---------------------------------------------------------------------------------------------


def test_light_dark_follows_protocol(model):
    check_model(model)
    assert isinstance(model, POMDPModel)
    assert (model.state_dim, model.obs_dim, model.n_actions) == (10, 5, 10)


def test_correlation_is_a_valid_pd_correlation_matrix(model):
    c = model.correlation
    assert c.shape == (10, 10)
    assert c.dtype == torch.float64
    torch.testing.assert_close(c, c.T, rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.diagonal(c), torch.ones(10, dtype=torch.float64), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(c).min() > 1e-4  # strictly positive definite
    assert bool((c.abs() <= 1.0 + 1e-12).all())
    chol, info = torch.linalg.cholesky_ex(c)
    assert int(info) == 0
    torch.testing.assert_close(chol @ chol.T, c)
    # the float32 factor the model samples with reproduces the noise covariance
    tril = model.transition_scale_tril()
    assert tril.shape == (10, 10) and tril.dtype == torch.float32
    torch.testing.assert_close(tril, torch.tril(tril))
    assert bool((torch.diagonal(tril) > 0).all())
    cov = model.correlation * 0.05**2  # default position/velocity noise std 0.05
    torch.testing.assert_close((tril @ tril.T).double(), cov, rtol=1e-4, atol=1e-8)
    torch.testing.assert_close(model.noise_covariance.double(), cov, rtol=1e-5, atol=1e-9)


def test_paper_correlations_entries_and_not_psd():
    c = paper_correlations()
    assert c.shape == (10, 10) and c.dtype == torch.float64
    torch.testing.assert_close(c, c.T)
    torch.testing.assert_close(torch.diagonal(c), torch.ones(10, dtype=torch.float64))
    for i in range(5):
        assert c[i, 5 + i] == 0.8
    for i in range(4):
        assert c[i, i + 1] == 0.5
    for i in range(1, 4):
        assert c[5 + i, 5 + i + 1] == 0.6
    assert c[0, 2] == 0.4 and c[1, 3] == 0.4
    assert c[5, 6] == 0.7 and c[5, 7] == 0.5
    evals = torch.linalg.eigvalsh(c)
    assert evals.min().item() == pytest.approx(-0.66, abs=0.01)
    # not PSD, so Cholesky must fail
    assert int(torch.linalg.cholesky_ex(c)[1]) != 0


def test_nearest_correlation_is_close_to_the_paper():
    """The repaired matrix is the (convex) projection of the paper's matrix onto the correlation set.

    Optimality of a projection X of A onto a convex set K: <A - X, Y - X> <= 0 for every Y in K. We
    check that against random correlation matrices and a few structured ones, and that X is at least
    as close to A as simpler repairs (shrinkage towards I, the identity).
    """
    a = paper_correlations()
    x = nearest_correlation_matrix(a)
    assert _is_correlation_matrix(x, tol=1e-7)
    dist = torch.linalg.norm(x - a)
    # shrinkage c·A + (1-c)·I with the largest c that makes it PSD
    lam = torch.linalg.eigvalsh(a).min()
    t = 1.0 / (1.0 - lam)
    shrunk = t * a + (1 - t) * torch.eye(10, dtype=torch.float64)
    assert _is_correlation_matrix(shrunk, tol=1e-7)
    assert dist < torch.linalg.norm(shrunk - a)
    assert dist < torch.linalg.norm(torch.eye(10, dtype=torch.float64) - a)
    g = gen(0)
    candidates = [_random_correlation(10, g) for _ in range(50)]
    candidates += [torch.eye(10, dtype=torch.float64), shrunk]
    for y in candidates:
        assert torch.sum((a - x) * (y - x)) <= 1e-6
        assert dist <= torch.linalg.norm(y - a) + 1e-9
    # the paper's larger correlations survive the repair with their sign
    for i in range(5):
        assert x[i, 5 + i] > 0.5  # paper: 0.8
    assert x[5, 6] > 0.3  # paper: 0.7
    # the entries moved on average by well under the size of the entries themselves
    assert (x - a).abs().max() < 0.25
    # the model's matrix is the nearest one lifted to be PD: still close to it
    model_c = LightDark10D().correlation
    assert torch.linalg.norm(model_c - x) < 0.02


def test_nearest_correlation_keeps_a_valid_matrix_fixed():
    c = _random_correlation(6, gen(1))
    torch.testing.assert_close(nearest_correlation_matrix(c), c, rtol=0, atol=1e-8)
    torch.testing.assert_close(make_positive_definite(c, min_eig=1e-6), c, rtol=0, atol=1e-8)


# ---------------------------------------------------------------------------------------------
# Light-Dark 10D: dynamics
# ---------------------------------------------------------------------------------------------


def test_transition_mean_formula(model):
    g = gen(2)
    s = torch.randn(7, 10, generator=g)
    a = torch.arange(7) % 10
    mean = model.transition_mean(s, a)
    pos, vel = s[:, :5], s[:, 5:]
    exp_pos = pos + 0.1 * vel
    exp_vel = 0.9 * vel
    for k in range(7):
        i, sign = int(a[k]) // 2, (1.0 if int(a[k]) % 2 == 0 else -1.0)
        exp_vel[k, i] += sign * 0.1
    torch.testing.assert_close(mean, torch.cat([exp_pos, exp_vel], -1))


def test_transition_log_prob_matches_torch_mvn(model):
    g = gen(3)
    s = 3 * torch.randn(6, 4, 10, generator=g)
    a = torch.randint(0, 10, (6, 4), generator=g)
    s_next = model.transition(s, a, g)
    # also some states far from the mean
    s_far = s_next + 0.2 * torch.randn(s_next.shape, generator=g)
    ref = torch.distributions.MultivariateNormal(
        model.transition_mean(s, a).double(), scale_tril=model.transition_scale_tril().double()
    )
    for x in (s_next, s_far):
        lp = model.transition_log_prob(x, s, a)
        assert lp.shape == (6, 4)
        torch.testing.assert_close(lp.double(), ref.log_prob(x.double()), rtol=1e-4, atol=1e-3)


def test_transition_samples_have_the_noise_covariance(model):
    g = gen(4)
    n = 40000
    s = torch.zeros(n, 10)
    a = torch.full((n,), 3)
    x = model.transition(s, a, g) - model.transition_mean(s, a)
    emp = torch.cov(x.T.double())
    # relative standard error of a sample covariance entry is about sqrt(2/n) ≈ 0.007
    torch.testing.assert_close(emp, model.noise_covariance.double(), rtol=0, atol=5 * math.sqrt(2 / n) * 0.05**2)


def test_initial_state_and_belief(model):
    s0 = model.initial_state((3, 2), gen(5))
    assert s0.shape == (3, 2, 10)
    assert bool(((s0[..., :5] >= 0) & (s0[..., :5] <= 2)).all())
    assert bool((s0[..., 5:] == 0).all())
    b = model.initial_belief((3,), 11, gen(5))
    assert b.shape == (3, 11, 10)
    torch.testing.assert_close(model.initial_state((4,), gen(9)), model.initial_state((4,), gen(9)))


def test_prior_around_an_exploring_start_is_a_box_of_prior_width_that_holds_the_start():
    """Exploring starts (``prior_width``): the prior is a box of side ``w`` that holds the start, with
    the start uniform in it, so the particles' mean is unbiased for the start; velocities are zero."""
    w = 2.0
    model = LightDark10D(start_low=0.0, start_high=10.0, prior_width=w)
    start = model.initial_state((2000,), gen(3))
    prior = model.initial_belief_around(start, 50, gen(4))
    assert prior.shape == (2000, 50, 10) and bool((prior[..., 5:] == 0).all())
    gap = prior[..., :5] - start[:, None, :5]
    # every particle and the start lie in one box of side w
    span = gap.amax(-2).clamp_min(0.0) - gap.amin(-2).clamp_max(0.0)  # of the particles and the start
    assert bool((span <= w + 1e-5).all())
    # start uniform in its box: E[mean − start] = 0 per coordinate; the per-belief std is about
    # w/sqrt(12) = 0.58, so over 2000 beliefs the standard error is 0.013 (the bound is 6 of them)
    assert float(gap.mean(-2).mean(0).abs().max()) < 0.08
    with pytest.raises(ValueError, match="prior_width"):
        LightDark10D().initial_belief_around(start, 5)
    with pytest.raises(ValueError, match="prior_width"):
        LightDark10D(prior_width=0.0)


def test_filter_init_places_the_prior_around_the_start_only_where_the_model_asks():
    from escort_rl.belief import SIRFilter

    start = torch.full((3, 10), 7.0)
    start[:, 5:] = 0.0
    placed = SIRFilter().init(LightDark10D(prior_width=1.0), (3,), 40, gen(1), start_state=start)
    assert bool(((placed.particles[..., :5] - 7.0).abs() <= 1.0).all())
    plain = SIRFilter().init(LightDark10D(), (3,), 40, gen(1), start_state=start)  # no prior_width: ignored
    torch.testing.assert_close(plain.particles, LightDark10D().initial_belief((3,), 40, gen(1)))
    with pytest.raises(ValueError, match="^start_state: expected shape"):
        SIRFilter().init(LightDark10D(prior_width=1.0), (3,), 40, gen(1), start_state=start[:2])


# ---------------------------------------------------------------------------------------------
# Light-Dark 10D: the light field and observations
# ---------------------------------------------------------------------------------------------


def _light_reference(pos: torch.Tensor) -> torch.Tensor:
    """L(x) = max(0.05, max_j I_j (1 - (d_j/r_j)²) [d_j < r_j]) in float64, one region at a time."""
    pos = pos.double()
    level = torch.zeros(pos.shape[:-1], dtype=torch.float64)
    for centre, radius, intensity in LIGHT_REGIONS:
        d = torch.linalg.vector_norm(pos - torch.tensor(centre, dtype=torch.float64), dim=-1)
        lj = torch.where(d < radius, intensity * (1 - (d / radius) ** 2), torch.zeros_like(d))
        level = torch.maximum(level, lj)
    return level.clamp_min(0.05)


def _spread_and_lit_positions(n_spread: int, n_per_region: int, g: torch.Generator) -> torch.Tensor:
    """Positions uniform over [-2, 12]^5 plus positions inside each light region."""
    spread = -2 + 14 * torch.rand(n_spread, 5, generator=g)
    lit = []
    for centre, radius, _ in LIGHT_REGIONS:
        direction = torch.randn(n_per_region, 5, generator=g)
        direction = direction / direction.norm(dim=-1, keepdim=True)
        r = radius * torch.rand(n_per_region, 1, generator=g) ** 0.5
        lit.append(torch.tensor(centre) + r * direction)
    return torch.cat([spread, *lit, torch.tensor([c for c, _, _ in LIGHT_REGIONS])])


def test_light_matches_direct_formula(model):
    pos = _spread_and_lit_positions(4000, 200, gen(6))
    light = model.light(pos)
    assert light.shape == (pos.shape[0],)
    torch.testing.assert_close(light.double(), _light_reference(pos), rtol=0, atol=1e-4)
    # exact values at the centres (intensities) and far away (the 0.05 floor)
    centres = torch.tensor([c for c, _, _ in LIGHT_REGIONS])
    torch.testing.assert_close(model.light(centres), torch.tensor([i for _, _, i in LIGHT_REGIONS]),
                               rtol=0, atol=1e-5)
    assert model.light(torch.full((5,), 40.0)).item() == pytest.approx(0.05)
    # batch shapes are kept
    assert model.light(pos[:70].reshape(10, 7, 5)).shape == (10, 7)


def _observation_log_prob_reference(model: LightDark10D, o: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Brute force: Normal log-probs of the three permuted position vectors, mixed 0.8/0.1/0.1 in the
    dark (L < 0.1), the unpermuted one elsewhere. float64."""
    pos = s[..., :5].double()
    o = o.double()
    light = _light_reference(pos)
    std = torch.sqrt(0.5**2 * (1 - light) + 0.01**2).unsqueeze(-1)
    perms = ([0, 1, 2, 3, 4], [1, 0, 2, 3, 4], [0, 1, 3, 2, 4])
    comps = torch.stack(
        [torch.distributions.Normal(pos[..., p], std).log_prob(o).sum(-1) for p in perms], dim=-1
    )
    log_w = torch.log(torch.tensor([0.8, 0.1, 0.1], dtype=torch.float64))
    mixed = torch.logsumexp(comps + log_w, dim=-1)
    return torch.where(light < 0.1, mixed, comps[..., 0])


def test_observation_log_prob_matches_brute_force(model):
    g = gen(7)
    pos = _spread_and_lit_positions(3000, 150, g)
    s = torch.cat([pos, torch.randn(pos.shape, generator=g)], -1)
    a = torch.randint(0, 10, pos.shape[:1], generator=g)
    dark = _light_reference(pos) < 0.1
    assert 0.2 < dark.float().mean() < 0.95  # both regimes are exercised
    obs_sampled = model.observe(s, a, g)
    obs_random = -2 + 14 * torch.rand(pos.shape, generator=g)
    obs_near = pos + 0.3 * torch.randn(pos.shape, generator=g)
    for o in (obs_sampled, obs_random, obs_near):
        lp = model.observation_log_prob(o, s, a)
        ref = _observation_log_prob_reference(model, o, s)
        assert lp.shape == ref.shape
        assert bool(torch.isfinite(lp).all())
        torch.testing.assert_close(lp.double(), ref, rtol=1e-4, atol=1e-3)


def test_observation_log_prob_mixture_is_not_the_plain_gaussian_in_the_dark(model):
    """A swapped observation is likely under the mixture in the dark, and very unlikely in the light."""
    dark_pos = torch.tensor([-3.0, 3.0, -3.0, 3.0, 10.0])
    assert model.light(dark_pos) < 0.1
    s = torch.cat([dark_pos, torch.zeros(5)])
    o_swapped = dark_pos[[1, 0, 2, 3, 4]]
    lp = model.observation_log_prob(o_swapped, s, torch.tensor(0))
    sigma = model.observation_std(dark_pos)
    expected = math.log(0.1) + torch.distributions.Normal(o_swapped, sigma).log_prob(o_swapped).sum()
    assert lp.item() == pytest.approx(expected.item(), abs=1e-3)


def test_observe_swap_frequency_in_the_dark(model):
    """With coordinates ±50 apart, a swap is unmistakable: o_1 > 0 means swap(1,2), o_3 > 0 swap(3,4)."""
    n = 100_000
    pos = torch.tensor([-50.0, 50.0, -50.0, 50.0, 0.0])
    assert model.light(pos) < model.dark_threshold
    s = torch.cat([pos, torch.zeros(5)]).expand(n, 10)
    o = model.observe(s, torch.zeros(n, dtype=torch.long), gen(8))
    swap12 = o[:, 0] > 0
    swap34 = o[:, 2] > 0
    assert bool((swap12 == (o[:, 1] < 0)).all())
    assert bool((swap34 == (o[:, 3] < 0)).all())
    assert not bool((swap12 & swap34).any())  # one event at a time
    half = model.confusion_prob / 2
    se = math.sqrt(half * (1 - half) / n)  # ≈ 0.00095
    assert abs(swap12.float().mean().item() - half) < 5 * se
    assert abs(swap34.float().mean().item() - half) < 5 * se
    assert abs((swap12 | swap34).float().mean().item() - model.confusion_prob) < 5 * math.sqrt(0.2 * 0.8 / n)
    # coordinate 5 is never permuted
    assert bool((o[:, 4].abs() < 5).all())


def test_observe_never_swaps_in_the_light():
    """Inside the goal beacon (L = 0.75 here) no swap happens: the identity explains every draw best."""
    model = LightDark10D(sigma_base=0.05)  # σ ≈ 0.027 here: 1.0 apart coordinates are ~37σ apart
    n = 50_000
    pos = torch.tensor([0.5, -0.5, 0.5, -0.5, 7.0])
    assert model.light(pos).item() == pytest.approx(0.75, abs=1e-5)
    s = torch.cat([pos, torch.zeros(5)]).expand(n, 10)
    o = model.observe(s, torch.zeros(n, dtype=torch.long), gen(9))
    assert bool((o[:, 0] > o[:, 1]).all())
    assert bool((o[:, 2] > o[:, 3]).all())
    # and the same position in the dark (L < 0.1 by lowering the beacon threshold) does swap
    dark_model = LightDark10D(sigma_base=0.05, dark_threshold=0.8)
    o_dark = dark_model.observe(s, torch.zeros(n, dtype=torch.long), gen(9))
    assert 0.05 < (o_dark[:, 0] < o_dark[:, 1]).float().mean() < 0.15


def test_observation_noise_std_in_the_light(model):
    n = 50_000
    pos = torch.tensor([5.0, 0.0, 0.0, 0.0, 0.0])  # primary corridor centre: L = 0.9
    s = torch.cat([pos, torch.zeros(5)]).expand(n, 10)
    o = model.observe(s, torch.zeros(n, dtype=torch.long), gen(10))
    sigma = math.sqrt(0.25 * 0.1 + 0.01**2)
    assert model.observation_std(pos).item() == pytest.approx(sigma, rel=1e-5)
    emp = (o - pos).std(0)
    torch.testing.assert_close(emp, torch.full((5,), sigma), rtol=0.02, atol=0)
    torch.testing.assert_close((o - pos).mean(0), torch.zeros(5), rtol=0, atol=5 * sigma / math.sqrt(n))


def test_observation_log_prob_broadcasts(model):
    g = gen(11)
    b, n = 3, 17
    s = torch.cat([-2 + 14 * torch.rand(b, n, 5, generator=g), torch.randn(b, n, 5, generator=g)], -1)
    o = -2 + 14 * torch.rand(b, 1, 5, generator=g)
    a = torch.randint(0, 10, (b, n), generator=g)
    lp = model.observation_log_prob(o, s, a)
    assert lp.shape == (b, n)
    torch.testing.assert_close(lp, model.observation_log_prob(o.expand(b, n, 5), s, a))
    torch.testing.assert_close(lp.double(), _observation_log_prob_reference(model, o.expand(b, n, 5), s),
                               rtol=1e-4, atol=1e-3)
    # the transition broadcasts the same way
    a_next = torch.randint(0, 10, (b, n), generator=g)
    assert model.transition(s, a_next, g).shape == (b, n, 10)
    assert model.transition_log_prob(s, s, a_next).shape == (b, n)
    assert model.observe(s, a_next, g).shape == (b, n, 5)


def test_observation_log_prob_gradients_are_finite(model):
    g = gen(12)
    pos = _spread_and_lit_positions(500, 40, g)
    s = torch.cat([pos, torch.randn(pos.shape, generator=g)], -1).requires_grad_(True)
    o = model.observe(s.detach(), torch.zeros(pos.shape[0], dtype=torch.long), g)
    lp = model.observation_log_prob(o, s, torch.zeros(pos.shape[0], dtype=torch.long))
    (grad,) = torch.autograd.grad(lp.sum(), s)
    assert bool(torch.isfinite(grad).all())
    assert bool((grad[:, 5:] == 0).all())  # velocities are not observed
    assert grad[:, :5].abs().sum() > 0
    # at a light centre the squared distance is clamped at 0: the gradient is still finite
    centre = torch.tensor([[0.0, 0.0, 0.0, 0.0, 7.0] + [0.0] * 5], requires_grad=True)
    lp_c = model.observation_log_prob(torch.zeros(1, 5), centre, torch.zeros(1, dtype=torch.long))
    (grad_c,) = torch.autograd.grad(lp_c.sum(), centre)
    assert bool(torch.isfinite(grad_c).all())


def test_observation_log_prob_gradient_matches_finite_differences(model):
    """Autograd against central differences in float64 on the reference (which agrees in value)."""
    g = gen(13)
    pos = torch.tensor([[4.2, 0.5, -0.3, 0.2, 0.1], [8.0, 9.0, 1.0, 10.0, 3.0], [0.3, -0.2, 2.4, 2.9, 0.1]])
    s = torch.cat([pos, torch.zeros(3, 5)], -1).requires_grad_(True)
    o = pos + 0.4 * torch.randn(pos.shape, generator=g)
    lp = model.observation_log_prob(o, s, torch.zeros(3, dtype=torch.long))
    (grad,) = torch.autograd.grad(lp.sum(), s)
    eps = 1e-5
    s64 = s.detach().double()
    fd = torch.zeros(3, 5, dtype=torch.float64)
    for k in range(5):
        e = torch.zeros(10, dtype=torch.float64)
        e[k] = eps
        up = _observation_log_prob_reference(model, o, s64 + e)
        down = _observation_log_prob_reference(model, o, s64 - e)
        fd[:, k] = (up - down) / (2 * eps)
    torch.testing.assert_close(grad[:, :5].double(), fd, rtol=2e-3, atol=2e-3)


def test_reward_and_terminal_near_the_goal(model):
    goal = torch.full((5,), 8.0)
    vel = torch.zeros(5)
    at_goal = torch.cat([goal, vel])
    a = torch.tensor(0)
    assert model.reward(at_goal, a, at_goal).item() == pytest.approx(-0.1)
    assert bool(model.is_terminal(at_goal))
    unit = torch.tensor([1.0, 0, 0, 0, 0])
    inside = torch.cat([goal + 0.49 * unit, vel])
    outside = torch.cat([goal + 0.51 * unit, vel])
    one_away = torch.cat([goal - torch.full((5,), 1 / math.sqrt(5)), vel])
    assert bool(model.is_terminal(inside))
    assert not bool(model.is_terminal(outside))
    assert model.reward(at_goal, a, one_away).item() == pytest.approx(-0.2, abs=1e-6)
    # the reward is of the next state, not of the current one
    start = torch.zeros(10)
    assert model.reward(start, a, at_goal).item() == pytest.approx(-0.1)
    assert model.reward(at_goal, a, start).item() == pytest.approx(-0.1 * math.sqrt(5 * 64) - 0.1, abs=1e-5)
    batch = torch.stack([at_goal, inside, outside, start])
    assert model.is_terminal(batch).tolist() == [True, True, False, False]
    assert model.reward(batch, torch.zeros(4, dtype=torch.long), batch).shape == (4,)
    assert not bool(model.is_terminal(model.initial_state((100,), gen(14))).any())


def test_light_dark_rejects_bad_arguments():
    with pytest.raises(ValueError, match="confusion_prob"):
        LightDark10D(confusion_prob=1.0)
    with pytest.raises(ValueError, match="sigma_min"):
        LightDark10D(sigma_min=0.0)
    for bad in (4, 6.5, True):
        with pytest.raises(ValueError, match="n_pos"):
            LightDark10D(n_pos=bad)


def test_light_dark_in_more_dimensions_keeps_the_paper_light_and_splits_the_swaps():
    """n_pos = 12: state 24-D; the light is the paper's field of the first five coordinates; the six
    pairs (2i, 2i+1) each swap with probability confusion_prob / 6 in the dark, one at a time."""
    big, paper = LightDark10D(n_pos=12), LightDark10D()
    assert (big.state_dim, big.obs_dim, big.n_actions) == (24, 12, 24)
    assert big.position_dims == tuple(range(12)) and big.velocity_dims == tuple(range(12, 24))
    x = 10 * torch.rand(50, 12, generator=gen(30))
    torch.testing.assert_close(big.light(x), paper.light(x[:, :5]))
    assert _is_correlation_matrix(big.correlation)
    torch.testing.assert_close(big.correlation[:10, :10][:5, :5], big.correlation[:5, :5])
    n = 120_000
    pos = torch.tensor([-50.0, 50.0] * 6)
    assert big.light(pos) < big.dark_threshold
    o = big.observe(torch.cat([pos, torch.zeros(12)]).expand(n, 24), torch.zeros(n, dtype=torch.long), gen(31))
    swapped = o[:, 0::2] > 0  # [n, 6]: pair k swapped
    assert bool((swapped == (o[:, 1::2] < 0)).all())
    assert int(swapped.sum(1).max()) <= 1  # one event at a time
    share = big.confusion_prob / 6
    se = math.sqrt(share * (1 - share) / n)
    assert (swapped.float().mean(0) - share).abs().max().item() < 5 * se
    # the log-density is the 7-component mixture: a swapped observation costs log(share), not more
    s = torch.cat([pos, torch.zeros(12)])
    o_sw = pos.clone()
    o_sw[[6, 7]] = o_sw[[7, 6]]
    sigma = big.observation_std(pos)
    expected = math.log(share) + torch.distributions.Normal(o_sw, sigma).log_prob(o_sw).sum()
    assert big.observation_log_prob(o_sw, s, torch.tensor(0)).item() == pytest.approx(expected.item(), abs=1e-3)


# ---------------------------------------------------------------------------------------------
# Linear-Gaussian
# ---------------------------------------------------------------------------------------------


def test_kalman_step_one_dimensional_by_hand():
    f, q, h, r = 0.9, 0.2, 2.0, 0.5
    model = LinearGaussian(
        state_dim=1,
        transition_matrix=[[f]],
        process_cov=[[q]],
        observation_matrix=[[h]],
        observation_cov=[[r]],
        controls=[[0.5], [-0.25]],
    )
    m, p, o = 0.3, 0.7, 1.1
    a = 1
    # predict
    m_pred = f * m - 0.25
    p_pred = f * f * p + q
    # update
    s = h * p_pred * h + r
    k = p_pred * h / s
    m_post = m_pred + k * (o - h * m_pred)
    p_post = (1 - k * h) * p_pred
    mean, cov = model.kalman_step(
        torch.tensor([m]), torch.tensor([[p]]), torch.tensor(a), torch.tensor([o])
    )
    assert mean.dtype == torch.float64 and cov.dtype == torch.float64
    assert mean.shape == (1,) and cov.shape == (1, 1)
    assert mean.item() == pytest.approx(m_post, rel=1e-6)
    assert cov.item() == pytest.approx(p_post, rel=1e-6)
    # numbers, so a consistently wrong formula above cannot hide a wrong implementation
    assert m_post == pytest.approx(0.475729, abs=1e-6)
    assert p_post == pytest.approx(0.107483, abs=1e-6)


def test_kalman_step_matches_bayes_in_information_form():
    """Batched multi-dimensional check against P⁻¹ = P⁻⁻¹ + HᵀR⁻¹H, m = P(P⁻⁻¹m⁻ + HᵀR⁻¹o)."""
    g = gen(15)
    d, m_dim = 3, 2
    a_mat = torch.randn(d, d, generator=g, dtype=torch.float64)
    model = LinearGaussian(
        state_dim=d,
        obs_dim=m_dim,
        transition_matrix=0.5 * a_mat,
        process_cov=0.3 * torch.eye(d) + 0.05,
        observation_matrix=torch.randn(m_dim, d, generator=g),
        observation_cov=torch.tensor([[0.4, 0.1], [0.1, 0.3]]),
    )
    B = 4
    mean = torch.randn(B, d, generator=g, dtype=torch.float64)
    factor = torch.randn(B, d, d, generator=g, dtype=torch.float64)
    cov = factor @ factor.transpose(-1, -2) + 0.1 * torch.eye(d, dtype=torch.float64)
    a = torch.randint(0, model.n_actions, (B,), generator=g)
    o = torch.randn(B, m_dim, generator=g, dtype=torch.float64)
    m_post, p_post = model.kalman_step(mean, cov, a, o)
    F, Q, H, R = (t.double() for t in (model.F, model.Q, model.H, model.R))
    m_pred = mean @ F.T + model.controls.double()[a]
    p_pred = F @ cov @ F.T + Q
    info = torch.linalg.inv(p_pred) + H.T @ torch.linalg.inv(R) @ H
    p_ref = torch.linalg.inv(info)
    m_ref = (p_ref @ (torch.linalg.solve(p_pred, m_pred.unsqueeze(-1))
                      + (H.T @ torch.linalg.inv(R) @ o.unsqueeze(-1)))).squeeze(-1)
    torch.testing.assert_close(p_post, p_ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(m_post, m_ref, rtol=1e-5, atol=1e-5)


def test_linear_gaussian_log_probs_match_torch():
    g = gen(16)
    model = LinearGaussian(state_dim=4)
    s = torch.randn(5, 4, generator=g)
    a = torch.randint(0, 8, (5,), generator=g)
    s2 = model.transition(s, a, g)
    o = model.observe(s2, a, g)
    ref_t = torch.distributions.MultivariateNormal(s @ model.F.T + model.controls[a], model.Q)
    ref_o = torch.distributions.MultivariateNormal(s2 @ model.H.T, model.R)
    torch.testing.assert_close(model.transition_log_prob(s2, s, a), ref_t.log_prob(s2), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(model.observation_log_prob(o, s2, a), ref_o.log_prob(o), rtol=1e-5, atol=1e-5)


def test_linear_gaussian_rejects_non_pd_covariance():
    with pytest.raises(ValueError, match="process_cov"):
        LinearGaussian(state_dim=2, process_cov=torch.tensor([[1.0, 2.0], [2.0, 1.0]]))


def test_linear_gaussian_family_from_config_by_dimension_and_sharpness():
    from escort_rl.config import compose
    from escort_rl.trainers.builders import build_model

    model = build_model(compose(["env=linear_gaussian", "env.model.state_dim=50", "env.model.obs_std=0.1"]).env)
    assert model.state_dim == model.obs_dim == 50 and model.n_actions == 100
    torch.testing.assert_close(model.R, 0.01 * torch.eye(50))
    torch.testing.assert_close(model.Q, 0.1 * torch.eye(50))
    with pytest.raises(ValueError, match=r"^LinearGaussian.obs_std: must be > 0, got 0.0$"):
        LinearGaussian(obs_std=0.0)


def test_linear_gaussian_and_light_dark_1d_own_their_parameters():
    from escort_rl.models import LightDark1D, LightDark1DParams, LinearGaussianParams

    with pytest.raises(ValueError, match=r"^LinearGaussian.state_dim: expected an int, got '2.5'$"):
        LinearGaussian(state_dim=2.5)
    # the scalar family and the matrices together: a given matrix replaces its scalar default
    model = LinearGaussian(LinearGaussianParams(state_dim=3, obs_std=0.2), process_cov=0.5 * torch.eye(3))
    torch.testing.assert_close(model.Q, 0.5 * torch.eye(3))
    torch.testing.assert_close(model.R, 0.04 * torch.eye(3))
    assert model.obs_std == 0.2 and model.n_actions == 6
    with pytest.raises(ValueError, match=r"^LightDark1D.noise_slope: must be >= 0, got -1.0$"):
        LightDark1D(noise_slope=-1.0)
    with pytest.raises(ValueError, match=r"^LightDark1D.start_low: must be < start_high, got 1.0 >= 1.0$"):
        LightDark1D(start_low=1.0, start_high=1.0)
    assert LightDark1D(LightDark1DParams(step_size=2.0)).step_size == 2.0
