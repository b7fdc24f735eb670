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
