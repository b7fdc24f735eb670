"""Tests of the gymnasium wrapper that returns the particle belief as the observation."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import escort_rl.envs  # noqa: F401  (registers the gymnasium ids)
from escort_rl.belief import ESCORTFilter, SIRFilter
from escort_rl.envs import BeliefObservation
from escort_rl.models import KidnappedRobot20D, LightDark10D

LIGHTDARK = "escort_rl/LightDark10D-v0"
KIDNAPPED = "escort_rl/KidnappedRobot20D-v0"
MTT = "escort_rl/MultiTargetTracking20D-v0"
N = 16

# check_env warns about these and nothing else: a wrapper is checked (the brief allows it), and the
# Box bounds are infinite by design (as for the unwrapped POMDPGymEnv)
EXPECTED_WARNINGS = ("different from the unwrapped version", "infinity")


def make(env_id: str = LIGHTDARK, filt=None, n: int = N, **kwargs) -> BeliefObservation:
    return BeliefObservation(gym.make(env_id), SIRFilter() if filt is None else filt, n, **kwargs)


def run(env: BeliefObservation, seed: int, actions) -> list[dict]:
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for a in actions:
        obs, *_ = env.step(a)
        out.append(obs)
    return out


# ---------------------------------------------------------------------------------------------
# gymnasium's env checker
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "env_id, filt",
    [
        (LIGHTDARK, SIRFilter()),
        (LIGHTDARK, ESCORTFilter(num_steps=5)),
        (KIDNAPPED, SIRFilter()),
        (KIDNAPPED, ESCORTFilter(num_steps=5)),
        (MTT, SIRFilter()),
        (MTT, ESCORTFilter(num_steps=5)),
    ],
    ids=["lightdark-sir", "lightdark-escort", "kidnapped-sir", "kidnapped-escort", "mtt-sir", "mtt-escort"],
)
def test_check_env(env_id, filt):
    env = make(env_id, filt)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    unexpected = [str(w.message) for w in caught if not any(s in str(w.message) for s in EXPECTED_WARNINGS)]
    assert not unexpected, unexpected
    env.close()


def test_spec_recreates_wrapper():
    """The constructor arguments are recorded, so ``env.spec.make()`` rebuilds the whole stack
    (check_env's close check relies on it)."""
    env = make(LIGHTDARK, n=8)
    spec = env.spec
    assert spec.additional_wrappers[-1].name == "BeliefObservation"
    rebuilt = spec.make()
    assert isinstance(rebuilt, BeliefObservation)
    obs, _ = rebuilt.reset(seed=1)
    assert obs["particles"].shape == (8, 10)
    np.testing.assert_array_equal(obs["particles"], env.reset(seed=1)[0]["particles"])


# ---------------------------------------------------------------------------------------------
# spaces, shapes and dtypes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("env_id, d", [(LIGHTDARK, 10), (KIDNAPPED, 20), (MTT, 20)])
def test_observation_space_and_dtypes(env_id, d):
    env = make(env_id)
    space = env.observation_space
    assert isinstance(space, gym.spaces.Dict)
    assert set(space.spaces) == {"particles", "log_weights"}
    assert space["particles"].shape == (N, d) and space["particles"].dtype == np.float32
    assert space["log_weights"].shape == (N,) and space["log_weights"].dtype == np.float32
    assert np.all(space["particles"].low == -np.inf) and np.all(space["particles"].high == np.inf)
    assert env.action_space == env.unwrapped.action_space

    obs, info = env.reset(seed=0)
    assert "true_state" in info
    for o in [obs, env.step(env.action_space.sample())[0]]:
        assert space.contains(o)
        assert o["particles"].dtype == np.float32 and o["particles"].shape == (N, d)
        assert o["log_weights"].dtype == np.float32 and o["log_weights"].shape == (N,)
        assert np.isfinite(o["particles"]).all()
        np.testing.assert_allclose(np.logaddexp.reduce(o["log_weights"].astype(np.float64)), 0.0, atol=1e-5)
    # the prior is uniform
    np.testing.assert_allclose(obs["log_weights"], -np.log(N), rtol=1e-6)
    assert env.belief.particles.shape == (N, d)


def test_returned_arrays_are_copies():
    env = make()
    obs, _ = env.reset(seed=0)
    before = obs["particles"].copy()
    env.step(0)
    obs["particles"][:] = 123.0  # writing into an old observation must not touch the belief
    np.testing.assert_array_equal(env.reset(seed=0)[0]["particles"], before)


# ---------------------------------------------------------------------------------------------
# determinism and pass-through
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("filt", [SIRFilter(), ESCORTFilter(num_steps=5)], ids=["sir", "escort"])
def test_same_seed_same_particles(filt):
    actions = [1, 3, 0]
    a = run(make(filt=filt), 7, actions)
    b = run(make(filt=filt), 7, actions)
    for oa, ob in zip(a, b):
        np.testing.assert_array_equal(oa["particles"], ob["particles"])
        np.testing.assert_array_equal(oa["log_weights"], ob["log_weights"])
    # resetting the same wrapper with the same seed replays it too
    env = make(filt=filt)
    run(env, 3, actions)
    c = run(env, 7, actions)
    np.testing.assert_array_equal(a[-1]["particles"], c[-1]["particles"])

    d = run(make(filt=filt), 8, actions)
    assert not np.allclose(a[0]["particles"], d[0]["particles"])
    assert not np.allclose(a[-1]["particles"], d[-1]["particles"])


def test_constructor_seed_and_unseeded_resets():
    env = make(seed=5)
    first = env.reset()[0]["particles"]
    np.testing.assert_array_equal(first, make().reset(seed=5)[0]["particles"])
    # later unseeded resets continue the stream: a fresh prior each episode
    second = env.reset()[0]["particles"]
    assert not np.allclose(first, second)
    # and a wrapper with no seed at all still works
    assert make().reset()[0]["particles"].shape == (N, 10)


def test_passes_reward_termination_and_info_through():
    """The belief's randomness is separate from the env's: the inner trajectory equals the plain
    env's for the same seed and actions."""
    wrapped, plain = make(), gym.make(LIGHTDARK)
    (_, info_w), (_, info_p) = wrapped.reset(seed=11), plain.reset(seed=11)
    np.testing.assert_array_equal(info_w["true_state"], info_p["true_state"])
    for a in [0, 2, 5, 9, 4]:
        _, r_w, term_w, trunc_w, info_w = wrapped.step(a)
        _, r_p, term_p, trunc_p, info_p = plain.step(a)
        assert (r_w, term_w, trunc_w) == (r_p, term_p, trunc_p)
        assert isinstance(r_w, float) and isinstance(term_w, bool) and isinstance(trunc_w, bool)
        np.testing.assert_array_equal(info_w["true_state"], info_p["true_state"])


def test_explicit_model_and_unwrapped_env():
    model = LightDark10D()
    env = BeliefObservation(gym.make(LIGHTDARK).unwrapped, SIRFilter(), N, model=model)
    assert env.model is model
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(np.int64(2))  # numpy integer actions, as from Discrete.sample()
    assert obs["particles"].shape == (N, 10)


def test_belief_tracks_state_with_sir():
    """The filter really gets the observations: after 10 steps the SIR belief mean is nearer the
    true position than the prior mean was (averaged over a few seeds)."""
    env = make(n=256)
    prior_errs, post_errs = [], []
    for seed in range(3):
        obs, info = env.reset(seed=seed)
        prior_errs.append(np.linalg.norm(obs["particles"].mean(0)[:5] - info["true_state"][:5]))
        for _ in range(10):
            obs, _, _, _, info = env.step(0)
        post_errs.append(np.linalg.norm(env.belief.mean().numpy()[:5] - info["true_state"][:5]))
    assert np.mean(post_errs) < 0.8 * np.mean(prior_errs), (prior_errs, post_errs)


# ---------------------------------------------------------------------------------------------
# bad arguments
# ---------------------------------------------------------------------------------------------


class BoxActionEnv(gym.Env):
    """A minimal env with continuous actions (not usable by the filters)."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (5,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(5, np.float32), {}

    def step(self, action):
        return np.zeros(5, np.float32), 0.0, False, False, {}


def _one_line_error(fn, match: str) -> str:
    with pytest.raises(ValueError, match=match) as err:
        fn()
    assert "\n" not in str(err.value)
    return str(err.value)


@pytest.mark.parametrize("n", [0, -3, 2.5, True, "16"])
def test_bad_num_particles(n):
    _one_line_error(lambda: make(n=n), r"^num_particles: expected a positive int")


def test_non_discrete_env():
    msg = _one_line_error(lambda: BeliefObservation(BoxActionEnv(), SIRFilter(), N, model=LightDark10D()),
                          r"^env: expected a Discrete action space")
    assert "Box" in msg


def test_env_without_model():
    _one_line_error(lambda: BeliefObservation(BoxActionEnv(), SIRFilter(), N), r"^model: .*pass model=")


def test_model_mismatch():
    # KidnappedRobot20D has 4 actions, LightDark10D's env 10
    msg = _one_line_error(lambda: make(LIGHTDARK, model=KidnappedRobot20D()), r"^model: n_actions is 4")
    assert "Discrete(10)" in msg


def test_model_obs_dim_mismatch():
    # same number of actions, different observation size
    _one_line_error(lambda: BeliefObservation(gym.make(KIDNAPPED), SIRFilter(), N, model=_FourActionLightDark()),
                    r"^model: obs_dim is 5")


def test_not_a_model_or_filter_or_env():
    _one_line_error(lambda: make(model=object()), r"^model: not a POMDP model")
    _one_line_error(lambda: BeliefObservation(gym.make(LIGHTDARK), object(), N), r"^filter: ")
    _one_line_error(lambda: BeliefObservation("LightDark", SIRFilter(), N), r"^env: expected a gymnasium.Env")
    _one_line_error(lambda: make(seed=-1), r"^seed: ")


def test_step_before_reset():
    with pytest.raises(RuntimeError, match="before reset"):
        BeliefObservation(gym.make(LIGHTDARK).unwrapped, SIRFilter(), N).step(0)


class _FourActionLightDark(LightDark10D):
    """LightDark10D with the action count of the kidnapped robot (for the obs_dim check)."""

    def __init__(self) -> None:
        super().__init__()
        self.n_actions = 4


# ---------------------------------------------------------------------------------------------
# episodes and a CleanRL-style consumer
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("env_id", [LIGHTDARK, MTT])
def test_random_action_episode(env_id):
    env = BeliefObservation(gym.make(env_id, max_episode_steps=15), SIRFilter(), N)
    env.action_space.seed(0)
    obs, _ = env.reset(seed=0)
    steps, done = 0, False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs) and np.isfinite(reward)
        done = terminated or truncated
        steps += 1
    assert steps <= 15
    assert truncated or terminated


class BeliefPolicy(torch.nn.Module):
    """A tiny DeepSets-style policy on a weighted particle set: logits [B, n_actions]."""

    def __init__(self, d: int, n_actions: int) -> None:
        super().__init__()
        self.phi = torch.nn.Sequential(torch.nn.Linear(d, 32), torch.nn.Tanh())
        self.head = torch.nn.Linear(32, n_actions)

    def forward(self, particles: torch.Tensor, log_weights: torch.Tensor) -> torch.Tensor:
        w = torch.softmax(log_weights, -1).unsqueeze(-1)  # [B, N, 1]
        return self.head((w * self.phi(particles)).sum(-2))


def test_cleanrl_style_loop():
    """A few steps of a CleanRL-style loop: a vector env of wrapped envs, numpy obs -> torch,
    sample actions, step, and one policy-gradient update."""
    num_envs, num_steps = 2, 4
    envs = gym.vector.SyncVectorEnv(
        [lambda: BeliefObservation(gym.make(LIGHTDARK, max_episode_steps=3), SIRFilter(), N) for _ in range(num_envs)]
    )
    assert isinstance(envs.single_observation_space, gym.spaces.Dict)
    d = envs.single_observation_space["particles"].shape[-1]
    policy = BeliefPolicy(d, int(envs.single_action_space.n))
    optim = torch.optim.Adam(policy.parameters(), lr=1e-3)

    obs, _ = envs.reset(seed=0)
    log_probs, rewards = [], []
    for _ in range(num_steps):  # crosses an episode boundary: the vector env autoresets unseeded
        particles = torch.as_tensor(obs["particles"])  # [num_envs, N, d], float32
        log_w = torch.as_tensor(obs["log_weights"])
        assert particles.shape == (num_envs, N, d) and particles.dtype == torch.float32
        dist = torch.distributions.Categorical(logits=policy(particles, log_w))
        action = dist.sample()
        log_probs.append(dist.log_prob(action))
        obs, reward, terminated, truncated, _ = envs.step(action.numpy())
        rewards.append(torch.as_tensor(reward, dtype=torch.float32))
    loss = -(torch.stack(log_probs) * torch.stack(rewards)).mean()
    optim.zero_grad()
    loss.backward()
    optim.step()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in policy.parameters())
    envs.close()
