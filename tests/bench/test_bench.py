"""Smoke runs of the benchmark commands (their --quick modes) and the cost helpers."""

import json
import math

import pytest
import torch

from escort_rl.bench.cost import arithmetic_bound_seconds, fit_exponent, update_flops
from escort_rl.cli import main


def test_fit_exponent_recovers_a_power_law():
    ds = [10, 20, 50, 100]
    assert abs(fit_exponent(ds, [3.0 * d**1.7 for d in ds]) - 1.7) < 1e-9


def test_update_flops_formula():
    assert update_flops(100, 10, 50, 1, corr=False, prior=False) == 50 * 6 * 100 * 100 * 10
    assert update_flops(100, 10, 50, 2, corr=True, prior=False) == 2 * 50 * (6 * 100 * 100 * 10 + 2 * 100 * 10 * 10)
    prior = 4 * 100 * 100 * 10 + 2 * 100 * 10 * 10
    assert update_flops(100, 10, 50, 1, corr=False) == 50 * (6 * 100 * 100 * 10 + prior)
    # 1 GFLOP at 200 GFLOP/s: 5 ms
    assert arithmetic_bound_seconds(1e9, 200.0) == 0.005


def test_bench_cost_quick(tmp_path, capsys):
    assert main(["bench", "cost", "--quick", "--repeats", "1", "--num-steps", "3", "--output", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "cost.json").read_text())
    assert {r["filter"] for r in result["rows"]} == {"escort", "svgd", "sir"}
    assert all(r["seconds"] > 0 for r in result["rows"])
    assert result["matmul_gflops"] > 0
    assert "ESCORT/SVGD" in (tmp_path / "cost.md").read_text()


def test_cost_benchmark_compiled_rows(tmp_path):
    """``filter.compile=true`` adds compiled ESCORT and SVGD rows and their table (one small shape)."""
    assert main(["bench", "cost", "filter.compile=true", "--dims", "4", "--particles", "20", "--batch-sizes", "1",
                 "--repeats", "1", "--num-steps", "2", "--output", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "cost.json").read_text())
    rows = {r["filter"]: r for r in result["rows"]}
    assert set(rows) == {"escort", "svgd", "sir", "escort_compiled", "svgd_compiled"}
    assert all(rows[k]["first_seconds"] > 0 for k in ("escort_compiled", "svgd_compiled"))  # timed apart
    assert "With `compile=True`" in (tmp_path / "cost.md").read_text()


def test_bench_synthetic_quick(tmp_path):
    assert main(["bench", "synthetic", "--quick", "--output", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "synthetic.json").read_text())
    methods = {r["method"] for r in result["rows"]}
    assert methods == {"escort", "escort_nocorr", "svgd", "sir", "dvrl", "oracle"}
    oracle = [r for r in result["rows"] if r["method"] == "oracle" and r["target"] == "gmm1d"][0]
    assert oracle["summary"]["mode_coverage"][0] == 1.0
    assert not math.isnan(oracle["summary"]["w1"][0])
    assert "| gmm2d | escort |" in (tmp_path / "synthetic.md").read_text()


def test_bench_scaling_quick(tmp_path):
    assert main(["bench", "scaling", "--quick", "--output", str(tmp_path)]) == 0
    text = (tmp_path / "scaling.md").read_text()
    assert "NoCorr gap" in text and "| 5 | block |" in text


def test_bench_throughput_quick(tmp_path, capsys):
    assert main(["bench", "throughput", "num_particles=10", "--collector-workers", "1", "--num-envs", "2",
                 "--steps", "5", "--batches", "1", "--output", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "throughput.json").read_text())["rows"]
    assert rows[0]["frames"] == 10 and rows[0]["frames_per_second"] > 0


def test_synthetic_bandwidth_scale_reaches_the_filters(tmp_path):
    """``--bandwidth-scale`` changes ESCORT's and SVGD's fits and is recorded in the output."""
    args = ["bench", "synthetic", "--quick", "--targets", "gmm2d", "--methods", "svgd", "--seeds", "1"]
    assert main([*args, "--output", str(tmp_path / "a")]) == 0
    assert main([*args, "--bandwidth-scale", "0.1", "--output", str(tmp_path / "b")]) == 0
    a = json.loads((tmp_path / "a" / "synthetic.json").read_text())
    b = json.loads((tmp_path / "b" / "synthetic.json").read_text())
    assert a["filter_kwargs"] == {} and b["filter_kwargs"] == {"bandwidth_scale": 0.1}
    assert a["rows"][0]["per_seed"]["sliced_w1"] != b["rows"][0]["per_seed"]["sliced_w1"]
    assert "`bandwidth_scale=0.1`" in (tmp_path / "b" / "synthetic.md").read_text()


def test_synthetic_specs_hold_the_defaults_and_name_a_bad_option():
    from escort_rl.bench.synthetic import ScalingSpec, SyntheticSpec
    from escort_rl.bench.synthetic.cli import spec_from_args
    from escort_rl.cli import _parser

    full, quick = SyntheticSpec(), SyntheticSpec.quick()
    assert (full.seeds, full.particles, full.num_steps, full.steps, full.init) == (30, 1000, 500, 10, "cloud")
    assert full.methods == ("escort", "escort_nocorr", "svgd", "sir", "dvrl", "oracle")
    assert (quick.targets, quick.seeds, quick.particles, quick.num_steps, quick.steps) == (
        ("gmm1d", "gmm2d", "gmm3d"), 2, 100, 30, 3)
    assert SyntheticSpec(protocol="tracking").num_steps == 50
    scaling = ScalingSpec.quick()
    assert (ScalingSpec().seeds, scaling.dims, scaling.structures, scaling.seeds) == (5, (1, 5), ("block",), 2)
    args = _parser().parse_args(["bench", "scaling", "--quick", "--dims", "3", "--steps", "7", "filter.num_steps=4"])
    spec = spec_from_args(args)  # explicit flags win over --quick
    assert spec.dims == (3,) and spec.steps == 7 and spec.seeds == 2 and spec.filter_arguments() == {"num_steps": 4}
    with pytest.raises(ValueError, match="--init: expected one of"):
        SyntheticSpec(init="prior")
    with pytest.raises(ValueError, match="--seeds: must be a positive int"):
        ScalingSpec(seeds=0)


@pytest.mark.parametrize("argv, name", [
    (["evaluate", "--checkpoint", "unused", "--episodes", "0"], "--episodes"),
    (["evaluate", "--checkpoint", "unused", "--episodes", "-3"], "--episodes"),
    (["bench", "cost", "--repeats", "0"], "--repeats"),
    (["bench", "cost", "--dims", "4", "-4"], "--dims"),
    (["bench", "throughput", "--collector-workers", "0"], "--collector-workers"),
    (["bench", "cost", "--batch-sizes", "0"], "--batch-sizes"),
])
def test_count_arguments_get_one_line_naming_them(argv, name, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {name}: must be a positive int") and "\n" not in err


def test_training_cost_rows_measure_every_filter(tmp_path, monkeypatch):
    """The training rows of ``bench cost``: one PPO run per filter and batch size (compile off here to
    keep the test short), frames/s over the iterations after the first, and the table with ratios to SIR."""
    from escort_rl.bench.cost import cost_markdown
    from escort_rl.bench.training_cost import TRAINING_FILTERS, training_cost_rows

    for name in ("svgd", "escort"):
        monkeypatch.setitem(TRAINING_FILTERS, name, [*TRAINING_FILTERS[name], "filter.compile=false"])
    result = training_cost_rows([2], tmp_path, max_steps=4, iterations=2, overrides=("num_particles=8",))
    rows = result["training"]
    assert [r["filter"] for r in rows] == list(TRAINING_FILTERS) and result["warmup"] is None
    assert all(r["B"] == 2 and r["frames"] == 2 * 4 and r["frames_per_second"] > 0 for r in rows)
    assert all(r["overrides"] == ["num_particles=8"] for r in rows)  # recorded with the row
    table = cost_markdown(result)
    assert "| 2 | sir |" in table and "| 1.000 |" in table and "| 2 | escort |" in table
    from escort_rl.bench.training_cost import training_throughput

    with pytest.raises(ValueError, match="filter: 'pf'"):
        training_throughput("pf", 2, tmp_path / "x")


def test_bench_adaptive_stop_reports_iterations_per_tolerance(tmp_path, capsys):
    assert main(["bench", "adaptive-stop", "--domains", "lightdark10d", "--tolerances", "0", "1e9", "--seeds", "2",
                 "--steps", "2", "--output", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "adaptive_stop.json").read_text())["rows"]
    by = {(r["domain"], r["tolerance"]): r for r in rows}
    assert by[("lightdark10d", 0.0)]["iterations"] == 50.0  # no stop: K
    assert by[("lightdark10d", 1e9)]["iterations"] == 5.0  # everything stops at the first check
    assert by[("calibration", 0.0)]["iterations"] == 50.0 and by[("calibration", 1e9)]["iterations"] == 5.0
    assert "| lightdark10d | 1e+09 | 5.0 |" in (tmp_path / "adaptive_stop.md").read_text()
    capsys.readouterr()
    assert main(["bench", "adaptive-stop", "--tolerances", "-1", "--output", str(tmp_path)]) == 2
    assert "--tolerances" in capsys.readouterr().err
    assert main(["bench", "adaptive-stop", "--domains", "atlantis", "--output", str(tmp_path)]) == 2
    assert "--domains" in capsys.readouterr().err


def test_bench_decisions_rows_share_episodes_and_report_what_the_controller_reads(tmp_path):
    from escort_rl.bench.decisions import paired_difference

    argv = ["bench", "decisions", "--rows", "sir", "--add-row", "eager", "filter=escort", "filter.num_steps=2",
            "filter.compile=false", "--episodes", "3", "--steps", "12", "--particles", "16",
            "--baseline", "eager", "--output", str(tmp_path)]
    assert main(argv) == 0
    result = json.loads((tmp_path / "decisions.json").read_text())
    assert [r["label"] for r in result["rows"]] == ["sir", "eager"]
    for r in result["rows"]:
        assert len(r["success"]) == len(r["agreement"]) == 3 and r["particles"] == 16
        assert all(0.0 <= a <= 1.0 for a in r["agreement"])
        assert all(s == 12 for s in r["steps"])  # no episode reaches the goal in 12 steps from the start box
        assert all(e > 0 for e in r["position_error"] + r["velocity_error"] + r["velocity_spread"])
        assert len(r["velocity_error_over_time"][0]) == 12
    assert result["rows"][1]["filter"] == "escort"
    assert (tmp_path / "velocity_error_over_time.png").stat().st_size > 0
    table = (tmp_path / "decisions.md").read_text()
    assert "| eager | 16 |" in table and "success − eager" in table
    assert paired_difference([1.0, 0.0, 1.0], [0.0, 0.0, 1.0]) == pytest.approx((1 / 3, 1 / 3))


def test_bench_decisions_true_state_row_says_where_the_steps_go(tmp_path):
    """``--true-state``: the rule on the simulator's state beside the belief rows, on the same episodes. It agrees
    with itself at every step (the agreement compares at the row's own gain), and an episode's steps split into
    the steps to come near the goal and the steps from there."""
    from escort_rl.bench.decisions import TRUE_STATE_ROW

    argv = ["bench", "decisions", "--rows", "sir", "--true-state", "env.model.goal=1.0", "env.scripted_gain=0.25",
            "--episodes", "6", "--steps", "60", "--particles", "16", "--output", str(tmp_path)]
    assert main(argv) == 0
    rows = json.loads((tmp_path / "decisions.json").read_text())["rows"]
    assert [r["label"] for r in rows] == ["sir", TRUE_STATE_ROW]
    belief, state = rows
    assert state["on_true_state"] and not belief["on_true_state"]
    assert state["agreement"] == [1.0] * 6
    assert any(s == 1.0 for s in state["success"])  # the goal lies beside the start box: some episodes arrive
    for r in rows:
        for steps, near, rest, arrived in zip(r["steps"], r["steps_to_near"], r["steps_near_to_goal"], r["success"]):
            assert 1 <= near <= steps
            assert (rest == steps - near) if arrived else math.isnan(rest)
    assert "steps near → goal" in (tmp_path / "decisions.md").read_text()


@pytest.mark.parametrize("rows, message", [(["--rows", "nonsense"], "--rows: unknown row 'nonsense'"),
                                           (["--add-row", "label"], "--add-row: 'label' needs overrides"),
                                           (["--add-row", "filter=sir"], "--add-row: give a label first"),
                                           (["--add-row", "x", "filter.no_such_key=1"], "no_such_key")])
def test_bench_decisions_bad_rows_get_one_line(rows, message, tmp_path, capsys):
    assert main(["bench", "decisions", *rows, "--output", str(tmp_path)]) != 0
    assert message in capsys.readouterr().err


def test_bench_decisions_baseline_must_be_a_row(tmp_path, capsys):
    assert main(["bench", "decisions", "--rows", "sir", "--baseline", "svgd", "--output", str(tmp_path)]) != 0
    assert "--baseline: 'svgd' is not one of the rows (sir)" in capsys.readouterr().err


def test_bench_decisions_cell_changes_with_the_composed_config():
    """A row is named by its overrides, but its stored result belongs to the config they compose to."""
    from escort_rl.bench.decisions import DecisionCell

    def cell(*overrides):
        return DecisionCell(label="x", domain="lightdark10d", overrides=overrides, particles=20, episodes=2, seed=0)

    assert cell("filter=escort").spec() == cell("filter=escort").spec()
    assert cell("filter=escort").spec() != cell("filter=escort", "filter.prior=shrunk").spec()
    assert cell("filter=escort").spec()["config"]["filter"]["prior"] == "smoothed"


def test_synthetic_filter_set_types_and_checks_the_arguments():
    from escort_rl.bench.synthetic import filter_arguments

    assert filter_arguments(["filter.anneal_cycles=2", "filter.bandwidth_start=4", "filter.compile=true"]) == {
        "anneal_cycles": 2, "bandwidth_start": 4, "compile": True}
    with pytest.raises(ValueError, match="overrides: ESCORT has no argument 'bandwith_start'"):
        filter_arguments(["filter.bandwith_start=4"])
    with pytest.raises(ValueError, match="ESCORTFilter.anneal_fraction: must be"):
        filter_arguments(["filter.anneal_fraction=2"])
    with pytest.raises(ValueError, match="is not a filter override filter.KEY=VALUE"):
        filter_arguments(["anneal_cycles=2"])


def test_resampled_start_puts_the_target_mass_on_each_mode():
    # a two-mode 1-D target with masses 0.8 / 0.2 at ±3, from a wide cloud: the resampled start holds
    # about 0.8 of its particles on the right, where the cloud itself holds about 0.5
    from escort_rl.bench.synthetic import initial_particles
    from escort_rl.bench.targets import GaussianMixture

    target = GaussianMixture([0.2, 0.8], [[-3.0], [3.0]], [[[0.25]], [[0.25]]])
    initial = GaussianMixture([1.0], [[0.0]], [[[16.0]]])
    g = torch.Generator().manual_seed(0)
    x0 = initial.sample(4000, g).float()[None].expand(8, -1, -1).contiguous()
    x = initial_particles(x0, target, initial, "resampled", torch.Generator().manual_seed(1))
    right = (x[..., 0] > 0).float().mean(-1)
    # binomial s.e. of one set is 0.0063; 8 sets: every one within 5 s.e. of 0.8
    assert ((right - 0.8).abs() < 0.035).all(), right
    assert x.unique().numel() > 0.9 * x.numel()  # the kernel separated the copies
    assert torch.equal(initial_particles(x0, target, initial, "cloud", g), x0)
    with pytest.raises(ValueError, match="init: expected one of cloud, overlap, resampled"):
        initial_particles(x0, target, initial, "prior", g)


def test_init_scale_widens_the_initial_cloud(tmp_path):
    from escort_rl.bench.synthetic import scaled
    from escort_rl.bench.targets import initial_distribution

    q = initial_distribution("gmm2d")
    assert torch.allclose(scaled(q, 2.0).covariances, 4.0 * q.covariances)
    with pytest.raises(ValueError, match="init_scale: expected a positive finite number"):
        scaled(q, 0.0)
    args = ["bench", "synthetic", "--quick", "--targets", "gmm2d", "--methods", "svgd", "--seeds", "1"]
    assert main([*args, "--output", str(tmp_path / "a")]) == 0
    assert main([*args, "--init", "resampled", "--init-scale", "2", "--output", str(tmp_path / "b")]) == 0
    a = json.loads((tmp_path / "a" / "synthetic.json").read_text())
    b = json.loads((tmp_path / "b" / "synthetic.json").read_text())
    assert b["init"] == "resampled" and b["init_scale"] == 2.0
    assert a["rows"][0]["per_seed"]["sliced_w1"] != b["rows"][0]["per_seed"]["sliced_w1"]
    md = (tmp_path / "b" / "synthetic.md").read_text()
    assert "`init_scale=2.0`" in md and "importance-resampled to the target" in md


def test_bench_scaling_takes_methods_and_the_tracking_protocol(tmp_path, capsys):
    args = ["bench", "scaling", "--quick", "--output"]  # --quick: d = 1 and 5
    assert main([*args, str(tmp_path / "s"), "--methods", "escort", "sir", "--init", "overlap"]) == 0
    s = json.loads((tmp_path / "s" / "scaling.json").read_text())
    assert [r["method"] for r in s["rows"]] == ["escort", "sir"] * 2 and s["init"] == "overlap"
    assert "mean_ess_fraction" in s["rows"][2]["importance"] and "ess_fraction" in s["rows"][3]["importance"]
    assert (tmp_path / "s" / "rmse_paper.md").read_text().count("| 5 |") == 1
    assert main([*args, str(tmp_path / "t"), "--protocol", "tracking", "--methods", "escort_nocorr", "sir"]) == 0
    t = json.loads((tmp_path / "t" / "scaling.json").read_text())
    assert t["protocol"] == "tracking" and sorted(t["rows"][0]["per_seed"]) == ["final_error", "rmse"]
    capsys.readouterr()
    assert main([*args, str(tmp_path / "u"), "--protocol", "tracking", "--methods", "oracle"]) == 2
    assert "--methods: unknown name 'oracle'" in capsys.readouterr().err


def test_lambda_overrides_reach_escort_and_leave_the_ablations_alone():
    from escort_rl.bench.methods import applied_filter_set
    from escort_rl.bench.synthetic import row_filter

    kw = {"lambda_corr": 0.3, "lambda_temp": 0.2, "num_steps": 4}
    assert row_filter("escort", kw).lambda_corr == 0.3
    nocorr = row_filter("escort_nocorr", kw)
    assert (nocorr.lambda_corr, nocorr.lambda_temp, nocorr.num_steps) == (0.0, 0.2, 4)
    svgd = row_filter("svgd", kw)
    assert (svgd.lambda_corr, svgd.lambda_temp, svgd.num_steps) == (0.0, 0.0, 4)
    sweep = (("lambda_corr", "0.3"), ("projection", "random"))
    assert applied_filter_set("escort", sweep) == {"lambda_corr": "0.3", "projection": "random"}
    assert applied_filter_set("escort_nocorr", sweep) == {"projection": "random"}
    assert applied_filter_set("escort_noproj", sweep) == {"lambda_corr": "0.3"}
    assert applied_filter_set("svgd", sweep) == {}


def test_tracking_model_scores_match_autograd(per_test_generator):
    from escort_rl.bench.synthetic.tracking import GMMTracking
    from escort_rl.bench.targets import load_target
    from escort_rl.models.protocol import check_model

    model = GMMTracking(load_target("gmm3d"))
    check_model(model)
    torch.testing.assert_close(model.noise.mean(), torch.zeros(3, dtype=torch.float64), atol=1e-12, rtol=0)
    s = model.initial_state((5,), per_test_generator).to(torch.float64)
    o = model.observe(s, None, per_test_generator)
    x = (s + torch.randn(5, 3, generator=per_test_generator, dtype=torch.float64)).requires_grad_(True)
    (grad,) = torch.autograd.grad(model.observation_log_prob(o, x, None).sum(), x)
    torch.testing.assert_close(model.observation_score(o, x.detach(), None), grad)


def test_bench_ablation_pairs_rows_across_runs(tmp_path):
    args = ["bench", "synthetic", "--quick", "--targets", "gmm2d", "--seeds", "3"]
    assert main([*args, "--methods", "escort", "escort_nocorr", "--output", str(tmp_path / "a")]) == 0
    assert main([*args, "filter.lambda_corr=0.3", "--methods", "escort", "--output", str(tmp_path / "b")]) == 0
    out = tmp_path / "ablation"
    assert main(["bench", "ablation", f"nocorr={tmp_path / 'a'}:escort_nocorr", f"l0.1={tmp_path / 'a'}",
                 f"l0.3={tmp_path / 'b'}", "--metric", "sliced_w1", "--output", str(out)]) == 0
    md = (out / "ablation.md").read_text()
    assert "| row | nocorr | l0.1 | vs nocorr | l0.3 | vs nocorr |" in md and md.count("| gmm2d |") == 1
    from escort_rl.bench.ablation import parse_run

    assert parse_run("x=1=dir/y:svgd") == ("x=1", "dir/y", "svgd") and parse_run("dir")[2] == "escort"


def test_bench_profile_quick(tmp_path):
    """``bench profile --quick``: the update's parts inside a rollout, the profiled split and the bound."""
    assert main(["bench", "profile", "--quick", "--output", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "profile.json").read_text())
    assert result["filter"] == "escort_train" and result["B"] == 4
    assert {"iterations", "predict", "checks"} <= set(result["parts_seconds"])
    assert 0 < result["update_seconds"] < result["step_seconds"]
    assert result["profiled_update_seconds"] > 0  # the filter::<class>.update scopes were found
    assert abs(sum(result["profiled_categories_seconds"].values()) - result["profiled_update_seconds"]) < 1e-6
    assert result["host_syncs_per_update"] >= 1  # at least the finiteness guard's
    assert result["graphs_compiled_while_profiling"] == 0  # no recompiles after the warm-up
    assert result["bound_seconds"] > 0
    assert "its bound" in (tmp_path / "profile.md").read_text()
