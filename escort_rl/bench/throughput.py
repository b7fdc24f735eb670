"""Collection throughput: environment frames per second through the training's TorchRL collector,
with the belief transform in the loop."""

from __future__ import annotations

import time

import torch
from omegaconf import DictConfig, OmegaConf

from escort_rl.bench.core import options
from escort_rl.reporting.metadata import with_metadata
from escort_rl.trainers.builders import build_model, build_policy, env_factory
from escort_rl.trainers.scaffold import make_collector


def collection_throughput(cfg: DictConfig, workers: int, num_envs: int, steps_per_batch: int,
                          batches: int, warmup: int = 1) -> dict:
    """Frames per second of the collector training builds (:func:`make_collector`: a ``Collector``
    for one worker, a ``MultiSyncCollector`` for K, TorchRL's ``RayCollector`` with K remote
    collectors under ``collector.backend=ray``) with ``num_envs`` envs split over ``workers``, each
    batch ``num_envs × steps_per_batch`` frames, timed over ``batches`` batches after ``warmup``
    batches. The policy is an untrained DeepSets actor sampling actions."""
    if num_envs % workers:
        raise ValueError(f"workers: num_envs ({num_envs}) must be divisible by workers ({workers})")
    cfg = OmegaConf.merge(cfg, {"collector": {"workers": workers}, "trainer": {"num_envs": num_envs}})
    model = build_model(cfg.env, cfg.device)
    _, policy = build_policy(cfg, model)
    frames = num_envs * steps_per_batch
    collector = make_collector(cfg, lambda n, seed: env_factory(cfg, n, seed=seed), policy, frames,
                               reset_at_each_iter=False)
    try:
        it = iter(collector)
        for _ in range(warmup):
            next(it)
        t0 = time.perf_counter()
        n = 0
        for _ in range(batches):
            n += next(it).numel()
        elapsed = time.perf_counter() - t0
    finally:
        collector.shutdown()
    return {"backend": str(cfg.collector.get("backend", "local")), "workers": workers, "num_envs": num_envs,
            "num_particles": int(cfg.num_particles),
            "filter": cfg.filter.name, "frames": n, "seconds": elapsed, "frames_per_second": n / elapsed,
            "torch_threads": torch.get_num_threads()}


QUICK = dict(collector_workers=[1], num_envs=4, steps=10, batches=1)
"""``--quick``: one worker, 4 envs, 10 steps per batch, one timed batch."""


def register(subparsers) -> None:
    """Add ``bench throughput`` to the ``bench`` subparsers."""
    thr = subparsers.add_parser("throughput", help="collector frames/s with the belief transform",
                                description="Env frames per second through the training's collector: Collector "
                                "(1 worker), MultiSyncCollector (K workers), or RayCollector with K remote collectors "
                                "(overrides collector.backend=ray [collector.ray_address=auto]); belief transform and "
                                "DeepSets policy in the loop. Writes throughput.json into --output.")
    options.add_overrides_argument(thr, "Hydra overrides of the training config, e.g. filter=sir num_particles=200")
    thr.add_argument("--collector-workers", type=int, nargs="+", default=None, metavar="K",
                     help="the collector worker counts to time, one row each (default: 1 2)")
    thr.add_argument("--num-envs", type=int, default=None, metavar="B",
                     help="environments in all, split over the workers (default: 32)")
    thr.add_argument("--steps", type=int, default=None, help="steps per env per batch (default: 100)")
    thr.add_argument("--batches", type=int, default=None,
                     help="timed batches, a count, after one warm-up batch (default: 3)")
    options.add_quick_option(thr, "1 worker, 4 envs, 10 steps per batch, 1 timed batch")
    options.add_threads_option(thr)
    options.add_output_option(thr, "outputs/bench/throughput", "throughput.json")
    thr.set_defaults(handler=main)


def main(args) -> None:
    import json
    from pathlib import Path

    from escort_rl.config import compose

    full = dict(collector_workers=[1, 2], num_envs=32, steps=100, batches=3)
    kw = {k: getattr(args, k) if getattr(args, k) is not None else (QUICK if args.quick else full)[k] for k in full}
    bad = [k for k in kw["collector_workers"] if kw["num_envs"] % k]
    if bad:
        raise ValueError(f"--collector-workers: {bad[0]} does not divide --num-envs {kw['num_envs']}; each worker "
                         "runs num_envs / workers environments")
    options.set_threads(args)
    cfg = compose(args.overrides)
    rows = []
    for k in kw["collector_workers"]:
        row = collection_throughput(cfg, k, kw["num_envs"], kw["steps"], kw["batches"])
        rows.append(row)
        print(f"backend={row['backend']} workers={k} B={row['num_envs']} N={row['num_particles']} "
              f"filter={row['filter']}: "
              f"{row['frames_per_second']:.0f} frames/s ({row['frames']} frames in {row['seconds']:.2f} s)")
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    (out / "throughput.json").write_text(json.dumps(with_metadata(rows), indent=1))
    print(f"results: {(out / 'throughput.json').resolve()}")
