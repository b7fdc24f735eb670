"""The cells of ``escort-rl bench atari``: one agent's A2C training run on one game and seed, or a
uniform-random policy's games."""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig

from escort_rl.bench.atari.report import LAST_GAMES, RANDOM
from escort_rl.bench.atari.settings import cell_config, load_settings
from escort_rl.bench.core.runner import Cell
from escort_rl.envs.flickering import flickering_game


def run_atari_cell(cfg: DictConfig, progress: bool = False) -> dict:
    """Train (or resume, or skip when finished) the run of ``cfg`` (:func:`cell_config`) and return
    its history, the returns of its games, the frame and the training second at which each ended, and
    its training frames/s."""
    import torch

    from escort_rl.trainers.atari_a2c import AtariA2C, GameLog
    from escort_rl.trainers.checkpointing import checkpoint_dir, list_checkpoints, load_checkpoint
    from escort_rl.trainers.scaffold import run_training

    run_dir = Path(cfg.output_dir)
    history_file = run_dir / "history.json"
    finished = history_file.exists() and any(r["iteration"] >= int(cfg.trainer.iterations)
                                             for r in json.loads(history_file.read_text()))
    if not finished:
        resume = {"path": str(run_dir)} if list_checkpoints(checkpoint_dir(run_dir)) else None
        torch.manual_seed(int(cfg.seed))  # the initial weights
        run_training(cfg, AtariA2C(cfg), resume_state=resume, progress=progress,
                     desc=f"{cfg.game} {cfg.agent} seed {cfg.seed}", watch=("episode_return", "fps"))
    games = GameLog()
    state = load_checkpoint(run_dir, games=games)["trainer_state"]
    history = state["history"][: int(cfg.trainer.iterations)]
    seconds = list(itertools.accumulate(r["seconds"] for r in history))
    frames = int(history[-1]["frames"])
    curve = [{"frames": r["frames"], "seconds": s, "episode_return": r["episode_return"]}
             for r, s in zip(history, seconds)]
    return {"game": cfg.game, "agent": cfg.agent, "seed": int(cfg.seed), "frames": frames,
            "fps": frames / seconds[-1] if seconds[-1] > 0 else float("nan"), "seconds": seconds[-1],
            "game_returns": games.returns, "game_frames": games.frames,
            "game_seconds": _interpolate(games.frames, [c["frames"] for c in curve], seconds), "curve": curve}


def _interpolate(x: list[int], xs: list[int], ys: list[float]) -> list[float]:
    """``ys`` read at ``x`` by linear interpolation over ``(0, 0), (xs, ys)``."""
    import numpy as np

    return np.interp(np.asarray(x, dtype=float), [0.0, *xs], [0.0, *ys]).tolist() if x else []


def run_random_cell(game: str, seed: int, frames: int, games: int) -> dict:
    """Uniform-random actions on the flickering ``game`` (seeded by ``seed``) until ``games`` games have
    ended or ``frames`` frames have passed; the returns (unclipped) and the frame at which each game ended."""
    import gymnasium as gym
    import numpy as np

    from escort_rl.envs.registration import register_gymnasium_envs

    register_gymnasium_envs()
    env = gym.make(flickering_game(game).env_id)
    rng = np.random.default_rng(seed)
    returns, ends, running = [], [], 0.0
    env.reset(seed=seed)
    try:
        for t in range(1, frames + 1):
            _, reward, terminated, truncated, info = env.step(int(rng.integers(env.action_space.n)))
            running += float(reward)
            if info["game_over"]:
                returns.append(running)
                ends.append(t)
                running = 0.0
                if len(returns) >= games:
                    break
            if terminated or truncated:  # a lost life (Atari) or the game's end
                env.reset()
    finally:
        env.close()
    return {"game": game, "agent": RANDOM, "seed": int(seed), "frames": t, "fps": float("nan"),
            "seconds": float("nan"), "game_returns": returns, "game_frames": ends, "game_seconds": [], "curve": []}


@dataclass(frozen=True, kw_only=True)
class AtariCell(Cell):
    """One (game, agent, seed): a training run under ``runs``, or the random policy's games (at most
    ``frames`` frames, stopping after :data:`LAST_GAMES` games)."""

    game: str
    agent: str
    seed: int
    frames: int
    runs: str
    overrides: tuple[str, ...] = ()
    stored = False  # its result lives in the run's checkpoints, which a later run may extend

    def key(self) -> str:
        return f"atari/{self.game}/{self.agent}/seed{self.seed}"

    def run(self) -> dict:
        if self.agent == RANDOM:
            return run_random_cell(self.game, self.seed, self.frames, LAST_GAMES)
        run_dir = Path(self.runs) / self.game / self.agent / f"seed{self.seed}"
        settings = load_settings(self.overrides, flickering_game(self.game).tier)
        cfg = cell_config(settings, self.game, self.agent, self.seed, self.frames, run_dir, self.device)
        return run_atari_cell(cfg)
