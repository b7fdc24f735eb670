"""``bench headline``: the trained rows over seeds, the scripted gain chosen on held-out episodes,
aggregation across seeds, and a rerun that loads what finished."""

from __future__ import annotations

import math

import pytest

from escort_rl.bench.core.runner import make_backend
from escort_rl.bench.headline.run import best_gain, mean_se, paired_difference, run_headline, trained_row
from escort_rl.bench.headline.spec import HeadlineSpec


def test_mean_se_is_the_sample_mean_and_its_standard_error():
    m, se = mean_se([1.0, 2.0, 4.0, float("nan")])  # NaN (no goal) is left out
    assert m == pytest.approx(7 / 3)
    assert se == pytest.approx(math.sqrt(((1 - 7 / 3) ** 2 + (2 - 7 / 3) ** 2 + (4 - 7 / 3) ** 2) / 2 / 3))
    assert mean_se([3.0]) == (3.0, 0.0) and all(math.isnan(v) for v in mean_se([]))


def test_the_gain_of_the_highest_success_wins_then_the_higher_return_then_the_lower_distance():
    results = [{"gain": 1.0, "success": [1, 0], "final_distance": [0.1, 2.0], "episode_return": [9.0, 9.0]},
               {"gain": 2.0, "success": [1, 1], "final_distance": [0.4, 0.4], "episode_return": [-5.0, -5.0]},
               {"gain": 3.0, "success": [1, 1], "final_distance": [0.2, 0.2], "episode_return": [-5.0, -5.0]},
               {"gain": 4.0, "success": [1, 1], "final_distance": [0.3, 0.3], "episode_return": [-6.0, -5.0]}]
    assert best_gain(results) == 3.0  # 2 and 3 tie on success and return; 4 reaches the goal later
    results[1]["episode_return"] = [-4.0, -5.0]  # the gain that reaches the goal sooner wins the tie
    assert best_gain(results) == 2.0


def test_a_trained_row_aggregates_across_seeds_not_episodes():
    def seed(success, distance, ret, steps, seconds):
        return {"filter": "sir", "success": [success] * 4, "final_distance": [distance] * 4,
                "episode_return": [ret] * 4, "steps": [steps] * 4, "frames": 100, "train_seconds": seconds}

    seeds = [seed(1.0, 0.0, -1.0, 10.0, 60.0), seed(0.0, 1.0, -3.0, 20.0, 120.0)]
    row = trained_row("x", seeds)
    assert row["success"] == 0.5 and row["success_se"] == pytest.approx(0.5)  # s.d. of (1, 0) over sqrt(2)
    assert row["per_seed"]["success"] == [1.0, 0.0] and row["train_minutes"] == pytest.approx(1.5)


def test_the_comparison_with_the_controller_pairs_the_episodes_then_averages_the_seeds():
    scripted = {"success": [1, 0, 1], "steps": [100, 500, 300], "episode_return": [-10, -50, -30]}
    seeds = [{"success": [1, 1, 1], "steps": [90, 400, 310], "episode_return": [-9, -40, -31]},
             {"success": [1, 0, 0], "steps": [100, 500, 500], "episode_return": [-10, -50, -50]}]
    d = paired_difference(seeds, scripted)
    assert d["success"][0] == pytest.approx((1 / 3 - 1 / 3) / 2)
    assert d["steps"][0] == pytest.approx(((-10 - 100 + 10) / 3 + 200 / 3) / 2)  # per seed: -33.3, +66.7
    se_seeds = mean_se([-100 / 3, 200 / 3])[1]
    se_episodes = mean_se([(-10 + 0) / 2, (-100 + 0) / 2, (10 + 200) / 2])[1]  # per episode, over the seeds
    assert d["steps"][2:] == pytest.approx((se_seeds, se_episodes))
    assert d["steps"][1] == pytest.approx(math.hypot(se_seeds, se_episodes))
    assert d["episode_return"][0] == pytest.approx(((1 + 10 - 1) / 3 + (-20) / 3) / 2)


def test_the_steps_where_both_arrive_leave_out_the_episodes_either_misses():
    scripted = {"success": [1, 0, 1, 1], "steps": [100, 500, 300, 200], "episode_return": [0, 0, 0, 0]}
    seeds = [{"success": [1, 1, 1, 0], "steps": [90, 400, 310, 500], "episode_return": [0, 0, 0, 0]},
             {"success": [1, 0, 1, 1], "steps": [96, 500, 290, 180], "episode_return": [0, 0, 0, 0]}]
    mean, se, se_seeds, se_episodes = paired_difference(seeds, scripted)["steps_both_succeed"]
    # seed 0 pairs episodes 0 and 2 (-10, +10), seed 1 episodes 0, 2 and 3 (-4, -10, -20)
    assert mean == pytest.approx((0.0 + (-34 / 3)) / 2)
    assert se_seeds == pytest.approx(mean_se([0.0, -34 / 3])[1])
    assert se_episodes == pytest.approx(mean_se([(-10 - 4) / 2, (10 - 10) / 2, -20])[1])
    assert se == pytest.approx(math.hypot(se_seeds, se_episodes))
    one_pair = [{"success": [1, 0, 0, 0], "steps": [90, 500, 500, 500], "episode_return": [0, 0, 0, 0]}] * 2
    assert paired_difference(one_pair, scripted)["steps_both_succeed"] is None


def test_the_table_has_its_rows_and_a_rerun_loads_the_finished_cells(tmp_path):
    spec = HeadlineSpec.quick(seeds=1, episodes=2, gains=(1.0, 3.0), output=tmp_path)
    result = run_headline(spec, make_backend("inprocess"))
    policies = [r["policy"] for r in result["rows"]]
    assert policies[:2] == [label for label, _ in spec.rows]
    assert policies[-1] == "random" and sum(p.startswith("scripted controller (gain ") for p in policies) == 2
    assert [r["filter"] for r in result["rows"][:2]] == ["escort_train", "sir_rough"]
    assert {(s["filter"], s["gain"]) for s in result["selection"]} == {
        (f, g) for f in ("escort_train", "sir_rough") for g in (1.0, 3.0)}
    checkpoints = sorted(p.stat().st_mtime_ns for p in (tmp_path / "runs").rglob("manifest.json"))
    assert checkpoints  # every trained cell wrote its run
    compared = {"success", "steps", "episode_return", "steps_both_succeed"}
    assert all(set(r["vs_scripted"]) == compared for r in result["rows"][:2])
    # the episodes behind every row are kept, so that a paired difference can be recomputed from the table alone
    assert all(len(r["per_episode"]["steps"]) == 1 and len(r["per_episode"]["steps"][0]) == 2
               for r in result["rows"][:2])
    assert all(len(r["per_episode"]["steps"]) == 2 for r in result["rows"][2:])
    again = run_headline(spec, make_backend("inprocess"))
    assert again["rows"] == result["rows"]
    assert sorted(p.stat().st_mtime_ns for p in (tmp_path / "runs").rglob("manifest.json")) == checkpoints


def test_bad_settings_name_their_option():
    with pytest.raises(ValueError, match=r"^--episodes: must be >= 1, got 0$"):
        HeadlineSpec(episodes=0)
    with pytest.raises(ValueError, match=r"^--gains: give one or more velocity gains >= 0"):
        HeadlineSpec(gains=(1.0, -2.0))


def test_overrides_under_every_row_run_the_table_on_the_continuous_task(tmp_path):
    from escort_rl.bench.headline.cli import spec_from_args
    from escort_rl.bench.headline.report import headline_markdown
    from escort_rl.cli import _parser

    args = _parser().parse_args(["bench", "headline", "--quick", "--seeds", "1", "--episodes", "2", "--gains", "1",
                                 "--output", str(tmp_path), "env=lightdark10d_continuous"])
    spec = spec_from_args(args)
    assert spec.overrides[-1] == "env=lightdark10d_continuous" and spec.overrides[:-1] == HeadlineSpec.quick().overrides
    result = run_headline(spec, make_backend("inprocess"))
    assert result["spec"]["env"] == "lightdark10d_continuous"
    assert headline_markdown(result).startswith("# Headline: PPO on particle beliefs, lightdark10d_continuous\n")
    from omegaconf import OmegaConf

    configs = [OmegaConf.load(f"{r['run_dir']}/config.yaml") for r in result["runs"]]
    assert len(configs) == 2 and {c.env.name for c in configs} == {"lightdark10d_continuous"}
    policies = [r["policy"] for r in result["rows"]]
    assert policies[-1] == "random" and policies.count("scripted controller (gain 1)") == 2


def test_a_curve_evaluates_every_kept_checkpoint_and_averages_seeds_at_common_frames(tmp_path):
    """--curve-every 1: each seed's every iteration on the same episodes; the last point is the final policy's."""
    from escort_rl.bench.headline.cli import write_headline

    spec = HeadlineSpec.quick(seeds=2, episodes=2, gains=(1.0,), output=tmp_path, curve_every=1,
                              rows=(("sir", ("filter=sir_rough", "trainer.warm_start_iterations=0")),))
    result = run_headline(spec, make_backend("inprocess"))
    row = result["rows"][0]
    assert [p["frames"] for p in row["curve"]] == [row["frames"] // 2, row["frames"]]  # after iterations 1 and 2
    assert row["curve"][-1]["success"] == pytest.approx(row["success"])
    assert row["curve"][-1]["steps"] == pytest.approx(row["steps"]) and row["curve"][0]["seeds"] == 2
    md = write_headline(result, tmp_path)
    assert "against training frames" in md and (tmp_path / "curve.png").is_file()
    with pytest.raises(ValueError, match=r"^--curve-every: give 0"):
        HeadlineSpec(curve_every=-1)


def test_own_rows_each_meet_the_controller_on_their_own_belief(tmp_path):
    # --row replaces the named rows; the controller runs on each belief a row acts on (here SIR at two particle
    # counts, on the hidden goal) and pairs with that row only; the GRU reads no belief and is paired with none.
    from escort_rl.bench.headline.cli import spec_from_args
    from escort_rl.bench.headline.report import headline_markdown
    from escort_rl.cli import _parser

    gru = ["trainer=recurrent_ppo", "trainer.iterations=1", "trainer.num_envs=4", "trainer.rollout_steps=10",
           "trainer.minibatches=2", "trainer.epochs=1", "trainer.hidden=8"]
    args = _parser().parse_args(["bench", "headline", "--quick", "--seeds", "1", "--episodes", "2", "--gains", "1",
                                 "--output", str(tmp_path), "env=hidden_goal",
                                 "--row", "PPO on SIR N=24", "filter=sir", "num_particles=24",
                                 "trainer.warm_start_iterations=0",
                                 "--row", "PPO on SIR", "filter=sir", "trainer.warm_start_iterations=0",
                                 "--row", "GRU", *gru])
    spec = spec_from_args(args)
    assert spec.scripted_filters is None and [label for label, _ in spec.rows] == ["PPO on SIR N=24", "PPO on SIR",
                                                                                   "GRU"]
    result = run_headline(spec, make_backend("inprocess"))
    rows = {r["policy"]: r for r in result["rows"]}
    assert rows["PPO on SIR N=24"]["filter"] == "filter=sir num_particles=24"
    assert rows["PPO on SIR"]["filter"] == "filter=sir"
    assert rows["GRU"]["filter"].startswith("none") and "vs_scripted" not in rows["GRU"]
    assert all("vs_scripted" in rows[p] for p in ("PPO on SIR N=24", "PPO on SIR"))
    scripted = [r for r in result["rows"] if r["kind"] == "scripted"]
    assert [r["filter"] for r in scripted] == ["filter=sir num_particles=24", "filter=sir"]
    for policy, against in (("PPO on SIR N=24", scripted[0]), ("PPO on SIR", scripted[1])):
        # one seed: the paired mean difference is the difference of the means, against this belief's controller
        # (not the random policy, which runs on the last belief too)
        for key in ("episode_return", "steps"):
            assert rows[policy]["vs_scripted"][key][0] == pytest.approx(rows[policy][key] - against[key], abs=1e-6)
    # the hidden goal's controller (toward the heaviest mode) has no velocity gain: no gain search runs, and the
    # table says what it does instead of naming a gain it ignores
    from escort_rl.bench.headline.run import gainless_rule
    from escort_rl.config import compose

    rule = gainless_rule(compose(["env=hidden_goal"]))
    assert "heaviest mode" in rule and gainless_rule(compose(["env=lightdark10d"])) is None
    assert result["selection"] == [] and result["spec"]["scripted_rule"] == rule
    md = headline_markdown(result)
    assert f"| PPO on SIR N=24 | scripted controller ({rule}) on filter=sir num_particles=24 |" in md
    assert f"it pushes {rule}." in md and "Gain search" not in md and "velocity gain was chosen" not in md
    # the GRU's trainer group drops the run's trainer keys it does not name again, and the table says so
    assert rows["GRU"]["dropped_overrides"] == ["trainer.warm_start_iterations=1"]
    assert "Row *GRU* drops `trainer.warm_start_iterations=1`: it picks their group." in md
    assert rows["PPO on SIR"]["dropped_overrides"] == ["filter.compile=false"]


def test_rows_with_no_belief_need_the_controller_s_beliefs_named(tmp_path):
    spec = HeadlineSpec.quick(seeds=1, episodes=2, gains=(1.0,), output=tmp_path, scripted_filters=None,
                              rows=(("GRU", ("trainer=recurrent_ppo",)),))
    with pytest.raises(ValueError, match=r"^--scripted-on: no trained row acts on a filter's belief"):
        run_headline(spec, make_backend("inprocess"))


def test_a_run_override_after_scripted_on_is_refused_not_taken_for_a_belief(capsys):
    from escort_rl.cli import main

    # argparse gives every word after --scripted-on to it: env=... would have run the controller on another task
    assert main(["bench", "headline", "--quick", "--row", "PPO", "filter=sir", "--scripted-on", "sir",
                 "env=lightdark10d_continuous"]) == 2
    err = capsys.readouterr().err
    assert "--scripted-on: 'env=lightdark10d_continuous' sets env, which is not part of a belief" in err
    HeadlineSpec(scripted_filters=("sir", "filter=sir num_particles=3000", "filter=escort filter.num_steps=5"))


def test_a_second_controller_on_one_belief_is_its_own_row_and_the_first_is_the_pair(tmp_path):
    """``--scripted-on`` may give the controller's options (``env.scripted_options``): the hidden goal's look-first
    rule beside the committing one on the same belief, each row named by its rule; the trained row is paired with
    the first."""
    from escort_rl.bench.headline.cli import spec_from_args
    from escort_rl.cli import _parser

    belief = "filter=sir num_particles=24"
    args = _parser().parse_args(["bench", "headline", "--quick", "--seeds", "1", "--episodes", "2",
                                 "--output", str(tmp_path), "env=hidden_goal", "--row", "PPO", *belief.split(),
                                 "trainer.warm_start_iterations=0", "--scripted-on", belief,
                                 f"{belief} env.scripted_options={{confidence:0.9}}"])
    result = run_headline(spec_from_args(args), make_backend("inprocess"))
    trained = next(r for r in result["rows"] if r["kind"] == "trained")
    commit, look = [r for r in result["rows"] if r["kind"] == "scripted"]
    assert "after the beacon" not in commit["policy"]
    assert look["policy"].endswith("after the beacon while no mode weighs 0.9)")
    for key in ("episode_return", "steps"):
        assert trained["vs_scripted"][key][0] == pytest.approx(trained[key] - commit[key], abs=1e-6)
    from escort_rl.bench.headline.report import headline_markdown

    assert "Rows naming another rule run it" in headline_markdown(result)


def test_frontier_rows_train_on_each_filter_s_closest_configuration_within_the_budget(tmp_path):
    import json

    from escort_rl.bench.headline.cli import spec_from_args
    from escort_rl.cli import _parser

    rows = [dict(method="sir", base="sir", settings=[], particles=100, num_steps=0, ms_per_update=0.3, error=2.0),
            dict(method="sir", base="sir", settings=[], particles=3000, num_steps=0, ms_per_update=8.0, error=1.0),
            dict(method="escort_eps", base="escort", settings=["step_size=0.02"], particles=100, num_steps=15,
                 ms_per_update=9.0, error=0.5),
            dict(method="escort", base="escort", settings=[], particles=100, num_steps=50, ms_per_update=30.0,
                 error=0.1),
            dict(method="enkf", base="enkf", settings=[], particles=100, num_steps=0, ms_per_update=0.5,
                 error=float("nan"), failed="diverged")]
    path = tmp_path / "frontier.json"
    path.write_text(json.dumps({"rows": rows}))
    args = _parser().parse_args(["bench", "headline", "--frontier-rows", str(path), "10", "--row", "GRU",
                                 "trainer=recurrent_ppo"])
    spec = spec_from_args(args)
    assert spec.rows == (
        ("PPO on sir N=3000 (closest within 10 ms)", ("filter=sir", "num_particles=3000",
                                                      "trainer.warm_start_iterations=0")),
        ("PPO on escort_eps N=100 K=15 (closest within 10 ms)", (
            "filter=escort", "num_particles=100", "filter.num_steps=15", "filter.step_size=0.02",
            "trainer.warm_start_iterations=0")),
        ("GRU", ("trainer=recurrent_ppo",)))
    assert spec.scripted_filters is None
    bad = _parser().parse_args(["bench", "headline", "--frontier-rows", str(path), "0.1"])
    with pytest.raises(ValueError, match=r"^--frontier-rows: no filter of .* updates within 0.1 ms; raise the budget"):
        spec_from_args(bad)


def test_a_trained_cell_is_the_same_cell_wherever_its_run_is_written(tmp_path, monkeypatch):
    from escort_rl.bench.headline.cells import TrainedCell

    monkeypatch.chdir(tmp_path)

    def cell(run_dir: str, seed: int = 0) -> TrainedCell:
        return TrainedCell(label="row", overrides=("trainer.iterations=1",), seed=seed, run_dir=run_dir,
                           episodes=2, eval_seed=10000)

    relative = cell("out/runs/row-seed0")
    assert relative.spec() == cell(str(tmp_path / "out/runs/row-seed0")).spec()
    assert relative.spec() == cell("moved/runs/row-seed0").spec()
    assert relative.spec() != cell("out/runs/row-seed0", seed=1).spec()
    assert "run_dir" not in relative.spec() and "output_dir" not in relative.spec()["config"]

