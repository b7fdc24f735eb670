"""Tests of the synthetic GMM targets (escort_rl.bench.targets, configs/bench/synthetic.yaml):
the paper's numbers, positive definiteness, densities, sampling, gradients, scalability targets."""

from __future__ import annotations

import math

import pytest
import scipy.stats
import torch
from torch.distributions import Categorical, MixtureSameFamily, MultivariateNormal

from escort_rl.bench.targets import (
    SCALABILITY_DIMS,
    SCALABILITY_STRUCTURES,
    TARGET_NAMES,
    GaussianMixture,
    initial_distribution,
    load_target,
    scalability_initial,
    scalability_target,
    synthetic_config,
)
from escort_rl.config import config_dir
from escort_rl.metrics.modes import mode_coverage

F64 = torch.float64
# (dimension, number of modes) as the paper's appendix states them
PAPER_SHAPES = {"gmm1d": (1, 3), "gmm2d": (2, 3), "gmm3d": (3, 6), "gmm5d": (5, 8), "gmm20d": (20, 10)}


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def t64(x) -> torch.Tensor:
    return torch.tensor(x, dtype=F64)


@pytest.fixture(scope="module")
def targets() -> dict[str, GaussianMixture]:
    return {name: load_target(name) for name in TARGET_NAMES}


@pytest.fixture(scope="module")
def scal_targets() -> dict[tuple[int, str], GaussianMixture]:
    return {(d, s): scalability_target(d, s, 0) for d in SCALABILITY_DIMS for s in SCALABILITY_STRUCTURES}


def _is_pd(cov: torch.Tensor) -> bool:
    return bool(torch.allclose(cov, cov.transpose(-1, -2), atol=0) and (torch.linalg.eigvalsh(cov) > 0).all())


# ----------------------------------------------------------------------------- building

def test_config_lives_in_the_package_config_folder():
    assert (config_dir() / "bench" / "synthetic.yaml").is_file()
    cfg = synthetic_config()
    assert set(TARGET_NAMES) <= set(cfg["targets"]) and set(TARGET_NAMES) <= set(cfg["initial"])


@pytest.mark.parametrize("name", TARGET_NAMES)
def test_named_target_builds_with_the_paper_shape_and_is_pd(targets, name):
    t = targets[name]
    d, k = PAPER_SHAPES[name]
    assert (t.dim, t.num_components) == (d, k)
    assert t.means.shape == (k, d) and t.covariances.shape == (k, d, d) and t.weights.shape == (k,)
    assert _is_pd(t.covariances)
    assert float(t.weights.sum()) == pytest.approx(1.0, abs=1e-12)
    assert bool((t.weights > 0).all())


def test_gmm1d_is_the_papers(targets):
    t = targets["gmm1d"]
    assert t.weights.tolist() == [0.3, 0.4, 0.3]
    assert t.means[:, 0].tolist() == [-3.0, 0.0, 3.0]
    assert t.covariances[:, 0, 0].tolist() == [0.8, 0.5, 0.5]


def test_gmm2d_is_the_papers(targets):
    t = targets["gmm2d"]
    assert t.weights.tolist() == [0.35, 0.30, 0.35]
    assert t.means.tolist() == [[-2.0, -2.0], [0.0, 0.0], [2.0, 2.0]]
    assert t.covariances.tolist() == [[[1.0, 0.8], [0.8, 1.0]], [[0.5, 0.0], [0.0, 0.5]], [[1.0, -0.8], [-0.8, 1.0]]]


def test_gmm3d_matches_the_papers_numbers_and_text(targets):
    t = targets["gmm3d"]
    assert t.weights.tolist() == [0.2, 0.15, 0.15, 0.2, 0.15, 0.15]
    assert t.means.tolist() == [[-2.5, -2.5, -2.5], [2.5, -2.5, 2.5], [-2.5, 2.5, 2.5], [2.5, 2.5, -2.5],
                                [0.0, 0.0, 4.0], [0.0, 0.0, -4.0]]
    r = t.component_correlations()
    # modes 1-3: extreme planar correlation 0.95, the third axis the one with minimal variance
    for k, (a, b, other) in enumerate([(0, 1, 2), (0, 2, 1), (1, 2, 0)]):
        assert float(r[k, a, b]) == pytest.approx(0.95)
        var = torch.diagonal(t.covariances[k])
        assert float(var[other]) < 0.5 * float(var[[a, b]].min())
    assert t.covariances[3].tolist() == [[1.0, 0.7, -0.7], [0.7, 1.0, -0.7], [-0.7, -0.7, 1.0]]
    # mode 5: correlation strength decreases with dimensional distance
    assert abs(float(r[4, 0, 2])) < min(abs(float(r[4, 0, 1])), abs(float(r[4, 1, 2])))
    assert torch.diagonal(t.covariances[5]).tolist() == [0.2, 0.2, 4.0]


def test_gmm5d_matches_the_papers_numbers_and_text(targets):
    t = targets["gmm5d"]
    assert t.weights.tolist() == [0.15, 0.15, 0.10, 0.15, 0.10, 0.10, 0.10, 0.15]
    assert t.means.tolist() == [[-2, -2, -2, -2, -2], [2, -2, 2, -2, 2], [-2, 2, 2, 2, -2], [2, 2, -2, 2, 2],
                                [0, 0, 3, 0, 0], [0, 0, 0, 0, 3], [0, 3, 0, 3, 0], [-3, -3, -3, 3, 3]]
    r = t.component_correlations()
    assert float(r[0, 0, 1]) == pytest.approx(0.85)                                   # mode 1: x1-x2
    assert float(r[1, 0, 2]) == pytest.approx(0.8) and float(r[1, 2, 4]) == pytest.approx(0.8)  # mode 2
    assert float(r[2, 0, 4]) == pytest.approx(0.85)                                   # mode 3: x1-x5
    assert float(r[3, 0, 2]) == pytest.approx(-0.7) and float(r[3, 2, 4]) == pytest.approx(-0.7)  # mode 4
    var = torch.diagonal(t.covariances, dim1=-2, dim2=-1)
    assert float(var[5, 4]) > float(var[5, :4].max())                                # mode 6: x5 extended
    assert float(r[5, :4, 4].abs().max()) < 0.3                                       # ... weakly linked
    assert float(var[6, 1]) > float(var[6, 0]) and float(var[6, 3]) > float(var[6, 0])  # mode 7
    assert float(r[7, 0, 3:].abs().max()) == 0.0 and float(r[7, 3, 4]) > 0.5         # mode 8: split blocks


def test_gmm20d_matches_the_papers_numbers_and_text(targets):
    t = targets["gmm20d"]
    assert t.weights.tolist() == [0.12, 0.12, 0.10, 0.08, 0.08, 0.08, 0.08, 0.12, 0.12, 0.10]
    mu, r = t.means, t.component_correlations()
    assert bool((mu[0, :10] < 0).all() and (mu[0, 10:] > 0).all())                   # μ1 split
    assert bool((mu[1, 0::2] > 0).all() and (mu[1, 1::2] < 0).all())                 # μ2 alternates
    assert torch.allclose(mu[2], torch.linspace(-3, 3, 20, dtype=F64))                 # μ3 gradient
    for k in range(4):                                                                 # μ4..μ7 5-D subspaces
        block = slice(5 * k, 5 * k + 5)
        assert bool((mu[3 + k, block] != 0).all()) and int((mu[3 + k] != 0).sum()) == 5
        sub = r[3 + k, block, block]
        assert torch.allclose(sub[~torch.eye(5, dtype=torch.bool)], torch.full((20,), 0.85, dtype=F64))
        assert int((r[3 + k] != 0).sum()) == 25 + 15
    assert bool((mu[9] < 0).all()) and bool((mu[9] == mu[9, 0]).all())               # μ10 uniform negative
    i = torch.arange(20)
    lag = (i[:, None] - i[None, :]).abs()
    # mode 1: four 5×5 blocks with ±0.7
    same = (i[:, None] // 5) == (i[None, :] // 5)
    off = ~torch.eye(20, dtype=torch.bool)
    assert torch.allclose(r[0][same & off].abs(), torch.full(((same & off).sum().item(),), 0.7, dtype=F64))
    assert (r[0][same & off] > 0).any() and (r[0][same & off] < 0).any() and (r[0][~same] == 0).all()
    # mode 2: ±0.75 checkerboard between odd and even dimensions
    parity = (i[:, None] % 2) == (i[None, :] % 2)
    assert torch.allclose(r[1][parity & off], torch.full(((parity & off).sum().item(),), 0.75, dtype=F64))
    assert torch.allclose(r[1][~parity], torch.full(((~parity).sum().item(),), -0.75, dtype=F64))
    # mode 3: 0.9^|i-j| within 5 steps
    band = lag <= 5
    assert torch.allclose(r[2][band], 0.9 ** lag[band].to(F64))
    # mode 8: 0.7 inside 5-D groups, 0.3 across
    assert torch.allclose(r[7][same & off], torch.full(((same & off).sum().item(),), 0.7, dtype=F64))
    assert torch.allclose(r[7][~same], torch.full(((~same).sum().item(),), 0.3, dtype=F64))
    # mode 9: ρ(x_i, x_{19-i}) = +0.7 for even i, −0.7 for odd i
    for a in range(10):
        assert float(r[8, a, 19 - a]) == pytest.approx(0.7 if a % 2 == 0 else -0.7)
    assert int((r[8] != 0).sum()) == 20 + 20
    # mode 10: sparse, weak
    off10 = r[9][off]
    assert 0 < int((off10 != 0).sum()) < 0.1 * off10.numel() and float(off10.abs().max()) < 0.1


@pytest.mark.parametrize("name", TARGET_NAMES)
def test_the_oracle_covers_every_mode_with_margin(targets, name):
    # The design rule of synthetic.yaml: w_k · P(‖x − μ_k‖ < 1 | k) ≥ 3 · 0.05 / K for every mode,
    # so that N = 1000 exact samples (the oracle row) reach mode coverage 1.0.
    t = targets[name]
    k = t.num_components
    g = gen(50)
    for j in range(k):
        z = torch.randn(4000, t.dim, dtype=F64, generator=g)
        x = t.means[j] + z @ t.scale_tril[j].T
        p_in = float(((x - t.means[j]).norm(dim=1) < 1.0).to(F64).mean())
        assert float(t.weights[j]) * p_in >= 3 * 0.05 / k, f"mode {j + 1}"
    assert float(mode_coverage(t.sample(1000, gen(51)), t.means)) == 1.0


@pytest.mark.parametrize("name", TARGET_NAMES)
def test_initial_distribution_is_broad_and_covers_the_modes(targets, name):
    t, init = targets[name], initial_distribution(name)
    assert (init.dim, init.num_components) == (t.dim, 1)
    std = float(init.covariances[0, 0, 0]).__pow__(0.5)
    assert torch.allclose(init.covariances[0], std**2 * torch.eye(t.dim, dtype=F64))
    assert float((t.means - init.means[0]).abs().max()) <= 1.5 * std
    assert std >= float(torch.linalg.eigvalsh(t.covariances).max()) ** 0.5


# ----------------------------------------------------------------------------- density

def _reference(t: GaussianMixture) -> MixtureSameFamily:
    return MixtureSameFamily(Categorical(probs=t.weights), MultivariateNormal(t.means, covariance_matrix=t.covariances))


def _some_targets(targets):
    return list(targets.values()) + [scalability_target(50, "sparse", 3), scalability_target(20, "banded", 1)]


def test_log_prob_matches_torch_mixture_same_family(targets):
    for t in _some_targets(targets):
        ref = _reference(t)
        g = gen(60)
        x = torch.cat([t.sample(200, g), 4.0 * torch.randn(200, t.dim, dtype=F64, generator=g)])
        assert torch.allclose(t.log_prob(x), ref.log_prob(x), rtol=1e-10, atol=1e-9), t
        # batch shapes [..., d] and float32 input
        xb = x.reshape(4, 100, t.dim)
        assert t.log_prob(xb).shape == (4, 100)
        assert torch.allclose(t.log_prob(x.float()).double(), ref.log_prob(x), rtol=1e-4, atol=1e-3)


def test_gradients_are_finite_and_match_the_analytic_score(targets):
    for t in _some_targets(targets):
        g = gen(61)
        x = torch.cat([t.sample(50, g), 50.0 * torch.randn(20, t.dim, dtype=F64, generator=g)])
        x.requires_grad_(True)
        (grad,) = torch.autograd.grad(t.log_prob(x).sum(), x)
        assert bool(torch.isfinite(grad).all()), t
        assert torch.allclose(t.score(x.detach()), grad, rtol=1e-8, atol=1e-8), t
        xf = x.detach().float().requires_grad_(True)
        (gf,) = torch.autograd.grad(t.log_prob(xf).sum(), xf)
        assert bool(torch.isfinite(gf).all())


def test_log_prob_rejects_the_wrong_dimension(targets):
    with pytest.raises(ValueError, match="^x:"):
        targets["gmm2d"].log_prob(torch.zeros(5, 3))


# ----------------------------------------------------------------------------- sampling

@pytest.mark.parametrize("name", TARGET_NAMES)
def test_sampling_reproduces_the_mixture_weights(targets, name):
    # Pearson's χ² test of the component labels against the weights at level 1e-3.
    t = targets[name]
    n = 50_000
    x, labels = t.sample(n, gen(70), return_labels=True)
    counts = torch.bincount(labels, minlength=t.num_components).to(F64)
    expected = n * t.weights
    chi2 = float(((counts - expected) ** 2 / expected).sum())
    assert chi2 < scipy.stats.chi2.ppf(0.999, t.num_components - 1)
    # each component's samples sit at its mean (5 standard errors per coordinate)
    for k in range(t.num_components):
        xs = x[labels == k]
        se = torch.diagonal(t.covariances[k]).sqrt() / math.sqrt(len(xs))
        assert bool(((xs.mean(0) - t.means[k]).abs() < 5 * se).all())


def test_sampling_is_seeded(targets):
    t = targets["gmm5d"]
    assert torch.equal(t.sample(100, gen(1)), t.sample(100, gen(1)))
    assert not torch.equal(t.sample(100, gen(1)), t.sample(100, gen(2)))


def test_a_sampler_with_wrong_weights_fails_the_chi_square_check(targets):
    # the check above can fail: a mixture with the weights reversed does not pass it
    t = targets["gmm5d"]
    wrong = GaussianMixture(t.weights.flip(0), t.means, t.covariances)
    _, labels = wrong.sample(50_000, gen(70), return_labels=True)
    counts = torch.bincount(labels, minlength=8).to(F64)
    expected = 50_000 * t.weights
    assert float(((counts - expected) ** 2 / expected).sum()) > scipy.stats.chi2.ppf(0.999, 7)


# ----------------------------------------------------------------------------- validation

def test_non_symmetric_or_non_pd_covariance_names_the_component():
    w, mu = [0.5, 0.5], torch.zeros(2, 2)
    good = torch.eye(2, dtype=F64)
    with pytest.raises(ValueError, match=r"covariances\[1\].*not symmetric"):
        GaussianMixture(w, mu, torch.stack([good, t64([[1.0, 0.5], [0.2, 1.0]])]))
    with pytest.raises(ValueError, match=r"covariances\[0\].*not positive definite"):
        GaussianMixture(w, mu, torch.stack([t64([[1.0, 2.0], [2.0, 1.0]]), good]))
    with pytest.raises(ValueError, match=r"covariances\[1\].*not positive definite"):
        GaussianMixture(w, mu, torch.stack([good, torch.zeros(2, 2, dtype=F64)]))
    with pytest.raises(ValueError, match="^weights:"):
        GaussianMixture([0.5, 0.6], mu, torch.stack([good, good]))
    with pytest.raises(ValueError, match="^means:"):
        GaussianMixture(w, torch.zeros(3, 2), torch.stack([good, good]))


def test_unknown_names_are_rejected():
    with pytest.raises(ValueError, match="^name:"):
        load_target("gmm4d")
    with pytest.raises(ValueError, match="^correlation:"):
        scalability_target(5, "diagonal", 0)
    with pytest.raises(ValueError, match="^dim:"):
        scalability_target(0, "block", 0)


# ----------------------------------------------------------------------------- scalability

def test_every_scalability_target_builds_with_five_modes_and_is_pd(scal_targets):
    assert len(scal_targets) == 6 * 4
    for (d, s), t in scal_targets.items():
        assert (t.dim, t.num_components) == (d, 5), (d, s)
        assert _is_pd(t.covariances), (d, s)
        # every pair of modes is 3.0 apart in every coordinate
        gaps = (t.means[:, None, :] - t.means[None, :, :]).abs()
        off = ~torch.eye(5, dtype=torch.bool)
        assert float(gaps[off].min()) == pytest.approx(3.0), (d, s)


def test_scalability_correlation_structures(scal_targets):
    cfg = synthetic_config()["scalability"]
    i = torch.arange(50)
    lag = (i[:, None] - i[None, :]).abs()
    off = ~torch.eye(50, dtype=torch.bool)
    r = {s: scal_targets[(50, s)].component_correlations() for s in SCALABILITY_STRUCTURES}
    # block: nonzero exactly inside consecutive blocks
    same = (i[:, None] // cfg["block"]["block_size"]) == (i[None, :] // cfg["block"]["block_size"])
    assert bool((r["block"][:, same & off] != 0).all() and (r["block"][:, ~same] == 0).all())
    # banded: nonzero exactly within the bandwidth
    bw = cfg["banded"]["bandwidth"]
    assert bool((r["banded"][:, (lag <= bw) & off] != 0).all() and (r["banded"][:, lag > bw] == 0).all())
    # long-range: each dimension has exactly one partner, at least 25 = d/2 ... far for half_shift
    nz = (r["long_range"] != 0) & off
    assert bool((nz.sum(-1) == 1).all())
    assert bool((lag[nz[1]] == 25).all())  # mode 2 pairs i <-> i + d/2
    # (to rounding: C_ij = Σ_ij / √Σ_ii / √Σ_jj is two divisions)
    assert bool(((r["long_range"][0][nz[0]].abs() - cfg["long_range"]["rho"][0]).abs() < 1e-12).all())
    # sparse: at most `matchings` partners per dimension, weak-to-moderate values
    nzs = (r["sparse"] != 0) & off
    assert int(nzs.sum(-1).max()) <= cfg["sparse"]["matchings"] and int(nzs.sum()) > 0
    vals = r["sparse"][nzs].abs()
    assert float(vals.min()) >= cfg["sparse"]["rho_min"] and float(vals.max()) <= cfg["sparse"]["rho_max"]
    # in 1D all structures are the same target
    one = [scal_targets[(1, s)] for s in SCALABILITY_STRUCTURES]
    assert all(torch.equal(o.covariances, one[0].covariances) and torch.equal(o.means, one[0].means) for o in one)


def test_scalability_targets_are_deterministic_in_the_seed():
    a, b, c = (scalability_target(20, "sparse", s) for s in (7, 7, 8))
    assert torch.equal(a.means, b.means) and torch.equal(a.covariances, b.covariances)
    assert not torch.equal(a.means, c.means) and not torch.equal(a.covariances, c.covariances)


def test_scalability_initial_is_broad():
    for d in SCALABILITY_DIMS:
        init = scalability_initial(d)
        std = float(init.covariances[0, 0, 0]) ** 0.5
        t = scalability_target(d, "block", 0)
        assert init.dim == d and float(t.means.abs().max()) <= 1.5 * std
