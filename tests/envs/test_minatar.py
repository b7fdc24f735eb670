"""Flickering MinAtar: the five games' ids, the flicker's rate, independence and seeding on them, the
TorchRL envs, and a few hundred frames of each agent."""

from __future__ import annotations

import functools
import math
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from torchrl.envs import ParallelEnv
from torchrl.envs.utils import check_env_specs

import escort_rl  # noqa: F401  (registers the ids)
from conftest import hoeffding
from escort_rl.config import ConfigError
from escort_rl.envs.flickering import flickering_game, game_spaces, make_flickering_torchrl_env
from escort_rl.envs.minatar import GAMES, MinAtarFrames, make_flickering_minatar

CHANNELS = {"breakout": 4, "spaceinvaders": 6, "asterix": 4, "freeway": 7, "seaquest": 10}


def play(env: gym.Env, seed: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """``steps`` observations from ``reset(seed)`` on, under a fixed action sequence that restarts
    finished games: ``(frames [steps, C, 10, 10], blank flags [steps])``."""
    obs, info = env.reset(seed=seed)
    frames, flags = [obs], [info["blank"]]
    for t in range(steps - 1):
        obs, _, terminated, truncated, info = env.step(t % env.action_space.n)
        if terminated or truncated:
            obs, info = env.reset()
        frames.append(obs)
        flags.append(info["blank"])
    return np.stack(frames), np.array(flags, dtype=float)


@pytest.mark.parametrize("game", sorted(GAMES))
def test_each_id_gives_channels_first_binary_grids(game):
    env = gym.make(GAMES[game][1])
    assert env.observation_space.shape == (CHANNELS[game], 10, 10)
    frames, flags = play(env, 3, 30)
    assert frames.dtype == np.float32 and set(np.unique(frames)) <= {0.0, 1.0}
    # a blanked frame is all zeros; a shown one is the game's grid, which always holds the player
    assert np.array_equal(flags == 1, frames.reshape(30, -1).max(1) == 0)
    env.close()


def test_blank_rate_within_a_confidence_bound(per_test_seed):
    n = 3000
    _, flags = play(make_flickering_minatar("breakout"), per_test_seed, n)
    assert abs(flags.mean() - 0.5) <= hoeffding(n), flags.mean()
    _, none = play(make_flickering_minatar("breakout", p_blank=0.0), per_test_seed, 50)
    assert none.sum() == 0


def test_flicker_is_independent_across_envs_and_seeded(per_test_seed):
    n = 3000
    frames_a, a = play(make_flickering_minatar("asterix"), per_test_seed, n)
    _, b = play(make_flickering_minatar("asterix"), per_test_seed + 1, n)
    # two envs' blanks are independent fair coins: they agree half the time
    assert abs((a == b).mean() - 0.5) <= hoeffding(n)
    frames_again, again = play(make_flickering_minatar("asterix"), per_test_seed, n)
    assert np.array_equal(a, again) and np.array_equal(frames_a, frames_again)


def test_the_seed_drives_the_game_as_well_as_the_flicker(per_test_seed):
    def shown(seed):  # the game's own grids, flicker off
        return play(make_flickering_minatar("seaquest", p_blank=0.0), seed, 300)[0]

    assert np.array_equal(shown(per_test_seed), shown(per_test_seed))
    assert not np.array_equal(shown(per_test_seed), shown(per_test_seed + 1))


def test_a_game_ends_with_game_over_and_is_truncated_at_max_steps():
    env = MinAtarFrames("freeway", max_steps=25)  # freeway lasts 2500 steps: the limit comes first
    env.reset(seed=0)
    for t in range(25):
        _, _, terminated, truncated, info = env.step(0)
    assert truncated and not terminated and info["game_over"]
    env = MinAtarFrames("breakout")
    env.reset(seed=0)
    for _ in range(2000):  # staying still, the ball is lost within a few hundred steps
        _, _, terminated, truncated, info = env.step(0)
        if terminated:
            break
    assert terminated and info["game_over"]


def test_bad_game_arguments_and_missing_minatar_name_the_fix(monkeypatch):
    with pytest.raises(ConfigError, match="game: unknown MinAtar game 'tetris'"):
        MinAtarFrames("tetris")
    with pytest.raises(ConfigError, match="game: unknown 'tetris'; choose one of"):
        flickering_game("tetris")
    with pytest.raises(ValueError, match="sticky_action_prob"):
        MinAtarFrames("breakout", sticky_action_prob=2.0)
    with pytest.raises(ValueError, match="action: expected an int in \\[0, 3\\)"):
        env = MinAtarFrames("breakout")
        env.reset(seed=0)
        env.step(5)
    monkeypatch.setitem(sys.modules, "minatar", None)
    with pytest.raises(ImportError, match=r"pip install escort-rl\[minatar\]"):
        MinAtarFrames("breakout")


def test_one_name_per_game_across_atari_and_minatar():
    assert flickering_game("SpaceInvaders") == flickering_game("minatar-space_invaders")
    assert flickering_game("breakout").tier == "minatar" and flickering_game("pong").tier == "atari"
    assert game_spaces("spaceinvaders") == ((6, 10, 10), 4)


def test_torchrl_env_specs():
    env = make_flickering_torchrl_env("spaceinvaders", seed=1)
    check_env_specs(env)
    td = env.rollout(20)
    assert td["next", "observation"].shape[1:] == (6, 10, 10)
    assert td["action"].dtype == torch.int64 and td["next", "game_over"].dtype == torch.bool
    env.close()


@pytest.mark.slow
def test_parallel_env_with_spawned_workers_and_independent_flicker():
    env = ParallelEnv(2, functools.partial(make_flickering_torchrl_env, "breakout"), mp_start_method="spawn")
    try:
        env.set_seed(0)
        check_env_specs(env)
        n = 1000
        blank = (env.rollout(n, break_when_any_done=False)["next", "observation"].flatten(2).amax(-1) == 0).float()
        assert (abs(blank.mean(1) - 0.5) <= hoeffding(n)).all()
        assert abs((blank[0] == blank[1]).float().mean() - 0.5) <= hoeffding(n)
    finally:
        env.close()


# ---------------------------------------------------------------------------------------- agents
def tiny_minatar_config(agent: str, tmp_path, game: str = "breakout") -> OmegaConf:
    """``configs/bench/minatar.yaml`` at a size that trains in seconds."""
    from escort_rl.bench.atari import load_settings

    settings = OmegaConf.to_container(load_settings((
        "trainer.num_envs=4", "trainer.updates_per_iteration=10", "vrnn.num_particles=4", "vrnn.latent_dim=4",
        "vrnn.hidden=16", "vrnn.encoding_dim=16", "escort.compile=false", "gru.hidden=16"), tier="minatar"))
    return OmegaConf.create({"seed": 0, "device": "cpu", "output_dir": str(tmp_path / agent),
                             "logger": {"backend": "csv"}, "game": game, "agent": agent, **settings})


@pytest.mark.parametrize("agent", ["dvrl", "escort_latent", "gru"])
def test_each_agent_trains_a_few_hundred_minatar_frames(agent, tmp_path):
    from escort_rl.trainers.atari_a2c import AtariA2C

    torch.manual_seed(0)
    algorithm = AtariA2C(tiny_minatar_config(agent, tmp_path))
    try:
        before = {k: v.detach().clone() for k, v in algorithm.policy.named_parameters()}
        records = [algorithm.iteration(i, 100 + i) for i in range(2)]
    finally:
        algorithm.close()
    assert sum(r["frames"] for r in records) == 400
    for r in records:
        assert all(math.isfinite(r[k]) for k in ("policy_loss", "value_loss", "entropy", "elbo", "fps"))
    changed = {k for k, v in algorithm.policy.named_parameters() if not torch.equal(v, before[k])}
    for part in ("encoder", "actor_head", "critic_head"):
        assert any(part in k for k in changed), (part, changed)
    if agent != "gru":  # the model learns from its ELBO: the emission moves
        assert any("emission" in k for k in changed)


def test_bench_atari_trains_on_minatar_and_reports_beside_random(tmp_path):
    import argparse
    import json

    from escort_rl.bench import atari as atari_bench

    parser = argparse.ArgumentParser()
    atari_bench.register(parser.add_subparsers())
    tiny = ["trainer.num_envs=4", "trainer.updates_per_iteration=10", "gru.hidden=16"]
    args = parser.parse_args(["atari", *tiny, "--games", "breakout", "--agents", "gru", "random", "--frames", "400",
                              "--output", str(tmp_path)])
    args.handler(args)
    rows = {row["agent"]: row for row in json.loads((tmp_path / "atari.json").read_text())["rows"]}
    assert rows["gru"]["frames"] == 400 and rows["gru"]["games"] > 0 and rows["gru"]["above_random"] is not None
    assert rows["random"]["games"] > 0 and rows["random"]["above_random"] is None
    assert "| breakout | gru |" in (tmp_path / "atari.md").read_text()
    run_cfg = OmegaConf.load(tmp_path / "runs" / "breakout" / "gru" / "seed0" / "config.yaml")
    assert run_cfg.game == "breakout" and run_cfg.gru.hidden == 16
    assert run_cfg.trainer.lr == atari_bench.load_settings(tier="minatar").trainer.lr  # MinAtar's settings, not Atari's
