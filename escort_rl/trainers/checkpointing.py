"""Checkpoints of a training run on ``torchrl.checkpoint``: atomic writes and rotation."""

from __future__ import annotations

from pathlib import Path

from torchrl.checkpoint import Checkpoint, CheckpointError, CheckpointRotation


class CheckpointLoadError(RuntimeError):
    """A checkpoint that cannot be read: missing, corrupt or from an incompatible run."""


def checkpoint_dir(run_dir: Path) -> Path:
    return Path(run_dir) / "checkpoints"


def resolve_checkpoint(path: str | Path) -> Path:
    """Map a run directory, its ``checkpoints/`` folder or one checkpoint to one checkpoint path."""
    path = Path(path)
    if not path.exists():
        raise CheckpointLoadError(f"checkpoint: '{path}' does not exist; pass a run directory or a checkpoint")
    if Checkpoint.is_checkpoint(path):
        return path
    for folder in (checkpoint_dir(path), path):
        if folder.is_dir():
            try:
                latest = CheckpointRotation(folder, keep_last=1_000_000).latest()
            except Exception:  # noqa: BLE001 - any unreadable folder is reported below
                latest = None
            if latest is not None:
                return latest
    raise CheckpointLoadError(
        f"checkpoint: no checkpoint found under '{path}'; it should be a run directory with "
        "checkpoints/ or a checkpoint folder written by `escort-rl train`"
    )


def load_checkpoint(path: str | Path, **components) -> dict:
    """Restore ``components`` (modules, optimizers) in place from ``path`` and return the JSON
    values stored with them (``trainer_state``, ``config``).

    Raises :class:`CheckpointLoadError` with a one-line message when the file is corrupt,
    incomplete or does not match the components.
    """
    target = resolve_checkpoint(path)
    ckpt = Checkpoint(**components, trainer_state={}, config={})
    try:
        result = ckpt.load(target)
    except (CheckpointError, OSError, ValueError, KeyError, RuntimeError, EOFError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CheckpointLoadError(
            f"checkpoint: cannot load '{target}': {first[:300]} (the file is corrupt or was written "
            "by an incompatible configuration)"
        ) from None
    return {"path": str(target), **result.values}


def save_checkpoint(rotation: CheckpointRotation, step: int, trainer_state: dict, config: dict,
                    **components) -> Path:
    """Write one checkpoint atomically (torchrl writes to a temporary name and renames) and prune
    the rotation to its ``keep_last`` newest."""
    ckpt = Checkpoint(**components, trainer_state=trainer_state, config=config)
    return rotation.save(ckpt, step=step)
