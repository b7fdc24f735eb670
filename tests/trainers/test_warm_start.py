"""The warm start is explicit: a run prints its plan, records the filter of every iteration, and its
evaluation counts the frames on each filter; a warm start that would cover the whole run on another
filter is refused before anything runs."""

from __future__ import annotations

import json

import pytest

from escort_rl.config import ConfigError, compose
from escort_rl.trainers.checkpointing import load_checkpoint
from escort_rl.trainers.scaffold import describe_plan, frames_by_belief, training_plan
from escort_rl.trainers.training import train
from escort_rl.trainers.validation import validate_train_config

TINY_PPO = ["trainer=ppo", "trainer.num_envs=4", "trainer.rollout_steps=6", "env.max_steps=12", "num_particles=8",
            "actor.hidden=8", "trainer.minibatches=2", "trainer.epochs=1", "trainer.warm_start_epochs=null",
            "trainer.checkpoint_every=1", "evaluate.episodes=4"]


def test_a_warm_start_covering_every_iteration_on_another_filter_is_refused():
    cfg = compose([*TINY_PPO, "filter=sir_rough", "trainer.iterations=20", "trainer.warm_start_filter=sir",
                   "trainer.warm_start_iterations=30"])
    with pytest.raises(ConfigError) as info:
        validate_train_config(cfg)
    message = str(info.value)
    assert message.startswith("trainer.warm_start_iterations:") and "\n" not in message
    assert "never train on its filter (sir_rough)" in message
    assert "trainer.warm_start_iterations=10" in message and "trainer.warm_start_filter=null" in message


@pytest.mark.parametrize("overrides", [
    ("trainer.iterations=20", "trainer.warm_start_iterations=19"),  # one iteration left on the run's filter
    ("trainer.iterations=20", "trainer.warm_start_filter=null"),  # no warm start
    ("filter=sir", "trainer.iterations=2", "trainer.warm_start_filter=sir"),  # the warm start is the run's filter
])
def test_a_warm_start_that_leaves_the_runs_filter_its_iterations_is_accepted(overrides):
    validate_train_config(compose([*TINY_PPO, "filter=sir_rough", *overrides]))


def test_the_default_job_trains_at_least_half_its_frames_on_its_own_filter():
    cfg = compose([])
    validate_train_config(cfg)
    # every iteration has the same frames (num_envs x max_steps), so iterations count frames
    assert 2 * cfg.trainer.warm_start_iterations <= cfg.trainer.iterations


def test_the_plan_is_printed_recorded_per_iteration_and_counted_in_the_evaluation(tmp_path, capsys):
    from escort_rl.trainers.evaluate import evaluate

    run = tmp_path / "run"
    cfg = compose([*TINY_PPO, "filter=sir_rough", "trainer.iterations=3", "trainer.warm_start_filter=sir",
                   "trainer.warm_start_iterations=2", "env.scripted_gain=0.5", f"output_dir={run}"])
    train(cfg, progress=False)
    assert "iterations 1–2 on sir, 3 on sir_rough" in capsys.readouterr().out
    history = load_checkpoint(run)["trainer_state"]["history"]
    assert [h["filter"] for h in history] == ["sir", "sir", "sir_rough"]
    assert json.loads((run / "history.json").read_text())[2]["filter"] == "sir_rough"

    evaluate(run)
    metrics = json.loads((run / "evaluation" / "metrics.json").read_text())
    assert metrics["filter"] == "sir_rough"
    frames = 4 * 12  # an iteration: every env runs env.max_steps steps
    assert metrics["training"]["frames_by_filter"] == {"sir": 2 * frames, "sir_rough": frames}
    assert metrics["training"]["wall_s"] > 0
    summary = (run / "evaluation" / "summary.md").read_text()
    assert "Trained on 96 frames of sir, 48 of sir_rough" in summary
    # the scripted row runs at the env group's stored gain
    assert metrics["scripted_gain"] == 0.5 and "PD controller (velocity gain 0.5)" in summary


def test_a_resume_prints_where_it_starts(tmp_path, capsys):
    run = tmp_path / "run"
    base = [*TINY_PPO, "filter=sir", "trainer.warm_start_filter=null", f"output_dir={run}"]
    train(compose([*base, "trainer.iterations=1"]), progress=False)
    capsys.readouterr()
    train(compose([*base, "trainer.iterations=2"]), resume_state={"path": str(run)}, progress=False)
    assert "resuming at iteration 2 of 2; iterations 1–2 on sir" in capsys.readouterr().out


def test_frames_by_belief_reads_old_histories_through_the_plan():
    """A history saved before records named their filter takes each iteration's from the plan."""
    history = [{"iteration": 1, "frames": 100}, {"iteration": 2, "frames": 200}, {"iteration": 3, "frames": 250}]
    plan = training_plan(["sir_rough", "sir_rough", "escort_train"])
    assert frames_by_belief(history, plan) == {"sir_rough": 200, "escort_train": 50}
    assert describe_plan(plan) == "iterations 1–2 on sir_rough, 3 on escort_train"
