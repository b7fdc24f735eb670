"""Flickering Atari: the flicker wrapper, DVRL's preprocessing, the TorchRL envs, and a smoke training
run of each Atari agent."""

from __future__ import annotations

import functools
import math
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs import ParallelEnv
from torchrl.envs.utils import check_env_specs

import escort_rl.envs  # noqa: F401  (registers the ids)
from conftest import hoeffding
from escort_rl.config import ConfigError
from escort_rl.envs.atari import (
    GAMES,
    DVRLAtari,
    Flicker,
    area_resize_matrix,
    make_atari_torchrl_env,
    make_flickering_atari,
)


class Ones(gym.Env):
    """A trivial env whose observation is all ones: the flicker's draws without an emulator."""

    observation_space = gym.spaces.Box(0.0, 1.0, (1, 4, 4), np.float32)
    action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.ones((1, 4, 4), np.float32), {}

    def step(self, action):
        return np.ones((1, 4, 4), np.float32), 0.0, False, False, {}


def blanks(env: gym.Env, seed: int, steps: int) -> np.ndarray:
    obs, info = env.reset(seed=seed)
    out = [info["blank"]]
    for _ in range(steps - 1):
        obs, _, terminated, truncated, info = env.step(0)
        assert bool(info["blank"]) == (not obs.any())
        out.append(info["blank"])
    return np.array(out, dtype=float)


def test_blank_rate_within_a_confidence_bound(per_test_seed):
    n = 4000
    rate = blanks(Flicker(Ones()), per_test_seed, n).mean()
    assert abs(rate - 0.5) <= hoeffding(n), rate
    assert blanks(Flicker(Ones(), p_blank=0.0), per_test_seed, 50).sum() == 0
    assert blanks(Flicker(Ones(), p_blank=1.0), per_test_seed, 50).sum() == 50


def test_blanks_are_independent_across_envs_and_reproducible(per_test_seed):
    n = 4000
    a, b = blanks(Flicker(Ones()), per_test_seed, n), blanks(Flicker(Ones()), per_test_seed + 1, n)
    # independent fair coins agree half the time; identical or shared streams would agree always
    assert abs((a == b).mean() - 0.5) <= hoeffding(n)
    assert np.array_equal(a, blanks(Flicker(Ones()), per_test_seed, n))


def test_flicker_rejects_a_bad_probability():
    with pytest.raises(ValueError, match="p_blank"):
        Flicker(Ones(), p_blank=1.5)


def test_area_resize_keeps_constants_and_averages_boxes():
    m = area_resize_matrix(210, 84)
    assert m.shape == (84, 210) and np.allclose(m.sum(1), 1.0)
    assert np.allclose(m @ np.full(210, 7.0), 7.0)
    # 4 -> 2: each output pixel is the mean of two inputs
    assert np.allclose(area_resize_matrix(4, 2) @ np.array([0.0, 2.0, 4.0, 8.0]), [1.0, 6.0])


@pytest.mark.parametrize("game", sorted(GAMES))
def test_registered_games_give_preprocessed_frames(game):
    env = gym.make(GAMES[game][1])
    obs, info = env.reset(seed=0)
    assert env.observation_space.shape == (1, 84, 84)
    for _ in range(8):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert obs.shape == (1, 84, 84) and obs.dtype == np.float32
        assert 0.0 <= obs.min() and obs.max() <= 1.0
        assert set(info) >= {"game_over", "blank", "lives"}
    env.close()


def test_same_seed_same_frames_other_seed_other_blanks():
    def run(seed):
        env = make_flickering_atari("pong")
        frames = [env.reset(seed=seed)[0]]
        frames += [env.step(k % 6)[0] for k in range(40)]
        env.close()
        return np.stack(frames)

    a, b, c = run(5), run(5), run(6)
    assert np.array_equal(a, b)
    assert not np.array_equal(a.reshape(41, -1).any(1), c.reshape(41, -1).any(1))


def test_a_lost_life_ends_the_episode_but_not_the_game():
    env = DVRLAtari("mspacman")
    env.reset(seed=1)
    rng = np.random.default_rng(0)
    for _ in range(5000):
        _, _, terminated, truncated, info = env.step(int(rng.integers(env.action_space.n)))
        if terminated:
            break
    assert terminated and not info["game_over"] and info["lives"] >= 1
    lives = info["lives"]
    _, info = env.reset()
    assert info["lives"] == lives  # the game went on: a new game would have all its lives
    env.close()


def test_unknown_game_and_missing_ale_name_the_fix(monkeypatch):
    with pytest.raises(ConfigError, match="game: unknown 'tetris'"):
        make_flickering_atari("tetris")
    monkeypatch.setitem(sys.modules, "ale_py", None)
    with pytest.raises(ImportError, match=r"pip install escort-rl\[atari\]"):
        make_flickering_atari("pong")


def test_a_bench_without_its_extra_is_one_line_naming_the_install(monkeypatch, capsys):
    from escort_rl.cli import main

    monkeypatch.setitem(sys.modules, "ale_py", None)
    assert main(["bench", "atari", "--quick", "--games", "pong", "--agents", "random"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "error: Flickering Atari needs the ale-py package: install with pip install escort-rl[atari]"


def test_torchrl_env_specs_and_actions():
    env = make_atari_torchrl_env("asteroids", seed=2)
    check_env_specs(env)
    td = env.rollout(10)
    assert td["next", "observation"].shape == (10, 1, 84, 84)
    assert td["action"].dtype == torch.int64 and td["next", "game_over"].dtype == torch.bool
    env.close()


@pytest.mark.slow
def test_parallel_env_with_spawned_workers_and_independent_flicker():
    env = ParallelEnv(2, functools.partial(make_atari_torchrl_env, "pong"), mp_start_method="spawn")
    try:
        env.set_seed(0)
        check_env_specs(env)
        n = 600
        blank = (env.rollout(n, break_when_any_done=False)["next", "observation"].flatten(2).amax(-1) == 0).float()
        assert blank.shape == (2, n)
        assert (abs(blank.mean(1) - 0.5) <= hoeffding(n)).all()
        assert abs((blank[0] == blank[1]).float().mean() - 0.5) <= hoeffding(n)
    finally:
        env.close()


# ---------------------------------------------------------------------------------------- agents
from omegaconf import OmegaConf  # noqa: E402

from escort_rl.config.bench_schemas import AtariBenchConfig  # noqa: E402
from escort_rl.config.checking import load_typed  # noqa: E402
from escort_rl.modules import DVRLPolicy, ESCORTLatent  # noqa: E402
from escort_rl.trainers.atari_a2c import AGENTS, AtariA2C  # noqa: E402


def tiny_atari_config(agent: str, tmp_path, **trainer) -> OmegaConf:
    """``configs/bench/atari.yaml`` at a size that trains in seconds."""
    from escort_rl.config import config_dir

    settings = OmegaConf.to_container(load_typed(config_dir() / "bench" / "atari.yaml", AtariBenchConfig))
    settings["trainer"].update(num_envs=2, rollout_steps=5, updates_per_iteration=10, lr=1e-3, **trainer)
    settings["vrnn"].update(num_particles=3, latent_dim=4, hidden=8, encoding_dim=8)
    settings["escort"].update(num_steps=2, compile=False)  # compiling would dominate the test's time
    settings["gru"].update(hidden=8)
    return OmegaConf.create({"seed": 0, "device": "cpu", "output_dir": str(tmp_path / agent),
                             "logger": {"backend": "csv"}, "game": "pong", "agent": agent, **settings})


@pytest.mark.parametrize("agent", AGENTS)
def test_each_agent_trains_a_few_hundred_frames(agent, tmp_path):
    torch.manual_seed(0)
    algorithm = AtariA2C(tiny_atari_config(agent, tmp_path))
    try:
        before = {k: v.detach().clone() for k, v in algorithm.policy.named_parameters()}
        records = [algorithm.iteration(i, 100 + i) for i in range(2)]
    finally:
        algorithm.close()
    assert sum(r["frames"] for r in records) == 200
    for r in records:
        assert all(math.isfinite(r[k]) for k in ("policy_loss", "value_loss", "entropy", "elbo", "fps"))
        assert (r["elbo"] == 0.0) == (agent == "gru")
    changed = [k for k, v in algorithm.policy.named_parameters() if not torch.equal(v, before[k])]
    # the encoder, the recurrence and both heads learn
    for part in ("encoder", "actor_head", "critic_head"):
        assert any(part in k for k in changed), (part, changed)


def test_escort_latent_moves_particles_without_resampling_and_learns_its_model():
    torch.manual_seed(0)
    from escort_rl.belief import ESCORTFilter

    def model(steps):
        torch.manual_seed(0)
        return ESCORTLatent((1, 84, 84), 3, 4, hidden=8, num_particles=5, encoding_dim=8,
                            escort=ESCORTFilter(num_steps=steps, jitter=0.0))

    obs = torch.rand(2, 1, 84, 84)
    action, reset = torch.zeros(2, dtype=torch.long), torch.tensor([True, False])
    moved, still = model(3), model(0)
    state, elbo, summary = moved.step(moved.initial_state(2), action, obs, reset, torch.Generator().manual_seed(1))
    state0, _, _ = still.step(still.initial_state(2), action, obs, reset, torch.Generator().manual_seed(1))
    assert torch.allclose(state.log_w, torch.full((2, 5), -math.log(5)))  # uniform: nothing resampled
    assert not torch.allclose(state.z, state0.z)  # the SVGD iterations moved the predicted particles
    assert elbo.shape == (2,) and torch.isfinite(elbo).all() and summary.shape == (2, 8)
    elbo.sum().backward()
    for net in (moved.emission, moved.prior, moved.proposal, moved.observation_encoder):
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())
    with pytest.raises(ValueError, match="resample"):
        ESCORTLatent((1, 84, 84), 3, 4, resample=True)
    assert isinstance(DVRLPolicy(moved).dvrl, ESCORTLatent)


def test_unknown_agent_is_named(tmp_path):
    with pytest.raises(ConfigError, match="agent: unknown 'ppo'"):
        AtariA2C(tiny_atari_config("ppo", tmp_path))


# ---------------------------------------------------------------------------------------- bench
import argparse  # noqa: E402
import json  # noqa: E402

from escort_rl.bench import atari as atari_bench  # noqa: E402

TINY_SET = ["trainer.num_envs=2", "trainer.updates_per_iteration=10", "vrnn.num_particles=3", "vrnn.latent_dim=4",
            "vrnn.hidden=8", "vrnn.encoding_dim=8", "escort.num_steps=2", "escort.compile=false", "gru.hidden=8"]


def bench_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    atari_bench.register(parser.add_subparsers())
    return parser.parse_args(["atari", *argv])


def test_bench_cell_resumes_from_its_checkpoint_and_reports_beside_the_paper(tmp_path, capsys):
    out = tmp_path / "atari"
    args = bench_args(*TINY_SET, "--frames", "100", "--agents", "gru", "--output", str(out))
    args.handler(args)  # 100 frames = 10 updates of 2 envs x 5 steps: one iteration
    run_dir = out / "runs" / "pong" / "gru" / "seed0"
    first = json.loads((run_dir / "history.json").read_text())
    assert [r["iteration"] for r in first] == [1]
    # a larger budget continues the same run from its checkpoint instead of starting again
    args = bench_args(*TINY_SET, "--frames", "200", "--agents", "gru", "--output", str(out))
    args.handler(args)
    history = json.loads((run_dir / "history.json").read_text())
    assert [r["iteration"] for r in history] == [1, 2] and history[0] == first[0]
    args.handler(args)  # a finished run is read, not trained again
    assert json.loads((run_dir / "history.json").read_text()) == history
    report = (out / "atari.md").read_text()
    assert "| pong | gru |" in report and "50,000,000" not in report.split("| pong | gru |")[1].splitlines()[0]
    assert (out / "learning_curves.png").stat().st_size > 0
    row = json.loads((out / "atari.json").read_text())["rows"][0]
    assert row["frames"] == 200 and row["fps"] > 0
    capsys.readouterr()


def run_result(agent, seed, returns, seconds_per_game=1.0, frames=1000, fps=5.0):
    n = len(returns)
    return {"game": "pong", "agent": agent, "seed": seed, "frames": frames, "fps": fps, "seconds": frames / fps,
            "game_returns": returns, "game_frames": list(range(n)),
            "game_seconds": [seconds_per_game * (i + 1) for i in range(n)]}


def test_bench_report_puts_random_and_paper_rows_beside_ours():
    rows = atari_bench.summarise([
        run_result("escort_latent", 0, [-21.0] * 150 + [-19.0] * 100),
        run_result("escort_latent", 1, [-17.0, -21.0], frames=1200, fps=7.0),
        run_result("gru", 0, [-21.0] * 50 + [-20.0] * 50, fps=50.0),  # done in 20 s: the equal wall-clock
        run_result("random", 0, [-21.0] * 99 + [-20.0], fps=float("nan"))])
    by_agent = {row["agent"]: row for row in rows}
    row = by_agent["escort_latent"]
    assert row["seeds"] == 2 and row["games"] == 102 and row["frames"] == 1000 and row["fps"] == 6.0
    assert row["return"][0] == pytest.approx((100 * -19.0 - 38.0) / 102)
    assert row["seed_means"] == [-19.0, -19.0]
    # at 20 s, seed 0 had ended 20 games (all -21) and seed 1 its two
    assert row["equal_seconds"] == 20.0 and row["games_equal_time"] == 22
    assert row["return_equal_time"][0] == pytest.approx((20 * -21.0 - 38.0) / 22)
    # two seeds: the comparison's figure is across seeds (both -19: no spread); random has one seed: its games'
    assert row["return_seeds"] == (-19.0, 0.0)
    random_mean, random_se = by_agent["random"]["return"]
    assert row["above_random"] == pytest.approx((-19.0 - random_mean) / random_se)
    assert by_agent["random"]["above_random"] is None
    table = atari_bench.markdown_table(rows, atari_bench.load_settings().paper)
    assert "17.97 ± 3.74 (ESCORT)" in table and "50,000,000" in table
    assert "| pong | escort_latent | -19.00 ± 0.00 | -19.00, -19.00 |" in table
    assert "| pong | random | -20.99 ± 0.01 | -20.99 | — | — |" in table


def test_the_random_policy_plays_whole_games_on_both_tiers():
    for game in ("pong", "breakout"):
        result = atari_bench.run_random_cell(game, seed=0, frames=20000, games=3)
        assert len(result["game_returns"]) == 3 and result["frames"] == result["game_frames"][-1]
        if game == "pong":  # a whole game of Pong ends at 21 points to one side
            assert all(-21 <= r <= -15 for r in result["game_returns"])


@pytest.mark.parametrize("argv, message", [
    (["--frames", "10"], "--frames: must be at least 80"),
    (["--frames", "1000", "--games", "tetris"], "--games: unknown game 'tetris'"),
    (["--frames", "1000", "--agents", "ppo"], "--agents: unknown agent 'ppo'"),
    (["escort.num_steps=0", "--frames", "1000"], "escort.num_steps"),
    (["vrnn.widht=3", "--frames", "1000"], "widht"),
    (["--games", "pong"], "--frames: give the frames"),
])
def test_bench_bad_arguments_name_the_flag(argv, message, tmp_path):
    args = bench_args(*argv, "--output", str(tmp_path))
    with pytest.raises(ValueError, match=message):
        args.handler(args)


def test_cli_registers_bench_atari(capsys):
    from escort_rl.cli import main

    assert main(["bench", "atari", "--frames", "10"]) == 2
    assert "--frames: must be at least 80" in capsys.readouterr().err


def test_a_seed_curve_is_its_running_mean_at_each_point_until_the_run_ends():
    grid = np.array([0.0, 1.0, 2.0, 3.0, 5.0, 10.0])
    curve = atari_bench.report.seed_curve([1, 2, 4], [1.0, 3.0, 5.0], grid, window=2, upto=6.0)
    # nothing ended at 0; then the mean of the last two games ended by each point; nothing after the run
    np.testing.assert_array_equal(curve, [np.nan, 1.0, 2.0, 2.0, 4.0, np.nan])
