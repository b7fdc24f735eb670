"""The frontier (escort_rl.bench.frontier): the Pareto selection on a hand-made table, and the command
on the linear-Gaussian family and on a user's own model class that imports nothing from escort_rl."""

import json
import math

import pytest
import torch

from conftest import DRIFT_MODEL_SOURCE
from escort_rl.bench.frontier import best_at_budgets, pareto_front
from escort_rl.cli import main

USER_MODEL = DRIFT_MODEL_SOURCE


def test_pareto_front_and_budgets_on_a_hand_made_table():
    pts = [("sir 100", 1.0, 0.50), ("sir 1000", 3.0, 0.20), ("enkf 100", 0.5, 0.60),
           ("escort", 10.0, 0.25),  # dominated by sir 1000: slower and worse
           ("enkf 1000", 3.0, 0.20),  # ties sir 1000 exactly: both on the front
           ("svgd", 20.0, 0.05), ("bad", math.nan, 0.01)]
    assert [p[0] for p in pareto_front(pts)] == ["enkf 100", "sir 100", "sir 1000", "enkf 1000", "svgd"]
    best = best_at_budgets(pts, [0.1, 0.5, 2.0, 5.0, 100.0])
    assert best[0] is None and best[1][0] == "enkf 100" and best[2][0] == "sir 100"
    assert best[3][2] == 0.20 and best[4][0] == "svgd"


def test_bench_frontier_on_the_linear_gaussian_family(tmp_path):
    out = tmp_path / "lg"
    argv = ["bench", "frontier", "env=linear_gaussian", "env.model.state_dim=3", "env.model.obs_std=0.2",
            "--quick", "--sir-particles", "50", "200", "--enkf-particles", "50", "--escort-particles", "20",
            "--svgd-particles", "20", "--num-steps", "3", "--steps", "3", "--output", str(out)]
    assert main(argv) == 0
    result = json.loads((out / "frontier.json").read_text())
    assert result["reference"] == "exact" and result["state_dim"] == 3
    assert {r["method"] for r in result["rows"]} == {"sir", "enkf", "svgd", "escort"}
    assert result["front"] and all(r["ms_per_update"] > 0 for r in result["rows"])
    text = (out / "frontier.md").read_text()
    assert (out / "frontier.png").exists() and "per update, use" in text
    # the advice ends with the command that trains on the filter it names, and that command composes
    command = text.split("Train on it: `")[1].split("`")[0]
    assert command.startswith("escort-rl train env=linear_gaussian env.model.state_dim=3 env.model.obs_std=0.2 filter=")
    from escort_rl.config import compose

    cfg = compose(command.split()[2:])
    assert cfg.env.model.state_dim == 3 and cfg.filter.name in {"sir", "enkf", "svgd", "escort"}
    assert main(argv) == 0  # a rerun loads every cell


def test_a_degenerate_reference_gives_no_advice():
    from escort_rl.bench.frontier.report import advice

    result = {"reference_ess": {"median": 1.0, "min": 1.0, "fraction": 0.0005}, "budgets": [], "rows": [],
              "metric": "w1"}
    assert advice(result).startswith("No advice: the reference kept a median ESS of 1 particles")
    assert "--reference-filter resample_move" in advice(result)


def test_the_reference_error_is_zero_against_itself_and_positive_between_independent_runs():
    from escort_rl.bench.frontier.run import reference_error
    from escort_rl.bench.trajectories import generate_trajectories
    from escort_rl.metrics.reference import Reference, reference_posterior
    from escort_rl.models import LightDark10D

    model = LightDark10D()
    traj = generate_trajectories(model, 3, [0, 1], 0)
    first, again, second = (Reference(reference_posterior(model, traj, [0, 1], 400, replicate=r, name="ld"))
                            for r in (0, 0, 1))
    same, other = reference_error(first, again, 3, "position"), reference_error(first, second, 3, "position")
    assert same["mean"][0] == 0 and same["w1"][0] == 0  # the same draws: no distance
    assert other["mean"][0] > 0 and other["w1"][0] > 0


def test_the_advice_names_the_rows_the_reference_cannot_rank_below_its_pick():
    from escort_rl.bench.frontier.report import advice

    row = {"method": "sir", "base": "sir", "particles": 100, "num_steps": 0, "settings": []}
    result = {"model": "env:linear_gaussian", "model_args": [], "compile": False, "metric": "w1", "rows": [
        {**row, "error": 0.1}], "budgets": [{"ms": 10.0, "best": "sir N=100", "error": 0.1,
                                             "not_separated": ["enkf N=100"]}]}
    assert "The reference cannot rank it above enkf N=100 (within its own error of it)." in advice(result)


def test_a_variant_is_a_row_of_its_own_and_leaves_the_filters_cells_alone(tmp_path, capsys):
    from escort_rl.bench.frontier.cells import FrontierCell, parse_variant

    assert parse_variant(["enkf_loc", "filter=enkf", "filter.localisation_radius=2", "filter.inflation=1.1"]) == (
        "enkf_loc", "enkf", ("localisation_radius=2", "inflation=1.1"))
    for bad in (["x", "filter=escort"], ["x", "filter=nope", "filter.a=1"],
                ["sir", "filter=sir", "filter.roughening=0.1"], ["1x", "filter=sir", "filter.roughening=0.1"],
                ["x", "filter=sir", "filter.roughening"],
                ["x", "filter.roughening=0.1"], ["x", "filter=sir", "filter=enkf", "filter.roughening=0.1"],
                ["x", "filter=sir", "roughening=0.1"]):
        try:
            parse_variant(bad)
        except ValueError as err:
            assert "--variant" in str(err)
        else:
            raise AssertionError(f"{bad!r} was accepted")
    with pytest.raises(ValueError, match=r"--variant: the name 'escort_eps0.05' must be a letter, then letters"):
        parse_variant(["escort_eps0.05", "filter=escort", "filter.step_size=0.05"])
    # a filter's own row keeps its spec: the cells saved before variants existed are still found
    own = FrontierCell(model="env:linear_gaussian", method="sir", particles=10, seeds=(0,), steps=1)
    assert "variant" not in own.spec() and "filter_args" not in own.spec()
    out = tmp_path / "v"
    argv = ["bench", "frontier", "env=linear_gaussian", "env.model.state_dim=3", "--quick", "--methods", "enkf",
            "--enkf-particles", "40", "--steps", "3", "--variant", "enkf_loc", "filter=enkf",
            "filter.localisation_radius=1", "--output", str(out)]
    assert main(argv) == 0
    rows = json.loads((out / "frontier.json").read_text())["rows"]
    assert [(r["method"], r["base"], r["settings"]) for r in rows] == [
        ("enkf", "enkf", []), ("enkf_loc", "enkf", ["localisation_radius=1"])]
    assert rows[0]["per_seed"] != rows[1]["per_seed"]  # the taper changed the belief
    capsys.readouterr()
    assert main(argv[:-6] + ["--variant", "x", "filter=enkf", "filter.no_such_key=1", "--output", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --variant: EnKFFilter") and "no_such_key" in err


def test_a_resample_move_reference_agrees_with_itself_where_sir_s_does_not():
    # A sharp observation of every coordinate (obs_std 0.05): each SIR step keeps a few of its 1,000 particles,
    # so two independent SIR references differ by 0.16 in sliced W1; two resample-move references by 0.005.
    from escort_rl.bench.frontier.run import reference_error
    from escort_rl.bench.trajectories import generate_trajectories
    from escort_rl.metrics.reference import Reference, reference_posterior
    from escort_rl.models import LinearGaussian

    model = LinearGaussian(state_dim=4, obs_dim=4, obs_std=0.05)
    traj = generate_trajectories(model, 3, [0, 1, 2, 3], 0)
    errors = {}
    for method in ("sir", "resample_move"):
        first, second = (Reference(reference_posterior(model, traj, [0, 1, 2, 3], 1000, replicate=r, name="lg",
                                                       method=method)) for r in (0, 1))
        errors[method] = reference_error(first, second, 3, "position")["w1"][0]
    assert errors["resample_move"] < errors["sir"] / 5, errors
    # its report reads the weights its stages resampled (at least ess_target = 0.5 of N, up to the
    # bisection's precision), not SIR's untempered ESS, which this sharp likelihood drives to a few particles
    data = reference_posterior(model, traj, [0, 1, 2, 3], 1000, name="lg", method="resample_move")
    assert float(data["ess_fraction_of_stages"].min()) >= 0.5 - 1e-3
    assert float(data["ess_fraction_before_resampling"].median()) < 0.05
    with pytest.raises(ValueError, match=r"^--reference-filter: unknown reference filter 'mcmc'"):
        reference_posterior(model, traj, [0], 10, method="mcmc")


def test_bench_frontier_on_a_users_own_model_class(tmp_path, monkeypatch, capsys):
    (tmp_path / "my_models.py").write_text(USER_MODEL)
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "mine"
    argv = ["bench", "frontier", "--model", "my_models:Drift", "--model-arg", "obs_std=0.3", "--quick",
            "--methods", "sir", "enkf", "--sir-particles", "30", "100", "--enkf-particles", "30",
            "--reference-particles", "500", "--steps", "3", "--output", str(out)]
    assert main(argv) == 0
    result = json.loads((out / "frontier.json").read_text())
    assert result["reference"] == "SIR with 500 particles" and result["model_name"] == "Drift"
    assert len(result["rows"]) == 3 and len(list((out / "reference").rglob("*.pt"))) == 2  # two independent runs
    error = result["reference_error"]  # the distance between them: the reference's own error
    assert set(error) == {"w1", "mean", "cov", "mmd2"} and error["w1"][0] > 0 and math.isfinite(error["w1"][1])
    assert all("not_separated" in b for b in result["budgets"])
    assert "The reference's own error, measured" in (out / "frontier.md").read_text()
    assert main([*argv, "--reference-filter", "resample_move", "--output", str(tmp_path / "rm")]) == 0
    tempered = json.loads((tmp_path / "rm" / "frontier.json").read_text())
    assert tempered["reference"] == "resample-move SMC (tempered, with MCMC moves) with 500 particles"
    assert tempered["reference_ess"]["stages"] and tempered["reference_ess"]["fraction"] >= 0.5 - 1e-3
    assert "(the smallest of its tempering stages'): median" in (tmp_path / "rm" / "frontier.md").read_text()
    capsys.readouterr()
    assert main(["bench", "frontier", "--model", "my_models:Nope", "--quick", "--output", str(out)]) == 2
    assert "--model: cannot import my_models:Nope" in capsys.readouterr().err
    assert main(["bench", "frontier", "env=linear_gaussian", "--model", "my_models:Drift", "--output", str(out)]) == 2


def test_bench_regime_map_runs_a_frontier_per_point(tmp_path):
    out = tmp_path / "map"
    argv = ["bench", "regime-map", "--dims", "2", "3", "--obs-std", "0.2", "--methods", "sir", "enkf", "escort",
            "--sir-particles", "40", "--enkf-particles", "40", "--escort-particles", "16", "--num-steps", "2",
            "--seeds", "2", "--steps", "2", "--output", str(out)]
    assert main(argv) == 0
    result = json.loads((out / "regime_map.json").read_text())
    assert [(p["dim"], p["obs_std"]) for p in result["points"]] == [(2, 0.2), (3, 0.2)]
    md = (out / "regime_map.md").read_text()
    assert "front at:" in md and md.count("| 0.2 |") == 2
    assert (out / "D2_obs0.2" / "cells").is_dir() and (out / "D2_obs0.2" / "frontier.md").exists()
    assert (out / "regime_map.png").exists()


def test_frontier_decisions_pairs_the_episodes_and_names_bad_rows(tmp_path, capsys):
    """The greedy regulator on a controlled tracking model: rows meet the same starts and noise, so a
    row run twice gives the same returns, and the exact posterior's row runs beside the filters."""
    from escort_rl.bench.frontier.decisions import greedy_action, run_decisions
    from escort_rl.bench.frontier.spec import DecisionsSpec, parse_row
    from escort_rl.bench.synthetic.tracking import gmm_tracking

    model = gmm_tracking(dim=2, control=1.0)
    assert model.n_actions == 5
    mean = torch.tensor([[3.0, 0.2], [-0.1, -2.0], [0.1, 0.1]])
    assert greedy_action(model, mean).tolist() == [2, 3, 0]  # -x, +y, stay
    assert parse_row("escort:100:15") == ("escort", 100, 15) and parse_row("exact") == ("exact", 0, 0)
    for bad in ("sir", "sir:x", "escort:100", "sir:10:3", "nope:10"):
        with pytest.raises(ValueError, match="--rows"):
            parse_row(bad)
    spec = "class:escort_rl.bench.synthetic.tracking:gmm_tracking"
    args = ("dim=2", "control=1.0")
    r = run_decisions(DecisionsSpec(model=spec, model_args=args, rows=[("sir", 200, 0), ("exact", 0, 0),
                                                                       ("sir", 200, 0)], episodes=6, steps=4))
    first, exact, again = r["rows"]
    assert first["return"] == again["return"] and first["difference"][0] == 0.0
    assert exact["row"] == "exact posterior" and exact["mean_error"][0] > 0
    capsys.readouterr()
    assert main(["bench", "frontier-decisions", "--model", "escort_rl.bench.synthetic.tracking:gmm_tracking",
                 "--model-arg", "dim=2", "--rows", "sir:10", "--output", str(tmp_path)]) == 2
    assert "control=1" in capsys.readouterr().err


def test_escort_against_svgd_is_paired_by_seed():
    from escort_rl.bench.frontier.report import paired_lines

    def row(method, w1):
        return {"method": method, "particles": 10, "num_steps": 5, "failed": None,
                "per_seed": {f"s/{m}": list(w1) for m in ("w1", "mmd2", "mean", "cov")}}

    result = {"part": "s", "rows": [row("escort", [1.0, 2.0, 4.0]), row("svgd", [1.5, 2.5, 4.25]),
                                    row("sir", [9.0, 9.0, 9.0])]}
    lines = paired_lines(result)
    # differences -0.5, -0.5, -0.25: mean -0.4167, s.e. 0.0833 (the seeds' spread cancels in the pairing)
    assert lines[-1].startswith("| 10 | 5 | -0.4167 ± 0.0833")
    assert paired_lines({"part": "s", "rows": [row("sir", [1.0])]}) == []


def test_frontier_specs_hold_the_defaults_and_name_a_bad_option():
    from escort_rl.bench.frontier import DecisionsSpec, FrontierSpec, RegimeSpec
    from escort_rl.bench.frontier.cli import spec_from_args
    from escort_rl.cli import _parser

    full, quick = FrontierSpec(), FrontierSpec.quick()
    assert (full.seeds, full.steps, full.reference_particles, full.iterations) == (5, 20, 100_000, (5, 15, 50))
    assert (quick.seeds, quick.steps, quick.reference_particles, quick.iterations) == (2, 5, 2000, (5, 15))
    assert quick.particles["sir"] == (100, 1000, 10_000) and full.particles["escort"] == (30, 100, 300, 1000)
    args = _parser().parse_args(["bench", "frontier", "--quick", "--seeds", "5", "--sir-particles", "7"])
    spec = spec_from_args(args)  # explicit flags win over --quick
    assert spec.seeds == 5 and spec.steps == 5
    assert spec.particles["sir"] == (7,) and spec.particles["svgd"] == (50, 200)
    with pytest.raises(ValueError, match="--sir-particles: must be >= 1"):
        FrontierSpec(particles={"sir": (0,)})
    regime = RegimeSpec.quick()
    assert regime.dims == (2, 4) and regime.obs_stds == (1.0,) and regime.frontier == quick
    point = RegimeSpec(output="out").point(10, 0.1)
    assert point.model == "env:linear_gaussian" and point.model_args == ("model.state_dim=10", "model.obs_std=0.1")
    assert point.output.name == "D10_obs0.1" and point.seeds == full.seeds
    with pytest.raises(ValueError, match="--dims: must be a positive int"):
        RegimeSpec(dims=[0])
    rows = ["sir:10", "escort:20:3"]
    assert DecisionsSpec(model="class:m:M", rows=rows).rows == (("sir", 10, 0), ("escort", 20, 3))
    assert DecisionsSpec.quick(model="class:m:M", rows=rows).steps == 5
    assert DecisionsSpec(model="class:m:M", rows=rows).steps == 20
    with pytest.raises(ValueError, match="--rows"):
        DecisionsSpec(model="class:m:M", rows=["escort:20"])
