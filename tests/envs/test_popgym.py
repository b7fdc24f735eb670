"""POPGym's control tasks as TorchRL envs: the names and ids, the specs (discrete CartPole, continuous
Pendulum), batched and spawned envs, a collector, and the returns POPGym promises (the memory games:
test_popgym_memory_games.py)."""

from __future__ import annotations

import sys

import pytest
import torch
from torchrl.data import Bounded, Categorical
from torchrl.envs.utils import RandomPolicy, check_env_specs

pytest.importorskip("popgym")

from escort_rl.envs.popgym import (  # noqa: E402
    MISSING_POPGYM,
    POPGYM_CONTROL,
    import_popgym,
    make_popgym_env,
    popgym_model,
    popgym_task,
)


def test_the_twelve_control_tasks_and_their_registered_ids():
    import gymnasium as gym

    import_popgym()
    assert len(POPGYM_CONTROL) == 12
    assert {n.removeprefix("Noisy").removeprefix("PositionOnly") for n in POPGYM_CONTROL} == {
        f"{s}{lvl}" for s in ("CartPole", "Pendulum") for lvl in ("Easy", "Medium", "Hard")}
    for name, env_id in POPGYM_CONTROL.items():
        assert env_id == f"popgym-{name}-v0" and env_id in gym.registry, env_id
    assert popgym_task("popgym-PositionOnlyCartPoleEasy-v0") == "PositionOnlyCartPoleEasy"


def test_unknown_names_and_bad_sizes_are_refused():
    with pytest.raises(ValueError, match="unknown POPGym task 'CartPole'.*PositionOnlyCartPoleEasy"):
        make_popgym_env("CartPole")
    with pytest.raises(ValueError, match="num_envs: expected a positive int, got 0"):
        make_popgym_env("PositionOnlyCartPoleEasy", num_envs=0)
    with pytest.raises(ValueError, match="unknown POPGym control task"):
        popgym_model("VelocityOnlyCartPoleEasy")


def test_a_missing_popgym_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "popgym", None)  # ``import popgym`` then raises ImportError
    with pytest.raises(ImportError, match=r"pip install 'escort-rl\[popgym\]'") as info:
        make_popgym_env("PositionOnlyPendulumEasy")
    assert str(info.value) == MISSING_POPGYM


def test_cartpole_specs_are_discrete():
    env = make_popgym_env("NoisyPositionOnlyCartPoleHard", seed=0)
    try:
        check_env_specs(env)
        assert isinstance(env.action_spec, Categorical) and env.action_spec.space.n == 2
        td = env.rollout(50)
        assert td["action"].dtype == torch.int64 and td["next", "observation"].shape[-1] == 2
    finally:
        env.close()


def test_pendulum_specs_are_a_bounded_torque():
    env = make_popgym_env("PositionOnlyPendulumMedium", seed=0)
    try:
        check_env_specs(env)
        spec = env.action_spec
        assert isinstance(spec, Bounded) and spec.shape == (1,) and spec.dtype == torch.float32
        assert spec.space.low.tolist() == [-2.0] and spec.space.high.tolist() == [2.0]
        obs = env.rollout(20)["next", "observation"]
        assert obs.shape == (20, 2) and torch.allclose(obs.pow(2).sum(-1), torch.ones(20), atol=1e-5)  # cos² + sin²
    finally:
        env.close()


def test_serial_env_batches_and_seeds():
    def rollout(seed):
        env = make_popgym_env("NoisyPositionOnlyPendulumEasy", num_envs=3, seed=seed)
        try:
            assert env.batch_size == (3,)
            check_env_specs(env)
            torch.manual_seed(0)
            return env.rollout(10)["next", "observation"]
        finally:
            env.close()

    first = rollout(5)
    assert first.shape == (3, 10, 2) and torch.equal(first, rollout(5))
    assert not torch.equal(first[0], first[1])  # each worker its own seed


@pytest.mark.slow
def test_parallel_env_with_spawned_workers():
    env = make_popgym_env("PositionOnlyCartPoleMedium", num_envs=2, parallel=True, seed=3)
    try:
        assert env.batch_size == (2,)
        td = env.rollout(30, break_when_any_done=False)
        assert td["next", "observation"].shape == (2, 30, 2) and td["action"].dtype == torch.int64
        assert not torch.equal(td["observation"][0, 0], td["observation"][1, 0])
    finally:
        env.close()


def test_a_collector_with_a_random_policy():
    from torchrl.collectors import Collector

    env = make_popgym_env("PositionOnlyCartPoleEasy", num_envs=2, seed=1)
    collector = Collector(env, RandomPolicy(env.action_spec), frames_per_batch=100, total_frames=300)
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
    assert sum(b.numel() for b in batches) == 300
    assert all(b["next", "done"].any() for b in batches)  # a random CartPole falls within 50 steps


@pytest.mark.parametrize("name", ["PositionOnlyCartPoleHard", "NoisyPositionOnlyCartPoleEasy",
                                  "PositionOnlyPendulumHard", "NoisyPositionOnlyPendulumMedium"])
def test_random_returns_lie_in_minus_one_one(name):
    """POPGym scales rewards so that a return lies in [-1, 1]: CartPole pays 1/L a step (so a random
    policy's return is short of 1), Pendulum at most 1/L in absolute value; every episode ends."""
    env = make_popgym_env(name, seed=2)
    try:
        torch.manual_seed(0)
        for _ in range(3):
            td = env.rollout(1000)  # stops at the episode's end
            assert td["next", "done"][-1].item()
            ret = td["next", "reward"].sum().item()
            assert -1.0 <= ret <= 1.0, ret
            if "CartPole" in name:
                length = popgym_model(name).max_episode_length
                assert ret == pytest.approx(td.shape[0] / length, abs=1e-5)
    finally:
        env.close()
