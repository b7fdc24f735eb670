"""The one map from the names a config uses to the classes they build.

A config names a model by its env group (``env=lightdark10d``), a filter by its family
(``filter.kind: escort``) and a trainer by ``trainer.algorithm``. This module maps each name to the
dotted path of its class, and imports the class only when asked (:func:`resolve`), in the way
Hydra's ``_target_`` does: configuration sits below the models, filters and trainers it names, and
importing it loads none of them.

Examples:
    >>> target("filter", "sir")
    'escort_rl.belief.SIRFilter'
    >>> resolve("filter", "escort").__name__
    'ESCORTFilter'
    >>> names("trainer")
    ['dvrl_a2c', 'ppo', 'recurrent_ppo', 'reinforce']
"""

from __future__ import annotations

import importlib

from escort_rl.config.errors import ConfigError

REGISTRY: dict[str, dict[str, str]] = {
    "model": {
        "lightdark10d": "escort_rl.models.LightDark10D",
        "lightdark10d_continuous": "escort_rl.models.LightDark10DContinuous",
        "kidnapped20d": "escort_rl.models.KidnappedRobot20D",
        "mtt20d": "escort_rl.models.MultiTargetTracking20D",
        "hidden_goal": "escort_rl.models.HiddenGoal",
        "linear_gaussian": "escort_rl.models.LinearGaussian",
        "lightdark1d": "escort_rl.models.LightDark1D",
        "popgym_cartpole": "escort_rl.models.POPGymCartPole",
        "popgym_pendulum": "escort_rl.models.POPGymPendulum",
    },
    "filter": {
        "sir": "escort_rl.belief.SIRFilter",
        "enkf": "escort_rl.belief.EnKFFilter",
        "svgd": "escort_rl.belief.SVGDFilter",
        "escort": "escort_rl.belief.ESCORTFilter",
    },
    "trainer": {
        "ppo": "escort_rl.trainers.ppo.PPO",
        "reinforce": "escort_rl.trainers.reinforce.Reinforce",
        "dvrl_a2c": "escort_rl.trainers.dvrl_a2c.DVRLA2C",
        "recurrent_ppo": "escort_rl.trainers.recurrent_ppo.RecurrentPPO",
    },
}
"""kind -> name -> the class's dotted path. ``model`` names are env groups (``configs/env/``; the
1-D planning problem ``lightdark1d`` has none), ``filter`` names are filter families
(``filter.kind``), ``trainer`` names are ``trainer.algorithm``."""

TRAINER_PARAMS_MODULE = "escort_rl.trainers.params"
"""Where every trainer's parameters dataclass lives, as ``<class name>Params`` (``PPO`` ->
``PPOParams``): a light module, so that composing a config reads them without importing TorchRL."""

TASK_ONLY_ENVS: dict[str, str] = {
    "popgym": "escort_rl.envs.popgym.popgym_task_spaces",
}
"""Env groups with no model of the task, only its spaces (``name -> the function of (task, device)
that returns its :class:`~escort_rl.models.TaskSpaces`): no belief can be computed there, and only a
model-free trainer trains on them. ``env=popgym``: any of POPGym's tasks (``env.popgym_task``)."""


def is_task_only(env_name: str) -> bool:
    """Whether the env group ``env_name`` has only a task's spaces (:data:`TASK_ONLY_ENVS`), no model."""
    return str(env_name) in TASK_ONLY_ENVS


def class_name(kind: str, name: str) -> str:
    """The name of the class registered as ``name``, without importing it.

    Example:
        >>> class_name("trainer", "dvrl_a2c")
        'DVRLA2C'
    """
    return target(kind, name).rpartition(".")[2]


_FIELD = {"model": "env.name", "filter": "filter.kind", "trainer": "trainer.algorithm"}


def names(kind: str) -> list[str]:
    """The registered names of ``kind`` (``model``, ``filter`` or ``trainer``), sorted."""
    return sorted(_table(kind))


def target(kind: str, name: str) -> str:
    """The dotted path of the class registered as ``name``; a :class:`ConfigError` naming the config
    field and the choices for an unknown name."""
    table = _table(kind)
    if name not in table:
        raise ConfigError(f"{_FIELD[kind]}: unknown {kind} '{name}'; choose one of {', '.join(sorted(table))}")
    return table[name]


def resolve(kind: str, name: str) -> type:
    """The class registered as ``name`` (imported now)."""
    return import_target(target(kind, name))


def name_of(kind: str, cls: type) -> str:
    """The name ``cls`` is registered under (the inverse of :func:`resolve`); ``ValueError`` when none.

    Example:
        >>> from escort_rl.models import POPGymPendulum
        >>> name_of("model", POPGymPendulum)
        'popgym_pendulum'
    """
    for name in names(kind):
        if class_name(kind, name) == cls.__name__ and resolve(kind, name) is cls:
            return name
    raise ValueError(f"cls: {cls.__name__} is not a registered {kind}")


def params(kind: str, name: str) -> type:
    """The parameters dataclass of the class registered as ``name`` (its ``Params``)."""
    if kind == "trainer":
        return import_target(f"{TRAINER_PARAMS_MODULE}.{class_name(kind, name)}Params")
    return resolve(kind, name).Params


def import_target(path: str) -> type:
    """The object at the dotted path ``package.module.Name``."""
    module, _, attr = path.rpartition(".")
    return getattr(importlib.import_module(module), attr)


def _table(kind: str) -> dict[str, str]:
    if kind not in REGISTRY:
        raise ValueError(f"kind: expected one of {', '.join(REGISTRY)}, got {kind!r}")
    return REGISTRY[kind]
