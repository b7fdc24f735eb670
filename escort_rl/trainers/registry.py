"""The training algorithms by name (``trainer.algorithm``), and :func:`train`, which runs one on the
training scaffold."""

from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig

from escort_rl.config import ConfigError

ALGORITHMS = ("ppo", "reinforce", "dvrl_a2c", "recurrent_ppo")


def algorithm(cfg: DictConfig) -> str:
    """``cfg.trainer.algorithm``; configs saved before the key existed are ``reinforce``."""
    name = cfg.trainer.get("algorithm", "reinforce")
    if name not in ALGORITHMS:
        raise ConfigError(f"trainer.algorithm: unknown '{name}'; choose one of {list(ALGORITHMS)} "
                          "(trainer=ppo, trainer=reinforce, trainer=dvrl_a2c or trainer=recurrent_ppo)")
    return name


def build_algorithm(cfg: DictConfig, model):
    """The :class:`~escort_rl.trainers.algorithm.Algorithm` of ``cfg`` for ``model``."""
    name = algorithm(cfg)
    if name == "ppo":
        from escort_rl.trainers.ppo import PPO

        return PPO(cfg, model)
    if name == "dvrl_a2c":
        from escort_rl.trainers.dvrl_a2c import DVRLA2C

        return DVRLA2C(cfg, model)
    if name == "recurrent_ppo":
        from escort_rl.trainers.recurrent_ppo import RecurrentPPO

        return RecurrentPPO(cfg, model)
    from escort_rl.trainers.reinforce import Reinforce

    return Reinforce(cfg, model)


def train(cfg: DictConfig, resume_state: dict | None = None, progress: bool = True) -> Path:
    """Train with the algorithm of ``cfg`` on the scaffold; returns the run directory."""
    from escort_rl.trainers.builders import build_model
    from escort_rl.trainers.scaffold import run_training
    from escort_rl.trainers.validation import validate_train_config

    validate_train_config(cfg)
    torch.manual_seed(int(cfg.seed))  # the networks' initial weights
    model = build_model(cfg.env, cfg.device)
    name = algorithm(cfg)
    watch = ("episode_return", "elbo") if name == "dvrl_a2c" else ("episode_return", "final_distance", "success_rate")
    return run_training(cfg, build_algorithm(cfg, model), resume_state=resume_state, progress=progress,
                        desc=f"train {name}", watch=watch)
