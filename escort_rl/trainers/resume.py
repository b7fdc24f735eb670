"""Where a run starts from: a new run, or a checkpoint, its run directory and the config to continue
it with. Every decision about a resume is made here; reading and verifying checkpoint files is
:mod:`escort_rl.trainers.checkpointing`'s.

- **Which checkpoint.** ``resume=RUN_DIR`` gives the run's newest intact checkpoint (a damaged newer
  one is skipped with a warning); ``resume=CHECKPOINT`` names one; ``resume=null`` (or none) is a
  new run.
- **Which config.** A new run records its overrides in the config (``overrides``). A resume composes
  the saved run's overrides followed by the new ones again (:func:`recompose`), so that a group
  override (``filter=sir``) selects that option; the keys whose yaml default changed since the run
  started are named on stderr (:func:`saved_config_drift`).
- **Which run directory.** A resume writes into the run directory that holds its checkpoint,
  whatever ``output_dir`` the run was saved with, so resuming a moved or copied run never touches
  the original: the saved ``output_dir`` (and its recorded override) is rewritten to that
  directory. An ``output_dir`` that names another directory is refused by
  :func:`check_output_dir`, the one place that compares them (to branch a run, copy its directory
  and resume the copy).
- **Which state.** :func:`restore` loads the components and the trainer state (iteration, frames,
  seconds, history) that the scaffold continues from.

Example::

    >>> cfg, saved = train_config(["resume=outputs/run", "trainer.iterations=20"])   # doctest: +SKIP
    >>> state, run_dir, checkpoint = restore(cfg, components, saved)                 # doctest: +SKIP
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from escort_rl.config import files
from escort_rl.config.composition import check_composed, compose, hydra_error_line, is_group_override
from escort_rl.config.errors import ConfigError
from escort_rl.trainers.checkpointing import checkpoint_dir, list_checkpoints, load_checkpoint, run_dir_of

NEW_RUN = ("", "null", "None")


# ------------------------------------------------------------------------------------ the run directory
def output_path(output_dir: str) -> Path:
    """The run directory that ``output_dir`` names: ``~`` is the home folder, as in a shell (every
    file of the run, checkpoints included, goes there)."""
    return Path(str(output_dir)).expanduser()


def check_output_dir(output_dir: str, run_dir: Path) -> None:
    """Raise :class:`ConfigError` naming ``output_dir`` unless it names ``run_dir``, the run
    directory being resumed (the one place a resume's ``output_dir`` is checked)."""
    if output_path(output_dir).resolve() != Path(run_dir).resolve():
        raise ConfigError(f"output_dir: '{output_dir}' is not the run directory being resumed ('{run_dir}'); "
                          "a resume writes into the run it continues: drop output_dir=, or copy the run "
                          "directory and resume the copy")


def resumed_run_dir(cfg: DictConfig, checkpoint: str | Path) -> Path:
    """The directory a resume from ``checkpoint`` writes into: the run directory that holds it,
    which ``cfg.output_dir`` must name (:func:`check_output_dir`)."""
    run_dir = run_dir_of(checkpoint)
    check_output_dir(cfg.output_dir, run_dir)
    return run_dir


# ------------------------------------------------------------------------------------ the config
def train_config(overrides: list[str]) -> tuple[DictConfig, dict | None]:
    """The config ``escort-rl train`` runs with, and the checkpoint it resumes (``None``: a new run),
    from the command line's overrides (``resume=`` among them; the last one counts)."""
    resume = [o.split("=", 1)[1] for o in overrides if o.startswith("resume=")]
    rest = [o for o in overrides if not o.startswith("resume=")]
    if not resume or resume[-1] in NEW_RUN:
        return new_run_config(rest), None
    saved = load_checkpoint(resume[-1])
    run_dir = run_dir_of(saved["path"])
    cfg = recompose(saved["config"], rest)
    if not any(_override_key(o) == "output_dir" for o in rest):
        _write_into(cfg, run_dir)  # the run may have been moved or copied: write into it, not the original
    follow_saved_model(cfg, run_dir)
    check_output_dir(cfg.output_dir, run_dir)
    cfg.resume = saved["path"]
    changes = config_changes(saved["config"], cfg)
    if changes:  # before any weight is loaded: a change that does not fit them is named here first
        print(f"resuming with {len(changes)} change{'s' if len(changes) > 1 else ''} to the run's config: "
              + "; ".join(changes), file=sys.stderr)
    drift = saved_config_drift(saved["config"])
    if drift:
        print(f"note: the yaml changed since this run started; resuming with today's values of "
              f"{', '.join(drift[:8])}{' ...' if len(drift) > 8 else ''}", file=sys.stderr)
    return cfg, saved


def new_run_config(overrides: list[str]) -> DictConfig:
    """The config of a new run, with its overrides recorded (``overrides``) for a later resume."""
    cfg = compose(overrides)
    cfg.overrides = overrides
    return cfg


def _write_into(cfg: DictConfig, run_dir: Path) -> None:
    """Point ``cfg.output_dir`` (and its recorded override) at ``run_dir`` when it names another
    directory."""
    if output_path(cfg.output_dir).resolve() == run_dir.resolve():
        return
    cfg.output_dir = str(run_dir)
    if cfg.get("overrides") is not None:
        new = f"output_dir={quoted_override(str(run_dir))}"
        out = [new if _override_key(o) == "output_dir" else o for o in cfg.overrides]
        cfg.overrides = out if new in out else [*out, new]


SAVED_MODEL = "escort_rl.models.saved.load_saved_model"
"""``env.model._target_`` of a run trained with a model object (``model.pt`` in its run directory)."""


def follow_saved_model(cfg: DictConfig, run_dir: str | Path) -> None:
    """Point a saved model's ``env.model.path`` (and its recorded override) at ``<run_dir>/model.pt``.
    A model object is saved in its run directory, so a moved or copied run reads its own copy; its
    SHA-256 must still match the one recorded. Nothing happens for any other model."""
    env = cfg.get("env")
    model = env.get("model") if env is not None else None
    if model is None or model.get("_target_") != SAVED_MODEL:
        return
    path = str(Path(run_dir).resolve() / "model.pt")
    if model.get("path") == path:
        return
    model.path = path
    if cfg.get("overrides") is not None:
        cfg.overrides = [f"+env.model.path={quoted_override(path)}" if o.startswith("+env.model.path=") else o
                         for o in cfg.overrides]


def run_config(meta: dict) -> DictConfig:
    """The config of the run a checkpoint belongs to, from :func:`load_checkpoint`'s result, with the
    run's own files read from where the run is now (:func:`follow_saved_model`)."""
    cfg = OmegaConf.create(meta["config"])
    follow_saved_model(cfg, run_dir_of(meta["path"]))
    return cfg


def quoted_override(value: str) -> str:
    """``value`` as a single-quoted Hydra override value (any path parses back to itself)."""
    return "'" + value.replace("'", "\\'") + "'"


def _override_key(override: str) -> str:
    """The key of a Hydra override (``+a.b=1`` -> ``a.b``)."""
    return override.split("=", 1)[0].lstrip("+~")


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


BOOKKEEPING = ("resume", "overrides", "output_dir")
"""Keys a resume changes by itself: not changes to the run."""


def config_changes(saved: Mapping, cfg: DictConfig) -> list[str]:
    """Every key whose value in ``cfg`` (a resume's config) differs from the run's ``saved`` config, as
    ``"key: old → new"``, apart from :data:`BOOKKEEPING` and a saved model's path (which follows the run)."""
    before = OmegaConf.to_container(OmegaConf.create(dict(saved)), resolve=True)
    after = OmegaConf.to_container(cfg, resolve=True)
    out = []
    for key in _diff(before, after, ""):
        if key.split(".")[0] in BOOKKEEPING or key == "env.model.path":
            continue
        old, new = _lookup(before, key), _lookup(after, key)
        out.append(f"{key}: {old} → {new}")
    return out


def _lookup(tree, key: str):
    for part in key.split("."):
        tree = tree.get(part, "<absent>") if isinstance(tree, dict) else "<absent>"
    return tree


def _diff(a, b, path: str) -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in [*a, *(k for k in b if k not in a)]:
            out += _diff(a.get(k, "<absent>"), b.get(k, "<absent>"), f"{path}.{k}" if path else str(k))
        return out
    return [] if a == b else [path]


# ------------------------------------------------------------------------------------ the state
# keys that say how a run was started or where it is, not what it trains
_NOT_THE_RUN = ("resume", "overrides", "output_dir")


def check_new_run_dir(cfg: DictConfig, run_dir: Path) -> None:
    """Raise :class:`ConfigError` naming ``output_dir`` when ``run_dir`` already holds a run
    (its ``config.yaml``) whose config differs from ``cfg``: a new run must not mix its config and
    checkpoints with another's. The same config may start again there."""
    saved_path = Path(run_dir) / "config.yaml"
    elsewhere = f"continue that run with resume={run_dir}, or start this one in another folder (output_dir=...)"
    if not saved_path.exists():
        if list_checkpoints(checkpoint_dir(run_dir)):  # a run's checkpoints, its config.yaml deleted
            raise ConfigError(f"output_dir: '{run_dir}' holds another run's checkpoints but no config.yaml; "
                              f"{elsewhere}")
        return
    try:
        saved = OmegaConf.to_container(OmegaConf.load(saved_path), resolve=False)
    except Exception as err:  # noqa: BLE001 - yaml, OmegaConf and the file system raise many types
        saved = f"{type(err).__name__}: {(str(err).strip().splitlines() or [''])[0]}"
    if not isinstance(saved, dict):
        what = saved if isinstance(saved, str) else f"a {type(saved).__name__}, not a mapping"
        raise ConfigError(f"output_dir: '{run_dir}' holds a config.yaml that cannot be read ({what}); {elsewhere}, "
                          "or restore its config.yaml")
    now = OmegaConf.to_container(cfg, resolve=True)
    differ = [k for k in _diff({k: v for k, v in saved.items() if k not in _NOT_THE_RUN},
                               {k: v for k, v in now.items() if k not in _NOT_THE_RUN}, "")]
    if differ:
        shown = ", ".join(differ[:4]) + (f" and {len(differ) - 4} more" if len(differ) > 4 else "")
        raise ConfigError(f"output_dir: '{run_dir}' already holds another run (its config.yaml differs in {shown}); "
                          f"{elsewhere}")


def fresh_state() -> dict:
    """The trainer state of a new run."""
    return {"iteration": 0, "frames": 0, "seconds": 0.0, "history": []}


def restore(cfg: DictConfig, components: dict, resume_state: dict | None) -> tuple[dict, Path, Path | None]:
    """The trainer state a run starts from, its run directory and the checkpoint it resumes (``None``
    for a new run, which writes into ``cfg.output_dir``). ``resume_state["path"]`` (a checkpoint or
    a run directory) restores ``components`` in place (see
    :func:`escort_rl.trainers.checkpointing.load_checkpoint`); the run directory is the one that
    holds the checkpoint, which ``cfg.output_dir`` must name (:func:`resumed_run_dir`)."""
    if resume_state is None:
        run_dir = output_path(cfg.output_dir)
        check_new_run_dir(cfg, run_dir)
        return fresh_state(), run_dir, None
    loaded = load_checkpoint(resume_state["path"], **components)
    saved = loaded["trainer_state"]
    state = {**fresh_state(), **{k: saved[k] for k in ("iteration", "frames", "history") if k in saved},
             "seconds": float(saved.get("seconds", 0.0))}
    return state, resumed_run_dir(cfg, loaded["path"]), Path(loaded["path"])
