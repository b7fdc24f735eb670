"""REINFORCE with reward-to-go, a baseline and an entropy bonus, on TorchRL collectors.

Read top to bottom: build the env factory and the policy, resume if asked, then for each
iteration collect ``num_envs`` full episodes, compute returns-to-go, take one policy-gradient step,
log, and checkpoint.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict
from torchrl.checkpoint import CheckpointRotation
from torchrl.collectors import Collector, MultiSyncCollector
from tqdm import tqdm

from escort_rl.config import ConfigError
from escort_rl.modules import DeepSetsActor, make_deepsets_policy
from escort_rl.trainers.builders import build_actor, build_model, env_factory
from escort_rl.trainers.checkpointing import checkpoint_dir, load_checkpoint, save_checkpoint


def returns_to_go(reward: torch.Tensor, done: torch.Tensor, gamma: float) -> torch.Tensor:
    """Discounted reward-to-go ``G_t = r_t + γ·G_{t+1}·(1 - done_t)`` along the last dim.

    ``reward``, ``done``: ``[E, T]`` -> ``[E, T]``.
    """
    out = torch.zeros_like(reward)
    running = torch.zeros_like(reward[:, 0])
    for t in range(reward.shape[1] - 1, -1, -1):
        running = reward[:, t] + gamma * running * (~done[:, t]).to(reward.dtype)
        out[:, t] = running
    return out


def complete_episode_mask(done: torch.Tensor) -> torch.Tensor:
    """True at steps whose episode ends inside the batch (a done at that step or later).

    ``done``: ``[E, T]`` bool -> ``[E, T]`` bool. Steps of an episode cut by the batch end are
    excluded: their return-to-go is unknown.
    """
    return torch.flip(torch.cummax(torch.flip(done.long(), [1]), dim=1).values, [1]).bool()


def validate_train_config(cfg: DictConfig) -> None:
    t = cfg.trainer
    checks = [
        ("trainer.iterations", t.iterations >= 1, "a positive int"),
        ("trainer.num_envs", t.num_envs >= 1, "a positive int"),
        ("trainer.lr", t.lr > 0, "a positive float"),
        ("trainer.gamma", 0 < t.gamma <= 1, "in (0, 1]"),
        ("trainer.checkpoint_every", t.checkpoint_every >= 1, "a positive int"),
        ("trainer.keep_checkpoints", t.keep_checkpoints >= 1, "a positive int"),
        ("num_particles", cfg.num_particles >= 1, "a positive int"),
        ("collector.workers", cfg.collector.workers >= 1, "a positive int"),
        ("env.max_steps", cfg.env.max_steps is not None and cfg.env.max_steps >= 1, "a positive int"),
    ]
    for key, ok, what in checks:
        if not ok:
            raise ConfigError(f"{key}: must be {what}, got {OmegaConf.select(cfg, key)}")
    if t.baseline not in ("none", "time", "learned"):
        raise ConfigError(f"trainer.baseline: must be none, time or learned, got '{t.baseline}'")
    if t.num_envs % cfg.collector.workers:
        raise ConfigError(
            f"collector.workers: trainer.num_envs ({t.num_envs}) must be divisible by the number of "
            f"workers ({cfg.collector.workers})"
        )
    if cfg.logger.backend not in ("csv", "tensorboard"):
        raise ConfigError(f"logger.backend: must be csv or tensorboard, got '{cfg.logger.backend}'")


def make_logger(cfg: DictConfig, run_dir: Path):
    from torchrl.record.loggers import CSVLogger

    if cfg.logger.backend == "tensorboard":
        from torchrl.record.loggers import TensorboardLogger

        return TensorboardLogger(exp_name="logs", log_dir=str(run_dir))
    return CSVLogger(exp_name="logs", log_dir=str(run_dir))


def make_collector(cfg: DictConfig, policy, frames_per_batch: int, total_frames: int):
    workers = int(cfg.collector.workers)
    if workers == 1:
        factory = env_factory(cfg, int(cfg.trainer.num_envs), seed=int(cfg.seed))
        return Collector(factory, policy, frames_per_batch=frames_per_batch, total_frames=total_frames,
                         reset_at_each_iter=True, device=cfg.device,
                         auto_register_policy_transforms=False)
    per_worker = int(cfg.trainer.num_envs) // workers
    factories = [env_factory(cfg, per_worker, seed=int(cfg.seed) + 7919 * k) for k in range(workers)]
    return MultiSyncCollector(factories, policy, frames_per_batch=frames_per_batch, total_frames=total_frames,
                              reset_at_each_iter=True, device=cfg.device, cat_results="stack",
                              auto_register_policy_transforms=False)


def iteration_seed(base: int, iteration: int) -> int:
    """The seed of iteration ``i``: every iteration is reproducible on its own, so a resumed run
    collects exactly the data an uninterrupted run would have."""
    return (int(base) * 1_000_003 + int(iteration) * 7_919) % (2**31 - 1)


def policy_gradient_loss(actor: DeepSetsActor, critic: DeepSetsActor | None, batch: TensorDict,
                         cfg: DictConfig) -> dict:
    """Accumulate the gradients of the REINFORCE loss over minibatches; return scalar stats.

    ``batch``: ``[E, T]`` with ``particles``, ``particle_log_weights``, ``action`` and
    ``("next", "reward" | "done")``.
    """
    t = cfg.trainer
    reward = batch["next", "reward"].squeeze(-1)
    done = batch["next", "done"].squeeze(-1)
    valid = complete_episode_mask(done)
    returns = returns_to_go(reward, done, float(t.gamma))
    if t.baseline == "time":
        count = valid.sum(0).clamp_min(1)
        mean_t = (returns * valid).sum(0) / count  # [T]
        advantage = returns - mean_t
    else:
        advantage = returns.clone()

    flat = batch[valid]  # [M] valid samples
    adv = advantage[valid]
    ret = returns[valid]
    m = flat.shape[0]
    if m == 0:
        return {"loss": 0.0, "entropy": 0.0, "samples": 0}
    use_weights = "particle_log_weights" in flat.keys()
    total_loss = total_entropy = 0.0
    for start in range(0, m, int(t.minibatch_size)):
        mb = flat[start : start + int(t.minibatch_size)]
        log_w = mb["particle_log_weights"] if use_weights else None
        logits = actor(mb["particles"], log_w)
        dist = torch.distributions.Categorical(logits=logits)
        a = adv[start : start + int(t.minibatch_size)]
        if critic is not None:
            value = critic(mb["particles"], log_w).squeeze(-1)
            target = ret[start : start + int(t.minibatch_size)]
            a = (a - value.detach())
            value_loss = 0.5 * ((value - target) ** 2).sum() / m
        else:
            value_loss = 0.0
        scale = a.std() if a.numel() > 1 and t.baseline != "none" else 1.0
        a = a / (scale + 1e-8)
        entropy = dist.entropy()
        loss = (-(dist.log_prob(mb["action"]) * a).sum() - t.entropy_coef * entropy.sum()) / m + value_loss
        loss.backward()
        total_loss += float(loss.detach())
        total_entropy += float(entropy.detach().sum())
    return {"loss": total_loss, "entropy": total_entropy / m, "samples": m}


def episode_stats(batch: TensorDict, model) -> dict:
    """Mean return, final distance to goal and success rate of the episodes that ended in ``batch``
    ``[E, T]`` (batched: episode returns by one ``index_add`` over episode ids)."""
    done = batch["next", "done"].squeeze(-1)
    reward = batch["next", "reward"].squeeze(-1)
    e, t = done.shape
    episode_in_row = torch.cumsum(done.long(), dim=1) - done.long()  # [E, T]
    episode_id = torch.arange(e, device=done.device).unsqueeze(1) * t + episode_in_row
    returns = torch.zeros(e * t, dtype=reward.dtype, device=reward.device).index_add_(
        0, episode_id.flatten(), reward.flatten())
    rows, steps = done.nonzero(as_tuple=True)  # the last step of every finished episode
    if rows.numel() == 0:
        return {"episode_return": float("nan"), "final_distance": float("nan"), "success_rate": float("nan"),
                "episodes": 0}
    final_state = batch["next", "true_state"][rows, steps]
    distance = (model.distance_to_goal(final_state) if hasattr(model, "distance_to_goal")
                else torch.full((rows.numel(),), float("nan")))
    return {
        "episode_return": float(returns[episode_id[rows, steps]].mean()),
        "final_distance": float(distance.mean()),
        "success_rate": float(batch["next", "terminated"].squeeze(-1)[rows, steps].float().mean()),
        "episodes": int(rows.numel()),
    }


def record_iteration(record: dict, state: dict, logger, rotation, config_dict: dict, components: dict,
                     checkpoint_every: int, n_iter: int) -> None:
    """Append an iteration's ``record`` to the trainer state's history, log its scalars, and save a
    checkpoint every ``checkpoint_every`` iterations and after the last (shared by both trainers)."""
    it = int(record["iteration"])
    state["history"].append(record)
    for key, value in record.items():
        if key != "iteration":
            logger.log_scalar(key, value, step=it)
    if it % int(checkpoint_every) == 0 or it == n_iter:
        save_checkpoint(rotation, it, state, config_dict, **components)


def train(cfg: DictConfig, resume_state: dict | None = None, progress: bool = True) -> Path:
    """Train the DeepSets policy; returns the run directory.

    Writes ``config.yaml``, ``checkpoints/``, CSV logs under ``logs/`` and ``history.json`` into
    ``cfg.output_dir``. ``resume_state`` (from :func:`load_checkpoint`) continues a run.
    """
    validate_train_config(cfg)
    run_dir = Path(cfg.output_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    torch.manual_seed(int(cfg.seed))

    model = build_model(cfg.env, cfg.device)
    actor = build_actor(cfg, model.state_dim, model.n_actions)
    critic = build_actor(cfg, model.state_dim, 1) if cfg.trainer.baseline == "learned" else None
    params = list(actor.parameters()) + (list(critic.parameters()) if critic is not None else [])
    optimizer = torch.optim.Adam(params, lr=float(cfg.trainer.lr))
    components = {"actor": actor, "optimizer": optimizer}
    if critic is not None:
        components["critic"] = critic

    state = {"iteration": 0, "frames": 0, "history": []}
    if resume_state is not None:
        state = load_checkpoint(resume_state["path"], **components)["trainer_state"]
        state = {"iteration": int(state["iteration"]), "frames": int(state["frames"]), "history": list(state["history"])}
    rotation = CheckpointRotation(checkpoint_dir(run_dir), keep_last=int(cfg.trainer.keep_checkpoints))
    config_dict = OmegaConf.to_container(cfg, resolve=True)

    n_iter = int(cfg.trainer.iterations)
    if state["iteration"] >= n_iter:
        return run_dir
    frames_per_batch = int(cfg.trainer.num_envs) * int(cfg.env.max_steps)
    policy = make_deepsets_policy(actor)
    collector = make_collector(cfg, policy, frames_per_batch, frames_per_batch * (n_iter - state["iteration"]))
    logger = make_logger(cfg, run_dir)
    bar = tqdm(total=n_iter, initial=state["iteration"], desc="train", disable=not progress, dynamic_ncols=True)
    try:
        iterator = iter(collector)
        for it in range(state["iteration"], n_iter):
            seed = iteration_seed(cfg.seed, it)
            collector.set_seed(seed)
            torch.manual_seed(seed)
            t0 = time.perf_counter()
            batch = next(iterator)
            collect_s = time.perf_counter() - t0
            batch = batch.reshape(-1, batch.shape[-1])  # [E, T]

            optimizer.zero_grad(set_to_none=True)
            stats = policy_gradient_loss(actor, critic, batch, cfg)
            grad_norm = torch.nn.utils.clip_grad_norm_(params, float(cfg.trainer.max_grad_norm))
            optimizer.step()
            if cfg.collector.workers > 1:
                collector.update_policy_weights_()

            state["iteration"] = it + 1
            state["frames"] += batch.numel()
            record = {"iteration": it + 1, "frames": state["frames"], **episode_stats(batch, model),
                      "loss": stats["loss"], "entropy": stats["entropy"], "grad_norm": float(grad_norm),
                      "fps": batch.numel() / max(collect_s, 1e-9), "seconds": time.perf_counter() - t0}
            bar.set_postfix(ret=f"{record['episode_return']:.1f}", dist=f"{record['final_distance']:.2f}",
                            fps=f"{record['fps']:.0f}")
            bar.update(1)
            record_iteration(record, state, logger, rotation, config_dict, components,
                             int(cfg.trainer.checkpoint_every), n_iter)
    finally:
        bar.close()
        collector.shutdown()
    (run_dir / "history.json").write_text(json.dumps(state["history"], indent=1))
    return run_dir
