"""Protocol (b) of the domain benchmark: each method trains its own policy, then drives it."""

from __future__ import annotations

import json
import math

import pytest

from escort_rl.bench import closed_loop as cl
from escort_rl.bench.domains import DEFAULT_DOMAINS
from escort_rl.cli import main

TINY = ["bench", "domains", "--protocol", "b", "--domains", "lightdark10d", "--methods", "sir", "escort",
        "--seeds", "3", "--particles", "10", "--steps", "5", "--train-envs", "2", "--threads", "1",
        "--filter-set", "num_steps=2"]


def _rows(out):
    result = json.loads((out / "closed_loop.json").read_text())
    return result, {r["method"]: r for r in result["rows"]}


def test_trains_each_method_evaluates_and_resumes(tmp_path, capsys):
    out = tmp_path / "b"
    assert main([*TINY, "--train-iterations", "1", "--output", str(out)]) == 0
    result, rows = _rows(out)
    assert result["methods"] == ["sir", "escort", "random"]
    for m in ("sir", "escort"):
        r = rows[m]
        assert r["failed"] is None and r["policy"] == "trained"
        assert r["train"]["iterations"] == 1 and r["train"]["frames"] == 2 * 5 and r["train"]["resumed_from_iteration"] == 0
        assert (out / "runs" / "lightdark10d" / m / "checkpoints").is_dir()
        s = r["summary"]
        assert s["episodes"] == 3 and math.isfinite(s["final_position_error"]) and s["final_position_error"] >= 0
        assert len(r["error_over_time"]) == 5 and len(r["per_episode"]["episode_return"]) == 3
        assert r["seconds_per_step"] > 0
    assert rows["random"]["train"] is None and rows["random"]["filter"] == "sir"
    md = (out / "closed_loop.md").read_text()
    assert "## Final position error" in md and "| random policy (sir belief) |" in md and "| escort |" in md
    assert (out / "closed_loop_error_lightdark10d.png").stat().st_size > 0

    # a longer budget resumes from the last checkpoint; the same budget again trains nothing
    assert main([*TINY, "--train-iterations", "2", "--output", str(out)]) == 0
    _, rows = _rows(out)
    assert rows["escort"]["train"]["resumed_from_iteration"] == 1 and rows["escort"]["train"]["iterations"] == 2
    assert not rows["escort"]["evaluation_reused"]  # a new checkpoint: evaluated again
    assert main([*TINY, "--train-iterations", "2", "--output", str(out)]) == 0
    _, again = _rows(out)
    assert again["escort"]["train"]["resumed_from_iteration"] == 2
    assert again["escort"]["evaluation_reused"] and again["random"]["evaluation_reused"]
    assert again["escort"]["train"]["frames"] == rows["escort"]["train"]["frames"] == 2 * 2 * 5
    # evaluation is seeded: the same checkpoint gives the same episodes
    assert again["escort"]["per_episode"] == rows["escort"]["per_episode"]
    capsys.readouterr()

    # a run folder holding another configuration is refused, naming the flag
    assert main([*TINY, "--train-iterations", "2", "--particles", "12", "--output", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--output" in err and "another configuration" in err


def test_every_domain_has_a_budget_and_builds():
    settings = cl.load_settings()
    for d in DEFAULT_DOMAINS:
        assert settings["train"][d]["iterations"] >= 1
        cfg = cl.run_config(d, "escort", 7, "unused", settings["train"][d],
                            (("num_steps", "3"), ("lambda_corr", "0.5")), steps=4)
        assert cfg.env.name == d and cfg.num_particles == 7 and cfg.env.max_steps == 4
        assert cfg.filter.num_steps == 3 and cfg.filter.lambda_corr == 0.5
        assert cfg.trainer.iterations == settings["train"][d]["iterations"]
    # a key the method's filter lacks is not applied (SIR has no num_steps)
    cfg = cl.run_config("lightdark10d", "sir", 7, "unused", {}, (("num_steps", "3"),))
    assert "num_steps" not in cfg.filter


def test_training_flags_belong_to_protocol_b(tmp_path, capsys):
    assert main(["bench", "domains", "--train-iterations", "2", "--output", str(tmp_path)]) == 2
    assert "--protocol b" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--particles"):
        cl.run_closed_loop(["lightdark10d"], ["sir"], tmp_path, n=0)


def test_planner_rows_plan_on_their_filters_belief(tmp_path):
    result = cl.run_closed_loop(["lightdark10d"], ["pomcpow_sir"], tmp_path, episodes=2, n=10, steps=2, threads=1)
    rows = {r["method"]: r for r in result["rows"]}
    r = rows["pomcpow_sir"]
    assert r["policy"] == "planner" and r["filter"] == "sir" and r["train"] is None and r["failed"] is None
    assert r["seconds_per_decision"] > 0 and r["summary"]["episodes"] == 2
    assert not (tmp_path / "runs" / "lightdark10d" / "pomcpow_sir" / "checkpoints").exists()  # nothing trained
    assert "| POMCPOW (sir belief) |" in cl.closed_loop_markdown(result) and "ms per decision" in \
        cl.closed_loop_markdown(result)
    with pytest.raises(ValueError, match="--methods"):
        cl.run_closed_loop(["lightdark10d"], ["pomcpow_nowhere"], tmp_path)


def test_a_rerun_reuses_finished_evaluations_only_when_nothing_changed(tmp_path, monkeypatch):
    kwargs = dict(n=10, steps=2, threads=1)
    first = cl.run_closed_loop(["lightdark10d"], ["pomcpow_sir"], tmp_path, episodes=2, **kwargs)
    assert [r["evaluation_reused"] for r in first["rows"]] == [False, False]

    def must_not_run(*args, **kw):
        raise AssertionError("a saved evaluation should have been reused")

    monkeypatch.setattr(cl, "evaluate_run", must_not_run)
    again = cl.run_closed_loop(["lightdark10d"], ["pomcpow_sir"], tmp_path, episodes=2, **kwargs)
    assert [r["evaluation_reused"] for r in again["rows"]] == [True, True]
    assert [r["per_episode"] for r in again["rows"]] == [r["per_episode"] for r in first["rows"]]
    monkeypatch.undo()

    # more episodes, or a changed planner setting, is a new evaluation
    more = cl.run_closed_loop(["lightdark10d"], ["pomcpow_sir"], tmp_path, episodes=3, **kwargs)
    assert [r["evaluation_reused"] for r in more["rows"]] == [False, False]
    saved = tmp_path / "runs" / "lightdark10d" / "pomcpow_sir" / cl.EVALUATION_FILE
    (saved).write_text("{not json")  # a torn file is ignored, not an error
    torn = cl.run_closed_loop(["lightdark10d"], ["pomcpow_sir"], tmp_path, episodes=3, **kwargs)
    assert not torn["rows"][0]["evaluation_reused"] and torn["rows"][1]["evaluation_reused"]


def test_dvrl_row_trains_its_own_belief_and_reports_the_readout_error(tmp_path):
    result = cl.run_closed_loop(["lightdark10d"], ["dvrl"], tmp_path, episodes=2, n=10, steps=6, threads=1,
                                train_overrides={"iterations": 1, "num_envs": 2})
    rows = {r["method"]: r for r in result["rows"]}
    r = rows["dvrl"]
    assert r["policy"] == "learned" and r["failed"] is None and r["train"]["frames"] == 2 * 6
    assert math.isfinite(r["summary"]["final_position_error"]) and len(r["error_over_time"]) == 6
    cfg_text = (tmp_path / "runs" / "lightdark10d" / "dvrl" / "config.yaml").read_text()
    assert "algorithm: dvrl_a2c" in cfg_text
    assert "| DVRL (learned belief, readout) |" in cl.closed_loop_markdown(result)
