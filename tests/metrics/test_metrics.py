"""Tests of the synthetic-benchmark metrics (escort_rl.metrics) against closed forms, scipy
and (when installed) POT."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from escort_rl.bench.targets import load_target
from escort_rl.metrics import (
    correlation_error,
    correlation_matrix,
    mixture_correlation,
    mixture_mean_and_covariance,
    mmd_squared,
    mode_coverage,
    mode_fractions,
    rmse_of_mean,
    sliced_wasserstein,
    sphere_directions,
    wasserstein_1d,
    weighted_mmd_squared,
    weighted_sliced_wasserstein,
    weighted_wasserstein_1d,
)

F64 = torch.float64


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def randn(*shape, seed: int = 0) -> torch.Tensor:
    return torch.randn(*shape, dtype=F64, generator=gen(seed))


# ----------------------------------------------------------------------------- MMD

def _mmd_loops(x, y, gamma, unbiased):
    """MMD² straight from the paper's formula, with Python loops."""
    def k(a, b):
        return math.exp(-gamma * float(((a - b) ** 2).sum()))
    n, m = len(x), len(y)
    sxx = sum(k(x[i], x[j]) for i in range(n) for j in range(n) if not (unbiased and i == j))
    syy = sum(k(y[i], y[j]) for i in range(m) for j in range(m) if not (unbiased and i == j))
    sxy = sum(k(x[i], y[j]) for i in range(n) for j in range(m))
    if unbiased:
        return sxx / (n * (n - 1)) + syy / (m * (m - 1)) - 2 * sxy / (n * m)
    return sxx / n**2 + syy / m**2 - 2 * sxy / (n * m)


def test_mmd_of_identical_samples_is_zero_and_of_shifted_samples_is_not():
    x = randn(50, 3)
    assert abs(float(mmd_squared(x, x))) < 1e-12
    assert abs(float(mmd_squared(x, x[torch.randperm(50, generator=gen(1))]))) < 1e-12
    assert float(mmd_squared(x, x + 1.0)) > 0.1


@pytest.mark.parametrize("gamma", [0.5, 0.1, 2.0])
def test_mmd_of_two_point_masses(gamma):
    a = torch.tensor([[0.3, -1.0, 2.0]], dtype=F64)
    b = torch.tensor([[1.0, 0.5, 1.0]], dtype=F64)
    expected = 2.0 - 2.0 * math.exp(-gamma * float(((a - b) ** 2).sum()))
    assert float(mmd_squared(a, b, gamma=gamma)) == pytest.approx(expected, rel=1e-12, abs=1e-15)


@pytest.mark.parametrize("unbiased", [False, True])
def test_mmd_matches_the_formula_with_loops(unbiased):
    x, y = randn(7, 2, seed=2), randn(11, 2, seed=3) + 0.7
    got = float(mmd_squared(x, y, gamma=0.5, unbiased=unbiased))
    assert got == pytest.approx(_mmd_loops(x, y, 0.5, unbiased), rel=1e-10, abs=1e-14)


def test_mmd_unbiased_averages_to_zero_and_biased_does_not():
    # R independent pairs of size-30 samples from N(0, I₂); batched in one call.
    r, n = 400, 30
    x, y = randn(r, n, 2, seed=4), randn(r, n, 2, seed=5)
    u = mmd_squared(x, y, unbiased=True)
    b = mmd_squared(x, y)
    assert u.shape == (r,)
    se = float(u.std()) / math.sqrt(r)
    assert abs(float(u.mean())) < 4 * se
    # the V-statistic is biased upwards by (1/n + 1/m)(1 − E k(x, x')) > 0
    assert float(b.mean()) > float(u.mean()) + 4 * se
    assert bool((b >= -1e-12).all())


def test_mmd_batched_equals_one_by_one():
    x, y = randn(4, 9, 3, seed=6), randn(4, 12, 3, seed=7)
    batched = mmd_squared(x, y)
    single = torch.stack([mmd_squared(x[i], y[i]) for i in range(4)])
    assert torch.allclose(batched, single, atol=1e-14)


def test_mmd_accepts_one_dimensional_samples():
    x, y = randn(20, seed=8), randn(25, seed=9)
    assert float(mmd_squared(x, y)) == pytest.approx(float(mmd_squared(x[:, None], y[:, None])), abs=1e-14)


_SAMPLES = arrays(np.float64, st.tuples(st.integers(1, 8), st.integers(1, 3)),
                  elements=st.floats(-5, 5, allow_nan=False, width=64))


@settings(max_examples=40, deadline=None)
@given(x=_SAMPLES, data=st.data())
def test_mmd_is_symmetric_and_permutation_invariant(x, data):
    m = data.draw(st.integers(1, 8))
    y = data.draw(arrays(np.float64, (m, x.shape[1]), elements=st.floats(-5, 5, allow_nan=False, width=64)))
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)
    v = float(mmd_squared(xt, yt))
    assert v == pytest.approx(float(mmd_squared(yt, xt)), abs=1e-12)
    px = data.draw(st.permutations(range(x.shape[0])))
    py = data.draw(st.permutations(range(m)))
    assert v == pytest.approx(float(mmd_squared(xt[list(px)], yt[list(py)])), abs=1e-12)
    assert v >= -1e-12


def test_mmd_input_errors_name_the_argument():
    with pytest.raises(ValueError, match="^y:"):
        mmd_squared(randn(5, 2), randn(5, 3))
    with pytest.raises(ValueError, match="^x:"):
        mmd_squared(torch.full((3, 2), float("nan")), randn(3, 2))
    with pytest.raises(ValueError, match="^x:"):
        mmd_squared(randn(1, 2), randn(5, 2), unbiased=True)
    with pytest.raises(ValueError, match="^gamma:"):
        mmd_squared(randn(3, 2), randn(3, 2), gamma=0.0)


# ----------------------------------------------------------------------------- Wasserstein

@pytest.mark.parametrize("n,m,seed", [(1, 1, 0), (5, 3, 1), (37, 53, 2), (100, 100, 3), (64, 7, 4)])
def test_wasserstein_1d_equals_scipy(n, m, seed):
    x = randn(n, seed=seed)
    y = 2.0 * randn(m, seed=seed + 100) + 0.5
    expected = scipy.stats.wasserstein_distance(x.numpy(), y.numpy())
    assert float(wasserstein_1d(x, y)) == pytest.approx(expected, rel=1e-10, abs=1e-12)


def test_wasserstein_1d_with_ties_equals_scipy():
    x = torch.tensor([0.0, 0.0, 1.0, 1.0, 1.0, 3.0], dtype=F64)
    y = torch.tensor([1.0, 1.0, 2.0, 0.0], dtype=F64)
    assert float(wasserstein_1d(x, y)) == pytest.approx(scipy.stats.wasserstein_distance(x.numpy(), y.numpy()),
                                                        abs=1e-12)


def test_wasserstein_1d_equal_sizes_is_mean_abs_sorted_difference():
    x, y = randn(40, seed=5), randn(40, seed=6) * 3
    expected = (x.sort().values - y.sort().values).abs().mean()
    assert float(wasserstein_1d(x, y)) == pytest.approx(float(expected), rel=1e-12)


@pytest.mark.parametrize("shift", [0.0, 0.5, -2.0, 3.0])
def test_wasserstein_1d_between_shifted_normals_is_the_shift(shift):
    # E W1 between two size-n samples of the same law is O(n^{-1/2}) (≈ 0.01 here): tolerance 0.05.
    n = 20000
    x, y = randn(n, seed=10), randn(n, seed=11) + shift
    assert float(wasserstein_1d(x, y)) == pytest.approx(abs(shift), abs=0.05)


_VEC = arrays(np.float64, st.integers(1, 12), elements=st.floats(-10, 10, allow_nan=False, width=64))


@settings(max_examples=50, deadline=None)
@given(x=_VEC, y=_VEC, c=st.floats(-100, 100, allow_nan=False))
def test_wasserstein_1d_is_translation_equivariant(x, y, c):
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)
    w = float(wasserstein_1d(xt, yt))
    assert float(wasserstein_1d(xt + c, yt + c)) == pytest.approx(w, abs=1e-9)
    # shifting one side only moves the distance by exactly |c| when y is x itself
    assert float(wasserstein_1d(xt, xt + c)) == pytest.approx(abs(c), rel=1e-9, abs=1e-9)
    assert float(wasserstein_1d(yt, xt)) == pytest.approx(w, abs=1e-12)


def test_wasserstein_1d_is_differentiable():
    x = randn(10, seed=12).requires_grad_(True)
    y = randn(15, seed=13) + 1.0
    wasserstein_1d(x, y).backward()
    assert x.grad is not None and bool(torch.isfinite(x.grad).all()) and float(x.grad.abs().sum()) > 0


def test_wasserstein_1d_input_errors_name_the_argument():
    with pytest.raises(ValueError, match="^x:"):
        wasserstein_1d(randn(5, 2), randn(5))
    with pytest.raises(ValueError, match="^y:"):
        wasserstein_1d(randn(5), torch.empty(0, dtype=F64))


def test_sphere_directions_are_unit_and_seeded():
    a = sphere_directions(50, 4, gen(3))
    assert a.shape == (50, 4)
    assert torch.allclose(a.norm(dim=1), torch.ones(50, dtype=F64), atol=1e-12)
    assert torch.equal(a, sphere_directions(50, 4, gen(3)))
    assert not torch.equal(a, sphere_directions(50, 4, gen(4)))


def test_sliced_wasserstein_equals_averaged_scipy_per_projection():
    x, y = randn(30, 3, seed=14), randn(45, 3, seed=15) + torch.tensor([1.0, 0.0, -0.5], dtype=F64)
    theta = sphere_directions(25, 3, gen(16))
    by_hand = np.mean([scipy.stats.wasserstein_distance((x @ t).numpy(), (y @ t).numpy()) for t in theta])
    assert float(sliced_wasserstein(x, y, projections=theta)) == pytest.approx(by_hand, rel=1e-10)
    # default directions: num_projections drawn from the generator, same as passing them
    assert float(sliced_wasserstein(x, y, num_projections=25, generator=gen(16))) == pytest.approx(by_hand, rel=1e-10)


def test_sliced_wasserstein_p2_is_root_mean_of_squared_w2():
    x, y = randn(40, 2, seed=17), randn(40, 2, seed=18) * 2
    theta = sphere_directions(10, 2, gen(19))
    w2sq = [float(((x @ t).sort().values - (y @ t).sort().values).pow(2).mean()) for t in theta]
    expected = math.sqrt(np.mean(w2sq))
    assert float(sliced_wasserstein(x, y, projections=theta, p=2)) == pytest.approx(expected, rel=1e-10)


def test_sliced_wasserstein_in_1d_is_w1():
    x, y = randn(33, 1, seed=20), randn(21, 1, seed=21) + 2
    assert float(sliced_wasserstein(x, y, num_projections=7)) == pytest.approx(float(wasserstein_1d(x, y)), rel=1e-12)


def test_sliced_wasserstein_default_is_seeded():
    x, y = randn(30, 5, seed=22), randn(30, 5, seed=23) + 0.3
    a = sliced_wasserstein(x, y, num_projections=8)
    assert float(a) == float(sliced_wasserstein(x, y, num_projections=8))
    assert float(a) != float(sliced_wasserstein(x, y, num_projections=8, generator=gen(99)))


@pytest.mark.parametrize("p", [1, 2])
def test_sliced_wasserstein_equals_pot(p):
    ot = pytest.importorskip("ot")
    x, y = randn(40, 4, seed=24), randn(55, 4, seed=25) * 1.5 + 0.5
    theta = sphere_directions(30, 4, gen(26))
    expected = ot.sliced_wasserstein_distance(x.numpy(), y.numpy(), projections=theta.T.numpy(), p=p)
    assert float(sliced_wasserstein(x, y, projections=theta, p=p)) == pytest.approx(float(expected), rel=1e-9)


def test_sliced_wasserstein_input_errors_name_the_argument():
    with pytest.raises(ValueError, match="^projections:"):
        sliced_wasserstein(randn(5, 3), randn(5, 3), projections=randn(4, 2))
    with pytest.raises(ValueError, match="^p:"):
        sliced_wasserstein(randn(5, 3), randn(5, 3), p=3)
    with pytest.raises(ValueError, match="^num_projections:"):
        sliced_wasserstein(randn(5, 3), randn(5, 3), num_projections=0)


# ----------------------------------------------------------------------------- mode coverage

def _cloud(center, count, radius, seed):
    """``count`` points at distance < radius of ``center`` (2-D)."""
    g = gen(seed)
    ang = torch.rand(count, generator=g, dtype=F64) * 2 * math.pi
    r = torch.rand(count, generator=g, dtype=F64) * radius
    return torch.tensor(center, dtype=F64) + torch.stack([r * ang.cos(), r * ang.sin()], 1)


def test_mode_coverage_on_hand_made_particles():
    means = torch.tensor([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0], [10.0, 10.0]], dtype=F64)
    # threshold 0.05 / 4 = 1.25%: 50% and 49% are covered, 1% is not, 0% is not
    x = torch.cat([_cloud([0, 0], 50, 0.9, 1), _cloud([5, 0], 49, 0.9, 2), _cloud([0, 5], 1, 0.9, 3)])
    assert torch.allclose(mode_fractions(x, means), torch.tensor([0.5, 0.49, 0.01, 0.0], dtype=F64))
    assert float(mode_coverage(x, means)) == 0.5
    # a smaller radius leaves some of those particles out; a lower threshold admits mode 3
    assert float(mode_coverage(x, means, threshold=0.005)) == 0.75
    assert float(mode_coverage(x, means, tau=1e-9)) == 0.0


def test_mode_coverage_threshold_is_strict_and_distance_is_strict():
    mean = torch.zeros(1, 3, dtype=F64)
    far = torch.full((95, 3), 10.0, dtype=F64)
    five = torch.cat([torch.zeros(5, 3, dtype=F64), far])  # exactly 5% = 0.05 / K with K = 1
    six = torch.cat([torch.zeros(6, 3, dtype=F64), far[:94]])
    assert float(mode_coverage(five, mean)) == 0.0
    assert float(mode_coverage(six, mean)) == 1.0
    on_sphere = torch.cat([torch.tensor([[1.0, 0.0, 0.0]], dtype=F64).expand(10, 3), far[:90]])
    assert float(mode_fractions(on_sphere, mean)[0]) == 0.0  # ‖x − μ‖ = τ is outside


def test_mode_coverage_weights_and_batch():
    means = torch.tensor([[0.0, 0.0], [5.0, 0.0]], dtype=F64)
    x = torch.cat([_cloud([0, 0], 10, 0.5, 4), _cloud([5, 0], 10, 0.5, 5)])
    w = torch.cat([torch.ones(10), torch.zeros(10)]).to(F64)
    assert float(mode_coverage(x, means)) == 1.0
    assert float(mode_coverage(x, means, weights=w)) == 0.5
    batch = torch.stack([x, x[:10].repeat(2, 1)])
    assert mode_coverage(batch, means).tolist() == [1.0, 0.5]


def test_mode_coverage_input_errors_name_the_argument():
    with pytest.raises(ValueError, match="^means:"):
        mode_coverage(randn(10, 2), randn(3, 3))
    with pytest.raises(ValueError, match="^weights:"):
        mode_coverage(randn(10, 2), randn(3, 2), weights=-torch.ones(10))
    with pytest.raises(ValueError, match="^tau:"):
        mode_coverage(randn(10, 2), randn(3, 2), tau=-1.0)


# ----------------------------------------------------------------------------- correlations

def _samples_with_exact_correlation(c: torch.Tensor, n: int, seed: int) -> torch.Tensor:
    """n points whose sample covariance (1/n normalisation) is exactly c."""
    z = randn(n, c.shape[0], seed=seed)
    z = z - z.mean(0)
    s = z.T @ z / n
    z = z @ torch.linalg.inv(torch.linalg.cholesky(s)).T
    return z @ torch.linalg.cholesky(c).T + 3.0


def test_correlation_matrix_equals_numpy():
    x = randn(200, 4, seed=30) @ randn(4, 4, seed=31)
    assert torch.allclose(correlation_matrix(x), torch.from_numpy(np.corrcoef(x.numpy().T)), atol=1e-12)


def test_weighted_correlation_equals_duplicated_rows():
    x = randn(30, 3, seed=32) @ randn(3, 3, seed=33)
    counts = torch.randint(1, 4, (30,), generator=gen(34))
    dup = x.repeat_interleave(counts, dim=0)
    assert torch.allclose(correlation_matrix(x, weights=counts.to(F64)), correlation_matrix(dup), atol=1e-12)


def test_correlation_error_is_zero_for_the_exact_correlation_and_positive_otherwise():
    c = torch.tensor([[1.0, 0.6, -0.3], [0.6, 1.0, 0.2], [-0.3, 0.2, 1.0]], dtype=F64)
    x = _samples_with_exact_correlation(c, 500, seed=35)
    assert float(correlation_error(c, x)) < 1e-10
    c2 = c.clone()
    c2[0, 1] = c2[1, 0] = 0.4
    assert float(correlation_error(c2, x)) == pytest.approx(math.sqrt(2) * 0.2, rel=1e-8)
    assert float(correlation_error(torch.eye(3, dtype=F64), x)) == pytest.approx(
        math.sqrt(2 * (0.36 + 0.09 + 0.04)), rel=1e-8)


def test_correlation_of_a_constant_dimension_is_zero_not_nan():
    x = torch.cat([randn(50, 2, seed=36), torch.full((50, 1), 2.0, dtype=F64)], dim=1)
    c = correlation_matrix(x)
    assert bool(torch.isfinite(c).all())
    assert c[2].tolist() == [0.0, 0.0, 1.0]


def test_correlation_error_input_errors_name_the_argument():
    with pytest.raises(ValueError, match="^c_true:"):
        correlation_error(torch.eye(3), randn(10, 2))


def test_mixture_moments_closed_form_small_case():
    # two point-like components ±1 in 1-D with equal weights: mean 0, variance 1 + σ²
    w = torch.tensor([0.5, 0.5], dtype=F64)
    mu = torch.tensor([[-1.0], [1.0]], dtype=F64)
    cov = torch.full((2, 1, 1), 0.25, dtype=F64)
    mean, var = mixture_mean_and_covariance(w, mu, cov)
    assert mean.tolist() == [0.0] and var.tolist() == [[1.25]]
    # the paper's form Σ_k w_k (Σ_k + μ_k μ_kᵀ) − μ μᵀ on a random mixture
    g = gen(37)
    w = torch.rand(4, generator=g, dtype=F64)
    w = w / w.sum()
    mu = randn(4, 3, seed=38)
    a = randn(4, 3, 3, seed=39)
    cov = a @ a.transpose(1, 2) + 0.1 * torch.eye(3, dtype=F64)
    mean, total = mixture_mean_and_covariance(w, mu, cov)
    paper = torch.einsum("k,kij->ij", w, cov + mu[:, :, None] * mu[:, None, :]) - torch.outer(mean, mean)
    assert torch.allclose(total, paper, atol=1e-12)
    c = mixture_correlation(w, mu, cov)
    assert torch.allclose(torch.diagonal(c), torch.ones(3, dtype=F64))


@pytest.mark.parametrize("name,n", [("gmm2d", 200_000), ("gmm5d", 200_000), ("gmm20d", 100_000)])
def test_mixture_moments_match_monte_carlo(name, n):
    # Tolerance: 5 standard errors of each Monte-Carlo estimate, the standard errors estimated from
    # the same samples (sd of x_a / √n for the mean, sd of (x_a − μ_a)(x_b − μ_b) / √n for the
    # covariance). With ≤ 420 checked entries per target, a false failure has probability < 1e-3.
    t = load_target(name)
    x = t.sample(n, gen(40))
    mean, cov = t.mean(), t.covariance()
    se_mean = x.std(0) / math.sqrt(n)
    assert bool(((x.mean(0) - mean).abs() < 5 * se_mean).all())
    xc = x - mean
    prod = xc[:, :, None] * xc[:, None, :]
    se_cov = prod.std(0) / math.sqrt(n)
    assert bool(((prod.mean(0) - cov).abs() < 5 * se_cov + 1e-12).all())
    # and the analytic mixture correlation is the one the target reports
    assert torch.allclose(t.correlation(), mixture_correlation(t.weights, t.means, t.covariances))


def test_mixture_weights_must_sum_to_one():
    with pytest.raises(ValueError, match="^weights:"):
        mixture_mean_and_covariance(torch.tensor([0.5, 0.6]), torch.zeros(2, 1), torch.ones(2, 1, 1))
    with pytest.raises(ValueError, match="^covs:"):
        mixture_mean_and_covariance(torch.tensor([0.5, 0.5]), torch.zeros(2, 1), torch.ones(2, 2, 2))


# ----------------------------------------------------------------------------- RMSE

def test_rmse_of_mean_definition():
    x = torch.tensor([[1.0, 2.0, 3.0, 4.0], [3.0, 2.0, 1.0, 0.0]], dtype=F64)  # mean [2, 2, 2, 2]
    mu = torch.tensor([2.0, 0.0, 2.0, 4.0], dtype=F64)
    # error [0, 2, 0, -2]: ‖·‖₂ = √8, per coordinate √(8/4) = √2
    assert float(rmse_of_mean(x, mu)) == pytest.approx(math.sqrt(2.0))
    assert float(rmse_of_mean(x, mu, per_coordinate=False)) == pytest.approx(math.sqrt(8.0))
    assert float(rmse_of_mean(x, torch.full((4,), 2.0, dtype=F64))) == 0.0
    w = torch.tensor([1.0, 0.0], dtype=F64)  # mean = first row
    assert float(rmse_of_mean(x, x[0], weights=w)) == 0.0
    batch = torch.stack([x, x + 1.0])
    assert torch.allclose(rmse_of_mean(batch, torch.full((4,), 2.0, dtype=F64)), torch.tensor([0.0, 1.0], dtype=F64))


def test_rmse_input_errors_name_the_argument():
    with pytest.raises(ValueError, match="^true_mean:"):
        rmse_of_mean(randn(10, 3), torch.zeros(2))
    with pytest.raises(ValueError, match="^x:"):
        rmse_of_mean(torch.zeros(2, 3, dtype=F64) * float("inf"), torch.zeros(3))


# ----------------------------------------------------------------------------- weighted, batched

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_weighted_wasserstein_1d_equals_scipy(seed):
    g = torch.Generator().manual_seed(seed)
    u, v = torch.randn(4, 9, generator=g, dtype=torch.float64), torch.randn(4, 6, generator=g, dtype=torch.float64)
    wu, wv = torch.rand(4, 9, generator=g, dtype=torch.float64), torch.rand(4, 6, generator=g, dtype=torch.float64)
    wu[0, :3] = 0.0  # zero weights are allowed
    got = weighted_wasserstein_1d(u, v, wu, wv)
    want = [scipy.stats.wasserstein_distance(u[i], v[i], wu[i], wv[i]) for i in range(4)]
    assert torch.allclose(got, torch.tensor(want, dtype=torch.float64), atol=1e-12)


def test_weighted_wasserstein_1d_uniform_is_the_unweighted_one():
    g = torch.Generator().manual_seed(3)
    u, v = torch.randn(11, generator=g, dtype=torch.float64), torch.randn(5, generator=g, dtype=torch.float64)
    assert math.isclose(float(weighted_wasserstein_1d(u, v)), float(wasserstein_1d(u, v)), rel_tol=1e-12)


def test_weighted_sliced_wasserstein_uniform_is_sliced_wasserstein_per_batch():
    g = torch.Generator().manual_seed(4)
    x = torch.randn(3, 20, 4, generator=g, dtype=torch.float64)
    y = torch.randn(3, 30, 4, generator=g, dtype=torch.float64)
    theta = sphere_directions(10, 4)
    got = weighted_sliced_wasserstein(x, y, theta)
    want = torch.stack([sliced_wasserstein(x[i], y[i], projections=theta) for i in range(3)])
    assert torch.allclose(got, want, atol=1e-12)


def test_integer_weights_are_repeated_samples():
    """Weights (2, 1, 3) on x equal x's rows repeated 2, 1 and 3 times, for W1 and MMD²."""
    g = torch.Generator().manual_seed(5)
    x, y = torch.randn(3, 2, generator=g, dtype=torch.float64), torch.randn(4, 2, generator=g, dtype=torch.float64)
    w = torch.tensor([2.0, 1.0, 3.0], dtype=torch.float64)
    repeated = x.repeat_interleave(torch.tensor([2, 1, 3]), dim=0)
    theta = sphere_directions(7, 2)
    assert math.isclose(float(weighted_sliced_wasserstein(x, y, theta, w)),
                        float(sliced_wasserstein(repeated, y, projections=theta)), rel_tol=1e-12)
    assert math.isclose(float(weighted_mmd_squared(x, y, 0.5, w)), float(mmd_squared(repeated, y)), rel_tol=1e-12)


def test_weighted_mmd_takes_one_bandwidth_per_batch_element():
    g = torch.Generator().manual_seed(6)
    x = torch.randn(2, 8, 3, generator=g, dtype=torch.float64)
    y = torch.randn(2, 5, 3, generator=g, dtype=torch.float64)
    gamma = torch.tensor([0.5, 2.0], dtype=torch.float64)
    got = weighted_mmd_squared(x, y, gamma)
    want = torch.stack([mmd_squared(x[i], y[i], gamma=float(gamma[i])) for i in range(2)])
    assert torch.allclose(got, want, atol=1e-12)


def test_weighted_metrics_errors_name_the_argument():
    x, y = torch.randn(2, 5), torch.randn(2, 4)
    with pytest.raises(ValueError, match="u_weights: weights must be non-negative"):
        weighted_wasserstein_1d(x, y, -torch.ones(2, 5))
    with pytest.raises(ValueError, match="v_weights: expected shape"):
        weighted_wasserstein_1d(x, y, None, torch.ones(3))
    with pytest.raises(ValueError, match="projections: expected"):
        weighted_sliced_wasserstein(x[..., None], y[..., None], torch.ones(3, 2))
    with pytest.raises(ValueError, match="gamma"):
        weighted_mmd_squared(x[..., None], y[..., None], 0.0)


# ----------------------------------------------------------------------------- Mahalanobis coverage

def test_chi2_quantile_matches_closed_form_and_scipy():
    from escort_rl.metrics import chi2_quantile

    assert chi2_quantile(2, 0.99) == pytest.approx(-2 * math.log(0.01), rel=1e-9)
    for df in (1, 5, 20, 200):
        assert chi2_quantile(df, 0.99) == pytest.approx(float(scipy.stats.chi2.ppf(0.99, df)), rel=1e-8)
    with pytest.raises(ValueError, match="level"):
        chi2_quantile(3, 1.0)


@pytest.mark.parametrize("dim", [1, 5, 20, 50, 200])
def test_exact_samples_cover_every_mode_at_every_dimension(dim, per_test_generator):
    """The paper's τ = 1 ball misses the modes of exact samples from 20D; the Mahalanobis form does not."""
    from escort_rl.bench.targets import scalability_target
    from escort_rl.metrics import mode_coverage_mahalanobis

    t = scalability_target(dim, "block", 0)
    x = t.sample(1000, per_test_generator)
    assert float(mode_coverage_mahalanobis(x, t.means, t.covariances)) >= 0.95
    if dim >= 20:
        assert float(mode_coverage(x, t.means)) == 0.0  # the ball's degeneracy this replaces


def test_mahalanobis_coverage_of_one_mode_is_one_over_k(per_test_generator):
    from escort_rl.bench.targets import scalability_target
    from escort_rl.metrics import mode_coverage_mahalanobis, mode_fractions_mahalanobis

    t = scalability_target(20, "banded", 0)
    z = torch.randn(500, 20, generator=per_test_generator, dtype=torch.float64)
    x = t.means[2] + z @ t.scale_tril[2].T  # every particle from component 2
    f = mode_fractions_mahalanobis(x, t.means, t.covariances)
    assert float(f[2]) > 0.95 and float(f.sum() - f[2]) == 0.0
    assert float(mode_coverage_mahalanobis(x, t.means, t.covariances)) == pytest.approx(1 / 5)
    batched = mode_coverage_mahalanobis(torch.stack([x, x]), t.means, t.covariances)
    assert batched.shape == (2,)
