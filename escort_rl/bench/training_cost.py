"""What training on a belief costs: frames per second of PPO training on SIR, SVGD and
ESCORT beliefs at several batch sizes, and the compile warm-up of a compiled ESCORT update, cold and
from the on-disk cache.

- **Training throughput.** For each filter and ``B`` (``trainer.num_envs``), a short PPO run
  (``trainer=ppo``, no warm start, episodes of ``max_steps`` steps) on Light-Dark 10D with a DeepSets
  policy; frames per second are the frames of iterations ``2..`` over their wall-clock, collection
  and updates included (the first iteration, which compiles, is reported apart). SVGD runs with
  ESCORT's training budget (``K = 15``, ``ε = 0.15``, compiled), so the two differ only by ESCORT's
  regularisers.
- **Compile warm-up.** One compiled ESCORT update (``filter=escort_train``) in a fresh process with an
  empty inductor cache directory (cold), then again in a fresh process with the same directory
  (cached): the first update's seconds of each.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# the filters compared, as config overrides (configs/filter/)
TRAINING_FILTERS: dict[str, list[str]] = {
    "sir": ["filter=sir"],
    "svgd": ["filter=svgd", "filter.num_steps=15", "filter.step_size=0.15", "filter.compile=true"],
    "escort": ["filter=escort_train"],
}


def training_throughput(filter_name: str, num_envs: int, output_dir: str | Path, iterations: int = 2,
                        max_steps: int = 100, rollout_steps: int = 50, env: str = "lightdark10d",
                        overrides: tuple[str, ...] = ()) -> dict:
    """Train PPO for ``iterations`` iterations of ``num_envs × max_steps`` frames on ``filter_name``'s
    beliefs (a key of :data:`TRAINING_FILTERS`) into ``output_dir`` and return
    ``{"filter", "B", "frames_per_second", "first_iteration_seconds", "frames", "seconds"}``, where
    frames per second are over iterations ``2..iterations`` (the first one compiles)."""
    from escort_rl.config import compose
    from escort_rl.trainers.training import train

    if filter_name not in TRAINING_FILTERS:
        raise ValueError(f"filter: '{filter_name}' is not one of {sorted(TRAINING_FILTERS)}")
    if iterations < 2:
        raise ValueError(f"iterations: need at least 2 (the first one is the warm-up), got {iterations}")
    cfg = compose([f"env={env}", *TRAINING_FILTERS[filter_name], "trainer=ppo", f"trainer.num_envs={num_envs}",
                   f"trainer.iterations={iterations}", f"trainer.rollout_steps={rollout_steps}",
                   f"env.max_steps={max_steps}", "trainer.warm_start_filter=null", f"output_dir={output_dir}",
                   *overrides])
    run_dir = train(cfg, progress=False)
    history = json.loads((Path(run_dir) / "history.json").read_text())
    timed = history[1:]
    frames = history[-1]["frames"] - history[0]["frames"]
    seconds = sum(h["seconds"] for h in timed)
    return {"filter": filter_name, "B": num_envs, "frames": frames, "seconds": seconds,
            "frames_per_second": frames / seconds, "first_iteration_seconds": history[0]["seconds"],
            "overrides": list(overrides)}


def first_compiled_update_seconds(num_envs: int = 64, num_particles: int = 100) -> float:
    """Seconds of the first update of a compiled ESCORT filter (``filter=escort_train``) on
    Light-Dark 10D beliefs ``[num_envs, num_particles, 10]``, compile included (run it in a fresh
    process: see :func:`compile_warmup`)."""
    import torch

    from escort_rl.config import compose
    from escort_rl.models import LightDark10D
    from escort_rl.models.protocol import random_action
    from escort_rl.trainers.builders import build_filter

    filt, model = build_filter(compose(["filter=escort_train"]).filter), LightDark10D()
    g = torch.Generator().manual_seed(0)
    belief = filt.init(model, (num_envs,), num_particles, g)
    s = model.initial_state((num_envs,), g)
    a = random_action(model, (num_envs,), g)
    o = model.observe(model.transition(s, a, g), a, g)
    t0 = time.perf_counter()
    filt.update(model, belief, a, o, g)
    return time.perf_counter() - t0


def _probe_in_fresh_process(cache_dir: Path, num_envs: int, num_particles: int) -> float:
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(cache_dir)}
    code = ("from escort_rl.bench.training_cost import first_compiled_update_seconds as f; "
            f"print(f({num_envs}, {num_particles}))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        last = (out.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise RuntimeError(f"compile warm-up: the probe process failed: {last}")
    return float(out.stdout.strip().splitlines()[-1])


def compile_warmup(num_envs: int = 64, num_particles: int = 100) -> dict:
    """``{"cold_seconds", "cached_seconds"}``: the first compiled ESCORT update in a fresh process with
    an empty inductor cache, then in another fresh process that finds the first one's cache."""
    with tempfile.TemporaryDirectory(prefix="escort-inductor-") as tmp:
        cold = _probe_in_fresh_process(Path(tmp), num_envs, num_particles)
        cached = _probe_in_fresh_process(Path(tmp), num_envs, num_particles)
    return {"B": num_envs, "N": num_particles, "cold_seconds": cold, "cached_seconds": cached}


def training_cost_rows(batches: list[int], run_root: str | Path, max_steps: int = 100, warmup: bool = False,
                       iterations: int = 3, progress=None, overrides: tuple[str, ...] = ()) -> dict:
    """``{"training": rows, "warmup": dict | None}``: :func:`training_throughput` for every filter of
    :data:`TRAINING_FILTERS` at every ``B`` of ``batches`` (runs under ``run_root/<filter>_B<B>``,
    replaced if present; ``overrides`` go to every run), and :func:`compile_warmup` when ``warmup``."""
    import shutil

    rows = []
    for b in batches:
        for name in TRAINING_FILTERS:
            run_dir = Path(run_root) / f"{name}_B{b}"
            shutil.rmtree(run_dir, ignore_errors=True)
            row = training_throughput(name, b, run_dir, iterations=iterations, max_steps=max_steps,
                                      rollout_steps=max_steps // 2 if max_steps % 2 == 0 else max_steps,
                                      overrides=overrides)
            rows.append(row)
            if progress is not None:
                progress(f"training {name:>7} B={b:<4} {row['frames_per_second']:8.0f} frames/s "
                         f"(first iteration {row['first_iteration_seconds']:.1f} s)")
    out = {"training": rows, "warmup": None}
    if warmup:
        out["warmup"] = compile_warmup()
        if progress is not None:
            progress(f"compile warm-up: cold {out['warmup']['cold_seconds']:.1f} s, "
                     f"cached {out['warmup']['cached_seconds']:.1f} s")
    return out


def training_cost_markdown(rows: list[dict], warmup: dict | None) -> str:
    """The training-throughput table (frames/s per filter and ``B``, ratios to SIR) and the warm-up line."""
    lines = ["## Training throughput", "",
             "PPO with a DeepSets policy on Light-Dark 10D, N = 100, collection and updates included, "
             "iterations 2.. (the first, which compiles, in the last column). SVGD and ESCORT: K = 15, "
             "compiled.", "",
             "| B | filter | frames/s | × SIR | first iteration (s) |", "| --- | --- | --- | --- | --- |"]
    for b in sorted({r["B"] for r in rows}):
        by = {r["filter"]: r for r in rows if r["B"] == b}
        sir = by.get("sir")
        for name, r in by.items():
            ratio = f"{r['frames_per_second'] / sir['frames_per_second']:.3f}" if sir else "—"
            lines.append(f"| {b} | {name} | {r['frames_per_second']:.0f} | {ratio} | "
                         f"{r['first_iteration_seconds']:.1f} |")
    if warmup is not None:
        lines += ["", f"Compile warm-up of one ESCORT update (B = {warmup['B']}, N = {warmup['N']}, fresh "
                  f"process): cold cache {warmup['cold_seconds']:.1f} s, on-disk cache "
                  f"{warmup['cached_seconds']:.1f} s."]
    return "\n".join(lines) + "\n"
