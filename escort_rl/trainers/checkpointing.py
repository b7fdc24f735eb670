"""Checkpoints of a training run on ``torchrl.checkpoint``: atomic writes, rotation, and checks that
a checkpoint is what it claims to be.

A run keeps its checkpoints in ``RUN_DIR/checkpoints/checkpoint-<step>`` (a TorchRL
:class:`~torchrl.checkpoint.CheckpointRotation`). On top of TorchRL's format:

- **Integrity record.** Every component folder also holds ``integrity.json``: the size in bytes and
  the sha256 of each file the component wrote. It is written inside TorchRL's staging folder, so it
  is published atomically with the checkpoint. :func:`verify_checkpoint` checks every file of every
  component against it before anything is read, so a truncated tensor file is refused instead of
  being loaded (as mostly zeros) and grown back to full size by the memory-mapped loader.
  Checkpoints written before the record existed are loaded without this check.
- **Fall-back.** :func:`resolve_checkpoint` on a run directory takes the newest *intact*
  checkpoint: each damaged newer one (truncated or missing file, bad JSON, wrong checksum) gets one
  ``warning:`` line on stderr naming it and what is wrong. An explicit checkpoint folder that is
  damaged raises :class:`CheckpointDamaged` instead; so does a run directory with no intact
  checkpoint left.
- **Compatibility.** :func:`load_checkpoint` compares the tensor keys and shapes of each module (and
  the parameter groups of each optimizer) with the live object before loading it, and raises
  :class:`CheckpointIncompatible` with one line naming the first key that differs.
- **Interrupted writes.** :func:`remove_interrupted_writes` deletes the staging, backup and delete
  folders that TorchRL's atomic write and rotation leave behind when the process is killed.

Example::

    >>> path = resolve_checkpoint("outputs/run")                   # doctest: +SKIP
    >>> saved = load_checkpoint(path, actor=actor)                 # doctest: +SKIP
    >>> saved["trainer_state"]["iteration"]                        # doctest: +SKIP
    12
"""

from __future__ import annotations

import hashlib
import json
import re
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torchrl.checkpoint import (
    Checkpoint,
    CheckpointAdapter,
    CheckpointError,
    CheckpointRotation,
    JSONCheckpointAdapter,
    StateDictCheckpointAdapter,
)

INTEGRITY_FILE = "integrity.json"
RESUME_HINT = "resume with the run's own config"
# checkpoint-<step> (a folder) or checkpoint-<step>.torchrl (an archive), as CheckpointRotation names them
_CHECKPOINT_NAME = re.compile(r"^checkpoint-(\d+)(\.torchrl)?$")
# what torchrl's atomic save (.stage-, .archive-), publish (.backup-) and prune (.delete-) name their
# temporary entries: ".<checkpoint name>.<kind>-<uuid4 hex>"
_INTERRUPTED_WRITE = re.compile(r"^\..+\.(stage|archive|backup|delete)-[0-9a-f]{32}$")
_warned: set[tuple[str, str]] = set()


class CheckpointLoadError(RuntimeError):
    """A checkpoint that cannot be read: missing, corrupt or from an incompatible run."""


class CheckpointDamaged(CheckpointLoadError):
    """A checkpoint whose files do not match their integrity record, or that cannot be parsed."""


class CheckpointIncompatible(CheckpointLoadError):
    """A sound checkpoint whose components do not fit the live objects (another env or actor size)."""


def checkpoint_dir(run_dir: Path) -> Path:
    """The folder of a run's checkpoint rotation."""
    return Path(run_dir) / "checkpoints"


def run_dir_of(checkpoint: str | Path) -> Path:
    """The run directory that holds ``checkpoint`` (``RUN_DIR/checkpoints/checkpoint-<step>``).

    Raises :class:`CheckpointLoadError` for a checkpoint that does not sit in a run's
    ``checkpoints/`` folder: a resume needs the run directory to write into."""
    checkpoint = Path(checkpoint)
    if checkpoint.parent.name != "checkpoints":
        raise CheckpointLoadError(
            f"checkpoint: '{checkpoint}' is not inside a run directory's checkpoints/ folder; resume from "
            "the run directory (RUN_DIR/checkpoints/checkpoint-<step>) so that the run knows where to write")
    return checkpoint.parent.parent


def list_checkpoints(folder: str | Path) -> list[Path]:
    """The checkpoints of a rotation folder, newest step first, readable or not (unlike
    :meth:`CheckpointRotation.checkpoints`, which silently skips a checkpoint whose manifest is bad)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in folder.iterdir() if (m := _CHECKPOINT_NAME.match(p.name))]
    return [p for _, p in sorted(found, key=lambda item: item[0], reverse=True)]


def remove_interrupted_writes(folder: str | Path) -> list[Path]:
    """Delete the temporary entries that a killed save or prune leaves in a rotation folder (TorchRL's
    ``.<name>.stage-*``, ``.archive-*``, ``.backup-*`` and ``.delete-*``); returns what was removed.
    Only called when a run starts, so no save of this run can be in progress."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = [p for p in folder.iterdir() if _INTERRUPTED_WRITE.match(p.name)]
    for path in removed:
        Checkpoint._remove_path(path)
    return removed


# --------------------------------------------------------------------------- integrity record


def file_record(path: Path) -> dict:
    """``{"bytes": size, "sha256": hex digest}`` of one file."""
    digest = hashlib.sha256()
    with path.open("rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return {"bytes": path.stat().st_size, "sha256": digest.hexdigest()}


def write_integrity(component_path: Path) -> None:
    """Record the size and sha256 of every file under ``component_path`` in its ``integrity.json``."""
    files = sorted(p for p in component_path.rglob("*") if p.is_file() and p.name != INTEGRITY_FILE)
    record = {"files": {p.relative_to(component_path).as_posix(): file_record(p) for p in files}}
    (component_path / INTEGRITY_FILE).write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")


def component_damage(name: str, component_path: Path, listed: list[str]) -> str | None:
    """What is wrong with one component folder (``None``: nothing): a file the manifest lists is
    missing, or a file differs in size or sha256 from its ``integrity.json`` record."""
    for relative in listed:
        if not (component_path / relative).is_file():
            return f"{name}: '{relative}' is missing"
    if INTEGRITY_FILE not in listed:
        return None  # written before the integrity record existed: nothing to compare with
    try:
        recorded = json.loads((component_path / INTEGRITY_FILE).read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return f"{name}: {INTEGRITY_FILE} is unreadable"
    for relative, expected in recorded.items():
        path = component_path / relative
        if not path.is_file():
            return f"{name}: '{relative}' is missing"
        size = path.stat().st_size
        if size != expected["bytes"]:
            return f"{name}: '{relative}' has {size} bytes, {expected['bytes']} recorded"
        if file_record(path)["sha256"] != expected["sha256"]:
            return f"{name}: '{relative}' does not match its recorded sha256"
    return None


def checkpoint_damage(path: str | Path) -> str | None:
    """What is wrong with a checkpoint (``None``: nothing): an unreadable manifest, or the first
    damaged component (see :func:`component_damage`). An archive checkpoint is checked by its zip
    CRCs when it is read."""
    path = Path(path)
    try:
        manifest = Checkpoint.manifest(path)
        components = sorted(manifest["components"].items())
        records = [(name, path / record["path"], list(record["files"])) for name, record in components]
    except (CheckpointError, OSError, TypeError, ValueError, AttributeError, KeyError):
        return "manifest.json is missing or unreadable"
    if not path.is_dir():
        return None
    for name, folder, files in records:
        damage = component_damage(name, folder, files)
        if damage is not None:
            return damage
    return None


def verify_checkpoint(path: str | Path) -> None:
    """Raise :class:`CheckpointDamaged` (one line naming ``path`` and what is wrong) unless every
    file of the checkpoint matches its record."""
    damage = checkpoint_damage(path)
    if damage is not None:
        raise CheckpointDamaged(f"checkpoint: '{path}' is damaged ({damage}); pass its run directory to fall "
                                "back to the previous checkpoint, or another checkpoint")


# --------------------------------------------------------------------------- compatibility


def _shape(tensor: torch.Tensor) -> str:
    return str(list(tensor.shape))


def module_mismatch(current: Mapping, saved: Mapping) -> str | None:
    """The first key of a module's state dict that differs between ``saved`` and ``current``
    (absent on one side, or another tensor shape), as a phrase; ``None`` when they agree."""
    for key in saved:
        if key not in current:
            return f"'{key}' is in the checkpoint but not here"
    for key in current:
        if key not in saved:
            return f"'{key}' is here but not in the checkpoint"
    for key, value in saved.items():
        here = current[key]
        if isinstance(value, torch.Tensor) and isinstance(here, torch.Tensor) and value.shape != here.shape:
            return f"'{key}' has shape {_shape(value)} in the checkpoint but {_shape(here)} here"
    return None


def optimizer_mismatch(optimizer: torch.optim.Optimizer, saved: Mapping) -> str | None:
    """The first difference between an optimizer's parameter groups and a saved optimizer state
    (number of groups, tensors per group, or the shape of a saved moment), as a phrase."""
    groups = saved.get("param_groups", [])
    if len(groups) != len(optimizer.param_groups):
        return f"{len(groups)} parameter groups in the checkpoint but {len(optimizer.param_groups)} here"
    for index, (old, new) in enumerate(zip(groups, optimizer.param_groups)):
        if len(old["params"]) != len(new["params"]):
            return (f"parameter group {index} holds {len(old['params'])} tensors in the checkpoint but "
                    f"{len(new['params'])} here")
    params = [p for group in optimizer.param_groups for p in group["params"]]
    ids = [i for group in groups for i in group["params"]]
    for position, (pid, param) in enumerate(zip(ids, params)):
        for key, value in saved.get("state", {}).get(pid, {}).items():
            if isinstance(value, torch.Tensor) and value.dim() > 0 and value.shape != param.shape:
                return (f"state '{key}' of parameter {position} has shape {_shape(value)} in the checkpoint but "
                        f"the parameter has {_shape(param)} here")
    return None


def check_compatible(name: str, component: Any, saved: Mapping) -> None:
    """Raise :class:`CheckpointIncompatible` naming component ``name`` and the first key whose saved
    value does not fit ``component`` (a module or an optimizer; other objects are not compared)."""
    if isinstance(component, torch.optim.Optimizer):
        mismatch = optimizer_mismatch(component, saved)
    elif isinstance(component, torch.nn.Module):
        mismatch = module_mismatch(component.state_dict(), saved)
    else:
        mismatch = None
    if mismatch is not None:
        raise CheckpointIncompatible(f"checkpoint: {name}: {mismatch}; {RESUME_HINT}")


class _CheckedTarget:
    """Stands in for a component while TorchRL restores it: checks the saved state against the
    component (:func:`check_compatible`) before handing it over."""

    def __init__(self, name: str, component: Any) -> None:
        self.name, self.component = name, component

    def load_state_dict(self, state, *args, **kwargs):
        check_compatible(self.name, self.component, state)
        return self.component.load_state_dict(state, *args, **kwargs)


class RecordedAdapter(CheckpointAdapter):
    """A TorchRL adapter (state dict or JSON) that also writes the component's ``integrity.json``
    when saving and checks compatibility when loading. Its ``adapter_id`` is the wrapped adapter's,
    so its checkpoints stay readable by a plain :class:`~torchrl.checkpoint.Checkpoint`."""

    def __init__(self, name: str, inner: CheckpointAdapter) -> None:
        self.name, self.inner = name, inner
        self.adapter_id, self.format_version = inner.adapter_id, inner.format_version

    def save(self, component, path, *, args, kwargs):
        value = self.inner.save(component, path, args=args, kwargs=kwargs)
        write_integrity(path)
        return value

    def load(self, component, path, *, map_location, tensor_load_kwargs, args, kwargs):
        target = _CheckedTarget(self.name, component) if hasattr(component, "load_state_dict") else component
        return self.inner.load(target, path, map_location=map_location, tensor_load_kwargs=tensor_load_kwargs,
                               args=args, kwargs=kwargs)


def make_checkpoint(**components) -> Checkpoint:
    """A :class:`~torchrl.checkpoint.Checkpoint` of ``components`` (modules and optimizers through
    their state dicts, anything else as JSON), each through a :class:`RecordedAdapter`."""
    ckpt = Checkpoint()
    for name, value in components.items():
        inner = StateDictCheckpointAdapter() if hasattr(value, "state_dict") else JSONCheckpointAdapter()
        ckpt.register(name, value, adapter=RecordedAdapter(name, inner))
    return ckpt


# --------------------------------------------------------------------------- resolve, load, save


def warn_once(message: str, key: str) -> None:
    """Print ``warning: message`` on stderr, once per ``key`` and message in this process."""
    if (key, message) not in _warned:
        _warned.add((key, message))
        print(f"warning: {message}", file=sys.stderr, flush=True)


def newest_intact(folder: Path, where: Path) -> Path:
    """The newest checkpoint of rotation ``folder`` that passes :func:`checkpoint_damage`; warns
    once for each damaged newer one. Raises :class:`CheckpointDamaged` when none is intact."""
    damaged = []
    for candidate in list_checkpoints(folder):
        damage = checkpoint_damage(candidate)
        if damage is None:
            for path, what in damaged:
                warn_once(f"checkpoint: '{path}' is damaged ({what}); falling back to '{candidate}'", str(path))
            return candidate
        damaged.append((candidate, damage))
    if damaged:
        path, what = damaged[0]
        raise CheckpointDamaged(
            f"checkpoint: no intact checkpoint left under '{where}' ({len(damaged)} damaged; the newest, "
            f"'{path.name}': {what}); start a new run or restore the run directory from a copy")
    raise CheckpointLoadError(
        f"checkpoint: no checkpoint found under '{where}'; it should be a run directory with "
        "checkpoints/ or a checkpoint folder written by `escort-rl train`")


def is_checkpoint_path(path: Path) -> bool:
    """Whether ``path`` names one checkpoint (a manifest, or a ``checkpoint-<step>`` name) rather
    than a run directory or a rotation folder."""
    return (path / "manifest.json").exists() or bool(_CHECKPOINT_NAME.match(path.name)) or path.is_file()


def resolve_checkpoint(path: str | Path) -> Path:
    """One intact checkpoint from a run directory, its ``checkpoints/`` folder or one checkpoint.

    A run directory or rotation folder gives its newest intact checkpoint (falling back past
    damaged ones with one warning line each); an explicit checkpoint is verified and raises
    :class:`CheckpointDamaged` when damaged."""
    path = Path(path)
    if not path.exists():
        raise CheckpointLoadError(f"checkpoint: '{path}' does not exist; pass a run directory or a checkpoint")
    if is_checkpoint_path(path):
        verify_checkpoint(path)
        return path
    folder = checkpoint_dir(path) if checkpoint_dir(path).is_dir() else path
    return newest_intact(folder, path)


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0][:300] if text else type(err).__name__


def check_components_present(target: Path, names) -> None:
    """Raise :class:`CheckpointIncompatible` naming the first of ``names`` that ``target`` lacks."""
    held = sorted(Checkpoint.manifest(target)["components"])
    for name in names:
        if name not in held:
            raise CheckpointIncompatible(f"checkpoint: {name}: not in '{target}', which holds "
                                         f"{', '.join(held)}; {RESUME_HINT}")


def load_checkpoint(path: str | Path, **components) -> dict:
    """Restore ``components`` (modules, optimizers) in place from ``path`` and return the JSON
    values stored with them (``trainer_state``, ``config``) and ``path``, the checkpoint read.

    ``path`` is resolved by :func:`resolve_checkpoint` (verified; a run directory falls back past
    damaged checkpoints). Raises a one-line :class:`CheckpointLoadError`: :class:`CheckpointDamaged`,
    :class:`CheckpointIncompatible` (a component or key that differs) or, for anything else TorchRL
    refuses, ``checkpoint: cannot load ...``.
    """
    target = resolve_checkpoint(path)
    values = {"trainer_state": {}, "config": {}}
    check_components_present(target, [*components, *values])
    ckpt = make_checkpoint(**components, **values)
    try:
        result = ckpt.load(target)
    except (CheckpointError, OSError, ValueError, KeyError, RuntimeError, EOFError) as err:
        if isinstance(err.__cause__, CheckpointLoadError):
            raise err.__cause__.with_traceback(None) from None
        raise CheckpointLoadError(
            f"checkpoint: cannot load '{target}': {_first_line(err)} (the file is corrupt or was written "
            f"by an incompatible configuration; {RESUME_HINT})"
        ) from None
    return {"path": str(target), **values, **result.values}


def save_checkpoint(rotation: CheckpointRotation, step: int, trainer_state: dict, config: dict,
                    **components) -> Path:
    """Write one checkpoint atomically (TorchRL writes to a staging folder and renames), with each
    component's integrity record, and prune the rotation to its ``keep_last`` newest."""
    return rotation.save(make_checkpoint(**components, trainer_state=trainer_state, config=config), step=step)
