"""``escort-rl bench hidden-goal``: every filter with both controllers on the same episodes, and what the
belief did with the modes."""

from __future__ import annotations

import json

from escort_rl.cli import main


def test_rows_share_episodes_and_read_the_modes(tmp_path):
    argv = ["bench", "hidden-goal", "--dims", "3", "--filters", "sir", "--episodes", "6", "--steps", "20",
            "--particles", "40", "--output", str(tmp_path)]
    assert main(argv) == 0
    result = json.loads((tmp_path / "hidden_goal.json").read_text())
    commit, look = result["rows"]
    assert (commit["label"], look["label"]) == ("sir, commit", "sir, look first")
    assert (commit["confidence"], look["confidence"]) == (0.0, 0.9)
    for r in result["rows"]:
        assert r["dim"] == 3 and r["modes"] == 4 and r["particles"] == 40 and len(r["success"]) == 6
        assert all(0.0 <= p <= 1.0 + 1e-9 for p in r["true_mode@1"])
        assert all(1 <= k <= 4 for k in r["modes_held@1"])
    # the prior holds all four modes, about equally: before any step can tell them apart, no filter has
    # one that weighs 0.9 (the look-first controller heads for the beacon)
    assert sum(look["modes_held@1"]) / 6 > 2
    # at the beacon (reached within 6 pushes) the goal reading leaves one mode, and looking first finds the goal
    assert sum(look["modes_held@10"]) / len(look["modes_held@10"]) < 1.5
    table = (tmp_path / "hidden_goal.md").read_text()
    assert "## dim 3 (a 6-D belief), 4 modes" in table and "| sir, look first |" in table


def test_unknown_filters_and_sizes_get_one_line(tmp_path, capsys):
    assert main(["bench", "hidden-goal", "--filters", "pf", "--output", str(tmp_path)]) != 0
    assert "--filters: unknown pf" in capsys.readouterr().err
    assert main(["bench", "hidden-goal", "--dims", "2", "--modes", "4", "--output", str(tmp_path)]) != 0
    assert "HiddenGoal.modes: at most 2·(dim − 1) = 2" in capsys.readouterr().err


def test_escort_rows_run_with_overrides_under_them(tmp_path):
    """The ESCORT row on a tiny episode, eager (a positional override goes under every row)."""
    argv = ["bench", "hidden-goal", "filter.compile=false", "--dims", "3", "--filters", "escort_train",
            "--episodes", "2", "--steps", "4", "--particles", "12", "--output", str(tmp_path)]
    assert main(argv) == 0
    rows = json.loads((tmp_path / "hidden_goal.json").read_text())["rows"]
    assert [r["filter"] for r in rows] == ["escort_train", "escort_train"]
    assert all("filter.compile=false" in r["overrides"] for r in rows)


def test_a_filter_of_ones_own(tmp_path):
    argv = ["bench", "hidden-goal", "--add-filter", "sir systematic", "filter=sir", "filter.resampling=systematic",
            "--dims", "3", "--episodes", "2", "--steps", "3", "--particles", "12", "--output", str(tmp_path)]
    assert main(argv) == 0
    result = json.loads((tmp_path / "hidden_goal.json").read_text())
    assert [r["label"] for r in result["rows"]] == ["sir systematic, commit", "sir systematic, look first"]
    assert result["filters"] == {"sir systematic": ["filter=sir", "filter.resampling=systematic"]}


def test_frontier_rows_act_on_each_filters_closest_configuration_within_the_budget(tmp_path, capsys):
    rows = [dict(method="sir", base="sir", settings=[], particles=20, num_steps=0, ms_per_update=0.3, error=2.0),
            dict(method="sir", base="sir", settings=[], particles=40, num_steps=0, ms_per_update=0.8, error=1.0),
            dict(method="enkf", base="enkf", settings=[], particles=30, num_steps=0, ms_per_update=0.5, error=1.5),
            dict(method="escort", base="escort", settings=[], particles=12, num_steps=50, ms_per_update=30.0,
                 error=0.1)]
    path = tmp_path / "frontier.json"
    path.write_text(json.dumps({"rows": rows}))
    argv = ["bench", "hidden-goal", "--frontier-rows", str(path), "1", "--dims", "3", "--episodes", "2", "--steps",
            "3", "--output", str(tmp_path / "out")]
    assert main(argv) == 0
    result = json.loads((tmp_path / "out" / "hidden_goal.json").read_text())
    assert result["filters"] == {"sir N=40 (closest within 1 ms)": ["filter=sir", "num_particles=40"],
                                 "enkf N=30 (closest within 1 ms)": ["filter=enkf", "num_particles=30"]}
    assert {r["particles"] for r in result["rows"]} == {40, 30}
    assert main([*argv[:-1], str(tmp_path / "two"), "--dims", "3", "4"]) != 0
    assert "--frontier-rows: a frontier is measured at one dimension" in capsys.readouterr().err
