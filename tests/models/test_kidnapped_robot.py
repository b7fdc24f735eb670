"""Tests of the Kidnapped Robot 20D model (paper, Appendix "Domains: Kidnapped Robot Problem")."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import pytest
import torch
from omegaconf import OmegaConf

from conftest import gen
from escort_rl.config import ConfigError
from escort_rl.models import POMDPModel, check_model
from escort_rl.models.kidnapped_robot import (
    KidnappedRobot20D,
    KidnappedRobot20DParams,
    describe_correlations,
    paper_correlations,
)


@pytest.fixture(scope="module")
def model() -> KidnappedRobot20D:
    return KidnappedRobot20D()


def near_cluster_state(model: KidnappedRobot20D, dtype=torch.float32) -> torch.Tensor:
    """A state 3.5 units south-west of cluster 0's centre, looking at it (several slots visible
    with probabilities between 0 and 1), with a non-trivial calibration and descriptor."""
    s = model.initial_state((), gen(123)).to(dtype)
    s[0], s[1] = 5.0 - 2.5, 5.0 - 2.5
    s[2] = math.pi / 4 + 2 * math.pi  # unwrapped heading: only cos/sin matter
    s[5:10] = torch.tensor([0.05, -0.02, 0.1, 0.03, -0.04], dtype=dtype)
    return s


# ---------------------------------------------------------------------------------------------
# protocol, config
# ---------------------------------------------------------------------------------------------


def test_follows_protocol(model):
    check_model(model)
    assert isinstance(model, POMDPModel)
    assert (model.state_dim, model.obs_dim, model.n_actions) == (20, 12, 4)
    assert model.position_dims == (0, 1) and model.n_pos == 2
    assert (model.n_slots, model.n_clusters) == (4, 4)
    assert model.landmark_positions.shape == (4, 4, 2)
    torch.testing.assert_close(model.landmark_descriptors.norm(dim=-1), torch.ones(4, 4))
    s = model.initial_state((3,), gen(0))
    torch.testing.assert_close(model.position(s), s[..., list(model.position_dims)])


def _plain(value):
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def test_the_composed_config_is_the_params_defaults_and_builds_the_model():
    from escort_rl.config import compose

    cfg = compose(["env=kidnapped20d"]).env
    assert cfg.name == "kidnapped20d" and cfg.max_steps > 0
    model_cfg = {k: v for k, v in OmegaConf.to_container(cfg.model, resolve=True).items() if k != "_target_"}
    defaults = KidnappedRobot20DParams()
    assert model_cfg == {f.name: _plain(getattr(defaults, f.name)) for f in dataclasses.fields(defaults)}
    default = KidnappedRobot20D()
    for m in (KidnappedRobot20D(**model_cfg), KidnappedRobot20D(**{k: cfg.model[k] for k in model_cfg})):
        check_model(m)
        torch.testing.assert_close(m.landmark_positions, default.landmark_positions, rtol=0, atol=0)
        torch.testing.assert_close(m.landmark_descriptors, default.landmark_descriptors, rtol=0, atol=0)
        torch.testing.assert_close(m.transition_scale_tril(), default.transition_scale_tril(), rtol=0, atol=0)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"sensor_range": -1.0}, "sensor_range"),
        ({"map_size": 0.0}, "map_size"),
        ({"detection_prob": 1.0}, "detection_prob"),
        ({"field_of_view_deg": 0.0}, "field_of_view_deg"),
        ({"position_noise_std": 0.0}, "position_noise_std"),
        ({"feature_noise_std": float("nan")}, "feature_noise_std"),
        ({"start_calibration_std": -0.1}, "start_calibration_std"),
        ({"velocity_reversion": 1.5}, "velocity_reversion"),
        ({"rho_calibration": 1.0}, "rho_calibration"),
        ({"cluster_centres": [[1.0, 2.0, 3.0]]}, "cluster_centres"),
        ({"cluster_offsets": []}, "cluster_offsets"),
        ({"cluster_types": ["house", "castle", "shop", "warehouse"]}, "cluster_types"),
        ({"cluster_types": ["house", "shop"]}, "cluster_types"),
        ({"type_prototypes": {"house": [1.0, 2.0], "shop": [1.0] * 10, "warehouse": [1.0] * 10}}, "type_prototypes"),
        ({"reference_descriptor": [0.0] * 10}, "reference_descriptor"),
    ],
)
def test_bad_constructor_input_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=rf"^KidnappedRobot20D\.{field}"):
        KidnappedRobot20D(**kwargs)


def test_parameters_are_one_checked_dataclass():
    with pytest.raises(ConfigError, match=r"^KidnappedRobot20D\.detection_prob: must be < 1, got 1.0$"):
        KidnappedRobot20D(detection_prob=1.0)
    with pytest.raises(ConfigError, match=r"^KidnappedRobot20D\.sensor_range: expected a number, got 'x'$"):
        KidnappedRobot20D(sensor_range="x")
    with pytest.raises(ConfigError, match=r"^KidnappedRobot20D: unknown parameter 'sensor_rang'"):
        KidnappedRobot20D(sensor_rang=5.0)
    params = dataclasses.replace(KidnappedRobot20DParams(), sensor_range=4.0, map_seed=2)
    model = KidnappedRobot20D(params)
    assert model.params == params and model.sensor_range == 4.0 and model.map_seed == 2
    assert KidnappedRobot20D(cluster_centres=((5, 5), (15, 15))).n_clusters == 2  # tuples of ints read as lists


# ---------------------------------------------------------------------------------------------
# shapes and broadcasting
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(), (3,), (2, 4)])
def test_shapes(model, shape):
    g = gen(1)
    s = model.initial_state(shape, g)
    assert s.shape == (*shape, 20) and s.dtype == torch.float32
    assert model.initial_belief(shape, 7, g).shape == (*shape, 7, 20)
    a = torch.randint(0, 4, shape, generator=g)
    s2 = model.transition(s, a, g)
    assert s2.shape == s.shape and model.transition_mean(s, a).shape == s.shape
    assert model.transition_log_prob(s2, s, a).shape == shape
    o = model.observe(s2, a, g)
    assert o.shape == (*shape, 12)
    assert model.observation_log_prob(o, s2, a).shape == shape
    assert model.reward(s, a, s2).shape == shape and bool((model.reward(s, a, s2) == -1).all())
    t = model.is_terminal(s2)
    assert t.shape == shape and t.dtype == torch.bool and not bool(t.any())


def test_filter_style_broadcasting_matches_elementwise(model):
    g = gen(2)
    b, n = 2, 5
    x = model.initial_belief((b,), n, g)  # [B, N, d]
    a = torch.randint(0, 4, (b,), generator=g).unsqueeze(-1).expand(b, n)
    o = model.observe(model.initial_state((b,), g), a[:, 0], g)  # [B, obs]
    lp = model.observation_log_prob(o.unsqueeze(-2), x, a)
    assert lp.shape == (b, n)
    for i in range(b):
        for j in range(n):
            torch.testing.assert_close(lp[i, j], model.observation_log_prob(o[i], x[i, j], a[i, j]))
    # the prior mixture: [B, N, 1, d] against [B, 1, N, d] with actions [B, 1, N]
    z = model.transition(x, a, g)
    tl = model.transition_log_prob(z.unsqueeze(-2), x.unsqueeze(-3), a.unsqueeze(-2))
    assert tl.shape == (b, n, n)
    for i in range(b):
        for j in range(n):
            for k in range(n):
                torch.testing.assert_close(tl[i, j, k], model.transition_log_prob(z[i, j], x[i, k], a[i, k]))


def test_float64_states_are_accepted(model):
    s = model.initial_state((3,), gen(3)).double()
    a = torch.tensor([0, 1, 3])
    o = model.observe(s, a, gen(4))
    assert o.dtype == torch.float64
    torch.testing.assert_close(model.observation_log_prob(o, s, a),
                               model.observation_log_prob(o.float(), s.float(), a).double(), rtol=1e-4, atol=1e-4)
    s2 = model.transition(s, a, gen(5))
    torch.testing.assert_close(model.transition_log_prob(s2, s, a),
                               model.transition_log_prob(s2.float(), s.float(), a).double(), rtol=1e-4, atol=1e-3)


# ---------------------------------------------------------------------------------------------
# dynamics and process noise
# ---------------------------------------------------------------------------------------------


def test_transition_mean_follows_the_paper(model):
    s = model.initial_state((4,), gen(6))
    s[:, 0:2] = 10.0
    s[:, 10:] *= 2.0  # off the unit sphere
    a = torch.tensor([0, 1, 2, 3])
    m = model.transition_mean(s, a)
    x, y, th, v = s[:, 0], s[:, 1], s[:, 2], s[:, 3]
    moves = torch.tensor([1.0, 1.0, 1.0, 0.0])
    torch.testing.assert_close(m[:, 0], x + moves * v * torch.cos(th) * model.dt)
    torch.testing.assert_close(m[:, 1], y + moves * v * torch.sin(th) * model.dt)
    torch.testing.assert_close(m[:, 2], th + torch.tensor([0.1, -0.1, 0.0, 0.0]))
    torch.testing.assert_close(m[:, 3], v + 0.1 * (2.0 - v))
    torch.testing.assert_close(m[:, 4], 0.9 * s[:, 4])
    torch.testing.assert_close(m[:, 5:10], s[:, 5:10])
    torch.testing.assert_close(m[:, 10:].norm(dim=-1), torch.ones(4))
    # the mean stays in the map
    s[:, 0] = 19.99
    s[:, 2] = 0.0
    assert bool((model.transition_mean(s, a)[:, 0] <= model.map_size).all())


def test_paper_correlations_and_the_psd_fix(model):
    p = paper_correlations()
    assert p.shape == (20, 20)
    assert p[0, 2] == p[1, 2] == 0.6 and p[0, 3] == p[1, 3] == 0.8
    assert p[5, 6] == p[7, 9] == 0.4 and p[5, 10] == p[9, 19] == 0.3
    assert torch.linalg.eigvalsh(p).min() < -0.4  # the paper's matrix is not PSD
    c = model.correlation
    torch.testing.assert_close(c, c.T, rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.diagonal(c), torch.ones(20, dtype=torch.float64), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(c).min() > 1e-4
    text = describe_correlations(model)
    assert "not PSD" in text and "rho(x, v)" in text and "0.637" in text


def test_transition_noise_covariance_matches_the_spec(model):
    n = 100_000
    s = model.initial_state((n,), gen(7))
    a = torch.randint(0, 4, (n,), generator=gen(8))
    eps = (model.transition(s, a, gen(9)) - model.transition_mean(s, a)).double()
    tril = model.transition_scale_tril().double()
    assert torch.equal(tril, torch.tril(tril)) and bool((torch.diagonal(tril) > 0).all())
    cov = tril @ tril.T
    torch.testing.assert_close(cov, model.noise_covariance.double(), rtol=1e-4, atol=1e-9)
    std = torch.sqrt(torch.diagonal(cov))
    torch.testing.assert_close(cov / std[:, None] / std[None, :], model.correlation, rtol=0, atol=1e-5)
    emp = torch.cov(eps.T)
    assert ((emp - cov) / std[:, None] / std[None, :]).abs().max() < 0.02
    assert (eps.mean(0) / std).abs().max() < 0.02


def test_transition_log_prob_is_the_gaussian_of_the_noise(model):
    s = model.initial_state((6,), gen(10))
    a = torch.tensor([0, 1, 2, 3, 0, 1])
    s2 = model.transition(s, a, gen(11))
    ref = torch.distributions.MultivariateNormal(
        model.transition_mean(s, a).double(), scale_tril=model.transition_scale_tril().double()
    ).log_prob(s2.double())
    torch.testing.assert_close(model.transition_log_prob(s2, s, a).double(), ref, rtol=1e-4, atol=1e-2)


# ---------------------------------------------------------------------------------------------
# observation model
# ---------------------------------------------------------------------------------------------


def _reference_log_prob(model: KidnappedRobot20D, o: list[float], s: list[float]) -> float:
    """The observation law written out with scalars (float64 python), independently of the model's
    tensor code: per slot, copy c detected with p_kc; the first detected copy is reported."""

    def sig(z: float) -> float:
        return 1.0 / (1.0 + math.exp(-z)) if z > -700 else 0.0

    half = math.radians(model.field_of_view_deg) / 2
    x, y, th = s[0], s[1], s[2]
    c = s[5:10]
    f = s[10:20]
    fn = math.sqrt(sum(v * v for v in f))
    total = 0.0
    for k in range(model.n_slots):
        ps, md, ms = [], [], []
        for cl in range(model.n_clusters):
            lx, ly = (float(v) for v in model.landmark_positions[k, cl])
            dx, dy = lx - x, ly - y
            r = math.hypot(dx, dy)
            cos_d = (dx * math.cos(th + c[2]) + dy * math.sin(th + c[2])) / r
            ps.append(model.detection_prob * sig((model.sensor_range - r) / model.range_softness)
                      * sig((cos_d - math.cos(half)) / (math.sin(half) * model.fov_softness)))
            md.append((1 + c[1]) * r + c[0])
            sim = sum(fi * float(di) for fi, di in zip(f, model.landmark_descriptors[k, cl])) / fn
            ms.append((1 + c[3]) * sim + c[4])
        vis, dist, simo = o[3 * k: 3 * k + 3]
        if vis > 0.5:
            like, none_before = 0.0, 1.0
            for p, mu_d, mu_s in zip(ps, md, ms):
                nd = math.exp(-0.5 * ((dist - mu_d) / model.distance_noise_std) ** 2) / (
                    math.sqrt(2 * math.pi) * model.distance_noise_std)
                ns = math.exp(-0.5 * ((simo - mu_s) / model.similarity_noise_std) ** 2) / (
                    math.sqrt(2 * math.pi) * model.similarity_noise_std)
                like += none_before * p * nd * ns
                none_before *= 1 - p
            total += math.log(like)
        else:
            total += sum(math.log(1 - p) for p in ps)
    return total


def test_observation_log_prob_equals_the_written_out_law(model):
    s0 = near_cluster_state(model, torch.float64)
    states = [s0, s0.clone(), model.initial_state((), gen(12)).double()]
    states[1][0] += 0.7
    for i, s in enumerate(states):
        for seed in range(3):
            o = model.observe(s, torch.tensor(2), gen(100 + 10 * i + seed))
            o = o + 0.05 * torch.randn(o.shape, generator=gen(seed), dtype=o.dtype) * (o != 0)  # off-sample values too
            ref = _reference_log_prob(model, o.tolist(), s.tolist())
            got = model.observation_log_prob(o, s, torch.tensor(2)).item()
            assert got == pytest.approx(ref, rel=1e-6, abs=1e-6)
    assert model.visibility_log_prob(s0).exp().max() > 0.5  # the test state sees something


def test_observation_density_integrates_to_one_with_two_copies_in_range():
    """One slot, two copies 3 apart (both often in view): P(invisible) + ∫∫ p(visible, d, s) = 1."""
    m = KidnappedRobot20D(cluster_centres=[[8.0, 10.0], [11.0, 10.0]], cluster_offsets=[[0.0, 0.0]],
                          cluster_types=["shop"])
    assert m.obs_dim == 3
    s = near_cluster_state(m, torch.float64)
    s[0], s[1], s[2] = 9.5, 5.3, math.pi / 2  # both copies 4.9 away (at the soft range edge), both in view
    _, _, md, ms = (t.squeeze(0) for t in m.observation_components(s))
    p_vis = m.visibility_log_prob(s).exp().item()
    assert 0.05 < p_vis < 0.95
    sd, ss = m.distance_noise_std, m.similarity_noise_std
    dd = torch.linspace(md.min().item() - 8 * sd, md.max().item() + 8 * sd, 601, dtype=torch.float64)
    sg = torch.linspace(ms.min().item() - 8 * ss, ms.max().item() + 8 * ss, 501, dtype=torch.float64)
    d_grid, s_grid = torch.meshgrid(dd, sg, indexing="ij")
    o = torch.stack([torch.ones_like(d_grid), d_grid, s_grid], dim=-1)
    dens = m.observation_log_prob(o, s, torch.tensor(0)).exp()
    integral = torch.trapezoid(torch.trapezoid(dens, sg, dim=-1), dd).item()
    p_inv = m.observation_log_prob(torch.zeros(3, dtype=torch.float64), s, torch.tensor(0)).exp().item()
    assert integral == pytest.approx(p_vis, rel=1e-4)
    assert p_inv + integral == pytest.approx(1.0, abs=1e-5)


def test_observe_samples_match_observation_log_prob(model):
    s = near_cluster_state(model)
    n = 40_000
    o = model.observe(s.expand(n, 20), torch.zeros(n, dtype=torch.long), gen(13)).double()
    log_p, log_1mp, md, ms = (t.double() for t in model.observation_components(s))
    log_first = log_p + torch.cumsum(log_1mp, -1) - log_1mp  # [K, C]
    q = log_first.exp().sum(-1)  # P(slot visible)
    torch.testing.assert_close(q, model.visibility_log_prob(s).double().exp(), rtol=1e-5, atol=1e-7)
    o3 = o.unflatten(-1, (model.n_slots, 3))
    vis = o3[..., 0]
    assert set(vis.unique().tolist()) <= {0.0, 1.0}
    assert bool((o3[..., 1:][vis == 0] == 0).all())  # invisible slots are zeroed
    freq = vis.mean(0)
    se = torch.sqrt(q * (1 - q) / n).clamp_min(1e-4)
    assert ((freq - q).abs() / se).max() < 4.5
    w = log_first.exp() / q[:, None]
    for k in range(model.n_slots):
        rows = o3[vis[:, k] == 1, k]
        if rows.shape[0] < 500:
            continue
        for col, mean, std in ((1, md[k], model.distance_noise_std), (2, ms[k], model.similarity_noise_std)):
            mu = (w[k] * mean).sum()
            var = (w[k] * (mean - mu) ** 2).sum() + std**2
            assert abs(rows[:, col].mean() - mu) < 4.5 * math.sqrt(var / rows.shape[0])
            assert rows[:, col].var().item() == pytest.approx(var.item(), rel=0.1)
    # the sampled observations are where the density puts them: mean log-likelihood at the true
    # state beats that at a state 4 units away
    lp_true = model.observation_log_prob(o.float(), s, torch.zeros(n, dtype=torch.long)).mean()
    far = s.clone()
    far[0] += 4.0
    assert lp_true > model.observation_log_prob(o.float(), far, torch.zeros(n, dtype=torch.long)).mean()


def test_observation_aliasing_between_clusters(model):
    """The same view from the matching spot of another cluster is plausible too: exactly as likely
    without descriptor perturbations, and far more likely than a spot between clusters with them."""
    s = near_cluster_state(model)
    o = model.observe(s, torch.tensor(0), gen(14))
    assert o[0::3].sum() >= 2
    shifted, off = s.clone(), s.clone()
    shifted[0] += 10.0  # the same pose relative to cluster 1
    off[0] += 5.0  # between clusters 0 and 1
    poses = torch.stack([s, shifted, off])
    exact = KidnappedRobot20D(descriptor_perturbation_std=0.0).observation_log_prob(o, poses, torch.tensor(0))
    torch.testing.assert_close(exact[0], exact[1])
    lp = model.observation_log_prob(o, poses, torch.tensor(0))
    assert lp[1] > lp[2] + 20.0 and lp[0] > lp[2] + 20.0


def test_scores_are_finite(model):
    g = gen(15)
    n = 2000
    x = model.initial_state((n,), g)
    x[:5, 0:2] = model.landmark_positions[0, 0]  # exactly on a landmark
    x[5:10, 10:] = 0.0  # a zero descriptor
    x[10:15, 0:2] = torch.tensor([-50.0, 70.0])  # far off the map
    o = model.observe(model.initial_state((n,), g), torch.zeros(n, dtype=torch.long), g)
    o[:50, 0::3] = 1.0
    o[:50, 1::3] = 40.0  # visible at an impossible distance
    x.requires_grad_(True)
    lp = model.observation_log_prob(o, x, torch.zeros(n, dtype=torch.long))
    assert bool(torch.isfinite(lp).all())
    (grad,) = torch.autograd.grad(lp.sum(), x)
    assert bool(torch.isfinite(grad).all())
    assert grad[:, :3].abs().sum() > 0 and grad[:, 10:].abs().sum() > 0  # pose and descriptor enter
    # the transition log-density too
    s = model.initial_state((n,), g).requires_grad_(True)
    z = model.transition(s.detach(), torch.zeros(n, dtype=torch.long), g).requires_grad_(True)
    tl = model.transition_log_prob(z, s, torch.zeros(n, dtype=torch.long))
    gz, gs = torch.autograd.grad(tl.sum(), (z, s))
    assert bool(torch.isfinite(tl).all() and torch.isfinite(gz).all() and torch.isfinite(gs).all())


def test_observation_log_prob_gradcheck(model):
    s = near_cluster_state(model, torch.float64)
    o = model.observe(s, torch.tensor(0), gen(16))
    assert o[0::3].sum() >= 1
    x = s.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda z: model.observation_log_prob(o, z, torch.tensor(0)), (x,),
                                    eps=1e-6, atol=1e-4)


def test_initial_state_is_kidnapped(model):
    s = model.initial_state((20_000,), gen(17))
    pos = s[:, 0:2]
    assert bool(((pos >= 0) & (pos <= 20)).all())
    assert pos.mean(0).sub(10).abs().max() < 0.2 and pos.std(0).sub(20 / math.sqrt(12)).abs().max() < 0.1
    assert bool(((s[:, 2] >= 0) & (s[:, 2] < 2 * math.pi)).all())
    torch.testing.assert_close(s[:, 10:].norm(dim=-1), torch.ones(20_000))
    assert s[:, 3].mean().item() == pytest.approx(2.0, abs=0.01)
    b1, b2 = model.initial_belief((2,), 50, gen(18)), model.initial_belief((2,), 50, gen(18))
    torch.testing.assert_close(b1, b2, rtol=0, atol=0)


def test_runs_in_the_torchrl_env(model):
    from torchrl.envs.utils import check_env_specs

    from escort_rl.envs import POMDPEnv

    env = POMDPEnv(model, batch_size=(2,), seed=0, max_steps=5)
    check_env_specs(env)
    td = env.rollout(5)
    assert td["next", "reward"].eq(-1).all()
