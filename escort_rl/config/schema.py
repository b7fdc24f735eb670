"""Typed schemas of the configs in ``configs/``, and the checks their metadata drives.

Every Hydra group option starts with ``defaults: [<option>_schema, _self_]`` (e.g.
``configs/trainer/ppo.yaml`` -> ``ppo_schema``), and ``config.yaml`` with ``config_schema``: the
dataclasses below, registered in Hydra's ``ConfigStore`` under those names by :func:`register`.
Composing therefore gives a typed config: a value of the wrong type (``num_particles=2.5``) or a
key the schema lacks (``trainer.lrr=1``) fails while composing, naming the key.

Ranges are field metadata, checked by :func:`check_config` after composing (and again by
``escort_rl.trainers.validation.validate_train_config`` before training):

- ``ge``, ``gt``, ``le``, ``lt``: bounds on a number (on every number of a list);
- ``choices``: the allowed values (of every element of a list);
- ``finite``: every float must be finite. This is the default for every field; ``finite: False``
  opts out;
- ``check``: a function ``value -> message | None`` for what bounds cannot say (``device``,
  ``output_dir``, ``trainer.warm_start_filter``);
- ``stage: "train"``: checked only before training, not while composing;
- ``group``: the root field holds a Hydra group; a config without types (one saved by an older
  version) is checked against the option named by ``GROUPS``.

Schemas of classes (the models, the filters, the planner) mirror their constructors, defaults
included (tests check both), with ``_target_`` for ``hydra.utils.instantiate``; mappings have no
default (``???``) because OmegaConf merges mappings key by key: a default would keep keys the yaml
leaves out. The schemas of the other groups give types and ranges only: their values live in the
yaml (``???`` here).

The benchmark settings (``configs/bench/``) and the planner settings (``configs/planner/``) are
read without Hydra; :func:`load_typed` applies a schema to such a file.
"""

from __future__ import annotations

import dataclasses
import os
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf
from omegaconf.errors import (ConfigAttributeError, ConfigKeyError, MissingMandatoryValue, OmegaConfBaseException,
                              ValidationError)

from escort_rl.config import registry
from escort_rl.config.errors import ConfigError
from escort_rl.config.files import check_filter_name
from escort_rl.config.params import MAX_LR, describe_type, param, value_problem


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
LightDark10DModelConfig = model_schema("lightdark10d", "LightDark10DModelConfig")


KidnappedRobot20DModelConfig = model_schema("kidnapped20d", "KidnappedRobot20DModelConfig")
MultiTargetTracking20DModelConfig = model_schema("mtt20d", "MultiTargetTracking20DModelConfig")
LinearGaussianModelConfig = model_schema("linear_gaussian", "LinearGaussianModelConfig")


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


@dataclass
class LightDark10DEnvConfig(EnvConfig):
    """``configs/env/lightdark10d.yaml``."""

    name: str = _f("lightdark10d", choices=["lightdark10d"])
    model: LightDark10DModelConfig = _sub(LightDark10DModelConfig)


@dataclass
class KidnappedRobot20DEnvConfig(EnvConfig):
    """``configs/env/kidnapped20d.yaml``."""

    name: str = _f("kidnapped20d", choices=["kidnapped20d"])
    model: KidnappedRobot20DModelConfig = _sub(KidnappedRobot20DModelConfig)


@dataclass
class MultiTargetTracking20DEnvConfig(EnvConfig):
    """``configs/env/mtt20d.yaml``."""

    name: str = _f("mtt20d", choices=["mtt20d"])
    model: MultiTargetTracking20DModelConfig = _sub(MultiTargetTracking20DModelConfig)


@dataclass
class LinearGaussianEnvConfig(EnvConfig):
    """``configs/env/linear_gaussian.yaml``: the linear-Gaussian family, whose exact posterior is Kalman's."""

    name: str = _f("linear_gaussian", choices=["linear_gaussian"])
    model: LinearGaussianModelConfig = _sub(LinearGaussianModelConfig)


ENV_SCHEMAS = {"lightdark10d": LightDark10DEnvConfig, "kidnapped20d": KidnappedRobot20DEnvConfig,
               "mtt20d": MultiTargetTracking20DEnvConfig, "linear_gaussian": LinearGaussianEnvConfig}


# ------------------------------------------------------------------------------------ filters
SIRConfig = filter_schema("sir", "SIRConfig")
EnKFConfig = filter_schema("enkf", "EnKFConfig")
SVGDConfig = filter_schema("svgd", "SVGDConfig")
ESCORTConfig = filter_schema("escort", "ESCORTConfig")
FILTER_SCHEMAS = {"sir": SIRConfig, "enkf": EnKFConfig, "svgd": SVGDConfig, "escort": ESCORTConfig}


# ----------------------------------------------------------------------------------- trainers
ReinforceConfig = trainer_schema("reinforce", "ReinforceConfig")
PPOConfig = trainer_schema("ppo", "PPOConfig")
DVRLA2CConfig = trainer_schema("dvrl_a2c", "DVRLA2CConfig")
RecurrentPPOConfig = trainer_schema("recurrent_ppo", "RecurrentPPOConfig")
TRAINER_SCHEMAS = {"reinforce": ReinforceConfig, "ppo": PPOConfig, "dvrl_a2c": DVRLA2CConfig,
                   "recurrent_ppo": RecurrentPPOConfig}


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
    n_actions: int = _f(MISSING, ge=1)
    module: DVRLModuleConfig = _sub(DVRLModuleConfig)
    loss: DVRLLossConfig = _sub(DVRLLossConfig)


# -------------------------------------------------------------------------------------- bench
@dataclass
class TrainBudgetConfig:
    iterations: int = _f(MISSING, ge=1)
    num_envs: int = _f(MISSING, ge=1)


@dataclass
class PlannerRowConfig:
    filter: str = _f(MISSING, check=check_filter_name)


@dataclass
class LearnedRowConfig:
    trainer: str = MISSING


@dataclass
class ClosedLoopBenchConfig:
    """``configs/bench/closed_loop.yaml`` (protocol (b) of the domain benchmark)."""

    episodes: int = _f(MISSING, ge=1)
    eval_seed: int = MISSING
    particles: int = _f(MISSING, ge=1)
    greedy: bool = MISSING
    # the trainer of the filter rows (a DeepSets policy on a filter's belief); None: config.yaml's
    trainer: Optional[str] = _f(None, choices=["ppo", "reinforce"])
    train: Dict[str, TrainBudgetConfig] = MISSING
    planners: Dict[str, PlannerRowConfig] = MISSING
    # scripted rows have the planner rows' shape: {filter: <a configs/filter/ name>}
    scripted: Dict[str, PlannerRowConfig] = MISSING
    learned: Dict[str, LearnedRowConfig] = MISSING
    # recurrent rows (no belief) have the learned rows' shape: {trainer: <a configs/trainer/ name>}
    recurrent: Dict[str, LearnedRowConfig] = MISSING


@dataclass
class SyntheticTargetConfig:
    """One GMM target: components are ``{mean, cov}`` or ``{mean, var, corr}`` with several forms
    each (see the yaml's header), so they stay untyped."""

    dim: int = _f(MISSING, ge=1)
    weights: List[float] = _f(MISSING, gt=0, le=1)
    components: List[Any] = MISSING


@dataclass
class GaussianInitialConfig:
    mean: float = MISSING
    std: float = _f(MISSING, gt=0)


@dataclass
class ScalabilityConfig:
    dims: List[int] = _f(MISSING, ge=1)
    structures: List[str] = _f(MISSING, choices=["block", "banded", "long_range", "sparse"])
    weights: List[float] = _f(MISSING, gt=0, le=1)
    positions: List[float] = MISSING
    std: List[float] = _f(MISSING, gt=0)
    block: Dict[str, Any] = MISSING
    banded: Dict[str, Any] = MISSING
    long_range: Dict[str, Any] = MISSING
    sparse: Dict[str, Any] = MISSING
    initial: GaussianInitialConfig = _sub(GaussianInitialConfig)


@dataclass
class SyntheticBenchConfig:
    """``configs/bench/synthetic.yaml`` (the paper's synthetic targets)."""

    targets: Dict[str, SyntheticTargetConfig] = MISSING
    initial: Dict[str, GaussianInitialConfig] = MISSING
    scalability: ScalabilityConfig = _sub(ScalabilityConfig)


@dataclass
class AtariTrainerConfig:
    """``configs/bench/atari.yaml``'s ``trainer``: A2C with DVRL's Atari settings."""

    num_envs: int = _f(MISSING, ge=1)
    rollout_steps: int = _f(MISSING, ge=1)
    updates_per_iteration: int = _f(MISSING, ge=1)
    lr: float = _f(MISSING, gt=0, lt=MAX_LR)
    rmsprop_alpha: float = _f(MISSING, ge=0, lt=1)
    rmsprop_eps: float = _f(MISSING, gt=0)
    gamma: float = _f(MISSING, gt=0, le=1)
    entropy_coef: float = _f(MISSING, ge=0)
    value_loss_coef: float = _f(MISSING, ge=0)
    encoding_loss_coef: float = _f(MISSING, ge=0)
    max_grad_norm: float = _f(MISSING, gt=0)
    reward_clip: bool = MISSING
    parallel_envs: bool = MISSING
    checkpoint_every: int = _f(MISSING, ge=1)
    keep_checkpoints: int = _f(MISSING, ge=1)


@dataclass
class AtariVRNNConfig:
    """The VRNN of DVRL and ESCORT-latent (``escort_rl.modules.DVRL``'s size arguments)."""

    num_particles: int = _f(MISSING, ge=1)
    latent_dim: int = _f(MISSING, ge=1)
    hidden: int = _f(MISSING, ge=1)
    encoding_dim: int = _f(MISSING, ge=1)
    summary: str = _f(MISSING, choices=["gru", "deepsets"])


@dataclass
class AtariESCORTConfig:
    """ESCORT-latent's particle evolution (``ESCORTFilter``'s arguments)."""

    num_steps: int = _f(MISSING, ge=1)
    step_size: float = _f(MISSING, gt=0)
    lambda_corr: float = _f(MISSING, ge=0)
    lambda_temp: float = _f(MISSING, ge=0)
    n_proj: int = _f(MISSING, ge=1)
    proj_dim: int = _f(MISSING, ge=1)
    jitter: float = _f(MISSING, ge=0)


@dataclass
class AtariGRUConfig:
    hidden: int = _f(MISSING, ge=1)


@dataclass
class AtariPaperConfig:
    """The paper's Table 4: ``table4[game][method] = [mean, s.e.]`` at ``frames``."""

    frames: int = _f(MISSING, ge=1)
    table4: Dict[str, Dict[str, List[float]]] = MISSING


@dataclass
class AtariBenchConfig:
    """``configs/bench/atari.yaml`` (Flickering Atari, the paper's Table 4)."""

    trainer: AtariTrainerConfig = _sub(AtariTrainerConfig)
    vrnn: AtariVRNNConfig = _sub(AtariVRNNConfig)
    escort: AtariESCORTConfig = _sub(AtariESCORTConfig)
    gru: AtariGRUConfig = _sub(AtariGRUConfig)
    paper: AtariPaperConfig = _sub(AtariPaperConfig)


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
    backend: str = _f(MISSING, choices=["csv", "tensorboard"])


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


def _group_schema(group: str, node) -> type | None:
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


# ------------------------------------------------------------------------------ type messages
def _field_hint(schema, key) -> Any:
    if not (isinstance(schema, type) and dataclasses.is_dataclass(schema)) or not isinstance(key, str):
        return None
    return typing.get_type_hints(schema).get(key)


def _show(value) -> str:
    return f"'{value}'" if not isinstance(value, (list, dict, ListConfig, DictConfig)) else repr(value)


def describe_error(err: OmegaConfBaseException) -> str:
    """One line for an OmegaConf error, from its structured fields (``full_key``, ``value``, the
    schema's type of the key): ``num_particles: expected an int, got '2.5'``."""
    key = err.full_key or err.key or "?"
    if isinstance(err, (ConfigKeyError, ConfigAttributeError)) and err.object_type is not None:
        return f"unknown key '{key}'"
    if isinstance(err, MissingMandatoryValue):
        return f"{key}: missing (???); set it"
    if isinstance(err, ValidationError):
        hint = _field_hint(err.object_type, err.key)
        if hint is None and isinstance(err.parent_node, ListConfig):  # an element of a typed list
            hint = err.parent_node._metadata.element_type
        if hint is not None:
            return f"{key}: expected {describe_type(hint)}, got {_show(err.value)}"
    msg = (err.msg or type(err).__name__).strip().splitlines()[0]
    return f"{key}: {msg}" if err.full_key else msg


# ------------------------------------------------------------------------------------ checker
def check_config(cfg, schema: type | None = None, *, stage: str = "compose", prefix: str = "") -> None:
    """Raise ``ConfigError(prefix + "<full key>: <what is wrong>")`` for the first value that breaks
    its schema's type or metadata. ``schema``: for a config without types (default: the root
    :class:`Config`); a typed config carries its own. ``stage="train"`` adds the checks marked so."""
    problem = find_problem(cfg, schema or Config, stage=stage)
    if problem is not None:
        raise ConfigError(prefix + problem)


def find_problem(cfg, schema: type | None = None, *, stage: str = "compose", path: str = "") -> str | None:
    """The message :func:`check_config` raises, or ``None``."""
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    return _walk(cfg, schema, path, stage)


def _walk(node: DictConfig, schema, path: str, stage: str) -> str | None:
    own = OmegaConf.get_type(node)
    if own is not None and dataclasses.is_dataclass(own):
        schema = own
    if schema is None:
        return None
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        if f.name.startswith("_") or f.name not in node:
            continue
        key = f"{path}.{f.name}" if path else f.name
        if OmegaConf.is_missing(node, f.name):
            return f"{key}: missing (???); set it"
        problem = _check_value(node[f.name], hints[f.name], f.metadata, key, stage)
        if problem is not None:
            return problem
    return None


def _check_value(value, hint, meta, key: str, stage: str) -> str | None:
    if "group" in meta and isinstance(value, DictConfig):
        return _walk(value, _group_schema(meta["group"], value), key, stage)
    sub = hint
    if typing.get_origin(hint) is typing.Union:
        sub = next((a for a in typing.get_args(hint) if a is not type(None)), hint)
    if isinstance(value, DictConfig) and dataclasses.is_dataclass(sub):
        return _walk(value, sub, key, stage)
    args = typing.get_args(sub)
    if (isinstance(value, DictConfig) and typing.get_origin(sub) in (dict, Dict) and len(args) == 2
            and dataclasses.is_dataclass(args[1])):
        for k in value:
            problem = _walk(value[k], args[1], f"{key}.{k}", stage)
            if problem is not None:
                return problem
        return None
    plain = OmegaConf.to_container(value, resolve=True) if isinstance(value, (DictConfig, ListConfig)) else value
    return value_problem(plain, hint, meta, key, stage)


# ------------------------------------------------------------------------------ plain files
def load_typed(path: str | Path, schema: type) -> DictConfig:
    """A yaml file read without Hydra (``configs/bench/*.yaml``, ``configs/planner/*.yaml``) with
    ``schema`` applied: ``OmegaConf.merge(OmegaConf.structured(schema), yaml)``, then the checks of
    its metadata. Raises ``ConfigError("<path>: <key>: ...")``. A top-level ``defaults`` list (Hydra's)
    is dropped, so a group option can be read too."""
    loaded = OmegaConf.load(path)
    if isinstance(loaded, DictConfig) and "defaults" in loaded:
        loaded = OmegaConf.masked_copy(loaded, [k for k in loaded if k != "defaults"])
    try:
        cfg = OmegaConf.merge(OmegaConf.structured(schema), loaded)
    except OmegaConfBaseException as err:
        raise ConfigError(f"{path}: {describe_error(err)}") from None
    check_config(cfg, schema, prefix=f"{path}: ")
    return cfg


register()
