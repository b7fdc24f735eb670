"""Every POPGym task as a TorchRL env, the memory games included: flat one-hot float observations, one
discrete action in place of a multi-discrete one, the same steps as POPGym's own env, and the spaces
a model-free trainer reads (:class:`~escort_rl.models.TaskSpaces`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchrl.data import Bounded, Categorical
from torchrl.envs.utils import check_env_specs

pytest.importorskip("popgym")

import gymnasium as gym  # noqa: E402

from escort_rl.envs.popgym import (  # noqa: E402
    POPGYM_CONTROL,
    make_popgym_env,
    popgym_any_task,
    popgym_episode_length,
    popgym_task_spaces,
    popgym_tasks,
)

MEMORY_GAMES = ("Autoencode", "Battleship", "Concentration", "CountRecall", "HigherLower", "MineSweeper",
                "MultiarmedBandit", "RepeatFirst", "RepeatPrevious")


def test_every_task_is_listed_with_its_id():
    tasks = popgym_tasks()
    assert set(POPGYM_CONTROL) <= set(tasks)
    for game in MEMORY_GAMES:
        assert {f"{game}{level}" for level in ("Easy", "Medium", "Hard")} <= set(tasks)
    assert all(env_id == f"popgym-{name}-v0" for name, env_id in tasks.items())
    assert popgym_any_task("popgym-BattleshipHard-v0") == "BattleshipHard"
    with pytest.raises(ValueError, match="unknown POPGym task 'Pong'.*RepeatPreviousEasy"):
        popgym_any_task("Pong")


@pytest.mark.parametrize("name", sorted(popgym_tasks()))
def test_every_task_has_exact_specs_and_flat_float_observations(name):
    spaces = popgym_task_spaces(name)
    env = make_popgym_env(name, num_envs=2, seed=0)
    try:
        check_env_specs(env)
        td = env.rollout(4)
    finally:
        env.close()
    assert td["observation"].dtype == torch.float32
    assert td["observation"].shape[-1] == spaces.obs_dim
    assert spaces.state_dim == 0
    action_spec = env.action_spec
    if spaces.n_actions is not None:
        assert isinstance(action_spec, Categorical) and action_spec.n == spaces.n_actions
    else:
        assert isinstance(action_spec, Bounded) and action_spec.shape[-1] == spaces.action_dim


@pytest.mark.parametrize("name,blocks", [("RepeatPreviousEasy", 1), ("AutoencodeEasy", 2), ("MineSweeperEasy", 1),
                                         ("ConcentrationEasy", 52), ("CountRecallEasy", 2)])
def test_discrete_observations_are_one_hot_codes(name, blocks):
    """A Discrete observation is one block of one-hot code, a Tuple or MultiDiscrete one a block per part:
    every entry is 0 or 1 and each observation holds exactly ``blocks`` ones."""
    env = make_popgym_env(name, seed=3)
    try:
        obs = env.rollout(10)["observation"]
    finally:
        env.close()
    assert set(obs.unique().tolist()) <= {0.0, 1.0}
    assert torch.equal(obs.sum(-1), torch.full(obs.shape[:-1], float(blocks)))


def test_a_multi_discrete_action_is_one_action_over_the_product():
    """Battleship's (row, column) shot is one action ``a = row · 8 + column`` on the Easy board: our env
    and POPGym's own, seeded alike and shot at every square in turn (one square twice), see the same hits
    and misses (so the same ships), rewards and end."""
    ours = make_popgym_env("BattleshipEasy", seed=5)
    theirs = gym.make("popgym-BattleshipEasy-v0").unwrapped
    theirs.reset(seed=5)  # TorchRL's set_seed resets with the seed, and our first reset() is a second one
    theirs.reset()
    assert popgym_task_spaces("BattleshipEasy").n_actions == 64
    try:
        td = ours.reset()
        hits = 0
        for a in (9, *range(64)):
            td = ours.step(td.set("action", torch.tensor(a)))
            obs, reward, terminated, _, _ = theirs.step(np.array(np.unravel_index(a, (8, 8))))
            expected = gym.spaces.utils.flatten(theirs.observation_space, obs).astype(np.float32)
            assert torch.equal(td["next", "observation"], torch.from_numpy(expected))
            assert td["next", "reward"].item() == pytest.approx(float(reward))
            assert td["next", "terminated"].item() == bool(terminated)
            hits += int(td["next", "observation"][1].item())
            if terminated:
                break
            td = td["next"].exclude("reward", "done", "terminated", "truncated")
        assert terminated and hits > 0  # every ship sunk, on the same squares
    finally:
        ours.close()


def test_episode_lengths_are_popgyms():
    assert popgym_episode_length("RepeatPreviousEasy") == 51
    assert popgym_episode_length("BattleshipHard") == 144
    assert popgym_episode_length("ConcentrationEasy") == 104
    assert popgym_episode_length("HigherLowerEasy") is None  # a deck of cards: no stated length
    assert popgym_episode_length("NoisyPositionOnlyCartPoleHard") == 200
