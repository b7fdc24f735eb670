"""Flickering Atari on ALE's vector env: the same frames, lives, resets and blanks as
``Flicker(DVRLAtari(...))``, the same TorchRL specs and seeding as a ``SerialEnv`` of
``make_atari_torchrl_env``, the trainer's and the benchmark's use of it.

Frames are compared to ``ATOL``: the vectorised env computes DVRLAtari's box average exactly and
rounds it once, while DVRLAtari's two ``float32`` matrix products round at each step; on frames in
``[0, 1]`` they differ by a few ``float32`` ulps (1.2e-7 seen), and ``ATOL`` leaves room for that
while staying far below one grey level (1/255). Everything else (rewards, flags, lives, blanks) is
compared exactly.
"""

from __future__ import annotations

import functools
import math
import sys

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from torchrl.envs import SerialEnv
from torchrl.envs.utils import check_env_specs

from escort_rl.config import ConfigError
from escort_rl.envs.atari import (
    FLICKER_STREAM,
    area_resize_matrix,
    area_taps,
    make_atari_torchrl_env,
    make_flickering_atari,
    resize_screens,
)
from escort_rl.envs.atari_vector import (
    ALE_SEED_LIMIT,
    DVRLAtariVector,
    dvrl_ale_seed,
    make_atari_vector_env,
)

ATOL = 0.0  # both envs resize by the same exact sums: the frames are equal bit for bit
DETERMINISTIC = dict(repeat_action_probability=0.0, noop_max=0)  # the game then depends on the actions only


def hoeffding(n: int, delta: float = 1e-9) -> float:
    """Half-width of a two-sided Hoeffding bound on the mean of ``n`` draws in [0, 1]."""
    return math.sqrt(math.log(2 / delta) / (2 * n))


def ale_seed_fits(seed: int) -> bool:
    """Whether DVRLAtari's ALE seed for ``reset(seed=seed)`` is one ALE's vector env can take."""
    return dvrl_ale_seed(np.random.default_rng(seed).integers(0, 2**31 - 1)) < ALE_SEED_LIMIT


def seeds_from(start: int, count: int, fits: bool) -> list[int]:
    """The first ``count`` seeds from ``start`` whose ALE seed fits (``fits``) or does not."""
    seeds, seed = [], start
    while len(seeds) < count:
        if ale_seed_fits(seed) == fits:
            seeds.append(seed)
        seed += 1
    return seeds


class ReferenceGames:
    """``Flicker(DVRLAtari)`` games, one per seed, behind :class:`DVRLAtariVector`'s interface."""

    def __init__(self, game: str, num_envs: int, **kwargs) -> None:
        self.envs = [make_flickering_atari(game, **kwargs) for _ in range(num_envs)]
        self.n_actions = int(self.envs[0].action_space.n)
        self.blank, self.lives = np.zeros(num_envs, dtype=bool), np.zeros(num_envs, dtype=int)

    def _note(self, k: int, info: dict) -> None:
        self.blank[k], self.lives[k] = info["blank"], info["lives"]

    def reset(self, mask=None, seeds=None) -> np.ndarray:
        obs = []
        for k, env in enumerate(self.envs):
            if mask is None or mask[k]:
                frame, info = env.reset(seed=None if seeds is None else seeds[k])
                self._note(k, info)
                obs.append(frame)
            else:
                obs.append(self.last[k])
        self.last = np.stack(obs)
        return self.last

    def step(self, actions):
        out = [env.step(int(a)) for env, a in zip(self.envs, actions)]
        for k, o in enumerate(out):
            self._note(k, o[4])
        self.last = np.stack([o[0] for o in out])
        return (self.last, *(np.array([o[i] for o in out]) for i in (1, 2, 3)),
                np.array([bool(o[4]["game_over"]) for o in out]))


def play(games, seeds: list[int], steps: int) -> dict:
    """``steps`` steps of uniform actions (a fixed stream) in ``games`` (:class:`ReferenceGames` or
    :class:`DVRLAtariVector`), each env reset when its episode ends. Returns the record: ``first``
    (the seeded reset's frames), per step ``frame`` (the step's), ``root`` (the next step's start:
    the reset's frame where the episode ended), ``reward``, ``terminated``, ``truncated``,
    ``game_over``, ``lives`` and ``blank`` (after the step) and ``reset_blank``/``reset_lives``."""
    record = {key: [] for key in ("frame", "root", "reward", "terminated", "truncated", "game_over", "lives", "blank",
                                  "reset_blank", "reset_lives")}
    record["first"] = games.reset(seeds=seeds).copy()
    record["first_blank"] = games.blank.copy()
    rng = np.random.default_rng(0)
    for _ in range(steps):
        frame, reward, terminated, truncated, game_over = games.step(rng.integers(games.n_actions, size=len(seeds)))
        for key, value in (("frame", frame), ("reward", reward), ("terminated", terminated),
                           ("truncated", truncated), ("game_over", game_over), ("lives", games.lives),
                           ("blank", games.blank)):
            record[key].append(np.array(value, copy=True))
        done = terminated | truncated
        record["root"].append(games.reset(done).copy() if done.any() else frame.copy())
        record["reset_blank"].append(games.blank.copy())
        record["reset_lives"].append(games.lives.copy())
    return {key: np.stack(value) if isinstance(value, list) else value for key, value in record.items()}


def play_both(game: str, seeds: list[int], steps: int, **kwargs) -> dict:
    """Play the same actions in ``Flicker(DVRLAtari)`` games (one per seed) and in the vectorised env,
    one after the other (OpenBLAS's spinning threads would slow ALE's if interleaved); asserts that
    rewards, flags, lives and blanks agree at every step, and frames to ``ATOL``, but for the frame
    of the step that ends a game (the vectorised env's documented stale frame). Returns counts."""
    ours = play(DVRLAtariVector(game, len(seeds), **kwargs), seeds, steps)
    theirs = play(ReferenceGames(game, len(seeds), **kwargs), seeds, steps)
    for key in ("reward", "terminated", "truncated", "game_over", "lives", "blank", "reset_blank", "reset_lives",
                "first_blank"):
        np.testing.assert_array_equal(ours[key], theirs[key], err_msg=key)
    for key in ("first", "root"):
        np.testing.assert_allclose(ours[key], theirs[key], rtol=0, atol=ATOL, err_msg=key)
    close = np.abs(ours["frame"] - theirs["frame"]).reshape(steps, len(seeds), -1).max(-1) <= ATOL
    assert (close | theirs["game_over"]).all()
    done = theirs["terminated"] | theirs["truncated"]
    return {"life_losses": int((done & ~theirs["game_over"]).sum()), "game_overs": int(theirs["game_over"].sum()),
            "truncations": int(theirs["truncated"].sum()), "stale_frames": int((~close).sum())}


def test_resize_is_the_exact_box_average_rounded_once(per_test_seed):
    screens = np.random.default_rng(per_test_seed).integers(0, 256, (5, 210, 160), dtype=np.uint8)
    frames = resize_screens(screens, area_taps(210, 84), area_taps(160, 84))
    assert frames.shape == (5, 1, 84, 84) and frames.dtype == np.float32
    # the box average: the matrix's weights are overlaps in 1/84 of a pixel over the source size, so
    # integer sums (exact in float64) over 210·160·255; ours is it rounded once, within half a float32 ulp
    rows, cols = (np.rint(area_resize_matrix(n, 84).astype(np.float64) * n) for n in (210, 160))
    for weights, n in ((rows, 210), (cols, 160)):
        assert (weights.sum(1) == n).all()
        np.testing.assert_allclose(weights / n, area_resize_matrix(n, 84), rtol=1e-6)
    exact = np.stack([rows @ s @ cols.T for s in screens.astype(np.float64)])[:, None] / (210 * 160 * 255)
    assert (np.abs(frames - exact) <= np.spacing(np.float32(1.0)) / 2).all()


def test_same_frames_as_dvrl_atari_across_lost_lives_and_a_finished_game(per_test_seed):
    # without sticky actions and no-ops a game follows the actions alone: this action stream loses
    # MsPacman's three lives by step 368, the game continuing after each; the seed's ALE seed does not
    # fit the vector env, which matters to sticky actions only
    counts = play_both("mspacman", seeds_from(per_test_seed, 1, False), 375, **DETERMINISTIC)
    assert counts["life_losses"] >= 2 and counts["game_overs"] >= 1, counts


def test_truncation_ends_the_game_as_in_dvrl_atari(per_test_seed):
    counts = play_both("asteroids", [per_test_seed, per_test_seed + 1], 100, max_frames=160, **DETERMINISTIC)
    assert counts["truncations"] >= 3 and counts["life_losses"] >= 1, counts  # 160 frames: ~40 steps a game


def test_sticky_actions_and_noops_match_where_the_ale_seed_fits(per_test_seed):
    play_both("pong", seeds_from(per_test_seed, 2, True), 100)  # DVRL's settings: sticky 0.25, up to 30 no-ops


def test_a_seed_whose_ale_seed_does_not_fit_still_replays(per_test_seed):
    seed = seeds_from(per_test_seed, 1, False)

    def run():
        env = DVRLAtariVector("pong", 1)
        frames = [env.reset(seeds=seed).copy()]
        rng = np.random.default_rng(1)
        frames += [env.step(rng.integers(env.n_actions, size=1))[0].copy() for _ in range(60)]
        env.close()
        return np.stack(frames)

    assert np.array_equal(run(), run())


def test_torchrl_env_has_serial_env_specs_seeds_and_rollouts(per_test_seed):
    kwargs = DETERMINISTIC
    serial = SerialEnv(2, functools.partial(make_atari_torchrl_env, "mspacman", **kwargs))
    vec = make_atari_vector_env("mspacman", 2, **kwargs)
    check_env_specs(vec)
    for name in ("full_observation_spec", "full_action_spec", "full_reward_spec", "full_done_spec"):
        assert getattr(vec, name) == getattr(serial, name), name
    assert vec.set_seed(per_test_seed) == serial.set_seed(per_test_seed)  # the same seed chain

    def policy():  # the same uniform actions for both
        rng = np.random.default_rng(0)
        return lambda td: td.set("action", torch.as_tensor(rng.integers(9, size=2)))

    ours, theirs = (env.rollout(130, policy(), break_when_any_done=False) for env in (vec, serial))
    vec.close()
    serial.close()
    for key in ("action", ("next", "reward"), ("next", "done"), ("next", "terminated"), ("next", "truncated"),
                ("next", "game_over")):
        assert torch.equal(ours[key], theirs[key]), key
    assert (theirs["next", "done"].squeeze(-1) & ~theirs["next", "game_over"]).any()  # a life lost, the game on
    torch.testing.assert_close(ours["observation"], theirs["observation"], rtol=0, atol=ATOL)  # resets included
    same = (ours["next", "observation"] - theirs["next", "observation"]).abs().flatten(2).amax(-1) <= ATOL
    assert (same | theirs["next", "game_over"]).all()


def test_each_env_flickers_with_its_own_seeded_stream(per_test_seed):
    n, env = 1500, make_atari_vector_env("pong", 3, frame_skip=1, **DETERMINISTIC)
    env.set_seed(per_test_seed)
    rng = np.random.default_rng(0)
    rollout = env.rollout(n, lambda td: td.set("action", torch.as_tensor(rng.integers(6, size=3))),
                          break_when_any_done=False)
    env.close()
    assert not rollout["next", "done"].any()  # 1500 frames of Pong: no reset draws in between
    blank = (rollout["next", "observation"].flatten(2).amax(-1) == 0).double()
    assert blank.shape == (3, n)
    assert (abs(blank.mean(1) - 0.5) <= hoeffding(n)).all()
    for a, b in ((0, 1), (0, 2), (1, 2)):  # independent fair coins agree half the time
        assert abs((blank[a] == blank[b]).double().mean() - 0.5) <= hoeffding(n)
    # env 0 is seeded with the seed itself: after set_seed's reset and rollout's reset, Flicker's draws
    draws = np.random.default_rng([per_test_seed, FLICKER_STREAM]).random(n + 2)[2:] < 0.5
    assert blank[0].bool().tolist() == draws.tolist()


def test_bad_arguments_name_the_field(monkeypatch):
    for kwargs, field in ((dict(num_envs=0), "num_envs"), (dict(frame_skip=0), "frame_skip"),
                          (dict(noop_max=-1), "noop_max"), (dict(repeat_action_probability=2.0),
                                                            "repeat_action_probability"),
                          (dict(p_blank=1.5), "p_blank"), (dict(max_frames=0), "max_frames")):
        with pytest.raises(ValueError, match=field):
            DVRLAtariVector("pong", **{"num_envs": 1, **kwargs})
    with pytest.raises(ConfigError, match="game: 'breakout' has no vectorised env"):
        DVRLAtariVector("breakout")
    env = DVRLAtariVector("pong", 2)
    with pytest.raises(RuntimeError, match="reset them first"):
        env.step([0, 0])
    env.reset(seeds=[1, 2])
    with pytest.raises(ValueError, match=r"action: expected 2 ints in \[0, 6\)"):
        env.step([0, 6])
    with pytest.raises(ValueError, match="seeds: expected 2 seeds"):
        env.reset(seeds=[1])
    env.close()
    monkeypatch.setitem(sys.modules, "ale_py.vector_env", None)
    with pytest.raises(ImportError, match=r"pip install escort-rl\[atari\]"):
        DVRLAtariVector("pong")


# ---------------------------------------------------------------------------------------- trainer
def tiny_config(tmp_path, **trainer) -> OmegaConf:
    """``configs/bench/atari.yaml`` with the GRU agent at a size that trains in seconds."""
    from escort_rl.config import config_dir
    from escort_rl.config.bench_schemas import AtariBenchConfig
    from escort_rl.config.checking import load_typed

    settings = OmegaConf.to_container(load_typed(config_dir() / "bench" / "atari.yaml", AtariBenchConfig))
    assert settings["trainer"]["vectorized_envs"] is False  # the default: today's SerialEnv
    settings["trainer"].update(num_envs=2, rollout_steps=5, updates_per_iteration=4, **trainer)
    settings["gru"].update(hidden=8)
    return OmegaConf.create({"seed": 0, "device": "cpu", "output_dir": str(tmp_path), "logger": {"backend": "csv"},
                             "game": "pong", "agent": "gru", **settings})


def test_a2c_trains_on_the_vectorised_env(tmp_path):
    from escort_rl.trainers.atari_a2c import AtariA2C

    torch.manual_seed(0)
    algorithm = AtariA2C(tiny_config(tmp_path, vectorized_envs=True))
    try:
        assert type(algorithm.env.base_env).__name__ == "FlickeringAtariVectorEnv"
        record = algorithm.iteration(0, 5)
    finally:
        algorithm.close()
    assert record["frames"] == 2 * 5 * 4 and math.isfinite(record["policy_loss"])


def test_vectorised_and_parallel_envs_exclude_each_other(tmp_path):
    from escort_rl.trainers.atari_a2c import AtariA2C, make_atari_env

    with pytest.raises(ConfigError, match="trainer.vectorized_envs: .* trainer.parallel_envs=false"):
        AtariA2C(tiny_config(tmp_path, vectorized_envs=True, parallel_envs=True))
    with pytest.raises(ValueError, match="vectorized: .* parallel=False"):
        make_atari_env("pong", 2, None, parallel=True, vectorized=True)


# ---------------------------------------------------------------------------------------- bench
def test_bench_atari_envs_times_each_kind(tmp_path, capsys):
    import json

    from escort_rl.cli import main

    assert main(["bench", "atari-envs", "--quick", "--output", str(tmp_path)]) in (None, 0)
    rows = json.loads((tmp_path / "atari_envs.json").read_text())["rows"]
    assert [r["kind"] for r in rows] == ["serial", "vectorized"]
    assert all(r["frames"] == 2 * 20 and r["frames_per_second"] > 0 for r in rows)
    assert "| vectorized |" in (tmp_path / "atari_envs.md").read_text()
    assert main(["bench", "atari-envs", "--kinds", "threads", "--output", str(tmp_path)]) == 2
    assert "--kinds: unknown kind 'threads'" in capsys.readouterr().err
    assert main(["bench", "atari-envs", "--game", "tetris", "--output", str(tmp_path)]) == 2
    assert "--game: unknown game 'tetris'" in capsys.readouterr().err
