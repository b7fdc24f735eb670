"""Protocol (a)'s reference posterior (escort_rl.metrics.reference), the benchmark cell that computes it, and
the distances to it."""

from __future__ import annotations

import math

import pytest
import torch

from escort_rl.bench.reference_cell import ReferenceCell
from escort_rl.bench.trajectories import generate_trajectories
from escort_rl.metrics.distances import median_gamma
from escort_rl.metrics.moments import weighted_moments
from escort_rl.metrics.reference import DamagedReferenceError, Reference, content_hash, reference_posterior
from escort_rl.models.linear_gaussian import LinearGaussian


def _linear_model():
    # only the first two coordinates are observed, with R = I (so no step's weights degenerate)
    model = LinearGaussian(state_dim=4, obs_dim=2, observation_cov=torch.eye(2))
    model.position_dims, model.velocity_dims = (0, 1), (2, 3)
    return model


def test_reference_matches_the_kalman_posterior():
    """On a linear-Gaussian model the reference's mean and covariance converge to the Kalman filter's.
    At N = 40 000, over 4 base seeds × 3 seeds × 7 steps, the largest mean error was 4.0 standard
    errors sqrt(var / (N/10)) (resampling and the unobserved coordinates' path degeneracy make the
    effective size about N/10) and the largest relative covariance error 0.105. The bounds (8 and
    0.25) leave that margin; a reference without the update would be off by sqrt(N/10) ≈ 60 of them."""
    model = _linear_model()
    seeds = [0, 1, 2]
    traj = generate_trajectories(model, 6, seeds)
    n = 40_000
    ref = reference_posterior(model, traj, seeds, n, sample=64, name="linear")
    for i in range(len(seeds)):
        mean, cov = model.m0.double(), model.P0.double()
        for t in range(traj["actions"].shape[1] + 1):
            if t > 0:
                mean, cov = model.kalman_step(mean, cov, traj["actions"][i, t - 1], traj["observations"][i, t - 1])
                mean, cov = mean.double(), cov.double()
            for part, dims in (("position", [0, 1]), ("velocity", [2, 3])):
                got_mean = ref[part]["mean"][i, t].double()
                got_cov = ref[part]["cov"][i, t].double()
                want_mean, want_cov = mean[dims], cov[dims][:, dims]
                se = (torch.diagonal(want_cov) / (n / 10)).sqrt()
                assert ((got_mean - want_mean).abs() <= 8 * se).all(), (i, t, part)
                assert torch.linalg.matrix_norm(got_cov - want_cov) <= 0.25 * torch.linalg.matrix_norm(want_cov)


def test_reference_shapes_and_chunks():
    model = _linear_model()
    seeds = [0, 1, 2]
    traj = generate_trajectories(model, 3, seeds)
    ref = reference_posterior(model, traj, seeds, 500, sample=40, chunk_rows=1000, name="linear")  # 2 seeds a chunk
    assert ref["position"]["sample"].shape == (3, 4, 40, 2)
    assert ref["position"]["cov"].shape == (3, 4, 2, 2)
    assert ref["velocity"]["gamma"].shape == (3, 4)
    assert ref["ess"].shape == (3, 4)
    assert ref["position"]["projections"].shape[-1] == 2
    assert torch.isfinite(ref["position"]["kyy"]).all()


def test_weighted_moments_closed_form():
    x = torch.tensor([[0.0, 0.0], [2.0, 4.0]])
    w = torch.tensor([0.25, 0.75])
    mean, cov = weighted_moments(x, w)
    assert torch.allclose(mean, torch.tensor([1.5, 3.0], dtype=torch.float64))
    # Σ w (x − m)(x − m)ᵀ: variances 0.25·2.25 + 0.75·0.25 = 0.75 and 3.0, covariance 1.5
    assert torch.allclose(cov, torch.tensor([[0.75, 1.5], [1.5, 3.0]], dtype=torch.float64))


def test_median_gamma_closed_form():
    y = torch.tensor([[0.0], [1.0], [3.0]])  # distances 1, 3, 2: the median is 2
    assert math.isclose(float(median_gamma(y)), 1.0 / 8.0)


@pytest.fixture
def reference_cell(tmp_path):
    return ReferenceCell(domain="lightdark10d", particles=300, steps=3, seeds=(0, 1), sample=50, folder=str(tmp_path))


def test_reference_cell_round_trip(reference_cell, tmp_path):
    result = reference_cell.run()
    assert reference_cell.valid(result)
    ref = Reference.load(tmp_path / result["file"], result["hash"])
    # a belief made of the reference's own subsample is at distance 0 from it (W1, MMD², mean of the sample)
    y = torch.cat([ref.parts["position"]["sample"][:, 2], ref.parts["velocity"]["sample"][:, 2]], -1)
    x = torch.zeros(2, 50, 10)
    x[..., :5], x[..., 5:] = y[..., :5], y[..., 5:]
    d = ref.compare(x, torch.zeros(2, 50), 2)
    assert set(d) == {f"{p}/{m}" for p in ("position", "velocity") for m in ("w1", "mmd2", "mean", "cov")}
    assert float(d["position/w1"].abs().max()) < 1e-5 and float(d["velocity/w1"].abs().max()) < 1e-5
    assert float(d["position/mmd2"].max()) < 1e-5
    # against itself the floor is 0
    floor = ref.compare_reference(ref, 3)
    assert all(float(v.abs().max()) < 1e-5 for v in floor.values())
    # the folder is where the file lives, not what it holds: another folder, the same cell
    other = ReferenceCell(domain="lightdark10d", particles=300, steps=3, seeds=(0, 1), sample=50, folder="elsewhere")
    assert other.spec() == reference_cell.spec()


def test_a_far_belief_is_farther(reference_cell, tmp_path):
    result = reference_cell.run()
    ref = Reference.load(tmp_path / result["file"], result["hash"])
    near = torch.cat([ref.parts["position"]["sample"][:, 1], ref.parts["velocity"]["sample"][:, 1]], -1)
    far = near + 3.0
    d_near, d_far = (ref.compare(x, torch.zeros(2, 50), 1) for x in (near, far))
    for key in d_near:
        if key.endswith("/cov"):  # a shift leaves the covariance where it was
            assert torch.allclose(d_far[key], d_near[key], atol=1e-4), key
        else:
            assert (d_far[key] > d_near[key]).all(), key
    wide = ref.compare(3.0 * near, torch.zeros(2, 50), 1)
    assert (wide["position/cov"] > d_near["position/cov"]).all()
    want = (near[..., :5].double().mean(1) + 3.0 - ref.parts["position"]["mean"][:, 1].double()).norm(dim=-1)
    assert torch.allclose(d_far["position/mean"], want, atol=1e-4)


def test_a_belief_larger_than_the_sample_enters_mmd_thinned(reference_cell, tmp_path):
    result = reference_cell.run()
    ref = Reference.load(tmp_path / result["file"], result["hash"])
    near = torch.cat([ref.parts["position"]["sample"][:, 1], ref.parts["velocity"]["sample"][:, 1]], -1)
    x = near + 0.3 * torch.randn(near.shape, generator=torch.Generator().manual_seed(1))
    # four copies of each particle: N = 200 > M = 50, and M systematic draws take one copy of each
    big = x.repeat_interleave(4, dim=1)
    small, thinned = ref.compare(x, torch.zeros(2, 50), 1), ref.compare(big, torch.zeros(2, 200), 1)
    for key in small:
        assert torch.allclose(thinned[key], small[key], atol=1e-5), key
    assert (thinned["position/mmd2"] > 1e-3).all()  # not trivially 0: the belief was moved
    # with unequal weights the draws follow them: all weight on the first copy block
    log_w = torch.full((2, 200), -1e9)
    log_w[:, :4] = 0.0
    one = ref.compare(big, log_w, 1)
    point = ref.compare(x[:, :1].expand(2, 50, 10), torch.zeros(2, 50), 1)
    assert torch.allclose(one["position/mmd2"], point["position/mmd2"], atol=1e-5)


def test_damaged_reference_is_detected(reference_cell, tmp_path):
    result = reference_cell.run()
    path = tmp_path / result["file"]
    data = torch.load(path, weights_only=True)
    data["position"]["mean"][0, 0, 0] += 1.0  # a different file under the same name
    torch.save(data, path)
    assert not reference_cell.valid(result)
    with pytest.raises(DamagedReferenceError, match="do not match the hash"):
        Reference.load(path, result["hash"])
    path.write_bytes(path.read_bytes()[:100])  # truncated
    with pytest.raises(DamagedReferenceError, match="unreadable"):
        Reference.load(path, result["hash"])
    path.unlink()
    assert not reference_cell.valid(result)


def test_content_hash_sees_every_tensor():
    a = {"x": torch.zeros(3), "p": {"y": torch.ones(2)}}
    b = {"x": torch.zeros(3), "p": {"y": torch.tensor([1.0, 2.0])}}
    assert content_hash(a) == content_hash({"p": {"y": torch.ones(2)}, "x": torch.zeros(3)})
    assert content_hash(a) != content_hash(b)


def test_gaussian_sum_posterior_matches_bayes_on_a_grid():
    """GMMTracking's exact posterior (a Gaussian sum, nothing pruned: 3³ components) against recursive
    Bayes on a fine 1-D grid, after three observations through the 3-mode noise."""
    from escort_rl.bench.synthetic.tracking import GMMTracking
    from escort_rl.bench.targets import load_target

    model = GMMTracking(load_target("gmm1d"), prior_std=2.0, process_std=0.7)
    obs = torch.tensor([[1.3], [-0.4], [2.2]], dtype=torch.float64)
    log_w, means, covs = model.exact_posterior_init(1)
    x = torch.linspace(-15, 15, 6001, dtype=torch.float64)
    dx = float(x[1] - x[0])
    p = torch.exp(-0.5 * (x / 2.0) ** 2)
    kernel = torch.exp(-0.5 * ((x[:, None] - x[None, :]) / 0.7) ** 2)
    for o in obs:
        log_w, means, covs, dropped = model.exact_posterior_step(log_w, means, covs, None, o[None])
        assert float(dropped) == 0.0
        p = kernel @ p * dx
        p = p * model.noise.log_prob((o - x)[:, None]).exp()
        p = p / (p.sum() * dx)
    w = log_w.exp()[0]
    mean = float((w * means[0, :, 0]).sum())
    var = float((w * (covs[0, :, 0, 0] + means[0, :, 0] ** 2)).sum()) - mean**2
    grid_mean = float((x * p).sum() * dx)
    grid_var = float(((x - grid_mean) ** 2 * p).sum() * dx)
    assert mean == pytest.approx(grid_mean, abs=1e-4) and var == pytest.approx(grid_var, rel=1e-3)


def test_gaussian_sum_reference_samples_its_modes_and_counts_what_it_prunes():
    """The exact reference of a mixture model: its mean and covariance are the mixture's, its draws
    follow them, and a pruned sum reports the mass it cut."""
    from escort_rl.bench.synthetic.tracking import gmm_tracking
    from escort_rl.metrics.reference import exact_reference, has_exact_posterior

    model = gmm_tracking(dim=3, max_components=4)
    assert has_exact_posterior(model)
    seeds = [0, 1, 2]
    traj = generate_trajectories(model, 4, seeds, 0)
    ref = exact_reference(model, traj, seeds, sample=4000, name="gmm")
    part = ref["position"]
    assert part["mean"].shape == (3, 5, 3) and part["sample"].shape == (3, 5, 4000, 3)
    # 4000 draws: their mean is within 5 standard errors of the mixture mean, per coordinate
    se = torch.diagonal(part["cov"], dim1=-2, dim2=-1).sqrt() / math.sqrt(4000)
    assert bool(((part["sample"].double().mean(-2) - part["mean"]).abs() < 5 * se + 1e-6).all())
    assert ref["dropped_mass"].shape == (3, 5) and float(ref["dropped_mass"][:, 0].abs().max()) == 0.0
    assert float(ref["dropped_mass"].max()) < 1.0
    with pytest.raises(ValueError, match="max_components"):
        gmm_tracking(dim=3, max_components=0)
