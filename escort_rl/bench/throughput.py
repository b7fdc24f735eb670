"""Collection throughput: environment frames per second through a TorchRL collector, with the
belief transform in the loop."""

from __future__ import annotations

import time

import torch
from omegaconf import DictConfig
from torchrl.collectors import Collector, MultiSyncCollector

from escort_rl.modules import make_deepsets_policy
from escort_rl.trainers.builders import build_actor, build_model, env_factory


def collection_throughput(cfg: DictConfig, workers: int, num_envs: int, steps_per_batch: int,
                          batches: int, warmup: int = 1) -> dict:
    """Frames per second of a (Multi)SyncCollector with ``num_envs`` envs split over ``workers``
    processes, each batch ``num_envs × steps_per_batch`` frames, timed over ``batches`` batches
    after ``warmup`` batches. The policy is an untrained DeepSets actor sampling actions."""
    if num_envs % workers:
        raise ValueError(f"workers: num_envs ({num_envs}) must be divisible by workers ({workers})")
    model = build_model(cfg.env, cfg.device)
    policy = make_deepsets_policy(build_actor(cfg, model.state_dim, model.n_actions))
    frames = num_envs * steps_per_batch
    total = frames * (batches + warmup)
    if workers == 1:
        collector = Collector(env_factory(cfg, num_envs, seed=0), policy, frames_per_batch=frames,
                              total_frames=total, auto_register_policy_transforms=False)
    else:
        collector = MultiSyncCollector([env_factory(cfg, num_envs // workers, seed=k) for k in range(workers)],
                                       policy, frames_per_batch=frames, total_frames=total,
                                       cat_results="stack", auto_register_policy_transforms=False)
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
    return {"workers": workers, "num_envs": num_envs, "num_particles": int(cfg.num_particles),
            "filter": cfg.filter.name, "frames": n, "seconds": elapsed, "frames_per_second": n / elapsed,
            "torch_threads": torch.get_num_threads()}
