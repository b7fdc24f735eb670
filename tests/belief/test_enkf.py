"""The ensemble Kalman filter (escort_rl.belief.enkf) against the Kalman posterior, its pieces, and
its use through the config and the TorchRL transform."""

import math

import pytest
import torch

from escort_rl.belief import EnKFFilter
from escort_rl.belief.enkf import gaspari_cohn
from escort_rl.bench.calibration import kalman_episode, kalman_errors
from escort_rl.models import LinearGaussian


def _episode(filt, model, n, steps, batch, g):
    """The Mahalanobis error of the ensemble mean and tr(Σ̂)/tr(P) against Kalman, per belief, at the last step."""
    for belief, mean, cov in kalman_episode(filt, model, n, steps, batch, g):
        pass
    return kalman_errors(belief, mean, cov)


def test_enkf_converges_to_the_kalman_posterior(per_test_generator):
    """With N members the ensemble mean's error in Kalman-Mahalanobis units is O(sqrt(d/N)) and the
    covariance is within O(sqrt(1/N)) of Kalman's; bounds of several standard errors at any seed."""
    model = LinearGaussian(state_dim=10)
    g = per_test_generator
    small, small_ratio = _episode(EnKFFilter(), model, 50, 5, 16, g)
    large, large_ratio = _episode(EnKFFilter(), model, 4000, 5, 16, g)
    assert float(large.mean()) < 0.25  # sqrt(10 / 4000) = 0.05 per belief
    assert abs(float(large_ratio.mean()) - 1.0) < 0.06
    assert float(large.mean()) < 0.5 * float(small.mean())  # the error falls as N grows
    assert abs(float(large_ratio.mean()) - 1.0) < abs(float(small_ratio.mean()) - 1.0) + 0.03


def test_enkf_with_partial_observations_and_float64(per_test_generator):
    model = LinearGaussian(state_dim=6, obs_dim=2)
    maha, ratio = _episode(EnKFFilter(), model, 3000, 4, 8, per_test_generator)
    assert float(maha.mean()) < 0.3 and abs(float(ratio.mean()) - 1.0) < 0.08


def test_gaspari_cohn_closed_form():
    r = torch.tensor([0.0, 0.5, 1.0, 1.5, 2.0, 3.0], dtype=torch.float64)
    f = gaspari_cohn(r)
    assert float(f[0]) == 1.0 and float(f[4]) == 0.0 and float(f[5]) == 0.0
    # both pieces meet at r = 1 with value 5/24
    assert float(f[2]) == pytest.approx(5 / 24)
    z = 0.5
    assert float(f[1]) == pytest.approx(-z**5 / 4 + z**4 / 2 + 5 * z**3 / 8 - 5 * z**2 / 3 + 1)
    z = 1.5
    assert float(f[3]) == pytest.approx(z**5 / 12 - z**4 / 2 + 5 * z**3 / 8 + 5 * z**2 / 3 - 5 * z + 4 - 2 / (3 * z))


def test_localisation_cuts_far_correlations_and_inflation_widens(per_test_generator):
    model = LinearGaussian(state_dim=8)
    filt = EnKFFilter(localisation_radius=1.0)
    taper_xy, taper_yy = filt.tapers(model, 8, 8, torch.zeros(1))
    assert float(taper_xy[0, 0]) == 1.0 and float(taper_xy[0, 2]) == 0.0 and float(taper_xy[0, 1]) > 0
    maha, _ = _episode(filt, model, 500, 3, 4, per_test_generator)  # diagonal model: localisation is harmless
    assert float(maha.mean()) < 0.5
    g = per_test_generator
    b = EnKFFilter().init(model, (2,), 200, g)
    a = torch.zeros(2, dtype=torch.long)
    o = torch.zeros(2, 8)
    plain = EnKFFilter().update(model, b, a, o, torch.Generator().manual_seed(1))
    wide = EnKFFilter(inflation=1.5).update(model, b, a, o, torch.Generator().manual_seed(1))
    assert float(torch.diagonal(wide.covariance(), dim1=-2, dim2=-1).sum()) > float(
        torch.diagonal(plain.covariance(), dim1=-2, dim2=-1).sum())


@pytest.mark.parametrize("kwargs, match", [
    ({"inflation": 0.9}, "inflation: must be >= 1"),
    ({"inflation": math.nan}, "inflation: must be a finite number"),
    ({"localisation_radius": 0.0}, "localisation_radius: must be > 0, got 0.0"),
    ({"ridge": -1.0}, "ridge: must be >= 0"),
])
def test_bad_arguments_name_the_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        EnKFFilter(**kwargs)


def test_a_model_whose_observe_returns_nan_is_named():
    class Broken(LinearGaussian):
        def observe(self, s_next, a, generator=None):
            return super().observe(s_next, a, generator) * float("nan")

    model = Broken(state_dim=3)
    filt = EnKFFilter()
    b = filt.init(model, (2,), 20)
    with pytest.raises(ValueError, match="model.observe"):
        filt.update(model, b, torch.zeros(2, dtype=torch.long), torch.zeros(2, 3))


def test_enkf_from_config_in_the_belief_transform():
    from torchrl.envs import TransformedEnv

    from escort_rl.config import compose
    from escort_rl.envs import POMDPEnv
    from escort_rl.trainers.builders import build_filter
    from escort_rl.transforms import BeliefTransform

    filt = build_filter(compose(["filter=enkf", "filter.inflation=1.02"]).filter)
    assert isinstance(filt, EnKFFilter) and filt.inflation == 1.02
    model = LinearGaussian(state_dim=3)
    env = TransformedEnv(POMDPEnv(model, batch_size=(2,), seed=0, max_steps=5), BeliefTransform(model, filt, 16))
    td = env.rollout(4)
    assert td["next", "particles"].shape == (2, 4, 16, 3) and bool(torch.isfinite(td["next", "particles"]).all())


def test_enkf_kalman_bench_finds_no_mean_bias_and_names_bad_flags():
    """``bench enkf-kalman``: on a small model the EnKF's mean is unbiased (|t| with 15 degrees of
    freedom exceeds 6 with probability < 3e-5 per coordinate) and near the i.i.d. floor."""
    import argparse

    from escort_rl.bench.frontier.kalman import enkf_against_kalman, kalman_markdown, main

    r = enkf_against_kalman(dim=4, particles=2000, episodes=16, steps=5, seed=int(torch.randint(0, 10**6, (1,))))
    assert r["mean"]["entries"] == 4 and r["covariance"]["entries"] == 10
    assert r["mean"]["max_abs_z"] < 6
    assert 0.3 < r["mean"]["error_over_iid_floor"] < 10
    assert abs(r["covariance"]["trace_ratio"] - 1.0) < 0.1
    assert "| mean | 4 |" in kalman_markdown(r)
    args = argparse.Namespace(dim=4, particles=100, episodes=1, steps=3, obs_std=None, seed=0, inflation=None,
                              localisation_radius=None, output="unused")
    with pytest.raises(ValueError, match="--episodes"):
        main(args)
