"""``escort-rl bench atari-cost``: what a frame of each flickering-game agent costs, and what Table 4 would.

For each game's frame shape and the VRNN sizes of its settings (``configs/bench/atari.yaml`` or
``minatar.yaml``), the networks alone (no env) take A2C windows of ``rollout_steps`` steps over
``num_envs`` envs with gradients, then the window's backward pass, as the trainer does; the seconds
per frame are the fastest of ``--repeats`` windows after a warm-up (which holds any compilation).
Rows: the GRU, DVRL, and ESCORT-latent along the chain of speed choices, each row adding one to the
row above:

1. ``pixels, proposal, K=5, ascent 10, eager``: DVRL's pixel emission and ELBO, five iterations;
2. ``+ features``: the likelihood of the observation's encoding instead of its pixels;
3. ``+ prior ELBO``: the bootstrap ELBO of the predicted particles (no proposal network);
4. ``+ K=2``: two iterations;
5. ``+ ascent 3``: three ascent steps for the max-sliced directions of both forces;
6. ``+ compile``: the iteration through ``torch.compile`` (the settings' default).

The projection: the hours Table 4 would take at these rates, ``frames × games × seeds / (frames/s)``
per agent, with the paper's budget (50M frames, 4 games) and ``--seeds`` seeds; the networks' rate is an
upper bound on the training rate, which adds the envs.
"""

from __future__ import annotations

import time
from pathlib import Path

from escort_rl.bench.core import options
from escort_rl.reporting.paths import write_results

CHAIN = (
    ("pixels, proposal, K=5, ascent 10, eager", {"likelihood": "pixels", "elbo": "proposal", "num_steps": 5,
                                                 "temporal_ascent_steps": 10, "projection_ascent_steps": 10,
                                                 "compile": False}),
    ("+ features", {"likelihood": "features"}),
    ("+ prior ELBO", {"elbo": "prior"}),
    ("+ K=2", {"num_steps": 2}),
    ("+ ascent 3", {"temporal_ascent_steps": 3, "projection_ascent_steps": 3}),
    ("+ compile", {"compile": True}),
)
"""ESCORT-latent's speed choices, each row's changes on top of the row above."""


def window_seconds_per_frame(policy, obs_shape: tuple[int, ...], num_envs: int, steps: int, repeats: int,
                             device: str) -> float:
    """Seconds per frame of the networks of ``policy`` (a ``DVRLPolicy`` or ``FrameGRUPolicy``) over
    A2C windows of ``steps`` steps of ``num_envs`` envs: forward with gradients, then backward; the
    fastest of ``repeats`` windows after one warm-up window."""
    import torch
    from tensordict import TensorDict

    primer = policy.make_tensordict_primer()
    elbo_key = getattr(policy, "elbo_key", None)
    generator = torch.Generator(device=device).manual_seed(0)
    td = TensorDict({key: torch.zeros(num_envs, *spec.shape, dtype=spec.dtype, device=device)
                     for key, spec in primer.primers.items()}, batch_size=[num_envs], device=device)
    td.set("is_init", torch.ones(num_envs, 1, dtype=torch.bool, device=device))
    best = float("inf")
    for window in range(repeats + 1):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        loss = torch.zeros((), device=device)
        for _ in range(steps):
            frame = (torch.rand(num_envs, *obs_shape, generator=generator, device=device) < 0.1).float()
            td.set("observation", frame)
            out = policy(td)
            loss = loss + out["state_value"].sum() + out["action_log_prob"].sum()
            if elbo_key is not None:
                loss = loss + out[elbo_key].sum()
            td = out.get("next").select(*primer.primers.keys()).update({"is_init": torch.zeros_like(td["is_init"])})
        loss.backward()
        td = td.detach()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        if window > 0:
            best = min(best, (time.perf_counter() - t0) / (steps * num_envs))
    return best


def agent_rows(game: str, device: str, repeats: int) -> list[dict]:
    """Frames/s of the GRU, DVRL and ESCORT-latent's chain on ``game``."""
    import torch
    from omegaconf import OmegaConf

    from escort_rl.bench.atari.settings import load_settings
    from escort_rl.envs.flickering import flickering_game, game_spaces
    from escort_rl.trainers.atari_a2c import build_atari_policy

    obs_shape, n_actions = game_spaces(game)
    settings = load_settings(tier=flickering_game(game).tier)
    num_envs, steps = int(settings.trainer.num_envs), int(settings.trainer.rollout_steps)
    escort = OmegaConf.to_container(settings.escort)
    configs = [("gru", "gru", None), ("dvrl", "dvrl", None)]
    for label, change in CHAIN:
        escort = {**escort, **change}
        configs.append((f"escort_latent: {label}", "escort_latent", dict(escort)))
    rows = []
    for label, agent, escort_cfg in configs:
        cfg = OmegaConf.merge(OmegaConf.to_container(settings), {"agent": agent},
                              {"escort": escort_cfg} if escort_cfg else {})
        torch.manual_seed(0)
        policy = build_atari_policy(cfg, obs_shape, n_actions).to(device)
        seconds = window_seconds_per_frame(policy, obs_shape, num_envs, steps, repeats, device)
        rows.append({"game": game, "row": label, "agent": agent, "fps": 1.0 / seconds})
    dvrl_fps = next(r["fps"] for r in rows if r["agent"] == "dvrl")
    for r in rows:
        r["vs_dvrl"] = r["fps"] / dvrl_fps
    return rows


def table4_hours(fps: float, frames: int, games: int, seeds: int) -> float:
    """Hours of one agent's Table 4: ``frames × games × seeds`` frames at ``fps``."""
    return frames * games * seeds / fps / 3600.0


def main(args) -> None:
    import torch

    from escort_rl.bench.atari.settings import load_settings
    from escort_rl.bench.methods import check_choices
    from escort_rl.config.schema import check_device
    from escort_rl.envs.flickering import game_names

    check_choices("--games", args.games, game_names(), "game")
    problem = check_device(args.device)
    if problem is not None:
        raise ValueError(f"--device: {problem}")
    if args.repeats < 1:
        raise ValueError(f"--repeats: must be at least 1, got {args.repeats}")
    if args.threads:
        torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    rows = [row for game in args.games for row in agent_rows(game, args.device, args.repeats)]
    paper = load_settings().paper
    frames, n_games = int(paper.frames), len(paper.table4)
    lines = [f"# What a frame costs: the agents' networks, {args.device}, {torch.get_num_threads()} thread(s)\n",
             f"| game | row | frames/s | × DVRL | Table 4 hours ({frames:,} frames × {n_games} games × "
             f"{args.seeds} seeds) |", "| --- | --- | --- | --- | --- |"]
    for r in rows:
        r["table4_hours"] = table4_hours(r["fps"], frames, n_games, args.seeds)
        lines.append(f"| {r['game']} | {r['row']} | {r['fps']:,.1f} | {r['vs_dvrl']:.2f} | {r['table4_hours']:,.0f} |")
    markdown = ("\n".join(lines) + "\n\nNetworks only (A2C windows with their backward pass, random binary frames), "
                "no env: an upper bound on a training run's rate. Each ESCORT-latent row adds one speed choice to "
                "the row above; the last is the settings' default.\n")
    write_results(Path(args.output), "atari_cost", {"rows": rows, "device": args.device, "seeds": args.seeds},
                  markdown, time.perf_counter() - t0)


def register(subparsers) -> None:
    """Add ``bench atari-cost`` to the ``bench`` subparsers."""
    p = subparsers.add_parser("atari-cost", help="frames/s of the flickering-game agents' networks, ESCORT-latent's "
                              "speed choices, and Table 4's projected hours",
                              description=__doc__.split("\n\n")[1])
    p.add_argument("--games", nargs="+", default=["pong", "breakout"], help="flickering games (their frame shapes)")
    p.add_argument("--device", default="cpu", help="torch device of the networks")
    p.add_argument("--repeats", type=int, default=5, help="timed windows after the warm-up")
    options.add_seeds_option(p, 3, "training seeds per game in the projection")
    options.add_threads_option(p)
    options.add_output_option(p, "outputs/bench/atari_cost", "atari_cost.md and atari_cost.json")
    p.set_defaults(handler=main)
