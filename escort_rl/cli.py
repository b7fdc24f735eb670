"""The ``escort-rl`` command.

    escort-rl run [KEY=VALUE ...]        train, then evaluate (the default job)
    escort-rl train [KEY=VALUE ...]      train; resume with resume=RUN_DIR
    escort-rl evaluate --checkpoint PATH evaluate a checkpoint against a random policy
    escort-rl config [KEY=VALUE ...]     print the composed config
    escort-rl describe                   print the Light-Dark process-noise correlations
    escort-rl bench throughput           collector frames/s with the belief transform
    escort-rl bench cost                 time per belief update, ESCORT vs SVGD vs SIR
    escort-rl bench synthetic            the paper's GMM targets (Table 2 layout)
    escort-rl bench scaling              RMSE against dimension, ESCORT vs NoCorr vs SVGD
    escort-rl bench domains              the paper's domains, protocol (a) shared trajectories (Table 1)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

OVERRIDES_HELP = (
    "Hydra-style overrides, e.g. trainer.iterations=100 num_particles=200 filter=sir "
    "collector.workers=2 output_dir=outputs/mine resume=outputs/mine"
)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="escort-rl",
        description="ESCORT-RL: particle belief tracking for POMDPs and policies trained on those beliefs.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="train a policy, then evaluate it (the default job)",
                         description="Train with the given overrides, then evaluate the final checkpoint.")
    run.add_argument("overrides", nargs="*", help=OVERRIDES_HELP)
    train = sub.add_parser("train", help="train a DeepSets policy with REINFORCE on particle beliefs",
                           description="Train; a killed run continues with resume=RUN_DIR.")
    train.add_argument("overrides", nargs="*", help=OVERRIDES_HELP)
    train.add_argument("--quiet", action="store_true", help="no progress bar")
    ev = sub.add_parser("evaluate", help="evaluate a checkpoint against a uniform-random policy",
                        description="Writes summary.md, metrics.json and PNG plots.")
    ev.add_argument("--checkpoint", required=True, help="a run directory, its checkpoints/ folder or a checkpoint")
    ev.add_argument("--episodes", type=int, default=None, help="number of episodes (default: evaluate.episodes)")
    ev.add_argument("--output", default=None, help="output folder (default: RUN_DIR/evaluation)")
    ev.add_argument("--greedy", action=argparse.BooleanOptionalAction, default=None,
                    help="--greedy: the most probable action; --no-greedy: sample from the policy "
                    "(default: evaluate.greedy, true)")
    sub.add_parser("describe", help="print the Light-Dark 10D process-noise correlations (paper vs used)",
                   description="The paper's correlations are not PSD; this prints the nearest correlation "
                   "matrix that the model uses.")
    bench = sub.add_parser("bench", help="benchmarks", description="Benchmarks; each prints what it measured.")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    thr = bench_sub.add_parser("throughput", help="collector frames/s with the belief transform",
                               description="Env frames per second through Collector (1 worker) or "
                               "MultiSyncCollector (K workers), belief transform and DeepSets policy in the loop.")
    thr.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts to time")
    thr.add_argument("--num-envs", type=int, default=32, help="environments in all (B)")
    thr.add_argument("--steps", type=int, default=100, help="steps per env per batch")
    thr.add_argument("--batches", type=int, default=3, help="timed batches (after one warm-up batch)")
    thr.add_argument("--output", default=None, help="write the results as JSON here")
    thr.add_argument("overrides", nargs="*", help=OVERRIDES_HELP)
    cost = bench_sub.add_parser("cost", help="time one belief update: ESCORT vs SVGD vs SIR over d, N, B",
                                description="Times one update for d, N and B, ESCORT, SVGD and SIR in the same "
                                "run; reports the ESCORT breakdown, the fitted exponent in d and GFLOP/s.")
    cost.add_argument("--dims", type=int, nargs="+", default=[10, 20, 50, 100, 200])
    cost.add_argument("--particles", type=int, nargs="+", default=[100, 1000])
    cost.add_argument("--batches", type=int, nargs="+", default=[1, 32])
    cost.add_argument("--repeats", type=int, default=3)
    cost.add_argument("--num-steps", type=int, default=50, help="K for ESCORT and SVGD")
    cost.add_argument("--device", default="cpu")
    cost.add_argument("--quick", action="store_true", help="a small smoke grid: d 10 20, N 100, B 1 2")
    cost.add_argument("--compile", action="store_true",
                      help="also time ESCORT and SVGD with compile=True (each shape compiles once first)")
    cost.add_argument("--max-pairs", type=float, default=1e7,
                      help="skip (d, N, B) with B·N² above this (default 1e7 skips N=1000 at B=32 on a CPU)")
    cost.add_argument("--training", type=int, nargs="+", default=[], metavar="B",
                      help="also measure PPO training frames/s on SIR, SVGD and ESCORT beliefs at these batch sizes")
    cost.add_argument("--training-steps", type=int, default=100,
                      help="episode length of the training rows (3 iterations of B x this many frames)")
    cost.add_argument("--warmup", action="store_true",
                      help="also time the first compiled ESCORT update in fresh processes, cold and from the cache")
    cost.add_argument("--no-updates", action="store_true", help="skip the per-update grid (training/warm-up rows only)")
    cost.add_argument("--output", default="outputs/bench/cost", help="folder for cost.md and cost.json")
    syn = bench_sub.add_parser("synthetic", help="fit the paper's GMM targets: ESCORT, NoCorr, SVGD, SIR, oracle",
                               description="Static-target benchmark (paper Table 2 layout): MMD², W1, sliced W1, "
                               "mode coverage, correlation error and RMSE, mean ± s.e. over seeds.")
    syn.add_argument("--targets", nargs="+", default=["gmm1d", "gmm2d", "gmm3d", "gmm5d", "gmm20d"])
    syn.add_argument("--methods", nargs="+", default=["escort", "escort_nocorr", "svgd", "sir", "dvrl", "oracle"])
    syn.add_argument("--seeds", type=int, default=30)
    syn.add_argument("--particles", type=int, default=1000)
    syn.add_argument("--num-steps", type=int, default=500)
    syn.add_argument("--quick", action="store_true", help="smoke run: gmm1d, gmm2d, gmm3d, 2 seeds, N=100, 30 steps")
    syn.add_argument("--output", default="outputs/bench/synthetic")
    sca = bench_sub.add_parser("scaling", help="RMSE of ESCORT vs ESCORT-NoCorr vs SVGD on 5-mode GMMs, 1D-200D",
                               description="The paper's RMSE-vs-dimension table, with the NoCorr gap.")
    sca.add_argument("--dims", type=int, nargs="+", default=[1, 5, 20, 50, 100, 200])
    sca.add_argument("--structures", nargs="+", default=["block", "banded", "long_range", "sparse"])
    sca.add_argument("--seeds", type=int, default=5)
    sca.add_argument("--particles", type=int, default=1000)
    sca.add_argument("--num-steps", type=int, default=500)
    sca.add_argument("--quick", action="store_true", help="smoke run: d 1 5, block, 2 seeds, N=100, 30 steps")
    sca.add_argument("--output", default="outputs/bench/scaling")
    for p in (syn, sca):
        p.add_argument("--bandwidth-scale", type=float, default=1.0,
                       help="multiply ESCORT's and SVGD's median-heuristic bandwidth (default 1)")
        p.add_argument("--compile", action="store_true", help="ESCORT and SVGD with compile=True")
    dom = bench_sub.add_parser("domains", help="filters on Light-Dark, Kidnapped Robot, MTT: shared trajectories",
                               description="Protocol (a) of SPEC §6 (paper Table 1 layout): every method filters the "
                               "same seeded trajectories (uniform random actions) from the same seeded priors; "
                               "final and time-averaged position error (mean ± s.e. over seeds), ms per step, "
                               "and a table at equal wall-clock per step. Methods are filter config names.")
    dom.add_argument("--domains", nargs="+", default=None,
                     help="env configs (default: lightdark10d kidnapped20d mtt20d)")
    dom.add_argument("--methods", nargs="+", default=None, help="filter configs (default: escort escort_nocorr "
                     "escort_notemp escort_noproj svgd sir; protocol b adds the planner rows pomcpow_sir "
                     "pomcpow_escort, the scripted rows scripted_sir scripted_escort, the learned belief dvrl and the recurrent policy "
                     "recurrent_ppo), or dvrl (trained first in <output>/runs with protocol b's budget)")
    dom.add_argument("--seeds", type=int, default=None, help="seeds 0..S-1, run as one batch (default 30)")
    dom.add_argument("--particles", type=int, default=None, help="N for every method (default 100)")
    dom.add_argument("--steps", type=int, default=None, help="steps per trajectory (default: env.max_steps)")
    dom.add_argument("--workers", type=int, default=1, help="split the seeds over K processes (default 1)")
    dom.add_argument("--max-particles", type=int, default=None,
                     help="largest N' for the equal wall-clock table (default 2000)")
    dom.add_argument("--threads", type=int, default=None,
                     help="torch threads here and in each worker (default: torch's; small updates are often "
                     "fastest with 1)")
    dom.add_argument("--no-equal-time", action="store_true", help="skip the equal wall-clock table")
    dom.add_argument("--filter-set", nargs="+", default=None, metavar="KEY=VALUE",
                     help="set a filter key on every method that has it, e.g. num_steps=10 or compile=true")
    dom.add_argument("--quick", action="store_true",
                     help="smoke run (flags given explicitly win): all three domains, escort svgd sir, 2 seeds, "
                     "20 steps, N=30, 1 torch thread, equal-time grid up to N'=60 with 1 timed step; protocol b: "
                     "10 steps, N=20, 1 training iteration of 2 envs")
    dom.add_argument("--protocol", choices=("a", "b"), default="a",
                     help="a: shared trajectories (default); b: closed loop, each method trains its own DeepSets "
                     "policy (budget per domain in configs/bench/closed_loop.yaml) and drives it on --seeds "
                     "evaluation episodes; a rerun with the same --output resumes from the checkpoints")
    dom.add_argument("--train-iterations", type=int, default=None,
                     help="protocol b: trainer.iterations for every domain (default: the yaml's)")
    dom.add_argument("--train-envs", type=int, default=None,
                     help="protocol b: trainer.num_envs for every domain (default: the yaml's)")
    dom.add_argument("--output", default="outputs/bench/domains", help="folder for domains.json, domains.md, PNGs "
                     "(protocol b: closed_loop.json, closed_loop.md, PNGs and runs/)")
    cur = bench_sub.add_parser("curves", help="learning curves of training runs side by side",
                               description="Return, final distance to goal and (DVRL) ELBO against frames for "
                               "each run directory; writes learning_curves.png, .md and .json.")
    cur.add_argument("runs", nargs="+", help="run directories (or checkpoints), e.g. outputs/lightdark10d")
    cur.add_argument("--output", default="outputs/bench/curves", help="folder for the figure and tables")
    cal = bench_sub.add_parser("calibration", help="SVGD/ESCORT variants against the Kalman filter",
                               description="Linear-Gaussian model (d=4), N=300, 12 steps, 4 episodes: mean "
                               "Mahalanobis error and variance ratio against the exact Kalman posterior.")
    cal.add_argument("--particles", type=int, default=300)
    cal.add_argument("--steps", type=int, default=12)
    stop = bench_sub.add_parser("adaptive-stop", help="ESCORT's adaptive stop: iterations used, error, calibration",
                                description="ESCORT (K = 50 the cap) with each --tolerances value of "
                                "filter.stop_tolerance on protocol (a)'s trajectories of each domain, and on the "
                                "Kalman calibration episode; writes adaptive_stop.md and adaptive_stop.json.")
    stop.add_argument("--domains", nargs="+", default=["lightdark10d", "kidnapped20d", "mtt20d"])
    stop.add_argument("--tolerances", type=float, nargs="+", default=[0.0, 0.05, 0.1])
    stop.add_argument("--seeds", type=int, default=8)
    stop.add_argument("--steps", type=int, default=30)
    stop.add_argument("--output", default="outputs/bench/adaptive_stop")
    pb = bench_sub.add_parser("planner-budget", help="POMCPOW return against simulations per decision",
                              description="POMCPOW on an SIR belief with each n_sim in --budgets, plus a "
                              "uniform-random policy, on the same seeded episodes: return, final distance to goal "
                              "and ms per decision (mean ± s.e.); writes planner_budget.json and planner_budget.md.")
    pb.add_argument("--domain", default="lightdark1d", help="lightdark1d (default) or a configs/planner domain")
    pb.add_argument("--budgets", type=int, nargs="+", default=None,
                    help="n_sim values (default: lightdark1d 10 30 100 300, others 10 50 200)")
    pb.add_argument("--episodes", type=int, default=None, help="episodes, one seeded batch (default 30 / 10)")
    pb.add_argument("--steps", type=int, default=None, help="steps per episode (default 15 / 100)")
    pb.add_argument("--output", default="outputs/bench/planner_budget", help="folder for the JSON and markdown")
    pb.add_argument("--quick", action="store_true", help="smoke run (flags given win): budgets 2 5, 2 episodes, "
                    "3 steps, 20 particles")
    cfg = sub.add_parser("config", help="print the composed config",
                         description="Print the config as YAML; with resume=RUN_DIR, the config that "
                         "`escort-rl train resume=RUN_DIR ...` would continue that run with.")
    cfg.add_argument("overrides", nargs="*", help=OVERRIDES_HELP)
    return parser


def _train_config(overrides: list[str]):
    """The config ``escort-rl train`` runs with, and the checkpoint it resumes (``None``: a new run).

    A new run records its overrides in the config (``overrides``); ``resume=RUN_DIR key=value ...``
    composes the saved run's overrides followed by the new ones again (see
    :func:`escort_rl.config.recompose`). ``RUN_DIR`` gives its newest intact checkpoint (a damaged
    newer one is skipped with a warning); ``resume=CHECKPOINT`` names one.

    A resume writes into the run directory that holds the checkpoint, whatever ``output_dir`` the
    run was saved with, so resuming a moved or copied run directory never touches the original. An
    ``output_dir=`` given with ``resume=`` must name that same directory; another one is an error
    (to branch a run, copy its directory and resume the copy)."""
    from escort_rl.config import ConfigError, recompose, saved_config_drift
    from escort_rl.trainers.checkpointing import load_checkpoint, run_dir_of
    from escort_rl.trainers.scaffold import output_path

    resume = [o.split("=", 1)[1] for o in overrides if o.startswith("resume=")]
    rest = [o for o in overrides if not o.startswith("resume=")]
    if not resume or resume[-1] in ("", "null", "None"):
        return _new_run_config(rest), None
    saved = load_checkpoint(resume[-1])
    run_dir = run_dir_of(saved["path"])
    cfg = recompose(saved["config"], rest)
    if output_path(cfg.output_dir).resolve() != run_dir.resolve():
        if any(_override_key(o) == "output_dir" for o in rest):
            raise ConfigError(f"output_dir: '{cfg.output_dir}' is not the run directory being resumed ('{run_dir}'); "
                              "a resume writes into the run it continues: drop output_dir=, or copy the run "
                              "directory and resume the copy")
        cfg.output_dir = str(run_dir)  # the run was moved or copied: write into it, not the original
        if cfg.get("overrides") is not None:
            cfg.overrides = _with_output_dir(list(cfg.overrides), run_dir)
    cfg.resume = saved["path"]
    drift = saved_config_drift(saved["config"])
    if drift:
        print(f"note: the yaml changed since this run started; resuming with today's values of "
              f"{', '.join(drift[:8])}{' ...' if len(drift) > 8 else ''}", file=sys.stderr)
    return cfg, saved


def _new_run_config(overrides: list[str]):
    """The config of a new run, with its overrides recorded (``overrides``) for a later resume."""
    from escort_rl.config import compose

    cfg = compose(overrides)
    cfg.overrides = overrides
    return cfg


def _with_output_dir(overrides: list[str], run_dir: Path) -> list[str]:
    """``overrides`` with their ``output_dir=`` naming ``run_dir``: replaced where it stood, appended
    when there was none."""
    new = f"output_dir={_quoted(str(run_dir))}"
    out = [new if _override_key(o) == "output_dir" else o for o in overrides]
    return out if new in out else [*out, new]


def _quoted(value: str) -> str:
    """``value`` as a single-quoted Hydra override value (any path parses back to itself)."""
    return "'" + value.replace("'", "\\'") + "'"


def _override_key(override: str) -> str:
    """The key of a Hydra override (``+a.b=1`` -> ``a.b``)."""
    return override.split("=", 1)[0].lstrip("+~")


def _train(overrides: list[str], quiet: bool = False) -> Path:
    from escort_rl.trainers.registry import train

    cfg, saved = _train_config(overrides)
    if saved is not None:
        print(f"resuming from {saved['path']} (iteration {saved['trainer_state']['iteration']})")
    return train(cfg, resume_state=saved, progress=not quiet)


def _bench_closed_loop(args) -> None:
    import time

    from escort_rl.bench import closed_loop as cl
    from escort_rl.bench import domains as dom

    quick = dict(domains=["lightdark10d", "kidnapped20d", "mtt20d"], methods=["escort", "svgd", "sir"], seeds=2,
                 particles=20, steps=10, filter_set=[], threads=1, train_iterations=1, train_envs=2)
    full = dict(domains=list(dom.DEFAULT_DOMAINS), methods=cl.default_methods(),
                seeds=None, particles=None, steps=None, filter_set=[], threads=None, train_iterations=None,
                train_envs=None)
    kw = {k: getattr(args, k) if getattr(args, k) is not None else (quick if args.quick else full)[k] for k in full}
    train = {k: v for k, v in (("iterations", kw["train_iterations"]), ("num_envs", kw["train_envs"])) if v is not None}

    def show(row):
        if row["failed"]:
            print(f"{row['domain']:>13} {row['method']:>14} FAILED: {row['failed']['message']}", flush=True)
            return
        s = row["summary"]
        trained = f"  trained {cl._train_cell(row)}" if row["train"] else ""
        if "seconds_per_decision" in row:
            trained += f"  {1e3 * row['seconds_per_decision']:.1f} ms per decision"
        print(f"{row['domain']:>13} {row['method']:>14} final error {s['final_position_error']:.3f} ± "
              f"{s['final_position_error_se']:.3f}  return {s['episode_return']:.1f} ± {s['episode_return_se']:.1f}  "
              f"distance {s['final_distance']:.3f}  success {s['success_rate']:.2f}  "
              f"{1e3 * row['seconds_per_step']:.1f} ms/step{trained}", flush=True)

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    result = cl.run_closed_loop(kw["domains"], kw["methods"], out, episodes=kw["seeds"], n=kw["particles"],
                                steps=kw["steps"], train_overrides=train,
                                filter_set=dom.parse_filter_set(kw["filter_set"]), threads=kw["threads"],
                                progress=show)
    for d in result["domains"]:
        cl.plot_closed_loop_error(result, d, out / f"closed_loop_error_{d}.png")
    write_results(out, "closed_loop", result, cl.closed_loop_markdown(result), time.perf_counter() - t0)


def write_results(out: Path, stem: str, result, markdown: str, seconds: float | None = None) -> None:
    """Write a benchmark's ``<stem>.json`` and ``<stem>.md`` into ``out`` (created), print the Markdown
    and where the results are (with the run's seconds, if given)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps(result, indent=1))
    (out / f"{stem}.md").write_text(markdown)
    print(markdown)
    print(f"results: {out.resolve()}" + (f" ({seconds:.1f} s)" if seconds is not None else ""))


def _bench_domains(args) -> None:
    import time

    from escort_rl.bench import domains as dom

    if args.protocol == "b":
        return _bench_closed_loop(args)
    if args.train_iterations is not None or args.train_envs is not None:
        raise ValueError("--train-iterations/--train-envs: only for --protocol b")

    quick = dict(domains=["lightdark10d", "kidnapped20d", "mtt20d"], methods=["escort", "svgd", "sir"], seeds=2,
                 particles=30, steps=20, max_particles=60, filter_set=[], threads=1)
    full = dict(domains=list(dom.DEFAULT_DOMAINS), methods=list(dom.DEFAULT_METHODS), seeds=30, particles=100,
                steps=None, max_particles=2000, filter_set=[], threads=None)
    kw = {k: getattr(args, k) if getattr(args, k) is not None else (quick if args.quick else full)[k] for k in full}

    def show(kind, payload):
        if kind == "row" and payload["failed"]:
            f = payload["failed"]
            print(f"{payload['domain']:>13} {payload['method']:>14} N={payload['particles']:<5} FAILED at step "
                  f"{f['step']}: {f['message']}", flush=True)
        elif kind == "row":
            s = payload["summary"]
            print(f"{payload['domain']:>13} {payload['method']:>14} N={payload['particles']:<5} final error "
                  f"{dom._fmt(s['final_error'])}  mean error {dom._fmt(s['mean_error'])}  "
                  f"{1e3 * payload['seconds_per_step']:.1f} ms/step", flush=True)
        else:
            times = ", ".join(f"N'={k}: {1e3 * v:.1f} ms" for k, v in payload["times"].items())
            print(f"{payload['domain']:>13} {payload['method']:>14} equal-time: budget "
                  f"{1e3 * payload['budget']:.1f} ms; {times} -> N'={payload['chosen']}", flush=True)

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    result = dom.run_domains(kw["domains"], kw["methods"], seeds=kw["seeds"], n=kw["particles"], steps=kw["steps"],
                             workers=args.workers, equal_time=not args.no_equal_time,
                             max_particles=kw["max_particles"], calibration_steps=1 if args.quick else 3,
                             filter_set=dom.parse_filter_set(kw["filter_set"]), threads=kw["threads"],
                             progress=show, plot_dir=out, runs_dir=out / "runs")
    write_results(out, "domains", result, dom.domains_markdown(result), time.perf_counter() - t0)


def _filter_kwargs(args) -> dict:
    """ESCORT/SVGD constructor arguments a benchmark's flags change from the defaults."""
    kw = {}
    if args.bandwidth_scale != 1.0:
        kw["bandwidth_scale"] = args.bandwidth_scale
    if args.compile:
        kw["compile"] = True
    return kw


def _quiet_compiler_notices() -> None:
    """torch.compile's C++ toolchain logs a CUDA_HOME notice and Inductor a deprecation warning on
    every CPU compile; neither says anything about the user's run."""
    import logging
    import warnings

    logging.getLogger("torch.utils.cpp_extension").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", message=r"`torch\._prims_common\.check` is deprecated", category=FutureWarning)


# Count arguments of the subcommands: each must be a positive int (or a list of them).
POSITIVE_ARGUMENTS = ("episodes", "repeats", "dims", "particles", "batches", "workers", "num_envs", "steps",
                      "seeds", "threads", "num_steps", "training", "training_steps")


def check_positive_arguments(args) -> None:
    """Raise ``ValueError`` naming the first count argument that is zero or negative."""
    for name in POSITIVE_ARGUMENTS:
        value = getattr(args, name, None)
        for v in (value if isinstance(value, list) else [value]):
            if isinstance(v, int) and not isinstance(v, bool) and v < 1:
                raise ValueError(f"--{name.replace('_', '-')}: must be a positive int, got {v}")


def check_output_argument(args) -> None:
    """Raise ``ValueError`` naming ``--output`` when it cannot hold the results: an existing file
    where a folder is wanted, a path under a file, or a folder that cannot be created. The folder
    (for ``bench throughput``, the JSON file's folder) is created here, before any work is done."""
    value = getattr(args, "output", None)
    if value is None:
        return
    from escort_rl.schema import check_output_dir

    is_file = args.command == "bench" and args.bench == "throughput"  # --output names a JSON file
    path = Path(value).expanduser()
    if is_file and path.is_dir():
        raise ValueError(f"--output: '{value}' is a folder; pass a file name, e.g. {Path(value) / 'throughput.json'}")
    folder = path.parent if is_file else path
    problem = check_output_dir(str(folder))
    if problem is not None:
        raise ValueError(f"--output: {problem}")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"--output: cannot create '{folder}' ({err.strerror or type(err).__name__}); pass a folder "
                         "you can write to") from None


def check_bench_arguments(args) -> None:
    """Raise ``ValueError`` naming the first benchmark argument that cannot be used: ``--device``
    (absent here), ``--max-pairs`` (not a finite positive number), ``--workers`` that do not divide
    ``--num-envs``, an unknown ``--methods`` or ``--targets`` of ``bench synthetic``, an unknown
    ``--structures`` of ``bench scaling``."""
    import math

    if args.command != "bench":
        return
    if args.bench == "cost":
        from escort_rl.schema import check_device

        problem = check_device(args.device)
        if problem is not None:
            raise ValueError(f"--device: {problem.replace('device=cpu', '--device cpu')}")
        if not (math.isfinite(args.max_pairs) and args.max_pairs > 0):
            raise ValueError(f"--max-pairs: must be a finite number > 0, got {args.max_pairs}")
    if args.bench == "throughput":
        bad = [k for k in args.workers if args.num_envs % k]
        if bad:
            raise ValueError(f"--workers: {bad[0]} does not divide --num-envs {args.num_envs}; each worker runs "
                             "num_envs / workers environments")
    if args.bench == "synthetic":
        from escort_rl.bench.synthetic import METHODS
        from escort_rl.bench.targets import synthetic_config

        targets = sorted(synthetic_config()["targets"])
        for flag, given, known in (("--methods", args.methods, METHODS), ("--targets", args.targets, targets)):
            unknown = [m for m in given if m not in known]
            if unknown:
                raise ValueError(f"{flag}: unknown name '{unknown[0]}'; choose from {', '.join(known)}")
    if args.bench == "scaling":
        from escort_rl.bench.targets import SCALABILITY_STRUCTURES

        unknown = [m for m in args.structures if m not in SCALABILITY_STRUCTURES]
        if unknown:
            raise ValueError(f"--structures: unknown structure '{unknown[0]}'; choose from "
                             f"{', '.join(SCALABILITY_STRUCTURES)}")


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    _quiet_compiler_notices()
    from escort_rl.config import ConfigError
    from escort_rl.trainers.checkpointing import CheckpointLoadError
    from escort_rl.trainers.scaffold import CollectorWorkerDied

    try:
        check_positive_arguments(args)
        check_bench_arguments(args)
        check_output_argument(args)
        if args.command == "config":
            from omegaconf import OmegaConf

            # with resume=RUN_DIR: the config `escort-rl train` would resume that run with
            print(OmegaConf.to_yaml(_train_config(args.overrides)[0]))
        elif args.command == "bench" and args.bench == "throughput":
            from escort_rl.bench.throughput import collection_throughput
            from escort_rl.config import compose

            cfg = compose(args.overrides)
            rows = []
            for k in args.workers:
                row = collection_throughput(cfg, k, args.num_envs, args.steps, args.batches)
                rows.append(row)
                print(f"workers={k} B={row['num_envs']} N={row['num_particles']} filter={row['filter']}: "
                      f"{row['frames_per_second']:.0f} frames/s ({row['frames']} frames in {row['seconds']:.2f} s)")
            if args.output:
                Path(args.output).parent.mkdir(parents=True, exist_ok=True)
                Path(args.output).write_text(json.dumps(rows, indent=1))
        elif args.command == "bench" and args.bench == "cost":
            from escort_rl.bench.cost import cost_markdown, run_cost_benchmark

            grid = dict(dims=args.dims, particles=args.particles, batches=args.batches)
            if args.quick:
                grid = dict(dims=[10, 20], particles=[100], batches=[1, 2])

            def show(row):
                print(f"{row['filter']:>15} d={row['d']:<4} N={row['N']:<5} B={row['B']:<3} "
                      f"{1e3 * row['seconds']:9.2f} ms", flush=True)

            out = Path(args.output)
            out.mkdir(parents=True, exist_ok=True)
            result = {} if args.no_updates else run_cost_benchmark(
                **grid, repeats=args.repeats, num_steps=args.num_steps, device=args.device, progress=show,
                max_pairs=args.max_pairs, compile=args.compile)
            if args.training or args.warmup:
                from escort_rl.bench.training_cost import training_cost_rows

                result.update(training_cost_rows(args.training, out / "training_runs", args.training_steps,
                                                 args.warmup, progress=print))
            write_results(out, "cost", result, cost_markdown(result))
        elif args.command == "bench" and args.bench in ("synthetic", "scaling"):
            from escort_rl.bench import synthetic as syn

            def show(row):
                where = row.get("target") or f"d={row['dim']} {row['structure']}"
                s = row["summary"]
                print(f"{where:>18} {row['method']:>14}: MMD2 {s['mmd2'][0]:.4f} SW1 {s['sliced_w1'][0]:.3f} "
                      f"cover {s['mode_coverage'][0]:.2f} corr {s['corr_error'][0]:.3f} RMSE {s['rmse'][0]:.3f} "
                      f"({row['seconds']:.1f} s)", flush=True)

            if args.bench == "synthetic":
                kw = dict(targets=args.targets, methods=args.methods, seeds=args.seeds, n=args.particles,
                          num_steps=args.num_steps, filter_kwargs=_filter_kwargs(args))
                if args.quick:
                    kw.update(targets=["gmm1d", "gmm2d", "gmm3d"], seeds=2, n=100, num_steps=30)
                Path(args.output).mkdir(parents=True, exist_ok=True)
                result = syn.run_synthetic(**kw, progress=show, plot_dir=args.output)
                md = syn.synthetic_markdown(result)
            else:
                kw = dict(dims=args.dims, structures=args.structures, seeds=args.seeds, n=args.particles,
                          num_steps=args.num_steps, filter_kwargs=_filter_kwargs(args))
                if args.quick:
                    kw.update(dims=[1, 5], structures=["block"], seeds=2, n=100, num_steps=30)
                Path(args.output).mkdir(parents=True, exist_ok=True)
                result = syn.run_scaling(**kw, progress=show, plot_dir=args.output)
                md = syn.scaling_markdown(result)
            write_results(Path(args.output), args.bench, result, md)
        elif args.command == "bench" and args.bench == "domains":
            _bench_domains(args)
        elif args.command == "bench" and args.bench == "planner-budget":
            from escort_rl.bench.planner_budget import cli as planner_budget_cli

            planner_budget_cli(args)
        elif args.command == "bench" and args.bench == "curves":
            from escort_rl.bench.curves import curves_markdown, write_curves

            print(curves_markdown(write_curves(args.runs, args.output)))
            print(f"results: {Path(args.output).resolve()}")
        elif args.command == "bench" and args.bench == "adaptive-stop":
            from escort_rl.bench.adaptive_stop import adaptive_stop_markdown, adaptive_stop_rows

            if any(not (t >= 0 and math.isfinite(t)) for t in args.tolerances):
                raise ValueError(f"--tolerances: each must be a finite number >= 0, got {args.tolerances}")
            rows = adaptive_stop_rows(args.domains, args.tolerances, seeds=args.seeds, steps=args.steps,
                                      progress=lambda r: print(f"{r['domain']:>12} tol={r['tolerance']:g}: "
                                                               f"{r['iterations']:.1f} iterations", flush=True))
            write_results(Path(args.output), "adaptive_stop", rows, adaptive_stop_markdown(rows))
        elif args.command == "bench" and args.bench == "calibration":
            from escort_rl.belief import ESCORTFilter, SIRFilter, SVGDFilter
            from escort_rl.bench.calibration import kalman_calibration

            variants = [("sir", SIRFilter()), ("svgd", SVGDFilter()), ("escort", ESCORTFilter()),
                        ("escort corr_form=position", ESCORTFilter(corr_form="position")),
                        ("escort temp_schedule=constant", ESCORTFilter(temp_schedule="constant")),
                        ("escort jitter=0", ESCORTFilter(jitter=0.0)),
                        ("svgd repulsion=enhanced", SVGDFilter(repulsion="enhanced")),
                        ("escort num_steps=15 step_size=0.15 (filter=escort_train)",
                         ESCORTFilter(num_steps=15, step_size=0.15)),
                        ("escort num_steps=10", ESCORTFilter(num_steps=10))]
            print("| filter | mean Mahalanobis error | variance ratio |")
            print("| --- | --- | --- |")
            for name, filt in variants:
                m, r = kalman_calibration(filt, steps=args.steps, n=args.particles)
                print(f"| {name} | {m:.3f} | {r:.3f} |", flush=True)
        elif args.command == "describe":
            from escort_rl.models.light_dark import describe_correlations

            print(describe_correlations())
        elif args.command == "train":
            run_dir = _train(args.overrides, args.quiet)
            print(f"checkpoints and logs: {run_dir.resolve()}")
        elif args.command == "run":
            from escort_rl.trainers.evaluate import evaluate

            run_dir = _train(args.overrides)
            result = evaluate(run_dir)
            out = run_dir.resolve() / "evaluation"
            print((out / "summary.md").read_text())
            print(f"results: {out} (summary.md, metrics.json, learning_curve.png, belief_projection.png)")
            print(f"checkpoints and logs: {run_dir.resolve()}")
            _ = result
        elif args.command == "evaluate":
            from escort_rl.trainers.evaluate import evaluate

            result = evaluate(args.checkpoint, args.episodes, args.output, args.greedy)
            from escort_rl.trainers.checkpointing import resolve_checkpoint

            out = Path(args.output) if args.output else resolve_checkpoint(args.checkpoint).parent.parent / "evaluation"
            _ = result
            print((out / "summary.md").read_text())
            print(f"results: {out.resolve()}")
    except (ConfigError, CheckpointLoadError, CollectorWorkerDied, FloatingPointError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except ValueError as err:
        print(f"error: {str(err).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
