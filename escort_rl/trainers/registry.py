"""Which trainer a config asks for: ``trainer.algorithm`` (``reinforce`` or ``dvrl_a2c``)."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from escort_rl.config import ConfigError

ALGORITHMS = ("reinforce", "dvrl_a2c")


def algorithm(cfg: DictConfig) -> str:
    """``cfg.trainer.algorithm``; configs saved before the key existed are ``reinforce``."""
    name = cfg.trainer.get("algorithm", "reinforce")
    if name not in ALGORITHMS:
        raise ConfigError(f"trainer.algorithm: unknown '{name}'; choose one of {list(ALGORITHMS)} "
                          "(trainer=reinforce or trainer=dvrl_a2c)")
    return name


def train(cfg: DictConfig, resume_state: dict | None = None, progress: bool = True) -> Path:
    """Run the trainer of ``cfg`` (see :func:`algorithm`); returns the run directory."""
    if algorithm(cfg) == "dvrl_a2c":
        from escort_rl.trainers.dvrl_a2c import train_dvrl

        return train_dvrl(cfg, resume_state=resume_state, progress=progress)
    from escort_rl.trainers.reinforce import train as train_reinforce

    return train_reinforce(cfg, resume_state=resume_state, progress=progress)
