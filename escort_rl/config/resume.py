"""Resuming a run: the saved run's overrides merged with new ones and composed again, and the keys
whose value changed since the run was saved."""

from __future__ import annotations

from collections.abc import Mapping

from omegaconf import DictConfig, OmegaConf

from escort_rl.config.composition import check_composed, compose, hydra_error_line, is_group_override
from escort_rl.config.errors import ConfigError
from escort_rl.config import files


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
        with initialize_config_dir(config_dir=str(files.config_dir()), version_base=None):
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
