"""Smoke tests of the planner-budget benchmark (``escort-rl bench planner-budget``): the structure
of its result and report, and the refusal of bad flags. Tiny budgets, two episodes, three steps."""

from __future__ import annotations

import json

import pytest

from escort_rl.bench.planner_budget import planner_budget_markdown, run_planner_budget
from escort_rl.cli import main


@pytest.mark.parametrize("domain", ["lightdark1d", "lightdark10d"])
def test_result_holds_a_row_per_budget_and_a_random_row(domain):
    result = run_planner_budget(domain, budgets=[2, 4], episodes=2, steps=3, seed=0, particles=20)
    assert (result["domain"], result["budgets"], result["episodes"], result["steps"]) == (domain, [2, 4], 2, 3)
    assert result["filter"] == "sir" and result["particles"] == 20 and "n_sim" not in result["planner"]
    assert [(r["policy"], r["n_sim"]) for r in result["rows"]] == [("pomcpow", 2), ("pomcpow", 4), ("random", None)]
    for row in result["rows"]:
        s = row["summary"]
        assert s["episodes"] == 2 and 1 <= s["mean_length"] <= 3
        for key in ("episode_return", "final_distance", "success_rate"):
            assert s[f"{key}_se"] >= 0 and s[key] == s[key]  # not NaN: both domains have a goal
        assert len(row["per_episode"]["episode_return"]) == 2
        if row["policy"] == "pomcpow":
            # one decision per env and step (an env whose episode ended is reset and keeps deciding)
            assert row["decisions"] == 2 * 3 and row["seconds_per_decision"] > 0
        else:
            assert row["decisions"] == 0 and row["seconds_per_decision"] is None
    json.dumps(result)  # the CLI writes it as JSON
    md = planner_budget_markdown(result)
    assert "| POMCPOW n_sim=2 |" in md and "| POMCPOW n_sim=4 |" in md and "| random policy |" in md


def test_same_seed_same_episodes():
    """The rows share their episodes: the random row, which ignores the planner, is the same on a rerun,
    and a planner row is reproducible under its seed."""
    first, second = (run_planner_budget("lightdark1d", budgets=[3], episodes=2, steps=3, particles=20)
                     for _ in range(2))
    for a, b in zip(first["rows"], second["rows"], strict=True):
        assert a["per_episode"] == b["per_episode"]


@pytest.mark.parametrize(
    "kwargs, flag",
    [
        (dict(domain="gridworld"), "--domains"),
        (dict(budgets=[0, 10]), "--budgets"),
        (dict(budgets=[]), "--budgets"),
        (dict(budgets=[2.5]), "--budgets"),
        (dict(budgets=[10, 10]), "--budgets"),
        (dict(episodes=0), "--episodes"),
        (dict(steps=-1), "--steps"),
    ],
)
def test_bad_inputs_raise_naming_the_flag(kwargs, flag):
    with pytest.raises(ValueError, match=flag):
        run_planner_budget(**{"domain": "lightdark1d", "budgets": [2], "episodes": 2, "steps": 2, **kwargs})


def test_cli_writes_the_report_and_refuses_bad_flags(tmp_path, capsys):
    out = tmp_path / "pb"
    assert main(["bench", "planner-budget", "--quick", "--output", str(out)]) == 0
    result = json.loads((out / "planner_budget.json").read_text())
    assert result["budgets"] == [2, 5] and result["episodes"] == 2 and result["steps"] == 3
    assert (out / "planner_budget.md").read_text().startswith("# POMCPOW return against the simulation budget")
    capsys.readouterr()
    for argv, flag in ((["--budgets", "0", "5"], "--budgets"), (["--domains", "gridworld"], "--domains"),
                       (["--episodes", "0"], "--episodes")):
        assert main(["bench", "planner-budget", "--quick", "--output", str(tmp_path / "bad"), *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"error: {flag}:") and "\n" not in err
