"""Training collection on Ray (``collector.backend=ray``): TorchRL's ``RayCollector``.

``collector.workers=K`` remote collectors, each a Ray actor holding a TorchRL ``Collector`` over
``trainer.num_envs / K`` environments (one CPU each); every batch is the stack of one rollout per
remote collector, ``[K, num_envs / K, T]``, as a ``MultiSyncCollector``'s. ``collector.ray_address``
(or ``RAY_ADDRESS``) joins a running cluster; without either a local Ray starts with the run and
stops with it.

Example (a cluster started with ``ray start --head`` on one machine and ``ray start --address
HEAD:6379`` on the others)::

    escort-rl train collector.backend=ray collector.workers=8 collector.ray_address=auto
"""

from __future__ import annotations

import os
import sys

from omegaconf import DictConfig
from torchrl.collectors.distributed import RayCollector

from escort_rl.config.schema import check_ray_installed


def ray_init_kwargs(address: str | None = None) -> dict:
    """The arguments of ``ray.init`` for ``address`` (``None``: ``RAY_ADDRESS`` if set, else a new
    local Ray): quiet (the workers' output is not forwarded), no dashboard for a local Ray.

    A new local Ray is asked for as ``address="local"``: Ray's own default would join whatever
    cluster Ray last recorded on this machine, which may be gone or another user's.

    Example::

        >>> ray_init_kwargs("auto")["address"]
        'auto'
    """
    address = address or os.environ.get("RAY_ADDRESS") or None
    kwargs = {"address": address or "local", "log_to_driver": False, "logging_level": "warning"}
    return kwargs if address else {**kwargs, "include_dashboard": False}


def make_ray_collector(cfg: DictConfig, factory, policy, frames_per_batch: int, reset_at_each_iter: bool):
    """A :class:`ResettableRayCollector` of ``collector.workers`` remote ``Collector`` s over
    ``factory(num_envs / K, seed_k)`` (the seeds of :func:`escort_rl.trainers.scaffold.make_collector`'s
    workers), synchronous, without a frame limit, with the policy's weights sent once."""
    problem = check_ray_installed("ray")
    if problem is not None:
        raise ValueError(f"collector.backend: {problem}")
    workers = int(cfg.collector.workers)
    per_worker = int(cfg.trainer.num_envs) // workers
    collector = ResettableRayCollector(
        [factory(per_worker, int(cfg.seed) + 7919 * k) for k in range(workers)], policy,
        frames_per_batch=frames_per_batch, total_frames=sys.maxsize, device=cfg.device,
        reset_at_each_iter=reset_at_each_iter, collector_class="single", sync=True,
        collector_kwargs={"auto_register_policy_transforms": False},
        remote_configs={"num_cpus": 1, "num_gpus": 1 if str(cfg.device).startswith("cuda") else 0},
        ray_init_config=ray_init_kwargs(cfg.collector.get("ray_address")))
    collector.update_policy_weights_(policy)
    return collector


class ResettableRayCollector(RayCollector):
    """``RayCollector`` with :meth:`reset`, which resets every remote collector's envs (the
    algorithms reset after seeding each iteration, as with the local collectors)."""

    def reset(self, index=None, **kwargs) -> None:
        self.map_fn("reset")
