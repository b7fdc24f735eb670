"""Checkpoints that cannot lie, and resumes that write where they should.

Integrity records and their verification, the fall-back past a damaged newest checkpoint, the
clean-up of interrupted writes, logs without repeated iterations, resuming a copied run, one-line
errors for incompatible checkpoints and for a collector worker that dies.
"""

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import types
from pathlib import Path

import pytest
import torch
import yaml

from conftest import actor_of
from escort_rl.cli import main
from escort_rl.config import ConfigError, compose
from escort_rl.modules import DeepSetsActor
from escort_rl.trainers.builders import build_model
from escort_rl.trainers.checkpointing import (
    CheckpointDamaged,
    CheckpointIncompatible,
    CheckpointLoadError,
    check_compatible,
    checkpoint_damage,
    list_checkpoints,
    load_checkpoint,
)
from escort_rl.trainers.scaffold import (
    CollectorWorkerDied,
    make_logger,
    run_training,
    truncate_scalar_logs,
    worker_death_message,
)
from escort_rl.trainers.training import build_algorithm, train

TINY = ["trainer=reinforce", "trainer.num_envs=4", "env.max_steps=12", "num_particles=16", "actor.hidden=16",
        "trainer.minibatch_size=64", "trainer.checkpoint_every=1", "filter.compile=false"]


def _cli_train(*args: str) -> None:
    assert main(["train", "--quiet", *TINY, *args]) == 0


def _actor() -> DeepSetsActor:
    return actor_of(TINY)


def _actor_params(run: Path) -> dict:
    actor = _actor()
    load_checkpoint(run, actor=actor)
    return {k: v.clone() for k, v in actor.state_dict().items()}


def _checkpoint(run: Path, step: int) -> Path:
    return run / "checkpoints" / f"checkpoint-{step:012d}"


def _tensor_file(ckpt: Path) -> Path:
    """The actor's largest tensor file (over 100 bytes)."""
    return max((ckpt / "components").glob("*-actor/state/tensor_*.memmap"), key=lambda p: (p.stat().st_size, p.name))


def _tree_digest(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _one_line(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line]
    assert len(lines) == 1, lines
    return lines[0]


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """Three iterations straight: what every resumed run must reach, bit for bit."""
    run = tmp_path_factory.mktemp("reference") / "run"
    _cli_train("trainer.iterations=3", f"output_dir={run}")
    return run


# ------------------------------------------------------------------------------- integrity records


def test_every_component_records_its_file_sizes_and_checksums(tmp_path):
    run = tmp_path / "run"
    train(compose([*TINY, "trainer.iterations=1", f"output_dir={run}"]), progress=False)
    ckpt = _checkpoint(run, 1)
    for component in (ckpt / "components").iterdir():
        recorded = json.loads((component / "integrity.json").read_text())["files"]
        on_disk = sorted(p.relative_to(component).as_posix() for p in component.rglob("*")
                         if p.is_file() and p.name != "integrity.json")
        assert sorted(recorded) == on_disk and on_disk
        for name, record in recorded.items():
            data = (component / name).read_bytes()
            assert record == {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


def test_truncated_tensor_file_is_refused_and_left_as_it_is(tmp_path):
    run = tmp_path / "run"
    train(compose([*TINY, "trainer.iterations=1", f"output_dir={run}"]), progress=False)
    ckpt = _checkpoint(run, 1)
    victim = _tensor_file(ckpt)
    full = victim.stat().st_size
    victim.write_bytes(victim.read_bytes()[:100])
    rel = victim.relative_to(victim.parents[1]).as_posix()
    with pytest.raises(CheckpointDamaged) as caught:
        load_checkpoint(ckpt, actor=_actor())
    assert str(caught.value).startswith(f"checkpoint: '{ckpt}' is damaged (actor: '{rel}' has 100 bytes, "
                                        f"{full} recorded)")
    assert "\n" not in str(caught.value)
    assert victim.stat().st_size == 100  # the loader never opened it


# ------------------------------------------------------------------------------- damaged newest checkpoint


def _truncate(ckpt: Path) -> str:
    victim = _tensor_file(ckpt)
    size = victim.stat().st_size
    victim.write_bytes(victim.read_bytes()[:100])
    return f"has 100 bytes, {size} recorded"


def _flip_a_byte(ckpt: Path) -> str:
    victim = _tensor_file(ckpt)
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(data))
    return "does not match its recorded sha256"


def _bad_trainer_state_json(ckpt: Path) -> str:
    victim = next((ckpt / "components").glob("*-trainer_state")) / "value.json"
    victim.write_text(victim.read_text()[:-40])
    return "trainer_state: 'value.json' has"


def _bad_manifest_json(ckpt: Path) -> str:
    (ckpt / "manifest.json").write_text("{\"format\": ")
    return "manifest.json is missing or unreadable"


def _missing_file(ckpt: Path) -> str:
    victim = _tensor_file(ckpt)
    victim.unlink()
    return f"actor: '{victim.relative_to(victim.parents[1]).as_posix()}' is missing"


DAMAGES = {"truncated": _truncate, "checksum": _flip_a_byte, "bad_json": _bad_trainer_state_json,
           "bad_manifest": _bad_manifest_json, "missing_file": _missing_file}


@pytest.mark.parametrize("damage", sorted(DAMAGES))
def test_damaged_newest_checkpoint_falls_back_with_one_warning(damage, reference, tmp_path, capsys):
    run = tmp_path / "run"
    _cli_train("trainer.iterations=3", f"output_dir={run}")
    newest, previous = _checkpoint(run, 3), _checkpoint(run, 2)
    what = DAMAGES[damage](newest)
    capsys.readouterr()

    assert main(["train", "--quiet", f"resume={run}"]) == 0
    warning = _one_line(capsys.readouterr().err)
    assert warning.startswith(f"warning: checkpoint: '{newest}' is damaged (")
    assert what in warning and warning.endswith(f"); falling back to '{previous}'")
    assert checkpoint_damage(newest) is None  # iteration 3 was run again and its checkpoint rewritten
    assert load_checkpoint(run)["trainer_state"]["iteration"] == 3
    ref, res = _actor_params(reference), _actor_params(run)
    assert all(torch.equal(ref[k], res[k]) for k in ref)


def test_explicit_damaged_checkpoint_is_a_one_line_error(tmp_path, capsys):
    run = tmp_path / "run"
    _cli_train("trainer.iterations=2", f"output_dir={run}")
    newest = _checkpoint(run, 2)
    _truncate(newest)
    capsys.readouterr()
    assert main(["train", "--quiet", f"resume={newest}"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"error: checkpoint: '{newest}' is damaged (actor: ")
    with pytest.raises(CheckpointLoadError):
        load_checkpoint(newest)


def test_no_intact_checkpoint_left_is_a_one_line_error(tmp_path, capsys):
    run = tmp_path / "run"
    _cli_train("trainer.iterations=2", f"output_dir={run}")
    for step in (1, 2):
        _flip_a_byte(_checkpoint(run, step))
    capsys.readouterr()
    assert main(["train", "--quiet", f"resume={run}"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"error: checkpoint: no intact checkpoint left under '{run}' (2 damaged; the newest, "
                          "'checkpoint-000000000002': actor: ")


# ------------------------------------------------------------------------------- interrupted writes

_KILLED_SAVE = """
import os, signal, sys, torch
from torchrl.checkpoint import CheckpointRotation
from escort_rl.trainers.checkpointing import save_checkpoint

class DiesWhileSaved(torch.nn.Linear):
    def state_dict(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGKILL)

rotation = CheckpointRotation(sys.argv[1], keep_last=3)
save_checkpoint(rotation, 2, {}, {}, actor=torch.nn.Linear(2, 2), zz=DiesWhileSaved(2, 2))
"""


@pytest.mark.slow
def test_interrupted_writes_are_removed_at_the_next_start(tmp_path):
    run = tmp_path / "run"
    cfg = compose([*TINY, "trainer.iterations=1", f"output_dir={run}"])
    train(cfg, progress=False)
    folder = run / "checkpoints"
    killed = subprocess.run([sys.executable, "-c", _KILLED_SAVE, str(folder)], capture_output=True)
    assert killed.returncode == -signal.SIGKILL, killed.stderr.decode()[-2000:]
    stages = [p for p in folder.iterdir() if ".stage-" in p.name]
    assert len(stages) == 1 and (stages[0] / "components").is_dir()  # a real leftover of a killed save
    for kind in ("delete", "backup", "archive"):  # what a kill leaves during prune or publish
        (folder / f".checkpoint-000000000001.{kind}-{'0' * 32}" / "components").mkdir(parents=True)

    train(compose([*TINY, "trainer.iterations=2", f"output_dir={run}"]), resume_state={"path": str(run)},
          progress=False)
    assert sorted(p.name for p in folder.iterdir()) == ["checkpoint-000000000001", "checkpoint-000000000002"]


# ------------------------------------------------------------------------------- logs


class Interrupted(Exception):
    """Stands for a kill between two checkpoints."""


def _interrupt_at(algorithm, index: int):
    run_one = algorithm.iteration

    def iteration(i, seed):
        if i == index:
            raise Interrupted
        return run_one(i, seed)

    algorithm.iteration = iteration
    return algorithm


def test_csv_logs_hold_each_iteration_once_after_a_resume(tmp_path):
    run = tmp_path / "run"
    cfg = compose([*TINY, "trainer.iterations=4", "trainer.checkpoint_every=2", f"output_dir={run}"])
    with pytest.raises(Interrupted):  # iterations 1-3 logged, the last checkpoint holds iteration 2
        run_training(cfg, _interrupt_at(build_algorithm(cfg, build_model(cfg.env)), 3), progress=False)
    assert [p.name for p in list_checkpoints(run / "checkpoints")] == ["checkpoint-000000000002"]
    frames_log = run / "logs" / "scalars" / "frames.csv"
    assert [line.split(",")[0] for line in frames_log.read_text().splitlines()] == ["1", "2", "3"]

    train(cfg, resume_state={"path": str(run)}, progress=False)
    history = load_checkpoint(run)["trainer_state"]["history"]
    for log in sorted((run / "logs" / "scalars").glob("*.csv")):
        steps = [int(line.split(",")[0]) for line in log.read_text().splitlines()]
        assert steps == [1, 2, 3, 4], log.name
    assert [float(line.split(",")[1]) for line in frames_log.read_text().splitlines()] == \
        [h["frames"] for h in history]


def test_truncation_drops_a_half_written_row(tmp_path):
    scalars = tmp_path / "logs" / "scalars"
    scalars.mkdir(parents=True)
    (scalars / "loss.csv").write_text("1,0.5\n2,0.25\n3,0.1\n4,0.0")
    truncate_scalar_logs(tmp_path / "logs", 3)
    assert (scalars / "loss.csv").read_text() == "1,0.5\n2,0.25\n3,0.1\n"
    truncate_scalar_logs(tmp_path / "logs", 1)
    assert (scalars / "loss.csv").read_text() == "1,0.5\n"


def test_tensorboard_purges_the_steps_after_the_resumed_iteration(tmp_path, monkeypatch):
    made = []

    class SummaryWriter:
        def __init__(self, log_dir, **kwargs):
            self.log_dir = log_dir
            made.append(kwargs)

    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", types.SimpleNamespace(SummaryWriter=SummaryWriter))
    make_logger(compose(["logger.backend=tensorboard"]), tmp_path, 7)
    assert made == [{"purge_step": 8}]


# ------------------------------------------------------------------------------- where a resume writes


def test_resuming_a_copied_run_writes_into_the_copy_only(tmp_path, capsys):
    original, copy = tmp_path / "original", tmp_path / "copy"
    _cli_train("trainer.iterations=2", "trainer.keep_checkpoints=2", f"output_dir={original}")
    shutil.copytree(original, copy)
    before = _tree_digest(original)

    assert main(["train", "--quiet", f"resume={copy}", f"output_dir={original}"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"error: output_dir: '{original}' is not the run directory being resumed ('{copy}')")
    with pytest.raises(ConfigError, match="^output_dir: "):
        train(compose([*TINY, "trainer.iterations=3", f"output_dir={original}"]), resume_state={"path": str(copy)},
              progress=False)

    assert main(["train", "--quiet", f"resume={copy}", "trainer.iterations=3"]) == 0
    assert _tree_digest(original) == before
    assert [p.name for p in list_checkpoints(copy / "checkpoints")] == ["checkpoint-000000000003",
                                                                         "checkpoint-000000000002"]
    saved = yaml.safe_load((copy / "config.yaml").read_text())
    assert saved["output_dir"] == str(copy) and load_checkpoint(copy)["config"]["output_dir"] == str(copy)
    assert f"output_dir='{copy}'" in saved["overrides"] and f"output_dir={original}" not in saved["overrides"]
    capsys.readouterr()
    assert main(["config", f"resume={copy}"]) == 0  # the recorded overrides compose back to the copy
    assert yaml.safe_load(capsys.readouterr().out)["output_dir"] == str(copy)


# ------------------------------------------------------------------------------- incompatible checkpoints


def test_incompatible_actor_size_names_the_key(tmp_path, capsys):
    run = tmp_path / "run"
    _cli_train("trainer.iterations=1", f"output_dir={run}")
    capsys.readouterr()
    assert main(["train", "--quiet", f"resume={run}", "actor.hidden=32", "trainer.iterations=2"]) == 2
    changes, *error = capsys.readouterr().err.strip().splitlines()
    # the changed keys first, named before any weight is loaded, then the checkpoint's one-line refusal
    assert changes == "resuming with 2 changes to the run's config: actor.hidden: 16 → 32; trainer.iterations: 1 → 2"
    assert _one_line("\n".join(error)) == (
        "error: checkpoint: actor: 'phi.0.weight' has shape [16, 10] in the checkpoint but [32, 10] here; "
        "resume with the run's own config")


def test_missing_or_extra_keys_and_optimizer_groups_are_named():
    small, other = torch.nn.Sequential(torch.nn.Linear(3, 4)), torch.nn.Sequential(torch.nn.Linear(3, 4),
                                                                                    torch.nn.Linear(4, 2))
    with pytest.raises(CheckpointIncompatible, match=r"^checkpoint: critic: '1.weight' is in the checkpoint but "
                                                     r"not here; resume with the run's own config$"):
        check_compatible("critic", small, other.state_dict())
    with pytest.raises(CheckpointIncompatible, match=r"^checkpoint: critic: '1.weight' is here but not in the "):
        check_compatible("critic", other, small.state_dict())
    saved = torch.optim.Adam(other.parameters()).state_dict()
    with pytest.raises(CheckpointIncompatible, match=r"^checkpoint: optimizer: parameter group 0 holds 4 tensors "
                                                     r"in the checkpoint but 2 here; "):
        check_compatible("optimizer", torch.optim.Adam(small.parameters()), saved)


def test_a_component_the_checkpoint_lacks_is_named(tmp_path):
    run = tmp_path / "run"
    train(compose([*TINY, "trainer.iterations=1", f"output_dir={run}"]), progress=False)
    with pytest.raises(CheckpointIncompatible, match=r"^checkpoint: readout_optimizer: not in '.*', which holds "
                                                     r"actor, config, critic, optimizer, trainer_state; "):
        load_checkpoint(run, readout_optimizer=torch.optim.Adam(_actor().parameters()))


# ------------------------------------------------------------------------------- a collector worker dies


def _kill_worker_before(algorithm, index: int, worker: int, pids: list):
    run_one = algorithm.iteration

    def iteration(i, seed):
        if i == index:
            proc = algorithm.collectors.collector.procs[worker]
            pids.append(proc.pid)
            os.kill(proc.pid, signal.SIGKILL)
            proc.join()
        return run_one(i, seed)

    algorithm.iteration = iteration
    return algorithm


@pytest.mark.slow
def test_killed_collector_worker_ends_the_run_with_one_line(tmp_path):
    run = tmp_path / "run"
    cfg = compose([*TINY, "trainer.iterations=3", "collector.workers=2", f"output_dir={run}"])
    pids = []
    algorithm = _kill_worker_before(build_algorithm(cfg, build_model(cfg.env)), 1, 1, pids)
    with pytest.raises(CollectorWorkerDied) as caught:
        run_training(cfg, algorithm, progress=False)
    assert str(caught.value) == (
        f"collector: worker 1 (pid {pids[0]}) killed by SIGKILL during iteration 2; the last checkpoint is "
        f"'{_checkpoint(run, 1)}'; resume with `escort-rl train resume={run}`")


def test_worker_death_message_without_a_checkpoint():
    assert worker_death_message(0, 123, 3, 1, None, Path("runs/a")) == (
        "collector: worker 0 (pid 123) exited with code 3 during iteration 1; no checkpoint was written yet; "
        "start the run again")


def test_cli_prints_a_dead_worker_as_one_line(monkeypatch, capsys):
    def dies(*args, **kwargs):
        raise CollectorWorkerDied(worker_death_message(0, 9, -9, 2, Path("r/checkpoints/c"), Path("r")))

    monkeypatch.setattr("escort_rl.trainers.training.train", dies)
    assert main(["train", "--quiet", *TINY]) == 2
    assert _one_line(capsys.readouterr().err).startswith("error: collector: worker 0 (pid 9) killed by SIGKILL")
