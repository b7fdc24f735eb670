"""The checks of a training config before training: the schema's types and ranges
(:mod:`escort_rl.schema`, including those marked ``stage="train"``) and what involves two keys."""

from __future__ import annotations

from omegaconf import DictConfig

from escort_rl.config import ConfigError
from escort_rl.schema import check_config


def validate_train_config(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` naming the first bad key of a training config.

    A composed config carries its schemas; a config without types (saved by an older version, or
    built by hand) is checked against the schemas its groups name (``env.name``, ``filter.kind``,
    ``trainer.algorithm``)."""
    check_config(cfg, stage="train")
    t = cfg.trainer
    if t.num_envs % cfg.collector.workers:
        raise ConfigError(
            f"collector.workers: trainer.num_envs ({t.num_envs}) must be divisible by the number of "
            f"workers ({cfg.collector.workers})"
        )
