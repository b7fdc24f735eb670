"""Training collection on Ray (``collector.backend=ray``): TorchRL's RayCollector with K remote
collectors inside the trainer scaffold. Needs the ``ray`` extra, which ``make test`` installs."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import tiny_overrides
from escort_rl.config import ConfigError, compose


@pytest.mark.slow
def test_remote_collectors_get_the_policy_weights_and_stack_their_batches(local_ray):
    from escort_rl.modules import make_deepsets_policy
    from escort_rl.trainers.builders import belief_keys, build_actor, build_model, env_factory
    from escort_rl.trainers.scaffold import make_collector

    cfg = compose(tiny_overrides("filter=sir", "collector.backend=ray", "collector.workers=2"))
    model = build_model(cfg.env)
    policy = make_deepsets_policy(build_actor(cfg, model.state_dim, model.n_actions, model), *belief_keys(cfg))
    steps = int(cfg.env.max_steps)
    collector = make_collector(cfg, lambda n, s: env_factory(cfg, n, seed=s), policy, 4 * steps, False)
    try:
        collector.set_seed(0)
        collector.reset()
        batch = next(iter(collector))
        assert batch.shape == (2, 2, steps)  # [K, num_envs / K, T], as a MultiSyncCollector's
        with torch.no_grad():
            for p in policy.parameters():
                p.zero_()  # uniform logits: every action has probability 1 / n_actions
        collector.update_policy_weights_()
        batch = next(iter(collector))
        expected = torch.full_like(batch["action_log_prob"], -math.log(model.n_actions))
        torch.testing.assert_close(batch["action_log_prob"], expected)
    finally:
        collector.shutdown()


@pytest.mark.slow
def test_a_run_trains_on_ray_collectors(tmp_path, local_ray):
    from escort_rl.trainers.checkpointing import load_checkpoint
    from escort_rl.trainers.training import train

    run = tmp_path / "run"
    train(compose(tiny_overrides("trainer.iterations=2", "collector.backend=ray", "collector.workers=2",
                                 f"output_dir={run}")), progress=False)
    history = load_checkpoint(run)["trainer_state"]["history"]
    assert len(history) == 2 and all(h["episodes"] == 4 for h in history)  # 4 envs over 2 remote collectors
    assert all(math.isfinite(h["loss_actor"]) for h in history)


def test_ray_missing_is_one_line_naming_the_key(monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a))
    with pytest.raises(ConfigError, match=r"collector.backend: ray is not installed; install with pip install "
                                          r"escort-rl\[ray\]"):
        compose(tiny_overrides("collector.backend=ray"))
    with pytest.raises(ConfigError, match="collector.backend"):
        compose(tiny_overrides("collector.backend=spark"))


@pytest.mark.slow
def test_bench_throughput_times_ray_collectors(local_ray):
    """``escort-rl bench throughput collector.backend=ray`` times the same RayCollector training uses."""
    from escort_rl.bench.throughput import collection_throughput

    cfg = compose(tiny_overrides("filter=sir", "collector.backend=ray"))
    row = collection_throughput(cfg, workers=2, num_envs=4, steps_per_batch=3, batches=2)
    assert row["backend"] == "ray" and row["workers"] == 2
    assert row["frames"] == 2 * 4 * 3 and row["frames_per_second"] > 0


def test_ray_init_joins_only_a_named_cluster(monkeypatch):
    from escort_rl.trainers.ray_collection import ray_init_kwargs

    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    assert ray_init_kwargs()["address"] == "local"  # not Ray's last-started cluster
    assert ray_init_kwargs()["include_dashboard"] is False
    assert ray_init_kwargs("auto")["address"] == "auto"
    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")
    assert ray_init_kwargs()["address"] == "10.0.0.1:6379"
    assert "include_dashboard" not in ray_init_kwargs()
