"""The checks of a training config before training: the schema's types and ranges
(:mod:`escort_rl.config.schema`, including those marked ``stage="train"``) and what involves two keys."""

from __future__ import annotations

import dataclasses
import importlib.util
import typing

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from escort_rl.config import ConfigError, registry
from escort_rl.config.checking import check_config, describe_error, find_problem
from escort_rl.config.schema import ENV_SCHEMAS
from escort_rl.trainers.algorithm import algorithm, typed_trainer


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
    check_warm_start(cfg)
    check_exploring_starts(cfg)
    check_exploring_starts(cfg, "simulator")
    check_popgym_task(cfg)
    if cfg.logger.backend == "tensorboard" and importlib.util.find_spec("tensorboard") is None:
        raise ConfigError("logger.backend: 'tensorboard' needs the tensorboard package "
                          "(pip install escort-rl[tensorboard]); or use logger.backend=csv")
    if cfg.logger.backend == "wandb" and importlib.util.find_spec("wandb") is None:
        raise ConfigError("logger.backend: 'wandb' needs the wandb package (pip install escort-rl[wandb]); "
                          "or use logger.backend=csv")


def check_warm_start(cfg: DictConfig) -> None:
    """A warm start on another filter must leave iterations on the run's own: ``ConfigError`` naming
    ``trainer.warm_start_iterations`` when it covers every iteration (the run would never train on
    ``filter``)."""
    t = typed_trainer(cfg)
    warm = getattr(t, "warm_start_filter", None)  # trainers without a warm start have no such field
    if not warm or str(warm) == str(cfg.filter.name):
        return
    iterations, covered = t.iterations, t.warm_start_iterations
    if covered >= iterations:
        raise ConfigError(
            f"trainer.warm_start_iterations: the warm start ({covered} iterations on {warm}) covers all "
            f"{iterations} iterations, so the run would never train on its filter ({cfg.filter.name}); set "
            f"trainer.warm_start_iterations below {iterations} (e.g. trainer.warm_start_iterations={iterations // 2}), "
            f"or trainer.warm_start_filter=null to train on {cfg.filter.name} throughout")


def check_exploring_starts(cfg: DictConfig, field: str = "exploring_starts") -> None:
    """``env.exploring_starts`` (model keys the training envs start from with
    ``trainer.exploring_starts=true``), or another ``env.<field>`` of model keys (``simulator``: where
    the env's simulator differs from the filter's model): each key must be one of ``env.model``'s, with
    a value of its type and range; ``ConfigError`` naming ``env.<field>.<key>`` otherwise."""
    starts = cfg.env.get(field, None)
    if not starts:
        return
    model = cfg.env.model
    schema = OmegaConf.get_type(model)
    if not dataclasses.is_dataclass(schema):  # a config saved without types: the env's schema
        env_schema = ENV_SCHEMAS.get(cfg.env.get("name"))
        schema = typing.get_type_hints(env_schema)["model"] if env_schema is not None else None
    if schema is None:
        return
    names = {f.name for f in dataclasses.fields(schema)}
    for key in starts:
        if key not in names or key.startswith("_"):
            raise ConfigError(f"env.{field}.{key}: not a key of env.model; use keys of the env's model "
                              "(e.g. start_low, start_high)")
    try:
        merged = OmegaConf.merge(OmegaConf.structured(schema), OmegaConf.to_container(model, resolve=True),
                                 OmegaConf.to_container(starts, resolve=True))
    except OmegaConfBaseException as err:
        raise ConfigError(f"env.{field}.{describe_error(err)}") from None
    problem = find_problem(merged, schema, stage="train")
    if problem is not None:
        key = problem.split(":", 1)[0]
        if key in starts:
            raise ConfigError(f"env.{field}.{problem}")



def trainer_class(cfg: DictConfig) -> type:
    """The :class:`~escort_rl.trainers.algorithm.Algorithm` class ``trainer.algorithm`` names."""
    return registry.resolve("trainer", algorithm(cfg))


def check_popgym_any_task(cfg: DictConfig) -> None:
    """``env=popgym``: any POPGym task (``env.popgym_task``), no model of it, so only the model-free GRU
    (``trainer=recurrent_ppo``) trains there, and an iteration (``env.max_steps`` per env) holds at least
    the task's longest episode."""
    from escort_rl.envs.popgym import popgym_any_task, popgym_episode_length
    from escort_rl.trainers.builders import build_task_spaces

    build_task_spaces(cfg.env)  # the task is named, known, and popgym installed
    keys = list(cfg.env.get("model") or {})
    if keys:
        raise ConfigError(f"env.model.{keys[0]}: env=popgym has no model of the task (the GRU reads POPGym's own "
                          "observations), so it would be ignored; drop it, or use env=popgym_cartpole or "
                          "env=popgym_pendulum for a model with its keys")
    if not trainer_class(cfg).model_free:
        raise ConfigError(f"trainer: env=popgym has no model of the task's dynamics, so no belief can be computed "
                          f"and only the model-free GRU trains on it (trainer=recurrent_ppo), got "
                          f"trainer={cfg.trainer.get('algorithm')}; with beliefs, use env=popgym_cartpole or "
                          "env=popgym_pendulum")
    length = popgym_episode_length(popgym_any_task(str(cfg.env.popgym_task)))
    if length is not None and int(cfg.env.max_steps) < length:
        raise ConfigError(f"env.max_steps: an iteration must hold {cfg.env.popgym_task}'s longest episode "
                          f"({length} steps), got {cfg.env.max_steps}; set env.max_steps={length} or more")


def check_popgym_task(cfg: DictConfig) -> None:
    """``env.popgym_task`` (the agents act in POPGym's own env): a POPGym control task of the env
    group's system, with its episode length as ``env.max_steps``; not with a trainer that reads the
    simulator's true state (``trainer=dvrl_a2c``'s readout, ``trainer.critic_input=state``)."""
    task = cfg.env.get("popgym_task", None)
    if registry.is_task_only(cfg.env.name):
        return check_popgym_any_task(cfg)
    if not task:
        return
    from escort_rl.config.registry import name_of
    from escort_rl.models import popgym_model_class
    from escort_rl.models.popgym_task import task_key

    try:
        model = popgym_model_class(task)
    except ValueError as error:
        raise ConfigError(f"env.popgym_task: {str(error).removeprefix('name: ')}") from None
    if str(cfg.env.name) != name_of("model", model):
        raise ConfigError(f"env.popgym_task: '{task}' is not a task of env={cfg.env.name}; use "
                          f"env={name_of('model', model)}")
    length = int(model.TASKS[task_key(task)]["max_episode_length"])
    if int(cfg.env.max_steps) != length:
        raise ConfigError(f"env.max_steps: POPGym's {task} runs {length} steps, got {cfg.env.max_steps}; set "
                          f"env.max_steps={length}")
    if trainer_class(cfg).reads_true_state(typed_trainer(cfg)):
        raise ConfigError("env.popgym_task: POPGym's own env has no true state, which trainer=dvrl_a2c's readout "
                          "and trainer.critic_input=state read; act in the model's simulator (env.popgym_task=null) "
                          "or set trainer.critic_input=belief")
    noise, assumed = float(model.TASKS[task_key(task)]["obs_noise"]), cfg.env.model.get("obs_noise", None)
    if not trainer_class(cfg).model_free and assumed is not None and abs(float(assumed) - noise) > 1e-9:
        raise ConfigError(f"env.model.obs_noise: POPGym's {task} adds observation noise {noise:g}, but the filters' "
                          f"model assumes {float(assumed):g}; set env.model.obs_noise={noise:g}")
