"""The hidden-goal family (:class:`escort_rl.models.HiddenGoal`): its densities against brute force at low
dimension, its prior's modes, its knobs, and the controller that commits to the heaviest mode."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import hoeffding
from escort_rl.config import ConfigError, compose
from escort_rl.models import HiddenGoal, check_model
from escort_rl.planners.scripted import HeaviestModeController, scripted_controller_for


def test_sizes_and_candidates():
    m = HiddenGoal(dim=6, modes=5)
    assert (m.state_dim, m.obs_dim, m.n_actions) == (12, 12, 12)
    expected = torch.zeros(5, 6)
    for j, (axis, sign) in enumerate([(0, 1), (0, -1), (1, 1), (1, -1), (2, 1)]):
        expected[j, axis] = sign * m.params.goal_distance
    assert torch.equal(m.candidate_goals, expected)
    assert torch.equal(m.beacon, torch.tensor([0.0] * 5 + [-m.params.beacon_distance]))
    check_model(m)


def test_too_many_modes_are_refused_naming_the_field():
    with pytest.raises(ConfigError, match=r"HiddenGoal\.modes: at most 2·\(dim − 1\) = 4"):
        HiddenGoal(dim=3, modes=5)


def test_config_builds_the_family_at_any_size():
    from escort_rl.trainers.builders import build_model

    m = build_model(compose(["env=hidden_goal", "env.model.dim=20", "env.model.modes=8"]).env, "cpu")
    assert isinstance(m, HiddenGoal) and m.state_dim == 40 and m.candidate_goals.shape == (8, 20)


def test_observation_density_integrates_to_one_on_a_grid(per_test_generator):
    """Brute force at d = 2 (a 4-D observation): the density summed over a grid covering ±6σ of every
    coordinate is 1, at a state near the beacon (where the goal's reading carries the goal)."""
    m = HiddenGoal(dim=2, modes=2, beacon_distance=0.5)
    s = m.initial_state((), per_test_generator)
    s[:2] = m.beacon + 0.3
    p = m.params
    x, z = s[:2], s[2:]
    centre = torch.cat([x, m.signal(x) * z]).double()
    half = torch.tensor([6 * p.position_obs_std] * 2 + [6 * p.goal_obs_std] * 2, dtype=torch.float64)
    axes = [torch.linspace(float(c - h), float(c + h), 41, dtype=torch.float64) for c, h in zip(centre, half)]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 4)
    cell = math.prod(float(a[1] - a[0]) for a in axes)
    m64 = HiddenGoal(dim=2, modes=2, beacon_distance=0.5)
    m64.beacon = m64.beacon.double()
    total = torch.exp(m64.observation_log_prob(grid, s.double(), torch.tensor(0))).sum() * cell
    assert total.item() == pytest.approx(1.0, abs=2e-3)


def test_observations_follow_the_density(per_test_generator):
    """Draws of ``observe`` have the mean ``(x, ℓ(x) z)`` and the per-coordinate spread the density says,
    within 5 standard errors."""
    m = HiddenGoal(dim=3, modes=4, beacon_distance=1.0)
    s = m.initial_state((), per_test_generator)
    s[:3] = m.beacon + torch.tensor([0.4, -0.2, 0.5])
    n = 20000
    o = m.observe(s.expand(n, 6), torch.zeros(n, dtype=torch.long), per_test_generator)
    p = m.params
    mean = torch.cat([s[:3], m.signal(s[:3]) * s[3:]])
    std = torch.tensor([p.position_obs_std] * 3 + [p.goal_obs_std] * 3)
    assert ((o.mean(0) - mean).abs() < 5 * std / math.sqrt(n)).all()
    assert ((o.std(0) / std - 1).abs() < 5 / math.sqrt(2 * n)).all()


def test_the_goal_reading_is_noise_far_from_the_beacon():
    """Far from the beacon every candidate explains an observation as well as the true goal does: the
    posterior keeps the prior's modes."""
    m = HiddenGoal(dim=5, modes=4, beacon_distance=6.0)
    x = torch.zeros(5)
    o = torch.cat([x, torch.zeros(5)])
    states = torch.cat([x.expand(4, 5), m.candidate_goals], dim=-1)
    lp = m.observation_log_prob(o, states, torch.zeros(4, dtype=torch.long))
    assert (lp - lp[0]).abs().max() < 1e-3
    near = torch.cat([m.beacon, m.candidate_goals[2]])  # at the beacon, reading goal 2 exactly
    lp = m.observation_log_prob(near, torch.cat([m.beacon.expand(4, 5), m.candidate_goals], -1),
                                torch.zeros(4, dtype=torch.long))
    assert lp.argmax() == 2 and (lp[2] - lp).sort().values[1] > 20


def test_the_prior_weighs_every_mode_equally(per_test_generator):
    m = HiddenGoal(dim=4, modes=6)
    n = 30000
    b = m.initial_belief((), n, per_test_generator)
    shares = torch.bincount(m.mode_of(b[:, 4:]), minlength=6).float() / n
    assert (shares - 1 / 6).abs().max() < hoeffding(n)
    assert (b[:, :4].abs() <= m.params.start_spread).all()


def test_the_controller_commits_to_the_heaviest_mode():
    m = HiddenGoal(dim=3, modes=4)
    g = torch.Generator().manual_seed(0)
    belief = m.initial_belief((), 200, g)
    belief[:, :3] = 0.0
    goal_mode = m.mode_of(belief[:, 3:])
    log_w = torch.where(goal_mode == 3, 0.0, -3.0)  # mode 3 (goal −r e_1) the heaviest
    assert HeaviestModeController(m)(belief, log_w).item() == 3  # push coordinate 1 down
    # below the confidence, it heads for the beacon (−β e_2): push coordinate 2 down
    assert HeaviestModeController(m, confidence=0.99)(belief, log_w).item() == 5
    assert isinstance(scripted_controller_for(m), HeaviestModeController)
    assert HeaviestModeController(m).rule == "toward the goal of the heaviest mode of the same filter's belief"
    assert HeaviestModeController(m, confidence=0.9).rule.endswith("after the beacon while no mode weighs 0.9")


def test_with_the_true_state_the_controller_always_arrives():
    """Full information (the true state as a one-particle belief): every episode reaches its goal in
    about ``r / step`` pushes."""
    m = HiddenGoal(dim=5, modes=8)
    g = torch.Generator().manual_seed(1)
    s = m.initial_state((64,), g)
    done = torch.zeros(64, dtype=torch.bool)
    control = HeaviestModeController(m)
    for _ in range(20):
        s = torch.where(done.unsqueeze(-1), s, m.transition(s, control(s.unsqueeze(-2), None), g))
        done |= m.is_terminal(s)
    assert done.all()


def test_a_belief_policy_passes_the_belief_to_the_controller():
    from torchrl.envs import TransformedEnv

    from escort_rl.belief import SIRFilter
    from escort_rl.envs import POMDPEnv
    from escort_rl.planners import ScriptedBeliefController
    from escort_rl.transforms import BeliefTransform

    m = HiddenGoal(dim=3, modes=2)
    env = TransformedEnv(POMDPEnv(m, batch_size=(4,), seed=0), BeliefTransform(m, SIRFilter(), 32))
    td = env.rollout(5, ScriptedBeliefController(m), break_when_any_done=False)
    assert td["action"].shape == (4, 5) and td["action"].dtype == torch.int64


def test_the_benchmarks_compare_the_goal_first_and_walk_toward_the_beacon():
    """The shared trajectories of the benchmarks walk toward the beacon (half the steps push the beacon's axis
    toward it), so the beacon's signal grows along them, and the reference compares the goal part first."""
    from escort_rl.bench.trajectories import behaviour_policy, generate_trajectories
    from escort_rl.metrics.reference import state_parts

    model = HiddenGoal(dim=4, modes=4)
    assert list(state_parts(model)) == ["goal", "position"] and state_parts(model)["goal"] == (4, 5, 6, 7)
    assert behaviour_policy(model).startswith("toward the beacon")
    traj = generate_trajectories(model, 12, list(range(8)), 0)
    signal = model.signal(traj["states"][..., :4])  # [8, 13]
    assert float(signal[:, 0].max()) < 0.1 and float(signal[:, 8:].mean()) > 0.3
    actions = traj["actions"]
    assert ((actions >= 0) & (actions < model.n_actions)).all()
    toward = (actions == 2 * 3 + 1).double().mean()  # the push down the last axis, toward b = −β e_3
    assert 0.4 < float(toward) < 0.85  # about 1/2 + 1/16


def _grid_2d(centres: torch.Tensor, half: float, points: int = 401) -> tuple[torch.Tensor, float]:
    """A square grid ``[points², 2]`` covering every centre ``[K, 2]`` ± ``half``, and its cell area."""
    lo, hi = centres.min(0).values - half, centres.max(0).values + half
    axes = [torch.linspace(float(lo[i]), float(hi[i]), points, dtype=torch.float64) for i in range(2)]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
    return grid, float(axes[0][1] - axes[0][0]) * float(axes[1][1] - axes[1][0])


def test_the_rao_blackwellised_goal_update_is_bayes_rule_on_a_grid(per_test_generator):
    """Given a particle's position, the goal's Gaussian sum after one step is the grid posterior of the
    prior sum (drifted) times the goal reading's density: the same evidence, mode weights and means. Near the
    beacon, where the reading carries the goal; d = 2, two modes weighted 0.3 and 0.7."""
    m = HiddenGoal(dim=2, modes=2, beacon_distance=1.0)
    p = m.params
    x = (m.beacon.double() + torch.tensor([0.3, -0.2], dtype=torch.float64)).reshape(1, 1, 2)
    log_w = torch.log(torch.tensor([[[0.3, 0.7]]], dtype=torch.float64))
    means = torch.tensor([[[[2.9, 0.1], [-3.1, -0.05]]]], dtype=torch.float64)
    var = torch.full((1, 1, 2), 0.02, dtype=torch.float64)
    a = torch.tensor([0])
    o = torch.tensor([[0.5, -1.1, -0.4, 0.2]], dtype=torch.float64)
    x_new, lw, mu, v, log_inc = m.rao_blackwell_step(x, log_w, means, var, a, o, per_test_generator)
    pred = x + m._pushes.double()[0, :2]
    sx2, so2 = p.position_noise_std ** 2, p.position_obs_std ** 2
    position_term = -0.5 * (((o[:, :2] - pred) ** 2).sum() / (sx2 + so2) + 2 * math.log(2 * math.pi * (sx2 + so2)))
    ell = float(m.signal(x_new.float()).double())
    prior_var = 0.02 + p.goal_drift_std ** 2
    grid, cell = _grid_2d(means[0, 0], 8 * math.sqrt(prior_var))
    mode_density = torch.stack([w * torch.exp(-0.5 * ((grid - mj) ** 2).sum(-1) / prior_var) / (2 * math.pi * prior_var)
                                for w, mj in zip((0.3, 0.7), means[0, 0])])  # [2, G]
    reading = torch.exp(-0.5 * ((o[0, 2:] - ell * grid) ** 2).sum(-1) / p.goal_obs_std ** 2) \
        / (2 * math.pi * p.goal_obs_std ** 2)
    joint = mode_density * reading
    evidence = joint.sum() * cell
    assert float(log_inc[0, 0] - position_term) == pytest.approx(math.log(float(evidence)), abs=1e-4)
    post_w = joint.sum(-1) * cell / evidence
    assert torch.softmax(lw[0, 0], -1).tolist() == pytest.approx(post_w.tolist(), abs=1e-5)
    post_means = (joint[..., None] * grid).sum(1) / joint.sum(-1, keepdim=True)
    assert mu[0, 0].flatten().tolist() == pytest.approx(post_means.flatten().tolist(), abs=1e-5)
    post_var = (joint * ((grid - post_means[:, None]) ** 2).sum(-1)).sum(-1) / joint.sum(-1) / 2
    assert [float(v[0, 0, 0])] * 2 == pytest.approx(post_var.tolist(), rel=1e-4)


def test_the_fully_adapted_start_draws_the_first_position_from_its_posterior(per_test_generator):
    """Far from the beacon (the goal's reading says nothing of the position), the first step's positions
    follow the posterior of ``x₁`` given the first reading under the start box's uniform prior: per
    coordinate, ``∫ U(x₀) N(x₁; x₀ + push, σ_x²) N(o; x₁, σ_o²) dx₀`` on a grid. Mean and standard deviation
    within 5 standard errors; a reading outside the box on one coordinate."""
    m = HiddenGoal(dim=2, modes=2, beacon_distance=30.0)
    p, n = m.params, 200_000
    o = torch.tensor([[0.9, -0.1, 0.0, 0.0]], dtype=torch.float64)
    a = torch.tensor([0])  # pushes coordinate 0 by +step
    x, lw, _, _, log_inc = m.rao_blackwell_first_step(1, n, a, o, per_test_generator)
    assert float(log_inc.max() - log_inc.min()) < 1e-9  # every particle weighs the same
    x0 = torch.linspace(-p.start_spread, p.start_spread, 2001, dtype=torch.float64)
    x1 = torch.linspace(-3.0, 3.0, 6001, dtype=torch.float64)
    for c in range(2):
        push = p.step if c == 0 else 0.0
        trans = torch.exp(-0.5 * (x1[:, None] - x0[None] - push) ** 2 / p.position_noise_std ** 2).sum(1)
        dens = trans * torch.exp(-0.5 * (float(o[0, c]) - x1) ** 2 / p.position_obs_std ** 2)
        dens = dens / dens.sum()
        mean = float((dens * x1).sum())
        std = math.sqrt(float((dens * (x1 - mean) ** 2).sum()))
        draws = x[0, :, c]
        assert abs(float(draws.mean()) - mean) < 5 * std / math.sqrt(n)
        assert abs(float(draws.std()) / std - 1) < 5 / math.sqrt(2 * n)
