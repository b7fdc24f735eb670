"""``bench popgym``: the task overrides, MMER, the grid, and one tiny cell of each kind end to end."""

import math
from argparse import Namespace

import pytest

from escort_rl.bench.popgym.cells import POPGymRandomCell, POPGymTrainCell, task_overrides
from escort_rl.bench.popgym.cli import grid, spec_from_args
from escort_rl.bench.popgym.report import GRU, markdown_table, mmer, summarise, versus, versus_table
from escort_rl.bench.popgym.spec import POPGymSpec
from escort_rl.config import compose

TINY = ("trainer.num_envs=2", "env.max_steps=10", "env.model.max_episode_length=10", "num_particles=8",
        "actor.hidden=8")


def test_task_overrides_compose_to_the_task_model():
    from escort_rl.trainers.builders import build_model

    for task, noise, length in (("NoisyPositionOnlyCartPoleHard", 0.3, 200), ("PositionOnlyCartPoleMedium", 0.0, 400),
                                ("NoisyPositionOnlyPendulumMedium", 0.2, 200), ("PositionOnlyPendulumHard", 0.0, 100)):
        cfg = compose(list(task_overrides(task)))
        model = build_model(cfg.env)
        assert model.obs_noise == noise and model.max_episode_length == length == cfg.env.max_steps
        assert cfg.env.simulator.process_noise == 0.0 and model.process_noise > 0  # the filter's model


def test_mmer_is_the_best_iteration_and_ignores_empty_ones():
    assert mmer([0.2, float("nan"), 0.5, 0.1]) == 0.5
    assert math.isnan(mmer([float("nan")]))


def test_summarise_aggregates_seeds_and_adds_random():
    runs = [{"task": "T", "label": "A", "seed": s, "frames": [10, 20], "episode_return": [0.1, r],
             "seconds": [1.0, 2.0]} for s, r in ((0, 0.5), (1, 0.7))]
    rows = summarise(runs, [{"task": "T", "episode_return": [0.0, 0.2]}])
    trained = next(r for r in rows if r["policy"] == "A")
    assert trained["mmer"][0] == pytest.approx(0.6) and trained["mmer"][1] == pytest.approx(0.1)
    assert trained["frames"] == 20 and trained["minutes"][0] == pytest.approx(0.05)
    random_row = next(r for r in rows if r["policy"] == "random")
    assert random_row["mmer"][0] == pytest.approx(0.1)
    assert "| T | A | 0.600 ± 0.100 |" in markdown_table(rows)


def test_versus_the_gru_per_task_with_the_combined_standard_error():
    runs = [{"task": task, "label": label, "seed": s, "frames": [10], "episode_return": [r], "seconds": [1.0]}
            for task, label, returns in (("T", GRU, (0.4, 0.6)), ("T", "B", (0.9, 0.7)), ("U", "B", (0.1, 0.3)))
            for s, r in enumerate(returns)]
    rows = summarise(runs, [{"task": "T", "episode_return": [0.0, 0.2]}])
    (only,) = versus(rows)  # U has no GRU row, and random is no trained row
    assert (only["task"], only["policy"]) == ("T", "B")
    assert only["difference"] == pytest.approx(0.3)
    assert only["se"] == pytest.approx(math.hypot(0.1, 0.1)) and only["z"] == pytest.approx(0.3 / math.hypot(0.1, 0.1))
    assert "| T | B | 0.300 ± 0.141 | +2.1 |" in versus_table(rows)


def test_grid_skips_dvrl_on_pendulum_and_names_runs_apart(tmp_path):
    spec = POPGymSpec(tasks=("NoisyPositionOnlyCartPoleEasy", "NoisyPositionOnlyPendulumEasy"), seeds=2,
                      output=tmp_path)
    trained, randoms = grid(spec)
    labels = {(c.task, c.label) for c in trained}
    assert ("NoisyPositionOnlyCartPoleEasy", "DVRL") in labels
    assert ("NoisyPositionOnlyPendulumEasy", "DVRL") not in labels
    assert len(trained) == 2 * (5 + 4) and len(randoms) == 2
    assert len({c.run_dir for c in trained}) == len(trained) and len({c.key() for c in trained}) == len(trained)
    # the importance cap goes under every trained row on Pendulum (continuous actions), nowhere else
    cap = "trainer.max_importance_ratio=3"
    assert all((cap in c.overrides) == ("Pendulum" in c.task) for c in trained)
    assert not any(cap in r.overrides for r in randoms)


def test_bad_options_are_named(tmp_path):
    with pytest.raises(ValueError, match="--tasks"):
        POPGymSpec(tasks=("CartPole",))
    with pytest.raises(ValueError, match="--seeds"):
        POPGymSpec(seeds=0)
    args = Namespace(quick=True, seeds=None, frames=None, threads=None, tasks=None, rows=["LSTM"],
                     output=str(tmp_path), overrides=[])
    with pytest.raises(ValueError, match="--rows"):
        spec_from_args(args)


def test_frames_per_iteration_follow_each_trainer():
    from escort_rl.bench.popgym.cells import frames_per_iteration

    base = list(task_overrides("NoisyPositionOnlyCartPoleEasy"))  # 200-step episodes
    assert frames_per_iteration(compose([*base, "trainer=ppo", "trainer.num_envs=2"])) == 2 * 125 * 2
    assert frames_per_iteration(compose([*base, "trainer=ppo", "trainer.num_envs=2",
                                         "trainer.rollout_steps=50"])) == 2 * 200
    assert frames_per_iteration(compose([*base, "trainer=dvrl_a2c", "trainer.num_envs=2"])) == 2 * 200


def test_iterations_reach_the_frames():
    cell = POPGymTrainCell(task="NoisyPositionOnlyCartPoleEasy", label="x", overrides=(*task_overrides(
        "NoisyPositionOnlyCartPoleEasy"), *TINY), seed=0, frames=45, run_dir="unused")
    assert "trainer.iterations=3" in cell.run_overrides()  # 2 envs x 10 steps per iteration: ceil(45 / 20)


RECURRENT = ("trainer=recurrent_ppo", "trainer.minibatches=2")
BELIEF = ("trainer=ppo", "filter=sir", "trainer.warm_start_iterations=0", "trainer.warm_start_filter=null")


@pytest.mark.parametrize("task,row", [("NoisyPositionOnlyCartPoleEasy", RECURRENT),
                                      ("NoisyPositionOnlyPendulumEasy", BELIEF)])
def test_a_training_cell_runs_and_resumes(tmp_path, task, row):
    cell = POPGymTrainCell(task=task, label="row", overrides=(*task_overrides(task), *TINY, *row), seed=0, frames=40,
                           run_dir=str(tmp_path / "run"))
    first = cell.run()
    assert first["frames"] == [20, 40] and len(first["episode_return"]) == 2
    assert all(-1.0 - 1e-5 <= r <= 1.0 + 1e-5 for r in first["episode_return"] if not math.isnan(r))  # float sums
    assert cell.run()["episode_return"] == first["episode_return"]  # finished: loaded, not retrained


def test_random_cell_returns_lie_in_popgyms_range():
    result = POPGymRandomCell(task="NoisyPositionOnlyPendulumEasy", overrides=task_overrides(
        "NoisyPositionOnlyPendulumEasy"), episodes=8).run()
    assert len(result["episode_return"]) == 8
    assert all(-1.0 - 1e-5 <= r <= 1.0 + 1e-5 for r in result["episode_return"])
