"""Protocol (b) of the domain benchmark: each method trains its own policy, then drives it."""

from __future__ import annotations

import json
import math

import pytest

from escort_rl.bench import domains as cl
from escort_rl.bench import methods as registry
from escort_rl.bench.domains import closed_loop_cells
from escort_rl.cli import main

TINY = ["bench", "domains", "--protocol", "b", "--domains", "lightdark10d", "--methods", "sir", "escort",
        "--seeds", "3", "--particles", "10", "--steps", "5", "--train-envs", "2", "--threads", "1",
        "filter.num_steps=2"]


def _spec(domains, methods, output, **settings):
    """A protocol (b) run of ``methods`` on ``domains`` into ``output``; unset settings are the defaults."""
    return cl.DomainsSpec.full("b", domains=domains, methods=methods, output=output, **settings)


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
        assert r["failed"] is None and r["policy"] == "trained" and r["trainer"] == "ppo"  # the yaml's trainer
        assert (r["train"]["iterations"] == 1 and r["train"]["frames"] == 2 * 5
                and r["train"]["resumed_from_iteration"] == 0)
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
    settings = registry.load_settings()
    for d in registry.DOMAINS:
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
        cl.run_closed_loop(_spec(["lightdark10d"], ["sir"], tmp_path, particles=0))


def test_planner_rows_plan_on_their_filters_belief(tmp_path):
    result = cl.run_closed_loop(_spec(["lightdark10d"], ["pomcpow_sir"], tmp_path,
                                      seeds=2, particles=10, steps=2, threads=1))
    rows = {r["method"]: r for r in result["rows"]}
    r = rows["pomcpow_sir"]
    assert r["policy"] == "planner" and r["filter"] == "sir" and r["train"] is None and r["failed"] is None
    assert r["seconds_per_decision"] > 0 and r["summary"]["episodes"] == 2
    assert not (tmp_path / "runs" / "lightdark10d" / "pomcpow_sir" / "checkpoints").exists()  # nothing trained
    assert "| POMCPOW (sir belief) |" in cl.closed_loop_markdown(result) and "ms per decision" in \
        cl.closed_loop_markdown(result)
    with pytest.raises(ValueError, match="--methods"):
        cl.run_closed_loop(_spec(["lightdark10d"], ["pomcpow_nowhere"], tmp_path))


def test_a_rerun_reuses_finished_evaluations_only_when_nothing_changed(tmp_path, monkeypatch):
    kwargs = dict(particles=10, steps=2, threads=1)
    first = cl.run_closed_loop(_spec(["lightdark10d"], ["pomcpow_sir"], tmp_path, seeds=2, **kwargs))
    assert [r["evaluation_reused"] for r in first["rows"]] == [False, False]

    def must_not_run(*args, **kw):
        raise AssertionError("a saved evaluation should have been reused")

    monkeypatch.setattr(closed_loop_cells, "evaluate_run", must_not_run)
    again = cl.run_closed_loop(_spec(["lightdark10d"], ["pomcpow_sir"], tmp_path, seeds=2, **kwargs))
    assert [r["evaluation_reused"] for r in again["rows"]] == [True, True]
    assert [r["per_episode"] for r in again["rows"]] == [r["per_episode"] for r in first["rows"]]
    monkeypatch.undo()

    # more episodes, or a changed planner setting, is a new evaluation
    more = cl.run_closed_loop(_spec(["lightdark10d"], ["pomcpow_sir"], tmp_path, seeds=3, **kwargs))
    assert [r["evaluation_reused"] for r in more["rows"]] == [False, False]
    saved = tmp_path / "runs" / "lightdark10d" / "pomcpow_sir" / cl.EVALUATION_FILE
    (saved).write_text("{not json")  # a torn file is ignored, not an error
    torn = cl.run_closed_loop(_spec(["lightdark10d"], ["pomcpow_sir"], tmp_path, seeds=3, **kwargs))
    assert not torn["rows"][0]["evaluation_reused"] and torn["rows"][1]["evaluation_reused"]


def test_dvrl_row_trains_its_own_belief_and_reports_the_readout_error(tmp_path):
    result = cl.run_closed_loop(_spec(["lightdark10d"], ["dvrl"], tmp_path,
                                      seeds=2, particles=10, steps=6, threads=1, train_iterations=1, train_envs=2))
    rows = {r["method"]: r for r in result["rows"]}
    r = rows["dvrl"]
    assert r["policy"] == "learned" and r["failed"] is None and r["train"]["frames"] == 2 * 6
    assert math.isfinite(r["summary"]["final_position_error"]) and len(r["error_over_time"]) == 6
    cfg_text = (tmp_path / "runs" / "lightdark10d" / "dvrl" / "config.yaml").read_text()
    assert "algorithm: dvrl_a2c" in cfg_text
    assert "| DVRL (learned belief, readout) |" in cl.closed_loop_markdown(result)


# ------------------------------------------------------------------------------ baseline rows
def test_the_registry_knows_every_row_and_the_defaults_include_the_baselines():
    settings = registry.load_settings()
    spec = {m: cl.method_spec(m, settings) for m in ("sir", "scripted_sir", "scripted_escort", "pomcpow_sir",
                                                     "dvrl", "recurrent_ppo", registry.RANDOM)}
    assert spec["sir"] == {"kind": "trained", "section": None, "filter": "sir", "trainer": "ppo"}
    assert spec["scripted_escort"]["kind"] == "scripted" and spec["scripted_escort"]["filter"] == "escort"
    assert spec["pomcpow_sir"]["kind"] == "planner"
    assert spec["dvrl"]["kind"] == spec["recurrent_ppo"]["kind"] == "learned"
    assert spec["recurrent_ppo"]["trainer"] == "recurrent_ppo" and spec["recurrent_ppo"]["section"] == "recurrent"
    defaults = registry.protocol_b_methods()
    assert {"scripted_sir", "scripted_escort", "recurrent_ppo", "dvrl", "pomcpow_sir", "sir"} <= set(defaults)
    assert len(set(defaults)) == len(defaults) and registry.RANDOM not in defaults
    # protocol (a)'s learned beliefs stay beliefs: the recurrent policy has none
    assert "recurrent_ppo" not in registry.learned_methods() and "dvrl" in registry.learned_methods()
    # the checks accept the new names and still refuse unknown ones
    with pytest.raises(ValueError, match="--methods: unknown method 'scripted_nowhere'"):
        cl.run_closed_loop(_spec(["lightdark10d"], ["scripted_nowhere"], "unused"))
    with pytest.raises(ValueError, match="'random' is always run"):
        cl.run_closed_loop(_spec(["lightdark10d"], ["scripted_sir", "random"], "unused"))
    with pytest.raises(ValueError, match="overrides: no method in --methods has the filter key 'num_steps'"):
        cl.run_closed_loop(_spec(["lightdark10d"], ["recurrent_ppo"], "unused", filter_set=(("num_steps", "2"),)))


def test_a_section_name_may_not_shadow_another_row(monkeypatch):
    settings = registry.load_settings()
    settings["scripted"] = {**settings["scripted"], "sir": {"filter": "sir"}}
    with pytest.raises(ValueError, match="'sir' in scripted is also a filter config"):
        registry.named_rows(settings)
    settings["scripted"] = {"dvrl": {"filter": "sir"}}
    with pytest.raises(ValueError, match="'dvrl' in learned is also the scripted section"):
        registry.named_rows(settings)


def test_filter_rows_use_the_yamls_trainer_with_whole_episode_batches(tmp_path, monkeypatch):
    settings = registry.load_settings()
    assert settings["trainer"] == "ppo"
    for d in registry.DOMAINS:  # the budget's frames keep their meaning: rollout_steps divides the episode
        cfg = cl.run_config(d, "sir", 7, "unused", settings["train"][d], trainer=settings["trainer"])
        assert cfg.trainer.algorithm == "ppo" and cfg.env.max_steps % cfg.trainer.rollout_steps == 0
        assert cfg.trainer.num_envs == settings["train"][d]["num_envs"]
        assert not cfg.trainer.warm_start_filter  # own belief
    assert [cl.batch_length(t, 125) for t in (500, 200, 100, 6, 127)] == [125, 100, 100, 6, 127]
    cfg = cl.run_config("lightdark10d", "sir", 7, "unused", {"num_envs": 2, "rollout_steps": 3}, steps=6,
                        trainer="ppo")
    assert cfg.trainer.rollout_steps == 3  # a budget that sets it wins
    cfg = cl.run_config("lightdark10d", "sir", 7, "unused", {"num_envs": 2}, steps=6, trainer="recurrent_ppo")
    assert cfg.trainer.minibatches == 2 and cfg.trainer.rollout_steps == 6  # minibatches are whole env rows

    # without the key: the config's default trainer (PPO)
    monkeypatch.setattr(registry, "load_settings", lambda: {k: v for k, v in settings.items() if k != "trainer"})
    result = cl.run_closed_loop(_spec(["lightdark10d"], ["sir"], tmp_path,
                                      seeds=2, particles=8, steps=6, threads=1, train_iterations=1, train_envs=2))
    assert result["trainer"] == "ppo" and result["trainers"] == {"sir": "ppo"}
    assert result["rows"][0]["trainer"] == "ppo" and result["rows"][0]["train"]["frames"] == 2 * 6
    assert "DeepSets policy (PPO)" in cl.closed_loop_markdown(result)


def test_a_bad_trainer_in_the_yaml_names_the_key(tmp_path, monkeypatch):
    from escort_rl.config import ConfigError

    bad = tmp_path / "closed_loop.yaml"
    bad.write_text(registry.settings_path().read_text().replace("trainer: ppo", "trainer: dvrl_a2c"))
    monkeypatch.setattr(registry, "settings_path", lambda: bad)
    with pytest.raises(ConfigError, match="trainer: must be one of ppo, reinforce; got 'dvrl_a2c'"):
        registry.load_settings()


def test_scripted_rows_train_nothing_and_do_not_apply_to_kidnapped_robot(tmp_path):
    result = cl.run_closed_loop(_spec(["lightdark10d", "kidnapped20d"], ["scripted_sir", "scripted_escort"], tmp_path,
                                      seeds=2, particles=8, steps=8, threads=1, filter_set=(("num_steps", "2"),)))
    rows = {(r["domain"], r["method"]): r for r in result["rows"]}
    for m, f in (("scripted_sir", "sir"), ("scripted_escort", "escort")):
        r = rows[("lightdark10d", m)]
        assert r["policy"] == "scripted" and r["filter"] == f and r["failed"] is None and r["train"] is None
        s = r["summary"]
        assert s["episodes"] == 2 and 0 <= s["success_rate"] <= 1 and math.isfinite(s["final_distance"])
        assert math.isfinite(s["final_position_error"]) and len(r["error_over_time"]) == 8
        assert not (tmp_path / "runs" / "lightdark10d" / m / "checkpoints").exists()  # nothing trained
        kr = rows[("kidnapped20d", m)]
        assert kr["failed"]["not_applicable"] and "summary" not in kr
        assert kr["failed"]["message"].startswith("not applicable: no scripted controller for KidnappedRobot20D")
    assert result["filter_set"]["scripted_escort"] == {"num_steps": "2"} and result["filter_set"]["scripted_sir"] == {}
    assert rows[("kidnapped20d", "random")]["failed"] is None  # the domain's other rows still run
    # nothing trained, so a rerun reuses the saved evaluation
    again = cl.run_closed_loop(_spec(["lightdark10d"], ["scripted_sir"], tmp_path,
                                     seeds=2, particles=8, steps=8, threads=1))
    assert again["rows"][0]["evaluation_reused"]
    md = cl.closed_loop_markdown(result)
    assert "| scripted PD (sir belief mean) | " in md and "| scripted PD (escort belief mean) | " in md
    assert "## Not applicable (n/a)" in md and "- scripted_sir on kidnapped20d: no scripted controller" in md
    assert "## Failed runs" not in md
    success = md.split("## Success rate")[1].split("##")[0]
    line = next(ln for ln in success.splitlines() if ln.startswith("| scripted PD (sir belief mean) |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert "±" in cells[1] and cells[2] == "n/a"


def test_recurrent_row_trains_a_gru_and_has_no_position_error(tmp_path):
    result = cl.run_closed_loop(_spec(["lightdark10d"], ["recurrent_ppo"], tmp_path,
                                      seeds=2, particles=8, steps=6, threads=1, train_iterations=1, train_envs=2))
    r = {row["method"]: row for row in result["rows"]}["recurrent_ppo"]
    assert r["policy"] == "learned" and r["trainer"] == "recurrent_ppo" and r["filter"] == "none"
    assert r["failed"] is None and r["train"]["frames"] == 2 * 6 and r["train"]["iterations"] == 1
    s = r["summary"]
    assert s["episodes"] == 2 and math.isfinite(s["episode_return"]) and 0 <= s["success_rate"] <= 1
    assert math.isnan(s["final_position_error"]) and all(math.isnan(e) for e in r["error_over_time"])
    cfg_text = (tmp_path / "runs" / "lightdark10d" / "recurrent_ppo" / "config.yaml").read_text()
    assert "algorithm: recurrent_ppo" in cfg_text
    assert result["recurrent"] == {"recurrent_ppo": {"trainer": "recurrent_ppo"}} and result["learned"] == {}
    md = cl.closed_loop_markdown(result)
    label = "| recurrent_ppo (GRU on observations, no belief) |"
    error = md.split("## Final position error")[1].split("##")[0]
    assert f"{label} — |" in error  # NaN prints as a dash
    assert label in md.split("## Return")[1] and "12 frames" in md.split("Training cost")[1]
    cl.plot_closed_loop_error(result, "lightdark10d", tmp_path / "error.png")  # a row without a curve is skipped
