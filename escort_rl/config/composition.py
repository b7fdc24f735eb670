"""Composing the Hydra configs shipped with the package, typed by :mod:`escort_rl.config.schema`, with
errors of one line that name the bad key."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from escort_rl.config import checking, files, schema
from escort_rl.config.errors import ConfigError

UNKNOWN_KEY_HINT = ("check the spelling against `escort-rl config`, or add a new key on purpose with "
                    "+key=value")


def compose(overrides: list[str] | None = None, config_name: str = "config") -> DictConfig:
    """Compose the config with Hydra-style overrides (``key=value``, ``group=option``).

    The result is typed by the schemas of :mod:`escort_rl.config.schema` and its values are checked
    against their ranges. A bad value or an unknown key raises :class:`ConfigError` with one line
    naming the key (use ``+key=value`` to add a key on purpose).
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    schema.register()
    overrides = list(overrides or [])
    _refuse_schema_options(overrides)
    try:
        with initialize_config_dir(config_dir=str(files.config_dir()), version_base=None):
            cfg = hydra_compose(config_name=config_name, overrides=overrides)
    except Exception as err:  # noqa: BLE001 - Hydra and OmegaConf errors, turned into one line below
        message = hydra_error_line(err)
        if message is None:
            raise
        raise ConfigError(message) from None
    OmegaConf.set_struct(cfg, True)
    if config_name == "config":
        check_composed(cfg)
        # the run's folder is fixed when the run is composed (config.yaml records the path itself)
        cfg.output_dir = str(cfg.output_dir)
    return cfg


def check_composed(cfg: DictConfig) -> None:
    """:func:`escort_rl.config.checking.check_config` on a composed config; a value that fails to resolve
    (e.g. ``${oc.env:UNSET}``) raises :class:`ConfigError` naming its key too."""
    from omegaconf.errors import OmegaConfBaseException

    try:
        checking.check_config(cfg, prefix="config: ")
    except OmegaConfBaseException as err:
        raise ConfigError(f"config: {checking.describe_error(err)}") from None


def hydra_error_line(err: Exception) -> str | None:
    """``config: ...``: one line for an error of Hydra's composition, from the exception's fields
    (``None`` for an exception that is not Hydra's or OmegaConf's)."""
    from hydra.errors import HydraException, MissingConfigException, OverrideParseException
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

    from escort_rl.config.checking import describe_error

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
                    f"{context.object_type.__name__} lacks; add it to escort_rl/config/schema.py")
        return f"config: {describe_error(context)} (in the yaml)"
    if isinstance(err, HydraException):
        return f"config: {_first_line(str(err))}"
    return None


def _refuse_schema_options(overrides: list[str]) -> None:
    """``filter=escort_schema``: the schemas sit in the groups (Hydra's pattern) but are not options."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from escort_rl.config.files import option_names

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


def is_group_override(override) -> bool:
    """Whether a parsed Hydra override picks a group option (``filter=sir``), not a value."""
    return "." not in override.key_or_group and (files.config_dir() / override.key_or_group).is_dir()
