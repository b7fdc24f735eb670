"""``escort-rl bench atari``: the command."""

from __future__ import annotations

import time
from pathlib import Path

from escort_rl.bench.atari.cells import AtariCell
from escort_rl.bench.atari.report import RANDOM, markdown_table, plot_curves, summarise
from escort_rl.bench.atari.settings import cell_config, load_settings
from escort_rl.bench.core import options
from escort_rl.bench.core.runner import CellStore, backend_from_args, run_cells
from escort_rl.bench.methods import check_choices
from escort_rl.envs.flickering import flickering_game, game_names
from escort_rl.reporting.paths import write_results

QUICK_FRAMES = 256
"""``--quick``: frames per run."""


def main(args) -> None:
    from escort_rl.config.schema import check_device
    from escort_rl.trainers.atari_a2c import AGENTS

    check_choices("--games", args.games or [], game_names(), "game")
    check_choices("--agents", args.agents, [*AGENTS, RANDOM], "agent")
    problem = check_device(args.device)
    if problem is not None:
        raise ValueError(f"--device: {problem}")
    frames = args.frames if args.frames is not None else QUICK_FRAMES if args.quick else None
    if frames is None:
        raise ValueError("--frames: give the frames (agent steps) per run, e.g. --frames 10000000, or --quick")
    games = args.games if args.games is not None else ["pong"]
    tiers = {game: flickering_game(game).tier for game in games}
    settings = {tier: load_settings(tuple(args.overrides), tier) for tier in set(tiers.values())}
    out = Path(args.output).expanduser()
    for game in games:  # checks --frames before any run starts
        cell_config(settings[tiers[game]], game, args.agents[0], 0, frames, out, args.device)
    cells = [AtariCell(game=g, agent=a, seed=s, frames=frames, runs=str(out / "runs"), overrides=tuple(args.overrides),
                       threads=args.threads or 1, device=args.device)
             for g in games for a in args.agents for s in range(args.seeds)]
    t0 = time.perf_counter()
    results = run_cells(cells, backend_from_args(args), CellStore(out / "cells"), desc="atari cells")
    rows = summarise(results)
    curves = plot_curves(results, out / "learning_curves.png")
    paper = settings["atari"].paper if "atari" in settings else None
    markdown = (f"# Flickering games: {frames:,} frames per run\n\n"
                + markdown_table(rows, paper)
                + "\nFrames are agent steps (4 emulator frames each on Atari, as DVRL counted them; one step each on "
                "MinAtar). Returns are whole games' unclipped scores: each seed's last 100 games averaged, then "
                "mean ± s.e. across seeds (the games' s.e. for one seed). Above random: the distance to the random "
                "policy's mean in combined standard errors. At equal wall-clock: the last games each run had "
                "ended by the training seconds in brackets, those the fastest agent took for its frames."
                + (f" The paper's rows ran {int(paper.frames):,} frames." if paper is not None else "")
                + f" Learning curves: {curves.name}.\n")
    write_results(out, "atari", {"rows": rows, "runs": results}, markdown, time.perf_counter() - t0)


def register(subparsers) -> None:
    """Add ``bench atari`` to the ``bench`` subparsers."""
    p = subparsers.add_parser("atari", help="Flickering Atari and MinAtar: DVRL, ESCORT-latent and a GRU by A2C "
                              "(Table 4)",
                              description="Trains each agent on each flickering game for --frames frames per seed "
                              "(A2C; the settings in configs/bench/atari.yaml for Atari, configs/bench/minatar.yaml "
                              "for MinAtar), then reports the last 100 games' returns (mean ± s.e.) beside a random "
                              "policy's and the paper's Table 4, at equal frames and at equal wall-clock, frames/s, "
                              "and learning curves. Rerunning the same command resumes unfinished runs from their "
                              "checkpoints.")
    options.add_overrides_argument(p, "overrides of the settings, e.g. escort.num_steps=10 trainer.parallel_envs=true")
    p.add_argument("--games", nargs="+", default=None,
                   help="of pong icehockey mspacman asteroids (Atari) and breakout spaceinvaders asterix freeway "
                   "seaquest (MinAtar) (default: pong)")
    p.add_argument("--agents", nargs="+", default=["dvrl", "escort_latent", "gru", RANDOM],
                   help="of dvrl escort_latent gru random")
    p.add_argument("--frames", type=int, default=None,
                   help=f"frames (agent steps) per run; required but for --quick (default: none; --quick: "
                   f"{QUICK_FRAMES})")
    options.add_seeds_option(p, 1, "seeds 0..N-1 per game and agent")
    p.add_argument("--device", default="cpu", help="torch device of the networks")
    options.add_quick_option(p, f"pong, every agent, {QUICK_FRAMES} frames per run")
    options.add_output_option(p, "outputs/bench/atari", "the runs, atari.md, atari.json and the learning curves")
    options.add_runner_options(p, seeds_per_cell=False)
    p.set_defaults(handler=main)
