"""Flickering Atari env throughput without an agent: frames (agent steps) per second of ``num_envs``
games under random actions, for each way the trainer can batch them (``escort_rl.trainers.atari_a2c
.make_atari_env``):

- ``serial``: a TorchRL ``SerialEnv`` of :func:`~escort_rl.envs.atari.make_atari_torchrl_env` (one
  process, ``trainer.parallel_envs=false``, the default);
- ``parallel``: a ``ParallelEnv`` of the same, one spawned worker process per env
  (``trainer.parallel_envs=true``);
- ``vectorized``: :class:`~escort_rl.envs.atari_vector.FlickeringAtariVectorEnv`, the games on ALE's C++
  vector env (``trainer.vectorized_envs=true``).

Each env is seeded, reset, stepped ``--warmup`` times, then timed over ``--steps`` steps of
``step_and_maybe_reset`` (as the trainer steps its envs), every step one uniform action per game.
"""

from __future__ import annotations

import functools
import os
import time
from pathlib import Path

from escort_rl.bench.core import options
from escort_rl.bench.methods import check_choices
from escort_rl.reporting.paths import write_results

KINDS = ("serial", "parallel", "vectorized")
FULL = dict(num_envs=16, steps=300, warmup=20, kinds=list(KINDS))
QUICK = dict(num_envs=2, steps=20, warmup=2, kinds=["serial", "vectorized"])
"""``--quick``: 2 envs, 20 timed steps, no worker processes."""


def make_envs(kind: str, game: str, num_envs: int):
    """``num_envs`` flickering games batched as ``kind`` (a name of :data:`KINDS`)."""
    from torchrl.envs import ParallelEnv, SerialEnv

    from escort_rl.envs.atari import make_atari_torchrl_env
    from escort_rl.envs.atari_vector import make_atari_vector_env

    if kind == "vectorized":
        return make_atari_vector_env(game, num_envs)
    factory = functools.partial(make_atari_torchrl_env, game)
    if kind == "parallel":
        return ParallelEnv(num_envs, factory, mp_start_method="spawn")
    return SerialEnv(num_envs, factory)


def env_throughput(kind: str, game: str, num_envs: int, steps: int, warmup: int, seed: int = 0) -> dict:
    """Frames per second of ``kind`` (see the module docstring): ``frames`` = ``num_envs × steps``
    agent steps (4 emulator frames each), ``seconds`` the timed steps' wall time, ``start_seconds``
    the time to build, seed and reset the envs."""
    import torch

    t0 = time.perf_counter()
    env = make_envs(kind, game, num_envs)
    try:
        env.set_seed(seed)
        td = env.reset()
        start = time.perf_counter() - t0
        n_actions = int(env.action_spec.space.n)
        generator = torch.Generator().manual_seed(seed)
        for step in range(warmup + steps):
            if step == warmup:
                t1 = time.perf_counter()
            td.set("action", torch.randint(n_actions, (num_envs,), generator=generator))
            _, td = env.step_and_maybe_reset(td)
        seconds = time.perf_counter() - t1
    finally:
        env.close()
    frames = num_envs * steps
    return {"kind": kind, "game": game, "num_envs": num_envs, "frames": frames, "seconds": seconds,
            "frames_per_second": frames / seconds, "start_seconds": start}


def markdown_report(rows: list[dict], game: str, num_envs: int) -> str:
    """A table of frames/s per kind, each beside ``serial``'s and ``parallel``'s (where measured)."""
    fps = {row["kind"]: row["frames_per_second"] for row in rows}
    bases = [k for k in ("serial", "parallel") if k in fps]
    lines = [f"# Flickering Atari env throughput: {game}, {num_envs} envs, random actions, no agent\n",
             "| envs | frames/s | emulator frames/s | " + " | ".join(f"× {b}" for b in bases) + " | start (s) |",
             "| --- | ---: | ---: | " + " | ".join("---:" for _ in bases) + " | ---: |"]
    for row in rows:
        ratios = " | ".join(f"{row['frames_per_second'] / fps[b]:.2f}" for b in bases)
        lines.append(f"| {row['kind']} | {row['frames_per_second']:,.0f} | {4 * row['frames_per_second']:,.0f} | "
                     f"{ratios} | {row['start_seconds']:.1f} |")
    lines.append("\nFrames are agent steps (4 emulator frames each, as DVRL counted them), timed over "
                 f"{rows[0]['frames'] // num_envs} steps of step_and_maybe_reset after a warm-up; start: building, "
                 "seeding and resetting the envs. BLAS threads (OPENBLAS_NUM_THREADS): "
                 f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}; CPUs: {os.cpu_count()}.\n")
    return "\n".join(lines)


def main(args) -> None:
    from escort_rl.envs.atari import GAMES

    kw = {k: getattr(args, k) if getattr(args, k) is not None else (QUICK if args.quick else FULL)[k] for k in FULL}
    check_choices("--kinds", kw["kinds"], list(KINDS), "kind")
    if kw["warmup"] < 0:
        raise ValueError(f"--warmup: must be at least 0, got {kw['warmup']}")
    check_choices("--game", [args.game], sorted(GAMES), "game")
    game = args.game
    options.set_threads(args)
    t0 = time.perf_counter()
    rows = []
    for kind in kw["kinds"]:
        rows.append(env_throughput(kind, game, kw["num_envs"], kw["steps"], kw["warmup"]))
        print(f"{kind}: {rows[-1]['frames_per_second']:.0f} frames/s")
    markdown = markdown_report(rows, game, kw["num_envs"])
    write_results(Path(args.output).expanduser(), "atari_envs", {"rows": rows}, markdown, time.perf_counter() - t0)


def register(subparsers) -> None:
    """Add ``bench atari-envs`` to the ``bench`` subparsers."""
    p = subparsers.add_parser("atari-envs", help="Flickering Atari env frames/s: SerialEnv, ParallelEnv, ALE's "
                              "vector env", description="Frames (agent steps) per second of --num-envs flickering "
                              "games under random actions, no agent: a SerialEnv and a ParallelEnv of the "
                              "per-game envs against the games on ALE's C++ vector env. Writes atari_envs.md and "
                              "atari_envs.json into --output.")
    p.add_argument("--game", default="pong", help="of pong icehockey mspacman asteroids")
    p.add_argument("--num-envs", type=int, default=None, metavar="N",
                   help=f"games stepped together (default: {FULL['num_envs']}; --quick: {QUICK['num_envs']})")
    p.add_argument("--steps", type=int, default=None,
                   help=f"timed steps of every game (default: {FULL['steps']}; --quick: {QUICK['steps']})")
    p.add_argument("--warmup", type=int, default=None,
                   help=f"untimed steps first (default: {FULL['warmup']}; --quick: {QUICK['warmup']})")
    p.add_argument("--kinds", nargs="+", default=None,
                   help=f"of {' '.join(KINDS)} (default: all; --quick: {' '.join(QUICK['kinds'])})")
    options.add_quick_option(p, f"{QUICK['num_envs']} envs, {QUICK['steps']} steps, "
                             f"{' and '.join(QUICK['kinds'])}")
    options.add_threads_option(p)
    options.add_output_option(p, "outputs/bench/atari-envs", "atari_envs.md and atari_envs.json")
    p.set_defaults(handler=main)
