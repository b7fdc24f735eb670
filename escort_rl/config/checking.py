"""The checker of composed configs: every value against its schema's type and field metadata
(:func:`escort_rl.config.params.value_problem`), and one line for an OmegaConf error."""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path
from typing import Any, Dict

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import (
    ConfigAttributeError,
    ConfigKeyError,
    MissingMandatoryValue,
    OmegaConfBaseException,
    ValidationError,
)

from escort_rl.config.errors import ConfigError
from escort_rl.config.params import describe_type, value_problem
from escort_rl.config.schema import Config, group_schema


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
        return _walk(value, group_schema(meta["group"], value), key, stage)
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
