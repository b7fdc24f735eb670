"""``escort-rl bench atari``: Flickering Atari, the paper's Table 4.

Each (game, agent, seed) is one cell (:class:`AtariCell`): an A2C training run
(:class:`escort_rl.trainers.atari_a2c.AtariA2C`) on the training scaffold, in
``<output>/runs/<game>/<agent>/seed<k>``. The scaffold checkpoints it every iteration, so a killed or
stopped benchmark resumes each unfinished cell from its last checkpoint when the same command runs
again, and a larger ``--frames`` continues finished cells. The cells run on the runner's backends
(``--backend inprocess | process | ray``).

The report (``atari.md``, ``atari.json``, ``learning_curves.png``): per game and agent the mean ±
s.e. of the last 100 games' returns (unclipped game scores, pooled over seeds: the last 100 of each
seed), the frames trained, and the training frames/s; beside it, the paper's Table 4 with its budget.
Frames are agent steps (4 emulator frames each), as DVRL counted them.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from escort_rl.bench.core import options
from escort_rl.bench.core.runner import Cell, CellStore, backend_from_args, run_cells
from escort_rl.bench.methods import check_choices
from escort_rl.envs.flickering import flickering_game, game_names
from escort_rl.reporting.paths import write_results
from escort_rl.reporting.stats import format_mean_se, mean_se

LAST_GAMES = 100  # the returns of the last games of each seed that the table averages
PAPER_METHOD = {"escort_latent": "escort", "dvrl": "dvrl"}  # our agent -> the paper's Table 4 column


def settings_path(tier: str = "atari") -> Path:
    """``configs/bench/atari.yaml`` (Atari's settings) or ``configs/bench/minatar.yaml`` (MinAtar's)."""
    from escort_rl.config import config_dir

    return config_dir() / "bench" / f"{tier}.yaml"


def load_settings(overrides: tuple[str, ...] | list[str] = (), tier: str = "atari") -> DictConfig:
    """The settings of ``tier`` (:func:`settings_path`) with ``overrides`` (``KEY=VALUE``, e.g.
    ``escort.num_steps=10``), typed and checked (:class:`escort_rl.config.bench_schemas.AtariBenchConfig`);
    a bad key or value raises ``ConfigError`` naming it."""
    from omegaconf.errors import OmegaConfBaseException

    from escort_rl.config import ConfigError
    from escort_rl.config.bench_schemas import AtariBenchConfig
    from escort_rl.config.checking import check_config, describe_error, load_typed

    settings = load_typed(settings_path(tier), AtariBenchConfig)
    bad = [o for o in overrides if "=" not in o]
    if bad:
        raise ConfigError(f"overrides: '{bad[0]}' is not KEY=VALUE, e.g. escort.num_steps=10")
    try:
        settings = OmegaConf.merge(settings, OmegaConf.from_dotlist(list(overrides)))
    except OmegaConfBaseException as err:
        raise ConfigError(f"overrides: {describe_error(err)}") from None
    check_config(settings, AtariBenchConfig, prefix="overrides: ")
    return settings


def frames_per_update(settings: DictConfig) -> int:
    return int(settings.trainer.num_envs) * int(settings.trainer.rollout_steps)


def cell_config(settings: DictConfig, game: str, agent: str, seed: int, frames: int, run_dir: Path,
                device: str = "cpu") -> DictConfig:
    """The run config of one cell for :class:`~escort_rl.trainers.atari_a2c.AtariA2C` and the scaffold.

    ``frames`` is rounded up to whole A2C updates of ``num_envs × rollout_steps`` frames; an iteration
    is ``updates_per_iteration`` updates, or all of them when the budget is smaller than one iteration.
    """
    per_update = frames_per_update(settings)
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < per_update:
        raise ValueError(f"--frames: must be at least {per_update} (one A2C update of "
                         f"{settings.trainer.num_envs} envs × {settings.trainer.rollout_steps} steps), got {frames}")
    updates = math.ceil(frames / per_update)
    per_iteration = min(int(settings.trainer.updates_per_iteration), updates)
    cfg = OmegaConf.create({"seed": int(seed), "device": device, "output_dir": str(run_dir),
                            "logger": {"backend": "csv"}, "game": game, "agent": agent,
                            **OmegaConf.to_container(settings, resolve=True)})
    cfg.trainer.updates_per_iteration = per_iteration
    cfg.trainer.iterations = math.ceil(updates / per_iteration)
    return cfg


def run_atari_cell(cfg: DictConfig, progress: bool = False) -> dict:
    """Train (or resume, or skip when finished) the run of ``cfg`` (:func:`cell_config`) and return
    its history, the returns of its games and its training frames/s."""
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
    seconds = sum(r["seconds"] for r in history)
    frames = int(history[-1]["frames"])
    return {"game": cfg.game, "agent": cfg.agent, "seed": int(cfg.seed), "frames": frames,
            "fps": frames / seconds if seconds > 0 else float("nan"),
            "game_returns": games.returns, "game_frames": games.frames,
            "curve": [{"frames": r["frames"], "episode_return": r["episode_return"]} for r in history]}


@dataclass(frozen=True, kw_only=True)
class AtariCell(Cell):
    """One (game, agent, seed) training run under ``runs`` (see the module docstring)."""

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
        run_dir = Path(self.runs) / self.game / self.agent / f"seed{self.seed}"
        settings = load_settings(self.overrides, flickering_game(self.game).tier)
        cfg = cell_config(settings, self.game, self.agent, self.seed, self.frames, run_dir, self.device)
        return run_atari_cell(cfg)


# ------------------------------------------------------------------------------------ the report
def summarise(results: list[dict]) -> list[dict]:
    """One row per (game, agent): the last :data:`LAST_GAMES` game returns of each seed pooled,
    their mean ± s.e., the frames and the frames/s (mean over seeds)."""
    rows: dict[tuple[str, str], dict] = {}
    for r in results:
        row = rows.setdefault((r["game"], r["agent"]), {"game": r["game"], "agent": r["agent"], "returns": [],
                                                        "frames": [], "fps": [], "seeds": 0})
        row["returns"] += r["game_returns"][-LAST_GAMES:]
        row["frames"].append(r["frames"])
        row["fps"].append(r["fps"])
        row["seeds"] += 1
    out = []
    for row in rows.values():
        out.append({"game": row["game"], "agent": row["agent"], "seeds": row["seeds"], "games": len(row["returns"]),
                    "return": mean_se(row["returns"]), "frames": min(row["frames"]),
                    "fps": sum(row["fps"]) / len(row["fps"])})
    return out


def markdown_table(rows: list[dict], paper: DictConfig | None) -> str:
    """Ours beside the paper's Table 4 (where ``paper`` has the game), each with its budget in frames
    (agent steps)."""
    lines = ["| game | agent | ours: last 100 games, mean ± s.e. | games (seeds) | our frames | frames/s "
             "| paper (same method) | paper frames |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in rows:
        method = PAPER_METHOD.get(row["agent"])
        ref = paper.table4.get(row["game"], {}).get(method) if method and paper is not None else None
        paper_text, paper_frames = ((f"{ref[0]} ± {ref[1]} ({method.upper()})", f"{int(paper.frames):,}")
                                    if ref is not None else ("—", "—"))
        lines.append(f"| {row['game']} | {row['agent']} | {format_mean_se(row['return'], 2)} | {row['games']} "
                     f"({row['seeds']}) | {row['frames']:,} | {row['fps']:.1f} | {paper_text} | {paper_frames} |")
    return "\n".join(lines) + "\n"


def plot_curves(results: list[dict], path: Path, window: int = 20) -> Path:
    """Learning curves, one panel per game: each agent's game returns (all seeds pooled, in the
    order of the frame at which each game ended), smoothed by a running mean over ``window`` games
    per seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    games = sorted({r["game"] for r in results})
    fig, axes = plt.subplots(1, len(games), figsize=(5 * len(games), 3.6), squeeze=False)
    for ax, game in zip(axes[0], games):
        for agent in sorted({r["agent"] for r in results if r["game"] == game}):
            runs = [r for r in results if r["game"] == game and r["agent"] == agent]
            points = sorted(p for r in runs for p in zip(r["game_frames"], r["game_returns"]))
            if not points:
                continue
            w = window * len(runs)
            xs = [x for x, _ in points]
            ys = [sum(y for _, y in points[max(0, i - w + 1): i + 1]) / (i + 1 - max(0, i - w + 1))
                  for i in range(len(points))]
            ax.plot(xs, ys, label=f"{agent} ({len(runs)} seeds)")
        ax.set_title(f"Flickering {game}")
        ax.set_xlabel("frames (agent steps)")
        ax.set_ylabel("game return")
        if ax.lines:
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "no game has ended yet", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------------ the command
QUICK_FRAMES = 256
"""``--quick``: frames per run."""


def main(args) -> None:
    from escort_rl.trainers.atari_a2c import AGENTS

    check_choices("--games", args.games or [], game_names(), "game")
    check_choices("--agents", args.agents, list(AGENTS), "agent")
    from escort_rl.config.schema import check_device

    problem = check_device(args.device)
    if problem is not None:
        raise ValueError(f"--device: {problem}")
    frames = args.frames if args.frames is not None else QUICK_FRAMES if args.quick else None
    if frames is None:
        raise ValueError("--frames: give the frames (agent steps) per run, e.g. --frames 10000000, or --quick")
    games = args.games if args.games is not None else ["pong"]
    settings = {tier: load_settings(tuple(args.overrides), tier) for tier in {flickering_game(g).tier for g in games}}
    out = Path(args.output).expanduser()
    for game in games:  # checks --frames before any run starts
        cell_config(settings[flickering_game(game).tier], game, args.agents[0], 0, frames, out, args.device)
    cells = [AtariCell(game=g, agent=a, seed=s, frames=frames, runs=str(out / "runs"), overrides=tuple(args.overrides),
                       threads=args.threads or 1, device=args.device)
             for g in games for a in args.agents for s in range(args.seeds)]
    t0 = time.perf_counter()
    results = run_cells(cells, backend_from_args(args), CellStore(out / "cells"), desc="atari cells")
    rows = summarise(results)
    curves = plot_curves(results, out / "learning_curves.png")
    paper = settings["atari"].paper if "atari" in settings else None
    markdown = (f"# Flickering games (Table 4): {frames:,} frames per run\n\n"
                + markdown_table(rows, paper)
                + "\nFrames are agent steps (4 emulator frames each on Atari, as DVRL counted them; one MinAtar "
                "step each). Random: a uniform-random policy on the same games."
                + (f" The paper's rows ran {int(paper.frames):,} frames." if paper is not None else "")
                + f" Learning curves: {curves.name}.\n")
    write_results(out, "atari", {"rows": rows, "runs": results}, markdown, time.perf_counter() - t0)


def register(subparsers) -> None:
    """Add ``bench atari`` to the ``bench`` subparsers."""
    p = subparsers.add_parser("atari", help="Flickering Atari: DVRL, ESCORT-latent and a GRU by A2C (Table 4)",
                              description="Trains each agent on each flickering game for --frames frames per seed "
                              "(A2C, DVRL's Atari settings in configs/bench/atari.yaml), then reports the last 100 "
                              "games' returns (mean ± s.e.) and frames/s beside the paper's Table 4, and learning "
                              "curves. Rerunning the same command resumes unfinished runs from their checkpoints.")
    options.add_overrides_argument(p, "overrides of configs/bench/atari.yaml, e.g. escort.num_steps=10 "
                           "trainer.parallel_envs=true")
    p.add_argument("--games", nargs="+", default=None,
                   help="of pong icehockey mspacman asteroids (Atari) and breakout spaceinvaders asterix freeway "
                   "seaquest (MinAtar) (default: pong)")
    p.add_argument("--agents", nargs="+", default=["dvrl", "escort_latent", "gru"], help="of dvrl escort_latent gru")
    p.add_argument("--frames", type=int, default=None,
                   help=f"frames (agent steps) per run; required but for --quick (default: none; --quick: "
                   f"{QUICK_FRAMES})")
    options.add_seeds_option(p, 1, "seeds 0..N-1 per game and agent")
    p.add_argument("--device", default="cpu", help="torch device of the networks")
    options.add_quick_option(p, f"pong, every agent, {QUICK_FRAMES} frames per run")
    options.add_output_option(p, "outputs/bench/atari", "the runs, atari.md, atari.json and the learning curves")
    options.add_runner_options(p, seeds_per_cell=False)
    p.set_defaults(handler=main)
