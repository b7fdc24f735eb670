"""Tests of the Multi-Target Tracking 20D model (escort_rl.models.multi_target)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import pytest
import torch
from omegaconf import OmegaConf

from conftest import gen
from escort_rl.config import ConfigError
from escort_rl.models.multi_target import (
    MultiTargetTracking20D,
    MultiTargetTracking20DParams,
    describe_correlations,
    paper_correlations,
)
from escort_rl.models.protocol import POMDPModel, check_model

N_T = 4


@pytest.fixture(scope="module")
def model() -> MultiTargetTracking20D:
    return MultiTargetTracking20D()


def make_state(agent=(1.0, 1.0), agent_vel=(0.0, 0.0), targets=((2.5, 2.5), (7.5, 2.5), (7.5, 7.5), (2.5, 7.5))):
    s = torch.zeros(20)
    s[0:2] = torch.tensor(agent)
    s[2:4] = torch.tensor(agent_vel)
    for i, p in enumerate(targets):
        s[4 + 4 * i: 6 + 4 * i] = torch.tensor(p)
    return s


def slot_obs(agent_obs, slot: int | None = None, xy=(0.0, 0.0)) -> torch.Tensor:
    """An observation with every slot missed, except ``slot`` detected at ``xy``."""
    o = torch.zeros(14)
    o[0:2] = torch.as_tensor(agent_obs)
    if slot is not None:
        o[2 + 3 * slot] = 1.0
        o[3 + 3 * slot: 5 + 3 * slot] = torch.as_tensor(xy)
    return o


# ---------------------------------------------------------------------------------------------
# protocol, config, constructor
# ---------------------------------------------------------------------------------------------


def test_follows_protocol(model):
    check_model(model)
    assert isinstance(model, POMDPModel)
    assert (model.state_dim, model.obs_dim, model.n_actions) == (20, 14, 4)
    assert model.position_dims == (4, 5, 8, 9, 12, 13, 16, 17)
    assert model.agent_position_dims == (0, 1)
    assert model.obs_mask_dims == (2, 5, 8, 11)


def _plain(value):
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def test_the_composed_config_is_the_params_defaults_and_builds_the_model():
    from escort_rl.config import compose

    cfg = OmegaConf.to_container(compose(["env=mtt20d"]).env, resolve=True)
    assert cfg["name"] == "mtt20d" and cfg["max_steps"] > 0
    cfg["model"].pop("_target_")
    defaults = MultiTargetTracking20DParams()
    assert cfg["model"] == {f.name: _plain(getattr(defaults, f.name)) for f in dataclasses.fields(defaults)}
    built = MultiTargetTracking20D(**cfg["model"])
    ref = MultiTargetTracking20D()
    torch.testing.assert_close(built.transition_scale_tril(), ref.transition_scale_tril())
    s = ref.initial_state((5,), gen(0))
    a = torch.arange(5) % 4
    o = ref.observe(s, a, gen(1))
    torch.testing.assert_close(built.observation_log_prob(o, s, a), ref.observation_log_prob(o, s, a))
    torch.testing.assert_close(built.transition_mean(s, a), ref.transition_mean(s, a))


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"dt": 0.0}, "dt"),
        ({"damping": 1.5}, "damping"),
        ({"position_noise_std": -0.1}, "position_noise_std"),
        ({"fov_degrees": 400.0}, "fov_degrees"),
        ({"zone_softness": 0.0}, "zone_softness"),
        ({"actions": [[1.0, 0.0], [0.0, 0.0]]}, "actions"),
        ({"actions": [[1.0, 0.0, 2.0]]}, "actions"),
        ({"goal": [1.0]}, "goal"),
        ({"target_start_centers": [[1.0, 1.0]]}, "target_start_centers"),
        ({"zone_x_edges": [5.0, 2.0]}, "zone_x_edges"),
        ({"zone_grid": [["clear", "limited"]]}, "zone_grid"),
        ({"zone_grid": [["clear", "foggy"], ["confusion", "blind"]]}, "zone_grid"),
        ({"zone_visibility": {"clear": 1.5, "limited": 0.3, "confusion": 0.7, "blind": 0.0}}, "zone_visibility"),
        ({"zone_swap_prob": {"clear": 0.0, "limited": 0.0, "confusion": 1.0, "blind": 0.0}}, "zone_swap_prob"),
        ({"zone_noise_std": {"clear": 0.1, "limited": 0.5, "confusion": 0.2}}, "zone_noise_std"),
        ({"flow_rate": float("nan")}, "flow_rate"),
    ],
)
def test_bad_constructor_input_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=rf"MultiTargetTracking20D\.{field}:"):
        MultiTargetTracking20D(**kwargs)


def test_parameters_are_one_checked_dataclass():
    with pytest.raises(ConfigError, match=r"^MultiTargetTracking20D\.zone_visibility: must be <= 1, got 1.5$"):
        MultiTargetTracking20D(zone_visibility={"clear": 1.5, "limited": 0.3, "confusion": 0.7, "blind": 0.0})
    with pytest.raises(ConfigError, match=r"^MultiTargetTracking20D\.dt: expected a number, got 'x'$"):
        MultiTargetTracking20D(dt="x")
    with pytest.raises(ConfigError, match=r"^MultiTargetTracking20D\.zone_noise_std: must have the same zones"):
        MultiTargetTracking20D(zone_noise_std={"clear": 0.1})
    # tuples, tensors and OmegaConf lists read as plain lists; a ready parameters object works too
    model = MultiTargetTracking20D(goal=(8, 8), actions=torch.tensor([[1.0, 0.0], [0.0, 1.0]]),
                                   **{"zone_x_edges": OmegaConf.create([5.0])})
    assert model.params.goal == [8, 8] and model.n_actions == 2 and model.goal.tolist() == [8.0, 8.0]
    params = dataclasses.replace(MultiTargetTracking20DParams(), accel=0.3)
    assert MultiTargetTracking20D(params).accel == 0.3


# ---------------------------------------------------------------------------------------------
# shapes and broadcasting
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(3,), (2, 4)])
def test_shapes(model, shape):
    g = gen(1)
    s = model.initial_state(shape, g)
    assert s.shape == (*shape, 20) and s.dtype == torch.float32
    assert model.initial_belief(shape, 7, g).shape == (*shape, 7, 20)
    a = torch.randint(0, model.n_actions, shape, generator=g)
    s2 = model.transition(s, a, g)
    assert s2.shape == (*shape, 20)
    assert model.transition_mean(s, a).shape == (*shape, 20)
    assert model.transition_log_prob(s2, s, a).shape == shape
    o = model.observe(s2, a, g)
    assert o.shape == (*shape, 14)
    assert model.observation_log_prob(o, s2, a).shape == shape
    assert model.reward(s, a, s2).shape == shape
    assert model.is_terminal(s2).shape == shape and model.is_terminal(s2).dtype == torch.bool
    assert model.target_position_error(s, s2).shape == shape
    assert model.transition_scale_tril().shape == (20, 20)


def test_broadcasting_matches_elementwise(model):
    g = gen(2)
    b, n = 2, 5
    x = model.initial_belief((b,), n, g) + 0.5 * torch.randn(b, n, 20, generator=g)
    a = torch.tensor([0, 2])
    o = model.observe(model.initial_state((b,), g), a, g)
    a_bn = a[:, None].expand(b, n)
    lp = model.observation_log_prob(o.unsqueeze(-2), x, a_bn)  # the filter's call
    assert lp.shape == (b, n)
    for i in range(b):
        for j in range(n):
            torch.testing.assert_close(lp[i, j], model.observation_log_prob(o[i], x[i, j], a[i]))
    # the prior-mixture call: [B, N, 1, d] against [B, 1, N, d]
    tl = model.transition_log_prob(x.unsqueeze(-2), x.unsqueeze(-3), a[:, None, None].expand(b, 1, n))
    assert tl.shape == (b, n, n)
    torch.testing.assert_close(tl[1, 3, 2], model.transition_log_prob(x[1, 3], x[1, 2], a[1]))
    # an action broadcast over states
    torch.testing.assert_close(model.transition_mean(x, a[:, None]), model.transition_mean(x, a_bn))


# ---------------------------------------------------------------------------------------------
# process noise
# ---------------------------------------------------------------------------------------------


def test_paper_correlations_are_not_psd_and_used_one_is():
    c = paper_correlations()
    assert c.shape == (20, 20) and c.dtype == torch.float64
    torch.testing.assert_close(c, c.T)
    assert c[4, 6] == 0.8 and c[5, 7] == 0.8 and c[0, 2] == 0.8  # x-vx, y-vy within entities
    assert c[4, 8] == 0.4 and c[5, 17] == 0.4 and c[6, 10] == 0.6 and c[7, 19] == 0.6  # between targets
    assert c[0, 4] == 0 and c[4, 9] == 0  # agent-target, cross-axis
    assert torch.linalg.eigvalsh(c).min().item() == pytest.approx(0.5 - math.sqrt(0.65), abs=1e-9)

    used = MultiTargetTracking20D().correlation
    torch.testing.assert_close(used, used.T, rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.diagonal(used), torch.ones(20, dtype=torch.float64), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(used).min() > 1e-4
    assert int(torch.linalg.cholesky_ex(used)[1]) == 0
    report = describe_correlations()
    assert "not PSD" in report and "rho(x_t1, vx_t1)" in report and "rho(vx_t1, vx_t2)" in report


def test_transition_noise_covariance_equals_spec(model):
    stds = torch.tensor([0.05, 0.05, 0.05, 0.05] * 5, dtype=torch.float64)
    cov = model.correlation * stds[:, None] * stds[None, :]
    tril = model.transition_scale_tril()
    assert tril.dtype == torch.float32
    torch.testing.assert_close(tril, torch.tril(tril))
    torch.testing.assert_close((tril @ tril.T).double(), cov, rtol=1e-4, atol=1e-8)
    torch.testing.assert_close(model.noise_covariance.double(), cov, rtol=1e-5, atol=1e-9)
    # sampled noise has that covariance
    g = gen(3)
    s = model.initial_state((1,), g).expand(20000, 20)
    a = torch.zeros(20000, dtype=torch.long)
    eps = (model.transition(s, a, g) - model.transition_mean(s, a)).double()
    emp = eps.T @ eps / eps.shape[0]
    assert (emp - cov).abs().max() < 5 * 0.05**2 * math.sqrt(2 / 20000) + 1e-6
    # and transition_log_prob is that Gaussian
    s2 = model.transition(s[:10], a[:10], g)
    ref = torch.distributions.MultivariateNormal(model.transition_mean(s[:10], a[:10]).double(), covariance_matrix=cov)
    torch.testing.assert_close(model.transition_log_prob(s2, s[:10], a[:10]).double(), ref.log_prob(s2.double()),
                               rtol=1e-4, atol=1e-3)


def test_transition_mean_dynamics(model):
    s = make_state(agent=(3.0, 3.0), agent_vel=(0.5, -0.2))
    for a, push in ((0, (0.2, 0.0)), (1, (-0.2, 0.0)), (2, (0.0, 0.2)), (3, (0.0, -0.2))):
        m = model.transition_mean(s, torch.tensor(a))
        torch.testing.assert_close(m[0:2], torch.tensor([3.05, 2.98]))
        torch.testing.assert_close(m[2:4], 0.9 * torch.tensor([0.5, -0.2]) + torch.tensor(push))
    # a target at rest on the ring is dragged along the counter-clockwise current
    m = model.transition_mean(s, torch.tensor(0))
    v1 = m[6:8]  # target 1 at (2.5, 2.5): current pointing to +x, -y
    assert v1[0] > 0 and v1[1] < 0
    # two targets closer than the repulsion radius push apart
    close = make_state(targets=((5.0, 2.0), (5.3, 2.0), (7.5, 7.5), (2.5, 7.5)))
    far = make_state(targets=((5.0, 2.0), (8.0, 2.0), (7.5, 7.5), (2.5, 7.5)))
    dv = model.transition_mean(close, torch.tensor(0))[6] - model.transition_mean(far, torch.tensor(0))[6]
    assert dv < 0  # target 1 (on the left) is pushed further left


def test_flow_pull_is_zero_on_the_ring_and_linear_far_out(model):
    c, ring = model.flow_center, model.flow_radius
    on_ring = c + torch.tensor([ring, 0.0])
    torch.testing.assert_close(model.flow(on_ring), model.flow_rate * torch.tensor([0.0, ring]))
    far = torch.tensor([1e3, 0.0])
    radial = model.flow(c + far)[0]
    torch.testing.assert_close(radial, torch.tensor(-2 * model.flow_attraction * 1e3), rtol=1e-3, atol=0.0)


def test_noise_free_dynamics_are_stable_from_far_away(model):
    """Particles far outside the map (an unseen target's belief can spread there) come back: the
    noise-free dynamics contract, they do not blow up (a cubic flow pull did, beyond ~14 from the centre)."""
    g = torch.Generator().manual_seed(0)
    s = 60.0 * torch.randn(256, 20, generator=g)
    a = torch.zeros(256, dtype=torch.long)
    for _ in range(400):
        s = model.transition_mean(s, a)
        assert torch.isfinite(s).all()
    targets = model.target_positions(s)
    assert (targets - model.flow_center).norm(dim=-1).max() < 30.0


# ---------------------------------------------------------------------------------------------
# observation model: normalisation, sampler agreement, gradients
# ---------------------------------------------------------------------------------------------

# target 3 (index 3) deep in the confusion zone with target 0 nearby; the agent looks up (+y) at it
CONFUSION_STATE = make_state(agent=(2.5, 4.2), targets=((3.5, 8.7), (7.5, 2.5), (7.5, 7.5), (2.5, 7.5)))
# agent looking along +x: target 0 on the clear/limited boundary (a mixture over zones), target 1 on
# the edge of the field of view
BOUNDARY_STATE = make_state(agent=(1.5, 2.4), targets=((5.02, 2.5), (4.5, 2.4 + 3.0 * math.tan(math.pi / 6)),
                                                        (8.0, 8.0), (2.5, 7.5)))


def _slot_integral(model, state, action, slot, h=0.05, lo=-1.0, hi=11.0, regions=None):
    """∫ exp(lp(m=1, xy) - lp(m=0)) dxy by a Riemann sum, optionally split into regions. For a
    mixture of Gaussians of std >= 0.1 on a step-0.05 grid, its error is below exp(-2π²·4)."""
    a = torch.tensor(action)
    agent_obs = state[0:2]
    lp0 = model.observation_log_prob(slot_obs(agent_obs), state, a)
    ticks = torch.arange(lo, hi + h / 2, h)
    gx, gy = torch.meshgrid(ticks, ticks, indexing="ij")
    pts = torch.stack([gx.flatten(), gy.flatten()], -1)
    o = slot_obs(agent_obs, slot).expand(pts.shape[0], 14).clone()
    o[:, 3 + 3 * slot: 5 + 3 * slot] = pts
    dens = torch.cat([(model.observation_log_prob(o[i:i + 100000], state, a) - lp0).double().exp()
                      for i in range(0, pts.shape[0], 100000)]) * h * h
    if regions is None:
        return dens.sum()
    return torch.stack([dens[(torch.linalg.vector_norm(pts - c, dim=-1) < r)].sum() for c, r in regions])


@pytest.mark.parametrize("state, action, slot",
                         [(CONFUSION_STATE, 2, 3), (BOUNDARY_STATE, 0, 0), (BOUNDARY_STATE, 0, 1)])
def test_observation_log_prob_normalises(model, state, action, slot):
    """Slots are independent, so Σ_m ∫ p(m, o_slot) = 1 reads f(0)·(1 + ∫ f(1, xy)/f(0)) = 1, with
    f(0) = 1 - P(detected)."""
    p_det = model.detection_prob(state, torch.tensor(action))[slot].double()
    assert 0.05 < p_det < 0.95  # both branches matter
    total = (1 - p_det) * (1 + _slot_integral(model, state, action, slot))
    assert total.item() == pytest.approx(1.0, abs=2e-4)


def test_observe_detection_rate_matches_detection_prob(model):
    n = 40000
    s = torch.stack([CONFUSION_STATE, BOUNDARY_STATE]).repeat_interleave(n, 0)
    a = torch.tensor([2, 0]).repeat_interleave(n)
    o = model.observe(s, a, gen(5))
    masks = o[:, list(model.obs_mask_dims)].unflatten(0, (2, n))
    assert set(masks.unique().tolist()) <= {0.0, 1.0}
    rate = masks.mean(1)
    p = model.detection_prob(s[:: n], a[:: n])
    se = torch.sqrt(p * (1 - p) / n)
    assert ((rate - p).abs() <= 4 * se + 1e-4).all(), (rate, p)
    # missed slots are zeroed, and the agent's own position is reported with its noise
    slots = o[:, 2:].unflatten(-1, (4, 3))
    assert bool((slots[..., 1:][slots[..., 0] == 0] == 0).all())
    err = o[:n, 0:2] - CONFUSION_STATE[0:2]
    assert err.mean(0).abs().max() < 4 * 0.1 / math.sqrt(n)
    assert err.std(0).sub(0.1).abs().max() < 0.003


def test_observe_swaps_match_observation_log_prob(model):
    """In the confusion zone: the sampled rate of (detected, report near target j) equals the mass
    that observation_log_prob puts there, for the true target (1 - q) and the swap partners (q·w_ij)."""
    state, action, slot = CONFUSION_STATE, 2, 3
    tp = model.target_positions(state)
    regions = [(tp[j], 0.7) for j in range(N_T)]  # 3.5 noise stds; targets 3 and 0 are 1.56 apart
    p_det = model.detection_prob(state, torch.tensor(action))[slot].double()
    mass = (1 - p_det) * _slot_integral(model, state, action, slot, regions=regions)
    n = 60000
    o = model.observe(state.expand(n, 20), torch.full((n,), action), gen(6))
    det = o[:, 2 + 3 * slot] > 0.5
    xy = o[:, 3 + 3 * slot: 5 + 3 * slot]
    dist = torch.linalg.vector_norm(xy.unsqueeze(-2) - tp, dim=-1)  # [n, 4]
    freq = torch.stack([(det & (dist[:, j] < 0.7)).double().mean() for j in range(N_T)])
    se = torch.sqrt(mass * (1 - mass) / n)
    assert ((freq - mass).abs() <= 4 * se + 1e-4).all(), (freq, mass)
    # the swap rate among detections is the paper's 30%, and its partners follow w_ij
    swapped = det & (dist.argmin(-1) != slot)
    rate = swapped.sum() / det.sum()
    assert rate.item() == pytest.approx(0.3, abs=4 * math.sqrt(0.21 / det.sum().item()))
    w = model.swap_log_weights(tp)[slot].exp()
    torch.testing.assert_close(freq[:3] / freq.sum(), 0.3 * w[:3].double(), atol=0.01, rtol=0)
    # reports of the own target scatter with the confusion-zone noise 0.2
    own = xy[det & ~swapped] - tp[slot]
    assert own.std(0).sub(0.2).abs().max() < 0.01


def test_blind_zone_targets_are_never_detected(model):
    s = make_state(agent=(5.5, 7.5), targets=((9.0, 8.0), (8.0, 7.0), (2.5, 2.5), (2.5, 7.5)))
    o = model.observe(s.expand(5000, 20), torch.zeros(5000, dtype=torch.long), gen(7))
    assert o[:, 2].sum() == 0 and o[:, 5].sum() == 0  # targets 0 and 1 are in the blind zone
    # a detection of a blind-zone target is extremely unlikely but has a finite log-density
    assert (model.in_view_prob(s, torch.tensor(0))[:2] > 0.99).all()  # in view: the zone hides them
    lp = model.observation_log_prob(slot_obs(s[0:2], 0, (9.0, 8.0)), s, torch.tensor(0))
    assert torch.isfinite(lp) and lp < -20


def test_score_is_finite_everywhere(model):
    g = gen(8)
    n = 400
    s = model.initial_state((n,), g)
    a = torch.randint(0, 4, (n,), generator=g)
    o = model.observe(model.transition(s, a, g), a, g)
    x = s + 3.0 * torch.randn(s.shape, generator=g)  # far from the truth, anywhere on (and off) the map
    x[0, 4:6] = torch.tensor([8.0, 8.0])  # deep in the blind zone
    x[1, 4:6] = torch.tensor([5.0, 5.0])  # the corner where all four zones meet
    x[2, 4:6] = x[2, 0:2]  # a target on the agent
    x[3, 8:10] = x[3, 4:6]  # two coincident targets
    x[4, 4:20:4] = 8.5  # every target in the blind zone
    x[4, 5:20:4] = 8.5
    x[5] = 1e3  # very far away
    x.requires_grad_(True)
    lp = model.observation_log_prob(o, x, a) + model.transition_log_prob(x, s, a)
    (score,) = torch.autograd.grad(lp.sum(), x)
    assert torch.isfinite(lp).all() and torch.isfinite(score).all()
    # the score of the blind-zone particle is also finite when that target was reported
    o2 = o[0].clone()
    o2[2:5] = torch.tensor([1.0, 8.0, 8.0])
    (sc,) = torch.autograd.grad(model.observation_log_prob(o2, x[0], a[0]), x)
    assert torch.isfinite(sc).all()


def test_log_density_prefers_the_truth(model):
    g = gen(9)
    s = model.initial_state((2000,), g)
    a = torch.randint(0, 4, (2000,), generator=g)
    o = model.observe(s, a, g)
    wrong = s.clone()
    wrong[:, 4:20] = wrong[:, 4:20].roll(4, dims=-1)  # permute the targets
    assert model.observation_log_prob(o, s, a).mean() > model.observation_log_prob(o, wrong, a).mean()


# ---------------------------------------------------------------------------------------------
# reward, termination, error metric
# ---------------------------------------------------------------------------------------------


def test_reward_terminal_and_errors(model):
    s = make_state(agent=(9.0, 8.7), targets=((9.2, 8.7), (7.5, 2.5), (9.0, 9.0), (2.5, 7.5)))
    a = torch.tensor(0)
    # 0.1 · 0.3 distance, 0.05 step, two targets within 0.5
    assert model.reward(s, a, s).item() == pytest.approx(-0.1 * 0.3 - 0.05 - 2.0, abs=1e-5)
    assert bool(model.is_terminal(s))
    assert not bool(model.is_terminal(make_state(agent=(8.0, 8.0))))
    est = s.clone()
    est[4] += 3.0  # target 0 off by (3, 4): error 5
    est[5] += 4.0
    est[16] += 2.0  # target 3 off by 2
    est[0] += 1.0  # the agent does not count
    assert model.target_position_error(est, s).item() == pytest.approx((5.0 + 2.0) / 4)
    assert model.agent_position_error(est, s).item() == pytest.approx(1.0)
    assert model.distance_to_goal(s).item() == pytest.approx(0.3, abs=1e-5)
