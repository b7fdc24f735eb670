"""Training a run: the algorithm a config names (``trainer.algorithm``, looked up in
:mod:`escort_rl.config.registry`), and :func:`train`, which runs it on the training scaffold."""

from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig

from escort_rl.config import registry
from escort_rl.trainers.algorithm import algorithm


def build_algorithm(cfg: DictConfig, model):
    """The :class:`~escort_rl.trainers.algorithm.Algorithm` of ``cfg`` for ``model``."""
    return registry.resolve("trainer", algorithm(cfg))(cfg, model)


def train(cfg: DictConfig, resume_state: dict | None = None, progress: bool = True) -> Path:
    """Train with the algorithm of ``cfg`` on the scaffold; returns the run directory."""
    from escort_rl.trainers.builders import build_model
    from escort_rl.trainers.scaffold import run_training
    from escort_rl.trainers.validation import validate_train_config

    validate_train_config(cfg)
    torch.manual_seed(int(cfg.seed))  # the networks' initial weights
    model = build_model(cfg.env, cfg.device)
    name = algorithm(cfg)
    from escort_rl.models import has_goal

    goal = ("final_distance", "success_rate") if has_goal(model) else ()
    algo = build_algorithm(cfg, model)
    return run_training(cfg, algo, resume_state=resume_state, progress=progress, desc=f"train {name}",
                        watch=algo.watch or ("episode_return", *goal))
