"""The typed schemas of the configs in ``configs/``, registered in Hydra's ConfigStore.

Every Hydra group option starts with ``defaults: [<option>_schema, _self_]`` (e.g.
``configs/trainer/ppo.yaml`` -> ``ppo_schema``), and ``config.yaml`` with ``config_schema``: the
dataclasses below, registered under those names by :func:`register`. Composing therefore gives a
typed config: a value of the wrong type (``num_particles=2.5``) or a key the schema lacks
(``trainer.lrr=1``) fails while composing, naming the key.

The schemas of the models, filters and trainers are made from their classes' parameter dataclasses
(:func:`params_schema`): the same fields, defaults and range metadata
(:mod:`escort_rl.config.params`), so a yaml holds only what differs from them. A mapping field has
no schema default (``???``): OmegaConf merges mappings key by key, and a default would keep the
keys a yaml leaves out. The other schemas (the env group's own keys, DVRL's sizes, the root) are
written here. Field metadata ``group`` marks a root field that holds a Hydra group: a config
without types (one saved by an older version) is checked against the option its contents name
(:func:`group_schema`). The checks themselves are :mod:`escort_rl.config.checking`'s.
"""

from __future__ import annotations

import dataclasses
import os
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

from omegaconf import MISSING

from escort_rl.config import registry
from escort_rl.config.params import param

_f = param


def _sub(cls) -> Any:
    return field(default_factory=cls)


# seeds are signed 64-bit ints (what torch.manual_seed takes); the env and iteration seeds derived
# from them stay in range
SEED_MIN, SEED_END = -(2**63), 2**63


# ------------------------------------------------------------------------------------- checks
def check_device(value: str) -> str | None:
    """``cpu``, ``cuda``, ``cuda:N`` or ``mps``, present on this machine."""
    import torch

    try:
        dev = torch.device(value)
    except (RuntimeError, TypeError, ValueError):
        return f"not a device: '{value}'; use cpu, cuda or cuda:N"
    if dev.type == "cpu":
        return None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            return f"'{value}' but this machine has no CUDA device (torch.cuda.is_available() is False); use device=cpu"
        count = torch.cuda.device_count()
        if dev.index is not None and dev.index >= count:
            return f"'{value}' but this machine has {count} CUDA device(s): cuda:0 .. cuda:{count - 1}"
        return None
    if dev.type == "mps":
        mps = getattr(torch.backends, "mps", None)
        return None if mps is not None and mps.is_available() else f"'{value}' but MPS is not available; use device=cpu"
    return f"'{value}' is not supported; use cpu, cuda or cuda:N"


def check_output_dir(value: str) -> str | None:
    """A folder, or a path that can become one: not empty (that would be the working directory), not
    an existing file, nor under one, and inside a folder this process may write to."""
    if not str(value).strip():
        return "empty; pass a folder, e.g. output_dir=outputs/mine ('.' for the working directory)"
    path = Path(value).expanduser()
    if path.exists() and not path.is_dir():
        return f"'{value}' is an existing file; pass a folder"
    for parent in (path, *path.parents):
        if parent.exists():
            if not parent.is_dir():
                return f"'{value}' is under the file '{parent}'; pass a folder"
            if not os.access(parent, os.W_OK | os.X_OK):
                return f"'{value}' cannot be written: '{parent}' is not writable; pass a folder you can write to"
            break
    return None


def check_nonempty(value: str) -> str | None:
    return None if value else "must not be empty"


def check_number_or_list(value) -> str | None:
    """A number or a list of numbers (``env.input_loc``, ``env.input_scale``)."""
    items = value if isinstance(value, list) else [value]
    if not items or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in items):
        return f"expected a number or a list of numbers, got {value!r}"
    return None


def check_options(value) -> str | None:
    """``null`` or a mapping of option names to values (``env.scripted_options``, ``env.teacher_options``)."""
    if value is None or isinstance(value, Mapping):
        return None
    return f"expected a mapping of option names to values, e.g. {{confidence: 0.9}}, or null, got {value!r}"


# ------------------------------------------------------------------- schemas of classes
def params_schema(params: type, schema_name: str, head: list[tuple] = ()) -> type:
    """The Hydra schema of a parameters dataclass: a dataclass with its fields, defaults and range
    metadata included, after the fields of ``head`` (``(name, type, field)`` triples, e.g.
    ``_target_``). A mapping field has no default (``???``): OmegaConf merges mappings key by key,
    so a default would keep the keys a yaml leaves out."""
    hints = typing.get_type_hints(params)
    specs = list(head)
    for f in dataclasses.fields(params):
        hint = hints[f.name]
        if typing.get_origin(hint) in (dict, Dict):
            spec = field(default=MISSING, metadata=f.metadata)
        elif f.default_factory is not dataclasses.MISSING:
            spec = field(default_factory=f.default_factory, metadata=f.metadata)
        else:
            spec = field(default=f.default, metadata=f.metadata)
        specs.append((f.name, hint, spec))
    schema = dataclasses.make_dataclass(schema_name, specs)
    schema.__module__ = __name__
    return schema


def _target_field(kind: str, name: str) -> tuple:
    return ("_target_", str, field(default=registry.target(kind, name)))


def model_schema(name: str, schema_name: str) -> type:
    """The schema of the model registered as ``name`` (``env.model``)."""
    return params_schema(registry.params("model", name), schema_name, [_target_field("model", name)])


def filter_schema(kind: str, schema_name: str) -> type:
    """The schema of a filter family (``configs/filter/*.yaml``): ``name`` labels the configuration,
    ``kind`` names the family (the class of configs saved without ``_target_``)."""
    head = [_target_field("filter", kind), ("name", str, field(default=kind)),
            ("kind", str, field(default=kind, metadata={"choices": [kind]}))]
    return params_schema(registry.params("filter", kind), schema_name, head)


def trainer_schema(algorithm: str, schema_name: str) -> type:
    """The schema of a trainer (``configs/trainer/*.yaml``): ``algorithm`` names it."""
    head = [("algorithm", str, field(default=algorithm, metadata={"choices": [algorithm]}))]
    return params_schema(registry.params("trainer", algorithm), schema_name, head)


# ------------------------------------------------------------------------------- env (models)
MODEL_SCHEMAS = {name: model_schema(name, f"{registry.class_name('model', name)}ModelConfig")
                 for name in registry.names("model")}
"""The schema of every registered model (``env.model``), by its env group's name."""


@dataclass
class EnvConfig:
    """The keys every env group option has."""

    name: str = _f(MISSING)
    max_steps: int = _f(MISSING, ge=1)
    # (x - input_loc) / input_scale per state dimension: a number or one per dimension
    input_loc: Any = _f(MISSING, check=check_number_or_list)
    input_scale: Any = _f(MISSING, check=check_number_or_list, gt=0)
    # model keys of the training envs' start distribution with trainer.exploring_starts=true
    exploring_starts: Optional[Dict[str, Any]] = _f(None)
    # model keys of the simulator the agents act in, where it differs from the filter's model
    # (e.g. POPGym's deterministic dynamics: {process_noise: 0.0})
    simulator: Optional[Dict[str, Any]] = _f(None)
    # state indices that are angles: the belief policy reads (cos, sin) of each
    periodic_dims: Optional[List[int]] = _f(None)
    # a POPGym task whose own env (TorchRL's GymEnv) the agents act in, instead of the simulator
    popgym_task: Optional[str] = _f(None)
    # the scripted controller's velocity gain in evaluation (the best of a sweep on the default
    # job's filter, stored with where it came from); null: the controller's default
    scripted_gain: Optional[float] = _f(None, ge=0)
    # the velocity gain of the kickstart teacher (trainer.teacher), where it differs from the evaluation's
    # best gain; null: scripted_gain
    teacher_gain: Optional[float] = _f(None, ge=0)
    # keyword options of the evaluation's scripted controller beyond its gain, e.g. the hidden goal's look-first
    # rule {confidence: 0.9} (its default commits at once); null: none
    scripted_options: Any = _f(None, check=check_options)
    # the same for the kickstart teacher, where it differs from the evaluation's controller; null: scripted_options
    teacher_options: Any = _f(None, check=check_options)
    # whether trainer.teacher=auto (PPO's default) kickstarts from the scripted controller in this env:
    # true where the controller (with teacher_options) is a good policy on the belief (Light-Dark; the hidden
    # goal's look-first rule), not where it is only a baseline to beat
    scripted_teacher: bool = _f(False)


def env_schema(name: str, model: type, schema_name: str) -> type:
    """The schema of the env group option ``name`` (``configs/env/<name>.yaml``): the keys of
    :class:`EnvConfig` and ``model``, the schema of the model registered as ``name``."""
    default = field(default_factory=dict) if typing.get_origin(model) in (dict, Dict) else field(default_factory=model)
    specs = [("name", str, field(default=name, metadata={"choices": [name]})), ("model", model, default)]
    schema = dataclasses.make_dataclass(schema_name, specs, bases=(EnvConfig,))
    schema.__module__ = __name__
    return schema


ENV_SCHEMAS = {name: env_schema(name, model, f"{registry.class_name('model', name)}EnvConfig")
               for name, model in MODEL_SCHEMAS.items()}
"""The schema of every env group option: each registered model's, then the groups below."""
ENV_SCHEMAS["popgym"] = env_schema("popgym", Dict[str, Any], "POPGymAnyEnvConfig")
"""``env=popgym``: any POPGym task (``env.popgym_task``) in POPGym's own env, for the model-free GRU
(``trainer=recurrent_ppo``); no model, so ``env.model`` stays empty."""
ENV_SCHEMAS["custom"] = env_schema("custom", Dict[str, Any], "CustomEnvConfig")
"""``env=custom``: a user's own model. ``env.model`` is open: its ``_target_`` (the class, or any
callable returning a model) and the keyword arguments that go with it, each added with
``+env.model.KEY=VALUE``; :func:`escort_rl.trainers.builders.build_model` instantiates it."""


# ------------------------------------------------------------------------------------ filters
FILTER_SCHEMAS = {kind: filter_schema(kind, f"{registry.class_name('filter', kind).removesuffix('Filter')}Config")
                  for kind in registry.names("filter")}
"""The schema of every registered filter family (``filter.kind``)."""


# ----------------------------------------------------------------------------------- trainers
TRAINER_SCHEMAS = {name: trainer_schema(name, f"{registry.class_name('trainer', name)}Config")
                   for name in registry.names("trainer")}
"""The schema of every registered trainer (``trainer.algorithm``)."""


# --------------------------------------------------------------------------------------- dvrl
@dataclass
class DVRLModuleConfig:
    """``escort_rl.modules.DVRL``'s size arguments (``dvrl.module``)."""

    num_particles: int = _f(MISSING, ge=1)
    latent_dim: int = _f(MISSING, ge=1)
    hidden: int = _f(MISSING, ge=1)
    encoding_dim: Optional[int] = _f(None, ge=1)
    summary: str = _f(MISSING, choices=["gru", "deepsets"])
    summary_dim: Optional[int] = _f(None, ge=1)
    resample: bool = MISSING


@dataclass
class DVRLLossConfig:
    """The DVRL trainer's loss weights (``dvrl.loss``)."""

    encoding_loss_coef: float = _f(MISSING, ge=0)
    value_loss_coef: float = _f(MISSING, ge=0)
    bptt_steps: int = _f(MISSING, ge=1)
    reward_scale: float = _f(MISSING, gt=0)


@dataclass
class DVRLConfig:
    """``configs/dvrl/<domain>.yaml``."""

    name: str = _f(MISSING, choices=list(ENV_SCHEMAS))
    obs_dim: int = _f(MISSING, ge=1)
    n_actions: Optional[int] = _f(MISSING, ge=1)  # None: continuous actions, which DVRL does not take
    module: DVRLModuleConfig = _sub(DVRLModuleConfig)
    loss: DVRLLossConfig = _sub(DVRLLossConfig)


# --------------------------------------------------------------------------------------- root
@dataclass
class KeysConfig:
    """The tensordict keys the belief transform writes and the policies read."""

    particles: str = _f(MISSING, check=check_nonempty)
    log_weights: str = _f(MISSING, check=check_nonempty)


@dataclass
class ActorConfig:
    hidden: int = _f(MISSING, ge=1)
    encoder_layers: int = _f(2, ge=1)
    summary: bool = _f(False)
    head: str = _f("auto", choices=["auto", "pooled", "per_coordinate"])
    group_hidden: int = _f(16, ge=1)
    max_particles: Optional[int] = _f(None, ge=1)
    pooling: str = _f("mean", choices=["mean", "attention"])
    attention_heads: int = _f(4, ge=1)
    min_scale: float = _f(1e-4, gt=0)
    distribution: str = _f("clipped_normal", choices=["tanh_normal", "clipped_normal"])


def check_ray_installed(value: str) -> str | None:
    """``ray`` needs the ``ray`` package (the ``ray`` extra)."""
    if value != "ray":
        return None
    import importlib.util

    return None if importlib.util.find_spec("ray") else "ray is not installed; install with pip install escort-rl[ray]"


@dataclass
class CollectorConfig:
    """``local``: a TorchRL ``Collector`` (``workers=1``) or ``MultiSyncCollector`` (K worker
    processes); ``ray``: TorchRL's ``RayCollector`` with ``workers`` remote collectors, on the Ray
    cluster at ``ray_address`` (``null``: ``RAY_ADDRESS``, else a local Ray)."""

    workers: int = _f(MISSING, ge=1)
    backend: str = _f("local", choices=["local", "ray"], check=check_ray_installed)
    ray_address: Optional[str] = None


@dataclass
class LoggerConfig:
    backend: str = _f(MISSING, choices=["csv", "tensorboard", "wandb"])
    project: str = "escort-rl"
    offline: bool = True


@dataclass
class EvaluateConfig:
    episodes: int = _f(MISSING, ge=1)
    seed: int = _f(MISSING, ge=SEED_MIN, lt=SEED_END)
    greedy: bool = MISSING


@dataclass
class Config:
    """``configs/config.yaml``. The groups are typed by their options' schemas."""

    env: Any = _f(MISSING, group="env")
    filter: Any = _f(MISSING, group="filter")
    trainer: Any = _f(MISSING, group="trainer")
    dvrl: Any = _f(MISSING, group="dvrl")
    seed: int = _f(MISSING, ge=SEED_MIN, lt=SEED_END)
    device: str = _f(MISSING, check=check_device)
    num_particles: int = _f(MISSING, ge=1)
    output_dir: str = _f(MISSING, check=check_output_dir)
    keys: KeysConfig = _sub(KeysConfig)
    resume: Optional[str] = None
    actor: ActorConfig = _sub(ActorConfig)
    collector: CollectorConfig = _sub(CollectorConfig)
    logger: LoggerConfig = _sub(LoggerConfig)
    evaluate: EvaluateConfig = _sub(EvaluateConfig)
    # The overrides `escort-rl train` composed this run from (null: composed in code, or saved by an
    # older version); `train resume=RUN_DIR ...` recomposes from them.
    overrides: Optional[List[str]] = None


def group_schema(group: str, node) -> type | None:
    """The schema of a group option from its contents (for configs without types)."""
    if group == "env":
        return ENV_SCHEMAS.get(node.get("name"))
    if group == "filter":
        return FILTER_SCHEMAS.get(node.get("kind", node.get("name")))
    if group == "trainer":
        return TRAINER_SCHEMAS.get(node.get("algorithm", "reinforce"))
    if group == "dvrl":
        return DVRLConfig
    return None


# ------------------------------------------------------------------------------ registration
_REGISTERED = False


def register() -> None:
    """Store the schemas in Hydra's ConfigStore under the names the yaml defaults lists use
    (idempotent)."""
    global _REGISTERED
    if _REGISTERED:
        return
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    cs.store(name="config_schema", node=Config)
    for name, node in ENV_SCHEMAS.items():
        cs.store(group="env", name=f"{name}_schema", node=node)
    for name, node in FILTER_SCHEMAS.items():
        cs.store(group="filter", name=f"{name}_schema", node=node)
    for name, node in TRAINER_SCHEMAS.items():
        cs.store(group="trainer", name=f"{name}_schema", node=node)
    cs.store(group="dvrl", name="dvrl_schema", node=DVRLConfig)
    _REGISTERED = True


register()
