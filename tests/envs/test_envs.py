"""Tests of the batched TorchRL environment and the gymnasium adapter."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import check_env_specs

import escort_rl.envs  # noqa: F401  (registers the gymnasium ids)
from escort_rl.envs import POMDPEnv, check_action
from escort_rl.models import LightDark10D, LinearGaussian


class CyclicAction(torch.nn.Module):
    """A deterministic policy: action = (step_count + offset) mod n_actions."""

    def __init__(self, n_actions: int, offset: int = 0) -> None:
        super().__init__()
        self.n_actions, self.offset = n_actions, offset

    def forward(self, step_count: torch.Tensor) -> torch.Tensor:
        return ((step_count.squeeze(-1) + self.offset) % self.n_actions).long()


def cyclic_policy(n_actions: int = 10, offset: int = 0) -> TensorDictModule:
    return TensorDictModule(CyclicAction(n_actions, offset), in_keys=["step_count"], out_keys=["action"])


def make_env(seed: int = 0, batch: int = 4, max_steps: int | None = 20) -> POMDPEnv:
    return POMDPEnv(LightDark10D(), batch_size=(batch,), seed=seed, max_steps=max_steps, expose_state=True)


# ---------------------------------------------------------------------------------------------
# POMDPEnv
# ---------------------------------------------------------------------------------------------


def test_check_env_specs():
    env = make_env()
    check_env_specs(env)
    assert env.batch_size == (4,)
    assert env.observation_spec["observation"].shape == (4, 5)
    assert env.observation_spec["true_state"].shape == (4, 10)
    assert env.action_spec.shape == (4,)
    assert env.action_spec.dtype == torch.int64


def test_check_env_specs_other_model():
    env = POMDPEnv(LinearGaussian(state_dim=3, obs_dim=2), batch_size=(2, 3), seed=1, max_steps=5, expose_state=True)
    check_env_specs(env)
    td = env.rollout(3, cyclic_policy(6))
    assert td["next", "observation"].shape == (2, 3, 3, 2)


def test_reset_and_step_contents():
    env = make_env(seed=3)
    td = env.reset()
    assert bool((td["step_count"] == 0).all())
    assert not bool(td["done"].any())
    s0 = td["true_state"]
    assert bool(((s0[:, :5] >= 0) & (s0[:, :5] <= 2)).all())
    torch.testing.assert_close(env.state, s0)
    td["action"] = torch.tensor([0, 1, 2, 3])
    out = env.step(td)["next"]
    assert bool((out["step_count"] == 1).all())
    s1 = out["true_state"]
    torch.testing.assert_close(env.state, s1)
    model = env.model
    torch.testing.assert_close(out["reward"].squeeze(-1), model.reward(s0, td["action"], s1))
    assert out["reward"].shape == (4, 1) and out["reward"].dtype == torch.float32
    # the step follows the model's dynamics: what is left after the mean is process noise (std 0.05)
    noise = s1 - model.transition_mean(s0, td["action"])
    assert bool((noise.abs() < 6 * 0.05).all())
    assert bool((noise.abs() > 0).any())


def test_truncation_exactly_at_max_steps():
    env = make_env(seed=0, max_steps=20)
    td = env.rollout(45, cyclic_policy(), break_when_any_done=False)
    truncated = td["next", "truncated"].squeeze(-1)  # [B, T]
    done = td["next", "done"].squeeze(-1)
    terminated = td["next", "terminated"].squeeze(-1)
    assert not bool(terminated.any())  # the goal is far from the start box
    expected = torch.zeros(45, dtype=torch.bool)
    expected[[19, 39]] = True
    for b in range(4):
        assert torch.equal(truncated[b], expected)
        assert torch.equal(done[b], expected)
    # the step counter restarts after the automatic reset
    steps = td["next", "step_count"][0].squeeze(-1)
    assert steps.tolist() == list(range(1, 21)) + list(range(1, 21)) + list(range(1, 6))
    assert td["step_count"][0, 20].item() == 0


def test_no_truncation_without_max_steps():
    env = make_env(max_steps=None)
    td = env.rollout(30, cyclic_policy(), break_when_any_done=False)
    assert not bool(td["next", "done"].any())


def test_terminated_is_set_at_the_goal():
    env = make_env(seed=4, max_steps=5)
    env.reset()
    env._state[:2, :5] = 8.0  # place two envs on the goal with zero velocity
    env._state[:2, 5:] = 0.0
    td = TensorDict({"action": torch.zeros(4, dtype=torch.long)}, batch_size=[4])
    out = env.step(td)["next"]
    # after one noisy step (std 0.05 per axis) both are still well inside the 0.5 radius
    assert out["terminated"].squeeze(-1).tolist() == [True, True, False, False]
    assert out["done"].squeeze(-1).tolist() == [True, True, False, False]
    assert not bool(out["truncated"].any())


def test_partial_reset_changes_only_selected_rows():
    env = make_env(seed=5)
    td = env.reset()
    for t in range(3):
        td["action"] = torch.full((4,), t, dtype=torch.long)
        td = env.step_mdp(env.step(td))
    assert bool((td["step_count"] == 3).all())
    before = env.state
    before_obs = td["observation"].clone()
    mask = torch.tensor([True, False, True, False])
    td["_reset"] = mask.unsqueeze(-1)
    out = env.reset(td)
    after = env.state
    # hidden state: only rows 0 and 2 were re-drawn
    assert bool((after[mask] != before[mask]).any(-1).all())
    assert torch.equal(after[~mask], before[~mask])
    assert bool(((after[mask][:, :5] >= 0) & (after[mask][:, :5] <= 2)).all())
    assert bool((after[mask][:, 5:] == 0).all())
    # returned data: reset rows are fresh, the others unchanged
    assert out["step_count"].squeeze(-1).tolist() == [0, 3, 0, 3]
    torch.testing.assert_close(out["true_state"], after)
    assert torch.equal(out["observation"][~mask], before_obs[~mask])
    assert not bool((out["observation"][mask] == before_obs[mask]).all())
    # the env's own step counters were reset for those rows only
    out["action"] = torch.zeros(4, dtype=torch.long)
    nxt = env.step(out)["next"]
    assert nxt["step_count"].squeeze(-1).tolist() == [1, 4, 1, 4]


def test_partial_reset_truncation_follows_each_row():
    env = make_env(seed=6, max_steps=4)
    td = env.reset()
    for t in range(2):
        td["action"] = torch.zeros(4, dtype=torch.long)
        td = env.step_mdp(env.step(td))
    td["_reset"] = torch.tensor([[True], [False], [False], [False]])
    td = env.reset(td)
    flags = []
    for t in range(4):
        td["action"] = torch.zeros(4, dtype=torch.long)
        out = env.step(td)
        flags.append(out["next", "truncated"].squeeze(-1).tolist())
        td = env.step_mdp(out)
    # rows 1-3 reach 4 steps after two more steps, row 0 after four
    assert flags[1] == [False, True, True, True]
    assert flags[3][0] is True


def _rollout(seed: int, steps: int = 25):
    env = make_env(seed=seed, max_steps=10)
    return env.rollout(steps, cyclic_policy(offset=3), break_when_any_done=False)


def test_same_seed_gives_identical_rollouts():
    a, b = _rollout(7), _rollout(7)
    for key in ["observation", "true_state", ("next", "observation"), ("next", "true_state"),
                ("next", "reward"), ("next", "done"), "action"]:
        assert torch.equal(a[key], b[key]), key
    c = _rollout(8)
    assert not torch.equal(a["true_state"], c["true_state"])


def test_set_seed_reproduces_a_rollout():
    env = make_env(seed=0, max_steps=10)
    env.set_seed(11)
    a = env.rollout(12, cyclic_policy(), break_when_any_done=False)
    env.set_seed(11)
    b = env.rollout(12, cyclic_policy(), break_when_any_done=False)
    assert torch.equal(a["next", "observation"], b["next", "observation"])


@pytest.mark.parametrize(
    "action",
    [
        torch.zeros(4),  # float
        torch.zeros(4, dtype=torch.float64),
        torch.zeros(4, dtype=torch.bool),
        torch.zeros(4, 10, dtype=torch.long),  # one-hot shaped
        torch.tensor([0, 1, 10, 2]),  # too large
        torch.tensor([0, -1, 2, 3]),  # negative
    ],
    ids=["float32", "float64", "bool", "onehot", "too_large", "negative"],
)
def test_bad_actions_raise(action):
    env = make_env()
    td = env.reset()
    bad = td.clone()
    bad["action"] = action
    with pytest.raises(ValueError) as info:
        env.step(bad)
    assert str(info.value).startswith("action:"), str(info.value)
    # and the env is unchanged: a good step still works
    td["action"] = torch.zeros(4, dtype=torch.long)
    assert env.step(td)["next", "step_count"].squeeze(-1).tolist() == [1, 1, 1, 1]


def test_check_action_directly():
    size, model = torch.Size([2]), LinearGaussian(n_actions=5)
    assert check_action(torch.tensor([1, 2], dtype=torch.int32), size, model).dtype == torch.int64
    for bad in ([1, 2], torch.tensor([0.0, 1.0]), torch.tensor([[1, 2]]), torch.tensor([5, 0])):
        with pytest.raises(ValueError) as info:
            check_action(bad, size, model)
        assert str(info.value).startswith("action:")


def test_env_rejects_bad_construction():
    with pytest.raises(ValueError, match="max_steps"):
        POMDPEnv(LightDark10D(), batch_size=(2,), max_steps=0, expose_state=True)
    with pytest.raises(TypeError, match="model"):
        POMDPEnv(object(), batch_size=(2,), expose_state=True)


# ---------------------------------------------------------------------------------------------
# gymnasium
# ---------------------------------------------------------------------------------------------


def test_gymnasium_env_checker():
    from gymnasium.utils.env_checker import check_env

    env = gymnasium.make("escort_rl/LightDark10D-v0")
    check_env(env.unwrapped, skip_render_check=True)
    assert env.spec.max_episode_steps == 500
    assert env.observation_space.shape == (5,)
    assert env.action_space.n == 10
    env.close()


def test_gymnasium_reset_seed_is_deterministic():
    env = gymnasium.make("escort_rl/LightDark10D-v0")

    def episode(seed):
        obs, info = env.reset(seed=seed)
        traj = [obs]
        states = [info["true_state"]]
        for t in range(15):
            obs, reward, terminated, truncated, info = env.step(t % 10)
            traj.append(obs)
            states.append(info["true_state"])
            assert isinstance(reward, float) and not terminated and not truncated
        return np.stack(traj), np.stack(states)

    a, sa = episode(123)
    b, sb = episode(123)
    c, _ = episode(124)
    assert a.dtype == np.float32 and a.shape == (16, 5)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(sa, sb)
    assert not np.array_equal(a, c)
    # a second gym env with the same seed agrees as well
    env2 = gymnasium.make("escort_rl/LightDark10D-v0")
    o2, _ = env2.reset(seed=123)
    np.testing.assert_array_equal(o2, a[0])


def test_gymnasium_truncates_at_max_episode_steps():
    env = gymnasium.make("escort_rl/LightDark10D-v0", max_episode_steps=7)
    env.reset(seed=0)
    flags = [env.step(0)[3] for _ in range(7)]
    assert flags == [False] * 6 + [True]


def test_gymnasium_rejects_bad_actions():
    env = gymnasium.make("escort_rl/LightDark10D-v0").unwrapped
    with pytest.raises(RuntimeError):
        env.step(0)  # before reset
    env.reset(seed=0)
    for bad in (10, -1, 1.5):
        with pytest.raises(ValueError) as info:
            env.step(bad)
        assert str(info.value).startswith("action:")


# ---------------------------------------------------------------------------------------------
# the three domains
# ---------------------------------------------------------------------------------------------

DOMAIN_IDS = ["escort_rl/LightDark10D-v0", "escort_rl/KidnappedRobot20D-v0", "escort_rl/MultiTargetTracking20D-v0"]


@pytest.mark.parametrize("env_id", DOMAIN_IDS)
def test_every_domain_passes_the_gymnasium_checker(env_id):
    from gymnasium.utils.env_checker import check_env

    from escort_rl.envs.registration import GYM_IDS, domain_max_steps

    env = gymnasium.make(env_id)
    check_env(env.unwrapped, skip_render_check=True)
    assert env.spec.max_episode_steps == domain_max_steps(GYM_IDS[env_id])
    obs, info = env.reset(seed=0)
    assert obs.shape == (env.unwrapped.model.obs_dim,) and np.isfinite(obs).all()
    env.close()


@pytest.mark.parametrize("domain", ["kidnapped20d", "mtt20d"])
def test_every_domain_passes_torchrl_check_env_specs(domain):
    from escort_rl.models import DOMAINS

    model = DOMAINS[domain]()
    env = POMDPEnv(model, batch_size=(3,), seed=0, max_steps=6, expose_state=True)
    check_env_specs(env)
    td = env.rollout(6, cyclic_policy(model.n_actions))
    assert td["next", "observation"].shape == (3, 6, model.obs_dim)
    assert torch.isfinite(td["next", "observation"]).all()


@pytest.mark.parametrize("batch_size", [(0,), (-1,), (2, 0)])
def test_empty_or_negative_batch_sizes_get_one_line(batch_size):
    from escort_rl.envs import POMDPEnv
    from escort_rl.models import LightDark10D

    with pytest.raises(ValueError, match=r"^POMDPEnv.batch_size: every size must be a positive int"):
        POMDPEnv(LightDark10D(), batch_size=batch_size, expose_state=True)


def test_the_hidden_state_is_not_an_observation_unless_asked_for():
    """A composed env holds no ``true_state`` (a generic actor reading every observation cannot see the
    hidden state); ``expose_state=True``, as training and evaluation build it, writes it."""
    env = POMDPEnv(LightDark10D(), batch_size=(2,), seed=0, max_steps=3)
    assert "true_state" not in env.observation_spec.keys()
    td = env.rollout(2)
    assert "true_state" not in td.keys() and "true_state" not in td["next"].keys()
    check_env_specs(env)
    shown = POMDPEnv(LightDark10D(), batch_size=(2,), seed=0, max_steps=3, expose_state=True)
    assert shown.rollout(2)["next", "true_state"].shape == (2, 2, 10)
    with pytest.raises(ValueError, match=r"^POMDPEnv.expose_state: must be True or False, got 1$"):
        POMDPEnv(LightDark10D(), batch_size=(2,), expose_state=1)


def test_a_prior_placed_around_the_start_needs_the_start():
    from torchrl.envs import TransformedEnv

    from escort_rl.belief import SIRFilter
    from escort_rl.transforms import BeliefTransform

    model = LightDark10D(start_low=0.0, start_high=10.0, prior_width=2.0)
    env = TransformedEnv(POMDPEnv(model, batch_size=(2,), seed=0), BeliefTransform(model, SIRFilter(), 8))
    with pytest.raises(ValueError, match=r"expose_state=True"):
        env.reset()
