"""The settings of ``escort-rl bench atari`` (``configs/bench/atari.yaml``, ``configs/bench/minatar.yaml``)
and the run config of one training cell."""

from __future__ import annotations

import math
from pathlib import Path

from omegaconf import DictConfig, OmegaConf


def settings_path(tier: str = "atari") -> Path:
    """``configs/bench/atari.yaml`` (Atari's settings) or ``configs/bench/minatar.yaml`` (MinAtar's)."""
    from escort_rl.config import config_dir

    return config_dir() / "bench" / f"{tier}.yaml"


def load_settings(overrides: tuple[str, ...] | list[str] = (), tier: str = "atari") -> DictConfig:
    """The settings of ``tier`` (:func:`settings_path`) with ``overrides`` (``KEY=VALUE``, e.g.
    ``escort.num_steps=10``), typed and checked (:class:`escort_rl.config.bench_schemas.AtariBenchConfig`);
    a bad key or value raises ``ConfigError`` naming it."""
    from omegaconf.errors import OmegaConfBaseException

    from escort_rl.config import ConfigError
    from escort_rl.config.bench_schemas import AtariBenchConfig
    from escort_rl.config.checking import check_config, describe_error, load_typed

    settings = load_typed(settings_path(tier), AtariBenchConfig)
    bad = [o for o in overrides if "=" not in o]
    if bad:
        raise ConfigError(f"overrides: '{bad[0]}' is not KEY=VALUE, e.g. escort.num_steps=10")
    try:
        settings = OmegaConf.merge(settings, OmegaConf.from_dotlist(list(overrides)))
    except OmegaConfBaseException as err:
        raise ConfigError(f"overrides: {describe_error(err)}") from None
    check_config(settings, AtariBenchConfig, prefix="overrides: ")
    return settings


def frames_per_update(settings: DictConfig) -> int:
    return int(settings.trainer.num_envs) * int(settings.trainer.rollout_steps)


def cell_config(settings: DictConfig, game: str, agent: str, seed: int, frames: int, run_dir: Path,
                device: str = "cpu") -> DictConfig:
    """The run config of one cell for :class:`~escort_rl.trainers.atari_a2c.AtariA2C` and the scaffold.

    ``frames`` is rounded up to whole A2C updates of ``num_envs × rollout_steps`` frames; an iteration
    is ``updates_per_iteration`` updates, or all of them when the budget is smaller than one iteration.
    """
    per_update = frames_per_update(settings)
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < per_update:
        raise ValueError(f"--frames: must be at least {per_update} (one A2C update of "
                         f"{settings.trainer.num_envs} envs × {settings.trainer.rollout_steps} steps), got {frames}")
    updates = math.ceil(frames / per_update)
    per_iteration = min(int(settings.trainer.updates_per_iteration), updates)
    cfg = OmegaConf.create({"seed": int(seed), "device": device, "output_dir": str(run_dir),
                            "logger": {"backend": "csv"}, "game": game, "agent": agent,
                            **OmegaConf.to_container(settings, resolve=True)})
    cfg.trainer.updates_per_iteration = per_iteration
    cfg.trainer.iterations = math.ceil(updates / per_iteration)
    return cfg
