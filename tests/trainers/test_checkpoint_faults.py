"""Faults in a run folder are detected with one line, and nothing of another run is mixed in or loaded:
a ``config.yaml`` edited into nonsense or deleted (a new run refuses the folder; a resume, which reads
the checkpoint's own config, still works), a checkpoint whose manifest is nonsense, a component whose
integrity record or folder is gone, a damaged newest checkpoint behind ``load_policy`` (the previous one
is loaded, with one warning), and the outputs of ``evaluate`` and ``train``: a file, a folder under a
file, a folder this process cannot write, or a count of episodes that is not a positive int."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

import escort_rl
from conftest import config_error, tiny_overrides
from escort_rl.config import ConfigError, compose
from escort_rl.trainers.checkpointing import CheckpointDamaged, CheckpointIncompatible, CheckpointLoadError
from escort_rl.trainers.resume import train_config
from escort_rl.trainers.training import train

TINY = ("filter=sir", "trainer.iterations=2", "trainer.num_envs=2", "env.max_steps=4", "num_particles=8",
        "actor.hidden=8")


def overrides(run: Path, *extra: str) -> list[str]:
    return tiny_overrides(*TINY, f"output_dir={run}", *extra)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A finished run of two iterations (SIR beliefs, a few seconds), copied by each test that damages it."""
    run = tmp_path_factory.mktemp("trained") / "run"
    train(compose(overrides(run)), progress=False)
    return run


@pytest.fixture
def run(trained, tmp_path) -> Path:
    copy = tmp_path / "run"
    shutil.copytree(trained, copy)
    return copy


def checkpoint(run: Path, step: int = 2) -> Path:
    return run / "checkpoints" / f"checkpoint-{step:012d}"


def component(run: Path, name: str) -> Path:
    return next((checkpoint(run) / "components").glob(f"*-{name}"))


def one_line(fn, kind: type[Exception]) -> str:
    with pytest.raises(kind) as info:
        fn()
    message = str(info.value)
    assert "\n" not in message, message
    return message


def digest(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ---------------------------------------------------------------------------------------------
# config.yaml edited by hand
# ---------------------------------------------------------------------------------------------


def _broken_yaml(path: Path) -> str:
    path.write_text("trainer: [unclosed\n  - :")
    return "holds a config.yaml that cannot be read (ParserError: "


def _a_list(path: Path) -> str:
    path.write_text("- 1\n- 2\n")
    return "holds a config.yaml that cannot be read (a list, not a mapping)"


def _a_folder(path: Path) -> str:
    path.unlink()
    path.mkdir()
    return "holds a config.yaml that cannot be read (IsADirectoryError: "


def _deleted(path: Path) -> str:
    path.unlink()
    return "holds another run's checkpoints but no config.yaml"


EDITS = {"broken-yaml": _broken_yaml, "a-yaml-list": _a_list, "a-folder": _a_folder, "deleted": _deleted}


@pytest.mark.parametrize("edit", sorted(EDITS))
def test_a_new_run_refuses_a_folder_whose_config_yaml_is_nonsense(edit, run):
    """A broken config.yaml used to end a new run with a yaml traceback; a deleted one let the new run
    write its checkpoint 1 beside the old run's checkpoint 2, which load_policy then returned."""
    what = EDITS[edit](run / "config.yaml")
    before = digest(run / "checkpoints")
    message = one_line(lambda: train(compose(overrides(run, "seed=5")), progress=False), ConfigError)
    assert message.startswith(f"output_dir: '{run}' {what}"), message
    assert f"continue that run with resume={run}" in message
    assert digest(run / "checkpoints") == before


def test_a_resume_reads_the_checkpoints_config_not_the_broken_yaml(run, capsys):
    _broken_yaml(run / "config.yaml")
    cfg, state = train_config([f"resume={run}"])
    assert state is not None and cfg.trainer.iterations == 2 and cfg.filter.name == "sir"
    train(cfg, resume_state=state, progress=False)
    assert "has finished its 2 iterations; nothing to train" in capsys.readouterr().out


# ---------------------------------------------------------------------------------------------
# Damaged checkpoints behind load_policy and evaluate
# ---------------------------------------------------------------------------------------------


def _manifest_list(run: Path) -> str:
    (checkpoint(run) / "manifest.json").write_text("[1, 2]")
    return "manifest.json is missing or unreadable"


def _components_not_a_mapping(run: Path) -> str:
    path = checkpoint(run) / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["components"] = 5
    path.write_text(json.dumps(manifest))
    return "manifest.json is missing or unreadable"


def _checkpoint_a_file(run: Path) -> str:
    shutil.rmtree(checkpoint(run))
    checkpoint(run).write_text("not a checkpoint")
    return "manifest.json is missing or unreadable"


def _integrity_deleted(run: Path) -> str:
    (component(run, "actor") / "integrity.json").unlink()
    return "actor: 'integrity.json' is missing"


def _integrity_a_list(run: Path) -> str:
    (component(run, "actor") / "integrity.json").write_text("[]")
    return "actor: integrity.json is unreadable"


def _actor_folder_deleted(run: Path) -> str:
    shutil.rmtree(component(run, "actor"))
    return "actor: '"


DAMAGES = {"manifest-a-list": _manifest_list, "components-not-a-mapping": _components_not_a_mapping,
           "checkpoint-a-file": _checkpoint_a_file, "integrity-deleted": _integrity_deleted,
           "integrity-a-list": _integrity_a_list, "actor-folder-deleted": _actor_folder_deleted}


@pytest.mark.parametrize("damage", sorted(DAMAGES))
def test_an_explicit_damaged_checkpoint_is_refused_by_load_policy(damage, run):
    """A manifest that is valid JSON but not a mapping used to raise an AttributeError from TorchRL."""
    what = DAMAGES[damage](run)
    message = one_line(lambda: escort_rl.load_policy(checkpoint(run)), CheckpointDamaged)
    assert message.startswith(f"checkpoint: '{checkpoint(run)}' is damaged ({what}"), message


def test_a_checkpoint_without_the_actor_names_the_component(run):
    path = checkpoint(run) / "manifest.json"
    manifest = json.loads(path.read_text())
    del manifest["components"]["actor"]
    path.write_text(json.dumps(manifest))
    message = one_line(lambda: escort_rl.load_policy(checkpoint(run)), CheckpointIncompatible)
    assert message.startswith(f"checkpoint: actor: not in '{checkpoint(run)}', which holds config, critic"), message


def test_load_policy_of_a_run_falls_back_past_a_damaged_newest_checkpoint(run, capsys):
    """The newest checkpoint is not loaded; the previous, intact one is, with one warning line."""
    _manifest_list(run)
    policy = escort_rl.load_policy(run)
    warning = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert warning == [f"warning: checkpoint: '{checkpoint(run)}' is damaged (manifest.json is missing or "
                       f"unreadable); falling back to '{checkpoint(run, 1)}'"]
    previous = escort_rl.load_policy(checkpoint(run, 1))
    for a, b in zip(policy.parameters(), previous.parameters()):
        assert torch.equal(a, b)


def test_a_run_folder_without_checkpoints_is_named(run):
    shutil.rmtree(run / "checkpoints")
    (run / "checkpoints").mkdir()
    message = one_line(lambda: escort_rl.load_policy(run), CheckpointLoadError)
    assert message.startswith(f"checkpoint: no checkpoint found under '{run}'"), message


def test_evaluate_refuses_a_damaged_explicit_checkpoint(run):
    _integrity_a_list(run)
    message = one_line(lambda: escort_rl.evaluate(checkpoint(run), episodes=1, output=run / "eval"), CheckpointDamaged)
    assert "actor: integrity.json is unreadable" in message
    assert not (run / "eval").exists()


# ---------------------------------------------------------------------------------------------
# Outputs that cannot hold results
# ---------------------------------------------------------------------------------------------


def test_evaluate_names_an_output_that_is_a_file_or_under_one(trained, tmp_path):
    """``escort_rl.evaluate(output=a_file)`` used to end in a FileExistsError after the episodes ran."""
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    assert one_line(lambda: escort_rl.evaluate(trained, episodes=1, output=a_file), ConfigError) == (
        f"output: '{a_file}' is an existing file; pass a folder")
    assert one_line(lambda: escort_rl.evaluate(trained, episodes=1, output=a_file / "sub"), ConfigError) == (
        f"output: '{a_file / 'sub'}' is under the file '{a_file}'; pass a folder")


def test_evaluate_names_an_output_folder_it_cannot_write(trained, tmp_path, monkeypatch):
    from escort_rl.config import schema

    locked = tmp_path / "locked"
    locked.mkdir()
    monkeypatch.setattr(schema.os, "access", lambda path, mode: Path(path) != locked)
    assert one_line(lambda: escort_rl.evaluate(trained, episodes=1, output=locked / "eval"), ConfigError) == (
        f"output: '{locked / 'eval'}' cannot be written: '{locked}' is not writable; pass a folder you can write to")


@pytest.mark.parametrize("episodes", [0, -2, 2.5, "2", True], ids=["zero", "negative", "fraction", "string", "bool"])
def test_evaluate_names_a_count_of_episodes_that_is_not_a_positive_int(episodes, trained):
    """Zero episodes used to be named as a POMDPEnv batch size; 2.5 was silently taken as 2."""
    assert one_line(lambda: escort_rl.evaluate(trained, episodes=episodes), ConfigError) == (
        f"episodes: expected a positive int (or None: the config's evaluate.episodes), got {episodes!r}")


def test_train_names_an_output_dir_that_is_a_file(tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    assert config_error([f"output_dir={a_file}"]) == (
        f"config: output_dir: '{a_file}' is an existing file; pass a folder")


def test_train_names_a_run_folder_that_exists_but_cannot_be_written(tmp_path, monkeypatch):
    """The run folder itself (not only its parent) must be writable; checked before anything runs."""
    from escort_rl.config import schema

    run = tmp_path / "run"
    run.mkdir()
    monkeypatch.setattr(schema.os, "access", lambda path, mode: Path(path) != run)
    assert config_error([f"output_dir={run}"]) == (
        f"config: output_dir: '{run}' cannot be written: '{run}' is not writable; pass a folder you can write to")
