"""POPGym's CartPole and Pendulum models against ``popgym`` itself, step by step: the next state, the
termination, the reward and the noiseless observation from random states; the clipped observation
noise's law against many popgym draws from one state; the start distribution against popgym's
resets; and the protocol (attributes, batching, densities finite and differentiable at the bounds).

Every statistical check is a Hoeffding bound at ``delta = 1e-9`` (a union of a few stays far below 1e-6)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

pytest.importorskip("popgym")

import gymnasium as gym  # noqa: E402

from conftest import gen, hoeffding  # noqa: E402
from escort_rl.envs.popgym import POPGYM_CONTROL, import_popgym, popgym_model  # noqa: E402
from escort_rl.models import POPGymCartPole, POPGymPendulum, check_model, popgym_model_class  # noqa: E402
from escort_rl.models.clipped_gaussian import clipped_gaussian_log_prob  # noqa: E402
from escort_rl.models.popgym_cartpole import CARTPOLE_TASKS, THETA_THRESHOLD, X_THRESHOLD  # noqa: E402
from escort_rl.models.popgym_pendulum import PENDULUM_TASKS  # noqa: E402

CARTPOLE_NAMES, PENDULUM_NAMES = sorted(CARTPOLE_TASKS), sorted(PENDULUM_TASKS)


def popgym_env(name: str, seed: int):
    """The raw popgym env of ``name`` (no gymnasium wrappers), reset with ``seed``."""
    import_popgym()
    env = gym.make(POPGYM_CONTROL[name]).unwrapped
    env.reset(seed=seed)
    return env


def step_from(env, state: np.ndarray, action):
    """popgym's step from ``state`` (set as the env's internal state, in float64):
    ``(next state, observation, reward, terminated)``."""
    env.state = np.asarray(state, dtype=np.float64)
    obs, reward, terminated, _, _ = env.step(action)
    return np.asarray(env.state, dtype=np.float64), np.asarray(obs), float(reward), bool(terminated)


def popgym_steps(env, states: torch.Tensor, actions: torch.Tensor):
    """popgym's step from each row of ``states`` under each action, a reset before each (so every
    step is the first of its episode): stacked next states, observations, rewards and terminations."""
    rows = []
    for s, a in zip(states.double().numpy(), actions.numpy()):
        env.reset()
        rows.append(step_from(env, s, a if a.ndim else int(a)))
    nxt, obs, rew, term = zip(*rows)
    return (torch.tensor(np.stack(nxt)), torch.tensor(np.stack(obs)), torch.tensor(rew, dtype=torch.float64),
            torch.tensor(term))


# ------------------------------------------------------------------------------ step by step
def random_cartpole_states(n: int, g: torch.Generator) -> torch.Tensor:
    """States inside the termination box (some step out of it), velocities up to ±2."""
    high = torch.tensor([X_THRESHOLD, 2.0, THETA_THRESHOLD, 2.0])
    return high * (2 * torch.rand(n, 4, generator=g) - 1)


@pytest.mark.parametrize("name", CARTPOLE_NAMES)
def test_cartpole_steps_as_popgym(name, per_test_seed):
    g, n = gen(per_test_seed), 300
    states, actions = random_cartpole_states(n, g), torch.randint(0, 2, (n,), generator=g)
    nxt, obs, rew, term = popgym_steps(popgym_env(name, per_test_seed), states, actions)
    model = POPGymCartPole.from_name(name, process_noise=0.0)
    mean = model.transition_mean(states, actions)
    torch.testing.assert_close(mean, nxt.float(), rtol=1e-5, atol=1e-5)
    assert torch.equal(model.transition(states, actions, g), mean)  # no process noise: POPGym's step
    # termination, away from float rounding at the thresholds
    clear = ((nxt[:, 0].abs() - X_THRESHOLD).abs() > 1e-5) & ((nxt[:, 2].abs() - THETA_THRESHOLD).abs() > 1e-5)
    assert clear.float().mean() > 0.99 and term.any() and not term.all()
    assert torch.equal(model.is_terminal(mean)[clear], term[clear])
    # the reward: 1/L on every step, the terminating one included
    torch.testing.assert_close(model.reward(states, actions, mean).double(), rew, rtol=0, atol=1e-7)
    if model.obs_noise == 0:  # the stateless tasks observe [x', θ'] exactly
        torch.testing.assert_close(model.observe(mean, actions, g), obs.float(), rtol=1e-5, atol=1e-5)


def test_cartpole_pays_minus_one_after_termination():
    env, model = popgym_env("PositionOnlyCartPoleEasy", 0), POPGymCartPole.from_name("PositionOnlyCartPoleEasy")
    s0 = np.array([3.0, 1.0, 0.0, 0.0])  # beyond the box, moving out
    s1, _, r1, t1 = step_from(env, s0, 1)
    with pytest.warns(UserWarning, match="already returned terminated"):  # gymnasium's warning, as it pays 0
        _, _, r2, t2 = step_from(env, s1, 1)
    assert t1 and t2 and r1 == pytest.approx(1 / 200) and r2 == -1.0
    s0, s1 = torch.tensor(s0, dtype=torch.float32), torch.tensor(s1, dtype=torch.float32)
    a = torch.tensor(1)
    assert model.reward(s0, a, s1).item() == -1.0  # from a terminal state into a terminal one
    assert model.reward(torch.zeros(4), a, s1).item() == pytest.approx(1 / 200)  # the terminating step


def random_pendulum_inputs(n: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Unwrapped angles over three turns, speeds past the clip of 8, torques past the clip of 2."""
    states = torch.tensor([3 * math.pi, 9.0]) * (2 * torch.rand(n, 2, generator=g) - 1)
    return states, 2.5 * (2 * torch.rand(n, 1, generator=g) - 1)


@pytest.mark.parametrize("name", PENDULUM_NAMES)
def test_pendulum_steps_as_popgym(name, per_test_seed):
    g, n = gen(per_test_seed), 300
    states, actions = random_pendulum_inputs(n, g)
    nxt, obs, rew, term = popgym_steps(popgym_env(name, per_test_seed), states, actions)
    model = POPGymPendulum.from_name(name, process_noise=0.0)
    mean = model.transition_mean(states, actions)
    torch.testing.assert_close(mean, nxt.float(), rtol=1e-5, atol=1e-5)
    assert (nxt[:, 1].abs() == 8).any() and (nxt[:, 0].abs() > math.pi).any()  # clipped speeds, unwrapped angles
    assert torch.equal(model.transition(states, actions, g), mean)
    assert not term.any() and not model.is_terminal(mean).any()
    torch.testing.assert_close(model.reward(states, actions, mean).double(), rew, rtol=0, atol=1e-6)
    within = states[:, 1].abs() <= 8  # POPGym's range: a speed past the clip costs more than its lowest reward
    limit = 1 / model.max_episode_length * (1 + 1e-6)
    assert (rew[within].abs() <= limit).all() and (model.reward(states, actions, mean)[within].abs() <= limit).all()
    if model.obs_noise == 0:  # the stateless tasks observe [cos θ', sin θ'] exactly
        torch.testing.assert_close(model.observe(mean, actions, g), obs.float(), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("name", [*CARTPOLE_NAMES, *PENDULUM_NAMES])
def test_from_name_reads_popgym_parameters(name):
    env = popgym_env(name, 0)
    model = popgym_model(name)
    assert model.max_episode_length == env.max_episode_length
    assert model.obs_noise == pytest.approx(float(np.max(getattr(env, "noise_sigma", 0.0))))
    assert type(model) is (POPGymCartPole if "CartPole" in name else POPGymPendulum)
    with pytest.raises(ValueError, match="unknown POPGym .* task 'Pendulum'"):
        type(model).from_name("Pendulum")
    assert popgym_model_class(f"popgym-{name}-v0") is type(model)  # the one map from a task to its model


def test_a_task_without_a_model_is_named():
    with pytest.raises(ValueError, match="unknown POPGym control task 'RepeatPreviousEasy'; choose one of "
                                         "NoisyPositionOnlyCartPoleEasy"):
        popgym_model_class("RepeatPreviousEasy")


# ------------------------------------------------------------------------------ the observation law
def popgym_observations(name: str, state: np.ndarray, action, n: int, seed: int) -> torch.Tensor:
    """``n`` popgym observations of the one next state of ``(state, action)``: the same step over and
    over, each drawing fresh noise from the env's ``np_random`` (seeded once)."""
    env = popgym_env(name, seed)
    return torch.tensor(np.stack([step_from(env, state, action)[1] for _ in range(n)])).float()


def check_observation_law(model, drawn: torch.Tensor, s_next: torch.Tensor, g: torch.Generator) -> None:
    """popgym's observations ``drawn`` ``[n, 2]`` of ``s_next`` against the model: per coordinate, the
    mass clipped to each bound against ``exp(observation_log_prob)`` there, and the mean, the second
    moment and the CDF at three points against the model's own draws (two-sample)."""
    n, low, high = drawn.shape[0], model.obs_low, model.obs_high
    ours = model.observe(s_next.expand(n, -1), None, g)
    width = (high - low).tolist()
    mean = model.observation_mean(s_next)
    peak = -math.log(model.observation_std) - 0.5 * math.log(2 * math.pi)  # the density at the mean
    for i in range(2):
        for bound in (low[i], high[i]):
            o = mean.clone()
            o[i] = bound  # the other coordinate at its mean, where its density is ``peak``
            mass = math.exp(model.observation_log_prob(o, s_next, None).item() - peak)
            seen = (drawn[:, i] == bound).double().mean().item()
            assert abs(seen - mass) <= hoeffding(n), (i, bound.item(), seen, mass)
        for moment in (1, 2):  # in [low, high] or [0, max|bound|²]: scaled to [0, 1]
            span = width[i] if moment == 1 else max(low[i].abs(), high[i].abs()).item() ** 2
            diff = (drawn[:, i].double() ** moment).mean() - (ours[:, i].double() ** moment).mean()
            assert abs(diff.item()) <= 2 * span * hoeffding(n), (i, moment, diff.item())
        for t in (mean[i] - model.obs_noise, mean[i], mean[i] + model.obs_noise):
            diff = (drawn[:, i] <= t).double().mean() - (ours[:, i] <= t).double().mean()
            assert abs(diff.item()) <= 2 * hoeffding(n), (i, t.item(), diff.item())


def test_noisy_cartpole_observation_law(per_test_seed):
    """Hard (σ = 0.3), the pole near its limit: about a quarter of the angles are clipped to 0.4189."""
    name, n = "NoisyPositionOnlyCartPoleHard", 40_000
    model, state = POPGymCartPole.from_name(name), np.array([-2.3, 0.0, 0.2, 0.1])
    drawn = popgym_observations(name, state, 1, n, per_test_seed)
    s_next = model.transition_mean(torch.tensor(state, dtype=torch.float32), torch.tensor(1))
    assert 0.15 < (drawn[:, 1] == model.obs_high[1]).float().mean() < 0.35
    check_observation_law(model, drawn, s_next, gen(per_test_seed))


def test_noisy_pendulum_observation_law(per_test_seed):
    """Medium (σ = 0.2), near the top: cos θ' ≈ 0.96, clipped to 1 about 40% of the time."""
    name, n = "NoisyPositionOnlyPendulumMedium", 40_000
    model, state, action = POPGymPendulum.from_name(name), np.array([0.3, -1.0]), np.array([0.5], dtype=np.float32)
    drawn = popgym_observations(name, state, action, n, per_test_seed)
    s_next = model.transition_mean(torch.tensor(state, dtype=torch.float32), torch.tensor(action))
    assert 0.3 < (drawn[:, 0] == 1.0).float().mean() < 0.5
    check_observation_law(model, drawn, s_next, gen(per_test_seed))


def test_the_censored_density_integrates_to_one():
    """Inside the box by the trapezoid rule, plus the two point masses, for means inside, on and
    beyond a bound."""
    low, high, std = torch.tensor([-1.0], dtype=torch.float64), torch.tensor([1.0], dtype=torch.float64), 0.3
    grid = torch.linspace(-1, 1, 20_001, dtype=torch.float64)[:, None]
    grid[0], grid[-1] = -1 + 1e-12, 1 - 1e-12  # the ends of the open interval, where the density is continuous
    for m in (0.0, 0.9, 1.0, 1.7, -3.0):
        mean = torch.tensor([m], dtype=torch.float64)
        inside = torch.trapezoid(clipped_gaussian_log_prob(grid, mean, std, low, high).exp(), grid[:, 0])
        ends = clipped_gaussian_log_prob(torch.stack([low, high]), mean, std, low, high).exp().sum()
        assert (inside + ends).item() == pytest.approx(1.0, abs=1e-6), m


# ------------------------------------------------------------------------------ the protocol
def test_protocol_attributes():
    cart, pend = POPGymCartPole(), POPGymPendulum()
    for model in (cart, pend):
        check_model(model)
        assert (model.obs_dim, model.max_episode_length) == (2, 200)
    assert (cart.state_dim, cart.n_actions) == (4, 2) and not hasattr(cart, "action_dim")
    assert pend.state_dim == 2 and pend.action_dim == 1 and not hasattr(pend, "n_actions")
    for bound, value in ((pend.action_low, -2.0), (pend.action_high, 2.0)):
        assert bound.dtype == torch.float32 and bound.tolist() == [value]


@pytest.mark.parametrize("kind", ["cartpole", "pendulum"])
def test_methods_batch_over_leading_dimensions(kind, per_test_generator):
    g = per_test_generator
    model = POPGymCartPole(obs_noise=0.2) if kind == "cartpole" else POPGymPendulum(obs_noise=0.2)
    d, lead = model.state_dim, (3, 5)
    a = torch.randint(0, 2, lead, generator=g) if kind == "cartpole" else 4 * torch.rand(*lead, 1, generator=g) - 2
    s = model.initial_state(lead, g)
    s_next = model.transition(s, a, g)
    o = model.observe(s_next, a, g)
    assert s.shape == s_next.shape == (*lead, d) and o.shape == (*lead, 2)
    assert model.initial_belief(lead, 7, g).shape == (*lead, 7, d)
    assert model.transition_mean(s, a).shape == (*lead, d) and model.transition_scale_tril().shape == (d, d)
    for out in (model.transition_log_prob(s_next, s, a), model.observation_log_prob(o, s_next, a),
                model.reward(s, a, s_next)):
        assert out.shape == lead and out.dtype == torch.float32 and torch.isfinite(out).all()
    assert model.is_terminal(s_next).shape == lead and model.is_terminal(s_next).dtype == torch.bool
    # particles [3, 5, 7, d] against one observation per batch element [3, 5, 1, 2]
    particles = model.initial_belief(lead, 7, g)
    assert model.observation_log_prob(o.unsqueeze(-2), particles, None).shape == (*lead, 7)
    # the transition density is the process noise's
    std = torch.diagonal(model.transition_scale_tril())
    expected = torch.distributions.Normal(model.transition_mean(s, a), std).log_prob(s_next).sum(-1)
    torch.testing.assert_close(model.transition_log_prob(s_next, s, a), expected)


@pytest.mark.parametrize("kind", ["cartpole", "pendulum"])
def test_process_noise_is_the_scale_tril(kind, per_test_generator):
    """``(s' − mean)/std`` is standard normal: about 68.27% within ±1 per coordinate."""
    model = POPGymCartPole() if kind == "cartpole" else POPGymPendulum()
    n = 20_000
    s = model.initial_state((n,), per_test_generator)
    a = torch.ones(n, dtype=torch.int64) if kind == "cartpole" else torch.ones(n, 1)
    z = (model.transition(s, a, per_test_generator) - model.transition_mean(s, a)) / torch.diagonal(
        model.transition_scale_tril())
    inside = (z.abs() <= 1).double().mean(0)
    assert ((inside - 0.682689492).abs() <= hoeffding(n)).all(), inside


def test_no_process_noise_gives_no_transition_density():
    for model in (POPGymCartPole(process_noise=0.0), POPGymPendulum(process_noise=0.0)):
        s = model.initial_state((2,))
        a = torch.zeros(2, dtype=torch.int64) if model.state_dim == 4 else torch.zeros(2, 1)
        with pytest.raises(ValueError, match=r"process_noise: is 0.*a filter needs process_noise > 0"):
            model.transition_log_prob(s, s, a)
        assert not model.transition_scale_tril().any()
    with pytest.raises(ValueError, match="obs_noise_floor: is 0 on a noiseless task"):
        POPGymPendulum(obs_noise_floor=0.0).observation_log_prob(torch.ones(2), torch.zeros(2), None)
    with pytest.raises(ValueError, match="POPGymCartPole.process_noise: must be >= 0"):
        POPGymCartPole(process_noise=-0.1)


@pytest.mark.parametrize("kind", ["cartpole", "pendulum"])
def test_observation_log_prob_is_finite_and_differentiable_at_the_bounds(kind):
    """Observations on the bounds (the clipped ones), for states whose mean lies inside, on and far
    beyond the bound: finite log densities and gradients, equal to finite differences (``gradcheck``
    in float64), and pointing the right way where the mean is not far beyond the bound (moving it
    towards the bound it was clipped to raises that mass; far beyond, the mass is 1 and flat)."""
    if kind == "cartpole":
        model = POPGymCartPole(obs_noise=0.3)
        high = model.obs_high
        states = torch.tensor([[0.0, 0, 0.0, 0], [4.8, 0, 0.4189, 0], [50.0, 0, 30.0, 0], [-50.0, 0, -30.0, 0]])
        o = torch.stack([high, high, high, -high])
        direction = torch.tensor([[1.0, 0, 1, 0], [1.0, 0, 1, 0], [0.0, 0, 0, 0], [0.0, 0, 0, 0]])
    else:
        model = POPGymPendulum(obs_noise=0.1)
        states = torch.tensor([[0.3, 0.0], [0.0, 0.0], [math.pi / 2, 0.0], [-2.0, 0.0], [40.0, 0.0]])
        # cos at 1 and sin at its mean (lowering θ raises cos), then cos at 1, sin at 1, both at -1
        o = torch.tensor([[1.0, math.sin(0.3)], [1.0, 0.0], [0.0, 1.0], [-1.0, -1.0], [1.0, 1.0]])
        direction = torch.tensor([[-1.0, 0.0]] + [[0.0, 0.0]] * 4)
    states.requires_grad_(True)
    logp = model.observation_log_prob(o, states, None)
    (grad,) = torch.autograd.grad(logp.sum(), states)
    assert torch.isfinite(logp).all() and torch.isfinite(grad).all(), (logp, grad)
    strict = direction.abs().sum(-1) > 0
    assert ((grad * direction).sum(-1) > 0)[strict].all(), grad
    s64 = states.detach().double().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda s: model.observation_log_prob(o.double(), s, None), (s64,))
    # the density alone, mean on and around the bounds
    lo, hi = model.obs_low.double(), model.obs_high.double()
    mean = torch.stack([hi - 0.05, hi, hi + 2.0]).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda m: clipped_gaussian_log_prob(hi.expand(3, -1), m, 0.2, lo, hi), (mean,))
    assert torch.autograd.gradcheck(lambda m: clipped_gaussian_log_prob(lo.expand(3, -1), m, 0.2, lo, hi), (mean,))


# ------------------------------------------------------------------------------ the start
@pytest.mark.parametrize("name", ["PositionOnlyCartPoleEasy", "NoisyPositionOnlyPendulumHard"])
def test_initial_states_match_popgym_resets(name, per_test_seed):
    """popgym's reset states and the model's lie in the same box, fill it (the extremes of n uniform
    draws within 1% of its ends, which fails with probability 2·(0.99)^n ≈ 4e-9), and are uniform (as
    many in each half, within Hoeffding's bound)."""
    n = 2000
    env, model = popgym_env(name, per_test_seed), popgym_model(name)
    theirs = []
    for _ in range(n):
        env.reset()
        theirs.append(np.asarray(env.state, dtype=np.float64))
    theirs = torch.tensor(np.stack(theirs)).float()
    ours = model.initial_state((n,), gen(per_test_seed))
    high = torch.full((4,), 0.05) if "CartPole" in name else torch.tensor([math.pi, 1.0])
    for draws in (theirs, ours):
        assert (draws.abs() <= high).all()
        assert (draws.amax(0) >= 0.98 * high).all() and (draws.amin(0) <= -0.98 * high).all()
        assert ((draws > 0).double().mean(0) - 0.5).abs().max() <= hoeffding(n)
    belief = model.initial_belief((3,), 50, gen(per_test_seed))
    assert belief.shape == (3, 50, model.state_dim) and (belief.abs() <= high).all()
