"""Continuous actions through the env stack: POMDPEnv's Bounded action spec and its validation, the
BeliefTransform with every filter, ParallelEnv workers, a Collector running the TanhNormal DeepSets
policy, and the gymnasium side (the registered id, POMDPGymEnv's Box and BeliefObservation)."""

from __future__ import annotations

import functools
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import Bounded
from torchrl.envs import ParallelEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

import escort_rl.envs  # noqa: F401  (registers the gymnasium ids)
from escort_rl.belief import EnKFFilter, ESCORTFilter, SIRFilter, SVGDFilter
from escort_rl.envs import BeliefObservation, POMDPEnv, check_action
from escort_rl.envs.gym_adapter import POMDPGymEnv, action_space, model_action
from escort_rl.models import LightDark10D, LightDark10DContinuous
from escort_rl.modules import DeepSetsActor, make_deepsets_policy, policy_outputs
from escort_rl.transforms import BeliefTransform

CONTINUOUS_ID = "escort_rl/LightDark10DContinuous-v0"
N = 16


# ---------------------------------------------------------------------------------------------
# Module-level factories: ParallelEnv pickles them (spawn start method).
# ---------------------------------------------------------------------------------------------


def make_belief_env(env_seed: int, filter_seed: int | None = None, batch: int = 2, num_particles: int = N,
                    max_steps: int | None = 6) -> TransformedEnv:
    model = LightDark10DContinuous()
    return TransformedEnv(POMDPEnv(model, batch_size=(batch,), seed=env_seed, max_steps=max_steps, expose_state=True),
                          BeliefTransform(model, SIRFilter(), num_particles, seed=filter_seed))


def in_box(action: torch.Tensor, model) -> bool:
    return bool(((action >= model.action_low) & (action <= model.action_high)).all())


def tanh_normal_policy(model, hidden: int = 16, seed: int = 0):
    torch.manual_seed(seed)
    n_out, box = policy_outputs(model)
    actor = DeepSetsActor(model.state_dim, n_out, hidden=hidden)
    return make_deepsets_policy(actor, action_box=box, distribution="tanh_normal")


# ---------------------------------------------------------------------------------------------
# POMDPEnv
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("batch", [(3,), (2, 2)])
def test_action_spec_is_bounded_and_the_env_passes_check_env_specs(batch):
    model = LightDark10DContinuous()
    env = POMDPEnv(model, batch_size=batch, seed=0, max_steps=5, expose_state=True)
    spec = env.action_spec
    assert isinstance(spec, Bounded)
    assert spec.shape == (*batch, 5) and spec.dtype == torch.float32
    assert torch.equal(spec.space.low, model.action_low.expand(*batch, 5))
    assert torch.equal(spec.space.high, model.action_high.expand(*batch, 5))
    check_env_specs(env)
    torch.manual_seed(0)
    td = env.rollout(5, break_when_any_done=False)  # random actions from the spec
    assert td["action"].shape == (*batch, 5, 5) and td["action"].dtype == torch.float32
    assert in_box(td["action"], model)
    assert bool(td["next", "truncated"][..., -1, :].all())


def test_a_step_follows_the_continuous_dynamics():
    model = LightDark10DContinuous()
    env = POMDPEnv(model, batch_size=(4,), seed=3, expose_state=True)
    td = env.reset()
    s0 = td["true_state"]
    a = torch.tensor([[0.1, -0.1, 0.0, 0.05, -0.02]] * 4)
    td["action"] = a
    out = env.step(td)["next"]
    s1 = out["true_state"]
    noise = s1 - model.transition_mean(s0, a)
    assert bool((noise.abs() < 6 * 0.05).all())  # process noise of std 0.05
    torch.testing.assert_close(out["reward"].squeeze(-1), model.reward(s0, a, s1))
    assert td["observation"].shape == (4, 5) and out["observation"].shape == (4, 5)


@pytest.mark.parametrize(
    "action",
    [
        torch.zeros(4, 5, dtype=torch.int64),  # integer dtype
        torch.zeros(4, 5, dtype=torch.bool),  # bool
        torch.zeros(4),  # the discrete shape
        torch.zeros(4, 4),  # wrong action_dim
        torch.full((4, 5), 0.2),  # outside the box
        torch.tensor([[0.0] * 5] * 3 + [[0.0, 0.0, -0.1001, 0.0, 0.0]]),  # one coordinate just below low
        torch.tensor([[0.0] * 5] * 3 + [[0.0, float("nan"), 0.0, 0.0, 0.0]]),  # NaN
        torch.tensor([[0.0] * 5] * 3 + [[0.0, 0.0, 0.0, 0.0, float("inf")]]),  # inf
    ],
    ids=["int64", "bool", "discrete_shape", "wrong_dim", "outside", "just_below", "nan", "inf"],
)
def test_bad_actions_raise_naming_the_action(action):
    model = LightDark10DContinuous()
    env = POMDPEnv(model, batch_size=(4,), seed=0, expose_state=True)
    td = env.reset()
    state = env.state.clone()
    bad = td.clone()
    bad["action"] = action
    with pytest.raises(ValueError) as info:
        env.step(bad)
    assert str(info.value).startswith("action:"), str(info.value)
    assert torch.equal(env.state, state)  # nothing moved
    td["action"] = model.action_high.expand(4, 5).clone()  # the boundary is inside (a closed box)
    assert env.step(td)["next", "step_count"].squeeze(-1).tolist() == [1, 1, 1, 1]


def test_check_action_directly():
    model, size = LightDark10DContinuous(), torch.Size([2])
    ok = torch.tensor([[0.1, -0.1, 0.0, 0.0, 0.05]] * 2, dtype=torch.float64)
    out = check_action(ok, size, model)
    assert out.dtype == torch.float32 and out.shape == (2, 5)
    torch.testing.assert_close(out, ok.float())
    for bad in ([[0.0] * 5] * 2, torch.zeros(2, 5, dtype=torch.int32), torch.zeros(2), torch.zeros(2, 6),
                torch.zeros(1, 2, 5), torch.full((2, 5), -0.5), torch.full((2, 5), float("nan"))):
        with pytest.raises(ValueError) as info:
            check_action(bad, size, model)
        assert str(info.value).startswith("action:"), str(info.value)
    # the discrete model is unchanged: integer actions of the batch shape
    assert check_action(torch.tensor([1, 9]), size, LightDark10D()).dtype == torch.int64
    with pytest.raises(ValueError, match="^action:"):
        check_action(torch.zeros(2, 5), size, LightDark10D())


# ---------------------------------------------------------------------------------------------
# BeliefTransform
# ---------------------------------------------------------------------------------------------

FILTERS = {
    "sir": SIRFilter,
    "enkf": EnKFFilter,
    "svgd": lambda: SVGDFilter(num_steps=2),
    "escort": lambda: ESCORTFilter(num_steps=2),
}


@pytest.mark.parametrize("name", list(FILTERS))
def test_belief_env_with_every_filter_rolls_out_with_random_actions(name):
    model = LightDark10DContinuous()
    env = TransformedEnv(POMDPEnv(model, batch_size=(3,), seed=1, max_steps=4, expose_state=True),
                         BeliefTransform(model, FILTERS[name](), N, seed=2))
    check_env_specs(env)
    torch.manual_seed(0)
    td = env.rollout(6, break_when_any_done=False)  # crosses a truncation and a reset
    assert td["action"].shape == (3, 6, 5) and td["action"].dtype == torch.float32
    assert in_box(td["action"], model)
    particles, logw = td["next", "particles"], td["next", "particle_log_weights"]
    assert particles.shape == (3, 6, N, 10) and logw.shape == (3, 6, N)
    assert bool(torch.isfinite(particles).all()) and bool(torch.isfinite(logw).all())
    assert bool(td["next", "truncated"][:, 3].all())
    # the belief moved with the steps: the step-1 particles are not the prior's
    assert not torch.equal(td["particles"][:, 1], td["particles"][:, 0])


def test_the_filter_sees_the_real_action():
    """The transform hands the float action to the filter: without resampling and with the same
    seeds (the same process noise), one step's particles differ between two actions by the action
    difference in the velocities and by nothing in the positions."""
    model = LightDark10DContinuous()

    def first_step(action):
        env = TransformedEnv(POMDPEnv(model, batch_size=(2,), seed=5, expose_state=True),
                             BeliefTransform(model, SIRFilter(resample_threshold=0.0), N, seed=6))
        td = env.reset()
        td["action"] = action
        return env.step(td)["next", "particles"]

    zero = first_step(torch.zeros(2, 5))
    pushed = first_step(torch.tensor([[0.1, 0.0, -0.1, 0.0, 0.05]] * 2))
    # same seeds, same noise: the difference is the action in the velocities, nothing in the positions
    torch.testing.assert_close((pushed - zero)[..., 5:], torch.tensor([0.1, 0.0, -0.1, 0.0, 0.05]).expand(2, N, 5))
    torch.testing.assert_close((pushed - zero)[..., :5], torch.zeros(2, N, 5))


def test_belief_transform_refuses_a_model_of_the_other_kind():
    with pytest.raises(ValueError, match=r"^BeliefTransform\.model:"):
        TransformedEnv(POMDPEnv(LightDark10DContinuous(), (2,), seed=0, expose_state=True),
                       BeliefTransform(LightDark10D(), SIRFilter(), 8)).reset()
    with pytest.raises(ValueError, match=r"^BeliefTransform\.model:"):
        TransformedEnv(POMDPEnv(LightDark10D(), (2,), seed=0, expose_state=True),
                       BeliefTransform(LightDark10DContinuous(), SIRFilter(), 8)).reset()


@pytest.mark.slow
def test_parallel_env_of_two_spawned_workers():
    env = ParallelEnv(2, [functools.partial(make_belief_env, 11, 101), functools.partial(make_belief_env, 12)],
                      mp_start_method="spawn")
    try:
        spec = env.action_spec
        assert spec.shape == (2, 2, 5) and spec.dtype == torch.float32
        torch.manual_seed(0)
        td = env.rollout(8, break_when_any_done=False)
    finally:
        env.close()
    assert td["action"].shape == (2, 2, 8, 5)
    assert in_box(td["action"], LightDark10DContinuous())
    assert td["next", "particles"].shape == (2, 2, 8, N, 10)
    assert bool(torch.isfinite(td["next", "particles"]).all())
    assert bool(td["next", "truncated"].any())  # max_steps = 6 inside 8 steps
    assert not torch.equal(td["next", "particles"][0], td["next", "particles"][1])  # seeded apart


def test_collector_runs_the_tanh_normal_deepsets_policy():
    model = LightDark10DContinuous()
    policy = tanh_normal_policy(model)
    env = make_belief_env(0, 1, batch=4, max_steps=20)
    collector = Collector(env, policy, frames_per_batch=100, total_frames=200, auto_register_policy_transforms=False)
    try:
        batches = [b.clone() for b in collector]
    finally:
        collector.shutdown()
    assert sum(b.numel() for b in batches) == 200
    for b in batches:
        action = b["action"]
        assert action.shape == (*b.shape, 5) and action.dtype == torch.float32
        assert in_box(action, model)
        assert b["action_log_prob"].shape == b.shape and bool(torch.isfinite(b["action_log_prob"]).all())
        assert b["loc"].shape == b["scale"].shape == (*b.shape, 5) and bool((b["scale"] > 0).all())
        assert bool(torch.isfinite(b["next", "particles"]).all())


# ---------------------------------------------------------------------------------------------
# gymnasium
# ---------------------------------------------------------------------------------------------


def test_the_registered_id_has_the_box_action_space():
    env = gym.make(CONTINUOUS_ID)
    space = env.action_space
    assert isinstance(space, gym.spaces.Box) and space.shape == (5,) and space.dtype == np.float32
    np.testing.assert_array_equal(space.low, np.full(5, -0.1, np.float32))
    np.testing.assert_array_equal(space.high, np.full(5, 0.1, np.float32))
    assert space == action_space(LightDark10DContinuous())
    assert isinstance(env.unwrapped.model, LightDark10DContinuous)
    from gymnasium.utils.env_checker import check_env

    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_pomdp_gym_env_steps_with_float_actions_and_refuses_bad_ones():
    env = POMDPGymEnv(LightDark10DContinuous())
    with pytest.raises(RuntimeError):
        env.step(np.zeros(5, np.float32))  # before reset
    _, info = env.reset(seed=0)
    s0 = info["true_state"]
    a = np.array([0.1, -0.1, 0.0, 0.05, 0.0], np.float32)
    obs, reward, terminated, truncated, info = env.step(a)
    assert obs.shape == (5,) and obs.dtype == np.float32 and isinstance(reward, float)
    mean = env.model.transition_mean(torch.as_tensor(s0), torch.as_tensor(a)).numpy()
    assert np.all(np.abs(info["true_state"] - mean) < 6 * 0.05)
    env.step([0.0, 0.0, 0.0, 0.0, 0.0])  # a list is an action too
    for bad in (np.full(5, 0.2, np.float32), np.zeros(4, np.float32), np.array([0, 0, 0, float("nan"), 0]), 3):
        with pytest.raises(ValueError) as info:
            env.step(bad)
        assert str(info.value).startswith("action:"), str(info.value)


def test_model_action_shapes():
    cont, disc = LightDark10DContinuous(), LightDark10D()
    a = model_action(cont, np.array([0.1, 0, 0, 0, -0.1]), (1,))
    assert a.shape == (1, 5) and a.dtype == torch.float32
    assert model_action(cont, [0.0] * 5).shape == (5,)
    i = model_action(disc, np.int64(3), (1,))
    assert i.shape == (1,) and i.dtype == torch.int64 and int(i) == 3


def test_gymnasium_check_env_on_the_belief_observation():
    from gymnasium.utils.env_checker import check_env

    env = BeliefObservation(gym.make(CONTINUOUS_ID), SIRFilter(), N)
    assert env.action_space == env.unwrapped.action_space
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    # the only warnings are the ones check_env gives the discrete env's wrapper too (a wrapper is
    # checked, and the belief's Box bounds are infinite by design)
    expected = ("different from the unwrapped version", "infinity")
    unexpected = [str(w.message) for w in caught if not any(s in str(w.message) for s in expected)]
    assert not unexpected, unexpected
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        obs, *_ = env.step(env.action_space.sample())
    assert obs["particles"].shape == (N, 10) and np.isfinite(obs["particles"]).all()
    env.close()


def test_belief_observation_replays_with_the_same_seed_and_actions():
    actions = [np.array([0.1, 0.0, -0.1, 0.05, 0.0], np.float32), np.full(5, -0.03, np.float32)]

    def run(seed):
        env = BeliefObservation(gym.make(CONTINUOUS_ID), SIRFilter(), N)
        out = [env.reset(seed=seed)[0]["particles"]]
        out += [env.step(a)[0]["particles"] for a in actions]
        return np.stack(out)

    np.testing.assert_array_equal(run(4), run(4))
    assert not np.allclose(run(4), run(5))


@pytest.mark.parametrize("env_id, model", [
    (CONTINUOUS_ID, LightDark10D()),  # a discrete model on the Box env
    ("escort_rl/LightDark10D-v0", LightDark10DContinuous()),  # a continuous model on the Discrete env
    (CONTINUOUS_ID, LightDark10DContinuous(force=0.2)),  # another box
], ids=["discrete-on-box", "continuous-on-discrete", "other-box"])
def test_belief_observation_refuses_a_mismatched_action_space(env_id, model):
    with pytest.raises(ValueError, match=r"^(env|model): .*action[ _]space"):  # names the field, says why
        BeliefObservation(gym.make(env_id), SIRFilter(), N, model=model)


def test_a_tanh_normal_policy_on_belief_observations():
    """The gymnasium side end to end: the policy's action, as numpy, is an element of the Box."""
    model = LightDark10DContinuous()
    policy = tanh_normal_policy(model, seed=3)
    env = BeliefObservation(gym.make(CONTINUOUS_ID), SIRFilter(), N)
    obs, _ = env.reset(seed=1)
    for _ in range(4):
        td = TensorDict({"particles": torch.as_tensor(obs["particles"])[None],
                         "particle_log_weights": torch.as_tensor(obs["log_weights"])[None]}, [1])
        with torch.no_grad():
            action = policy(td)["action"][0].numpy()
        assert env.action_space.contains(action)
        obs, *_ = env.step(action)
