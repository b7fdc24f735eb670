"""The training scaffold: config errors, checkpoints, kill/resume, evaluation reports."""

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from torchrl.checkpoint import CheckpointRotation

from conftest import actor_of
from escort_rl.cli import main
from escort_rl.config import ConfigError, compose
from escort_rl.modules import DeepSetsActor
from escort_rl.trainers.checkpointing import CheckpointLoadError, load_checkpoint
from escort_rl.trainers.training import train

# The default job's filter (ESCORT) at a tiny size; eager, because compiling in every test process
# would dominate the test time (tests/belief/test_escort.py checks that compiled and eager updates agree).
TINY = ["trainer=reinforce", "trainer.num_envs=4", "env.max_steps=12", "num_particles=16", "actor.hidden=16",
        "trainer.minibatch_size=64", "trainer.checkpoint_every=1", "filter.compile=false"]


def test_unknown_config_key_names_the_key():
    with pytest.raises(ConfigError, match="trainer.lrr"):
        compose(["trainer.lrr=0.1"])


def test_bad_config_value_names_the_key(tmp_path):
    cfg = compose([*TINY, "trainer.baseline=mean", f"output_dir={tmp_path}"])
    with pytest.raises(ConfigError, match="^trainer.baseline:"):
        train(cfg, progress=False)


def test_cli_unknown_key_is_one_line(capsys):
    assert main(["train", "nonsense_key=3"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: config: unknown key 'nonsense_key'") and "\n" not in err


def test_corrupt_checkpoint_gives_one_line_error(tmp_path, capsys):
    run = tmp_path / "run"
    train(compose([*TINY, "trainer.iterations=1", f"output_dir={run}"]), progress=False)
    ckpt = CheckpointRotation(run / "checkpoints", keep_last=10).latest()
    assert load_checkpoint(ckpt)["trainer_state"]["iteration"] == 1
    for f in (ckpt / "components").rglob("*"):
        if f.is_file() and f.suffix in (".memmap", ".json"):
            f.write_bytes(b"\x00garbage")
    with pytest.raises(CheckpointLoadError, match=f"^checkpoint: '{ckpt}' is damaged \\(actor: "):
        load_checkpoint(ckpt, actor=actor_of(TINY))
    assert main(["evaluate", "--checkpoint", str(run), "--episodes", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: checkpoint: no intact checkpoint left under '{run}'") and "\n" not in err


def test_missing_checkpoint_path(capsys):
    assert main(["evaluate", "--checkpoint", "/nonexistent/run"]) == 2
    assert capsys.readouterr().err.startswith("error: checkpoint: '/nonexistent/run' does not exist")


def _actor_params(run: Path) -> dict:
    actor = actor_of(TINY)
    load_checkpoint(run, actor=actor)
    return {k: v.clone() for k, v in actor.state_dict().items()}


@pytest.mark.slow
def test_killed_run_resumes_to_the_same_parameters(tmp_path):
    iterations = 12
    args = [*TINY, f"trainer.iterations={iterations}", "trainer.keep_checkpoints=3"]
    reference = tmp_path / "reference"
    assert main(["train", "--quiet", *args, f"output_dir={reference}"]) == 0

    killed = tmp_path / "killed"
    cmd = [sys.executable, "-m", "escort_rl.cli", "train", "--quiet", *args, f"output_dir={killed}"]
    log = tmp_path / "killed.stderr"
    with log.open("wb") as stderr:  # a file, not a pipe: a full pipe would block the child
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=stderr)
    rotation = CheckpointRotation(killed / "checkpoints", keep_last=100)
    hang_guard = time.monotonic() + 900  # ends a hung child only; the run takes seconds, this is no speed limit
    while True:  # until the checkpoint of iteration 3 (the run ends by itself after 12 iterations)
        latest = rotation.latest()
        if latest is not None and load_checkpoint(latest)["trainer_state"]["iteration"] >= 3:
            break
        try:
            proc.wait(timeout=0.05)  # returns at once if the child exits
        except subprocess.TimeoutExpired:
            if time.monotonic() > hang_guard:
                proc.kill()
                proc.wait()
                pytest.fail("hang guard, not a speed assertion: the training child neither wrote the "
                            f"checkpoint of iteration 3 nor exited in 900 s: {log.read_text()[-2000:]}")
            continue
        pytest.fail(f"training exited early: {log.read_text()[-2000:]}")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    survivors = rotation.checkpoints()
    assert survivors, "no checkpoint survived the kill"
    reached = [load_checkpoint(p)["trainer_state"]["iteration"] for p in survivors]  # none is corrupt
    assert max(reached) < iterations, "the run finished before it was killed; the test proves nothing"

    assert main(["train", "--quiet", f"resume={killed}"]) == 0
    final = load_checkpoint(killed)
    assert final["trainer_state"]["iteration"] == iterations
    ref, res = _actor_params(reference), _actor_params(killed)
    for key in ref:
        assert torch.equal(ref[key], res[key]), key
    ref_hist = load_checkpoint(reference)["trainer_state"]["history"]
    assert [h["episode_return"] for h in ref_hist] == [h["episode_return"] for h in final["trainer_state"]["history"]]


@pytest.mark.slow
def test_two_collector_workers_and_learned_baseline(tmp_path):
    run = tmp_path / "run"
    train(compose([*TINY, "trainer.iterations=2", "collector.workers=2", "trainer.baseline=learned",
                   f"output_dir={run}"]), progress=False)
    state = load_checkpoint(run)
    assert state["trainer_state"]["iteration"] == 2
    history = state["trainer_state"]["history"]
    assert all(h["episodes"] == 4 for h in history)  # 4 envs split over 2 workers, one episode each
    assert all(math.isfinite(h["loss_actor"]) for h in history)
    critic = DeepSetsActor(10, 1, hidden=16, encoder_layers=1)
    load_checkpoint(run, actor=actor_of(TINY), critic=critic)


def test_evaluate_writes_reports(tmp_path):
    run = tmp_path / "run"
    train(compose([*TINY, "trainer.iterations=1", f"output_dir={run}"]), progress=False)
    assert main(["evaluate", "--checkpoint", str(run), "--episodes", "3", "--output", str(tmp_path / "ev")]) == 0
    for name in ("summary.md", "metrics.json", "learning_curve.png", "belief_projection.png"):
        assert (tmp_path / "ev" / name).stat().st_size > 0
    import json

    metrics = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert metrics["trained"]["episodes"] == 3 and metrics["random"]["episodes"] == 3
    assert metrics["scripted"]["episodes"] == 3  # the PD controller on the same filter's belief
    summary = (tmp_path / "ev" / "summary.md").read_text()
    assert "| trained |" in summary and "| scripted |" in summary and "| random |" in summary


def test_episode_stats_by_hand():
    from tensordict import TensorDict

    from escort_rl.models import LightDark10D
    from escort_rl.trainers.scaffold import episode_stats

    done = torch.tensor([[False, True, False, True], [False, False, False, False]])
    reward = torch.tensor([[1.0, 2.0, 3.0, 4.0], [5.0, 5.0, 5.0, 5.0]])
    state = torch.zeros(2, 4, 10)
    state[0, 1, :5] = 8.0  # at the goal
    state[0, 3, :5] = 5.0
    batch = TensorDict({"next": {"done": done.unsqueeze(-1), "terminated": done.unsqueeze(-1) & (state[..., :1] == 8.0),
                                 "reward": reward.unsqueeze(-1), "true_state": state}}, [2, 4])
    stats = episode_stats(batch, LightDark10D())
    assert stats["episodes"] == 2
    assert stats["episode_return"] == (3.0 + 7.0) / 2
    assert abs(stats["final_distance"] - (0.0 + 3 * 5**0.5) / 2) < 1e-5
    assert stats["success_rate"] == 0.5
