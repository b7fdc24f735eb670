"""Loading the Hydra configs shipped with the package, with errors that name the bad key."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from omegaconf import DictConfig, OmegaConf


class ConfigError(ValueError):
    """A bad configuration value or key; the message names the key and the fix."""


def config_dir() -> Path:
    """The folder holding ``config.yaml`` and the groups ``env/``, ``filter/``, ``trainer/``."""
    return Path(str(resources.files("escort_rl.configs")))


def compose(overrides: list[str] | None = None, config_name: str = "config") -> DictConfig:
    """Compose the config with Hydra-style overrides (``key=value``, ``group=option``).

    Unknown keys raise :class:`ConfigError` naming the key (use ``+key=value`` to add one on purpose).
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.errors import ConfigCompositionException, MissingConfigException, OverrideParseException

    overrides = list(overrides or [])
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
            cfg = hydra_compose(config_name=config_name, overrides=overrides)
    except (ConfigCompositionException, MissingConfigException, OverrideParseException) as err:
        raise ConfigError(_one_line(err, overrides)) from None
    OmegaConf.set_struct(cfg, True)
    return cfg


def _one_line(err: Exception, overrides: list[str]) -> str:
    text = str(err)
    cause = err.__cause__
    if cause is not None and "not in struct" in str(cause):
        text = str(cause)
    first = text.strip().splitlines()[0] if text.strip() else type(err).__name__
    if "not in struct" in first or "Could not override" in first:
        key = first.split("'")[1] if "'" in first else "?"
        full = [o.split("=", 1)[0].lstrip("+~") for o in overrides]
        matches = [k for k in full if k == key or k.endswith("." + key)]
        key = matches[0] if matches else key
        return (f"config: unknown key '{key}'; check the spelling against `escort-rl config`, "
                "or add a new key on purpose with +key=value")
    if "Could not find" in first or "MissingConfig" in type(err).__name__:
        return f"config: {first}"
    return f"config: {first}"


def merge_overrides(cfg: DictConfig, overrides: list[str]) -> DictConfig:
    """Apply ``key=value`` overrides to an already composed config (used when resuming).

    Unknown keys raise :class:`ConfigError`.
    """
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
    OmegaConf.set_struct(cfg, True)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"config: override '{item}' is not of the form key=value")
        key, value = item.split("=", 1)
        if OmegaConf.select(cfg, key, default="__missing__") == "__missing__":
            raise ConfigError(f"config: unknown key '{key}'; check the spelling against `escort-rl config`")
        OmegaConf.update(cfg, key, _parse_value(value), merge=True)
    return cfg


def _parse_value(value: str):
    import yaml

    try:
        return yaml.safe_load(value)
    except yaml.YAMLError:
        return value
