"""Loading the Hydra configs shipped with the package, typed by :mod:`escort_rl.schema`, with
errors of one line that name the bad key."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from escort_rl.schema import ConfigError, config_dir  # noqa: F401 - part of this module's API

UNKNOWN_KEY_HINT = ("check the spelling against `escort-rl config`, or add a new key on purpose with "
                    "+key=value")


def compose(overrides: list[str] | None = None, config_name: str = "config") -> DictConfig:
    """Compose the config with Hydra-style overrides (``key=value``, ``group=option``).

    The result is typed by the schemas of :mod:`escort_rl.schema` and its values are checked
    against their ranges. A bad value or an unknown key raises :class:`ConfigError` with one line
    naming the key (use ``+key=value`` to add a key on purpose).
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from escort_rl import schema

    schema.register()
    overrides = list(overrides or [])
    _refuse_schema_options(overrides)
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
            cfg = hydra_compose(config_name=config_name, overrides=overrides)
    except Exception as err:  # noqa: BLE001 - Hydra and OmegaConf errors, turned into one line below
        message = hydra_error_line(err)
        if message is None:
            raise
        raise ConfigError(message) from None
    OmegaConf.set_struct(cfg, True)
    if config_name == "config":
        check_composed(cfg)
    return cfg


def check_composed(cfg: DictConfig) -> None:
    """:func:`escort_rl.schema.check_config` on a composed config; a value that fails to resolve
    (e.g. ``${oc.env:UNSET}``) raises :class:`ConfigError` naming its key too."""
    from omegaconf.errors import OmegaConfBaseException

    from escort_rl import schema

    try:
        schema.check_config(cfg, prefix="config: ")
    except OmegaConfBaseException as err:
        raise ConfigError(f"config: {schema.describe_error(err)}") from None


def hydra_error_line(err: Exception) -> str | None:
    """``config: ...``: one line for an error of Hydra's composition, from the exception's fields
    (``None`` for an exception that is not Hydra's or OmegaConf's)."""
    from hydra.errors import HydraException, MissingConfigException, OverrideParseException
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

    from escort_rl.schema import describe_error

    if isinstance(err, OverrideParseException):
        return f"config: cannot parse the override '{err.override}': {_first_line(err.message)}"
    if isinstance(err, MissingConfigException):
        missing = str(err.missing_cfg_file or "")
        group, _, option = missing.rpartition("/")
        options = [o for o in (err.options or []) if not o.endswith("_schema")]
        if group and options:
            return f"config: no {group} config '{option}'; choose one of {', '.join(options)}"
        return f"config: {_first_line(str(err))}"
    cause = err if isinstance(err, OmegaConfBaseException) else err.__cause__
    if isinstance(cause, OmegaConfBaseException):  # an override
        if isinstance(cause, (ConfigKeyError, ConfigAttributeError)) and cause.object_type is not None:
            return f"config: unknown key '{cause.full_key}'; {UNKNOWN_KEY_HINT}"
        return f"config: {describe_error(cause)}"
    context = err.__context__
    if isinstance(context, OmegaConfBaseException):  # a yaml file of configs/ against its schema
        if isinstance(context, (ConfigKeyError, ConfigAttributeError)) and context.object_type is not None:
            return (f"config: {context.full_key}: a key of the yaml that its schema "
                    f"{context.object_type.__name__} lacks; add it to escort_rl/schema.py")
        return f"config: {describe_error(context)} (in the yaml)"
    if isinstance(err, HydraException):
        return f"config: {_first_line(str(err))}"
    return None


def _refuse_schema_options(overrides: list[str]) -> None:
    """``filter=escort_schema``: the schemas sit in the groups (Hydra's pattern) but are not options."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from escort_rl.schema import option_names

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except Exception:  # noqa: BLE001 - compose reports it
        return
    for o in parsed:
        value = o.value()
        if is_group_override(o) and isinstance(value, str) and value.endswith("_schema"):
            raise ConfigError(f"config: no {o.key_or_group} config '{value}' (a schema, not an option); choose "
                              f"one of {', '.join(option_names(o.key_or_group))}")


def _first_line(text: str) -> str:
    text = (text or "").strip()
    return text.splitlines()[0] if text else "?"


# ------------------------------------------------------------------------------------ resuming
def is_group_override(override) -> bool:
    """Whether a parsed Hydra override picks a group option (``filter=sir``), not a value."""
    return "." not in override.key_or_group and (config_dir() / override.key_or_group).is_dir()


def merge_override_lists(saved: list[str], new: list[str]) -> list[str]:
    """``saved`` then ``new``, without the saved overrides that ``new`` replaces: the same key, or,
    for a new group option (``filter=sir``), that group and every key under it."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import OverrideType
    from hydra.errors import OverrideParseException

    parser = OverridesParser.create()
    try:
        old_parsed, new_parsed = parser.parse_overrides(list(saved)), parser.parse_overrides(list(new))
    except OverrideParseException as err:
        raise ConfigError(hydra_error_line(err)) from None
    keep = []
    for old in old_parsed:
        replaced = False
        for o in new_parsed:
            if is_group_override(o) and (old.key_or_group == o.key_or_group
                                         or old.key_or_group.startswith(o.key_or_group + ".")):
                replaced = True
            elif old.key_or_group == o.key_or_group and not (
                    old.type in (OverrideType.ADD, OverrideType.FORCE_ADD) and o.type == OverrideType.CHANGE):
                replaced = True  # a key added by +key=value stays added; a later key=value changes it
        if not replaced:
            keep.append(old.input_line)
    return [*keep, *(o.input_line for o in new_parsed)]


def recompose(saved: Mapping, overrides: list[str]) -> DictConfig:
    """The config to resume a run with: the saved run's overrides (``saved["overrides"]``) followed
    by ``overrides``, composed again, so that a group override (``filter=sir``) selects that
    option. A config saved without its overrides (by an older version, or composed in code) is taken
    as it is, with the value overrides applied by Hydra; a group cannot change then."""
    recorded = saved.get("overrides")
    if recorded is not None:
        merged = merge_override_lists(list(recorded), list(overrides))
        cfg = compose(merged)
        cfg.overrides = merged
        return cfg
    return _compose_saved(saved, list(overrides))


def _compose_saved(saved: Mapping, overrides: list[str]) -> DictConfig:
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.config_store import ConfigStore
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except OverrideParseException as err:
        raise ConfigError(hydra_error_line(err)) from None
    groups = [o.input_line for o in parsed if is_group_override(o)]
    if groups:
        raise ConfigError(f"config: {groups[0]}: this run's config was saved without the overrides that composed "
                          "it (an older version, or a run started from code), so a group cannot change on "
                          "resume; start a new run instead")
    plain = OmegaConf.to_container(OmegaConf.create(dict(saved)), resolve=True)
    ConfigStore.instance().store(name="escort_rl_saved_run", node=plain)
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
            cfg = hydra_compose(config_name="escort_rl_saved_run", overrides=overrides)
    except Exception as err:  # noqa: BLE001
        message = hydra_error_line(err)
        if message is None:
            raise
        raise ConfigError(message) from None
    OmegaConf.set_struct(cfg, True)
    check_composed(cfg)
    return cfg


def saved_config_drift(saved: Mapping) -> list[str]:
    """The keys whose saved value differs from what the saved overrides compose to today (the yaml
    changed since the run started); empty for a config saved without its overrides."""
    recorded = saved.get("overrides")
    if recorded is None:
        return []
    try:
        now = OmegaConf.to_container(compose(list(recorded)), resolve=True)
    except ConfigError:
        return ["(the saved overrides no longer compose)"]
    before = OmegaConf.to_container(OmegaConf.create(dict(saved)), resolve=True)
    return [k for k in _diff(before, now, "") if k.split(".")[0] not in ("resume", "overrides")]


def _diff(a, b, path: str) -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in [*a, *(k for k in b if k not in a)]:
            out += _diff(a.get(k, "<absent>"), b.get(k, "<absent>"), f"{path}.{k}" if path else str(k))
        return out
    return [] if a == b else [path]
