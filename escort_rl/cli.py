"""The ``escort-rl`` command.

    escort-rl run [KEY=VALUE ...]        train, then evaluate (the default job)
    escort-rl train [KEY=VALUE ...]      train; resume with resume=RUN_DIR
    escort-rl evaluate --checkpoint PATH evaluate a checkpoint beside the scripted controller and a random policy
    escort-rl config [KEY=VALUE ...]     print the composed config
    escort-rl describe                   print the Light-Dark process-noise correlations
    escort-rl bench NAME ...             the benchmarks (``escort-rl bench --help`` lists them)

Benchmarks register their own subcommands. Each module named in :data:`BENCHMARKS` has a function
``register(subparsers)`` that adds its parser(s) to ``escort-rl bench`` and sets the handler with
``parser.set_defaults(handler=fn)``; :func:`main` calls ``fn(args)`` (a returned int is the exit
status). To add a benchmark, write ``register`` in its module and append the module's name to
:data:`BENCHMARKS`::

    from escort_rl.bench.core.options import add_output_option, add_quick_option

    def register(subparsers):
        p = subparsers.add_parser("mine", help="...")
        add_output_option(p, "outputs/bench/mine", "mine.md and mine.json")
        add_quick_option(p, "2 seeds, 5 steps")
        p.set_defaults(handler=main)   # main(args) runs it; raise ValueError("--flag: ...") for bad input

The options every benchmark shares (``--output DIR``, ``--seeds N``, ``--quick``, the runner's
``--backend``/``--workers``/``--ray-address``/``--threads``, positional Hydra overrides, labelled
rows) are defined once, in :mod:`escort_rl.bench.core.options`; use those functions rather than
``add_argument`` for them. Every parser is a :class:`~escort_rl.bench.core.options.BenchParser`,
whose help shows each option's default; give every option a help string.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

import escort_rl

OVERRIDES_HELP = (
    "Hydra-style overrides, e.g. trainer.iterations=100 num_particles=200 filter=sir "
    "collector.workers=2 output_dir=outputs/mine resume=outputs/mine (default: none)"
)

MULTIRUN_HELP = ("a sweep, as Hydra's --multirun: comma-separated values (seed=0,1,2 filter=sir,escort_train) give "
                 "one run per combination, one after another, each in its own folder")

BENCHMARKS = (
    "escort_rl.bench.throughput",
    "escort_rl.bench.cost",
    "escort_rl.bench.profile",
    "escort_rl.bench.synthetic",
    "escort_rl.bench.domains",
    "escort_rl.bench.curves",
    "escort_rl.bench.gradient_noise",
    "escort_rl.bench.calibration",
    "escort_rl.bench.decisions",
    "escort_rl.bench.hidden_goal",
    "escort_rl.bench.adaptive_stop",
    "escort_rl.bench.planner_budget",
    "escort_rl.bench.compare",
    "escort_rl.bench.ablation",
    "escort_rl.bench.frontier",
    "escort_rl.bench.frontier.regime",
    "escort_rl.bench.frontier.kalman",
    "escort_rl.bench.frontier.decisions",
    "escort_rl.bench.atari",
    "escort_rl.bench.atari_envs",
    "escort_rl.bench.atari_cost",
    "escort_rl.bench.headline",
    "escort_rl.bench.popgym",
)
"""The modules whose ``register(subparsers)`` adds a ``bench`` subcommand, in the order of the help."""


def _parser() -> argparse.ArgumentParser:
    from escort_rl.bench.core.options import BenchParser

    parser = BenchParser(
        prog="escort-rl",
        description="ESCORT-RL: particle belief tracking for POMDPs and policies trained on those beliefs.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {escort_rl.__version__}",
                        help="print the version and exit")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="train a policy, then evaluate it (the default job)",
                         description="Train with the given overrides, then evaluate the final checkpoint.")
    run.add_argument("overrides", nargs="*", help=OVERRIDES_HELP)
    run.add_argument("-m", "--multirun", action="store_true", help=MULTIRUN_HELP)
    run.add_argument("--quiet", action="store_true", help="no progress bars")
    train = sub.add_parser("train", help="train a policy on particle beliefs (trainer=ppo by default)",
                           description="Train; a killed run continues with resume=RUN_DIR.")
    train.add_argument("overrides", nargs="*", help=OVERRIDES_HELP)
    train.add_argument("--quiet", action="store_true", help="no progress bar")
    train.add_argument("-m", "--multirun", action="store_true", help=MULTIRUN_HELP)
    ev = sub.add_parser("evaluate", help="evaluate a checkpoint beside the scripted controller and a random policy",
                        description="Evaluates the trained policy, the domain's scripted controller on the same "
                        "filter's belief (where the domain has one) and a uniform-random policy on the same seeded "
                        "episodes; writes summary.md, metrics.json and PNG plots.")
    ev.add_argument("--checkpoint", required=True, help="a run directory, its checkpoints/ folder or a checkpoint")
    ev.add_argument("--episodes", type=int, default=None,
                    help="number of episodes (default: the config's evaluate.episodes)")
    ev.add_argument("--output", default=None, help="output folder (default: RUN_DIR/evaluation)")
    ev.add_argument("--quiet", action="store_true", help="no progress bar")
    ev.add_argument("--greedy", action=argparse.BooleanOptionalAction, default=None,
                    help="--greedy: the most probable action; --no-greedy: sample from the policy "
                    "(default: the config's evaluate.greedy, true)")
    sub.add_parser("describe", help="print the Light-Dark 10D process-noise correlations (paper vs used)",
                   description="The paper's correlations are not PSD; this prints the nearest correlation "
                   "matrix that the model uses.")
    bench = sub.add_parser("bench", help="benchmarks", description="Benchmarks; each prints what it measured. They "
                           "share their options: --output DIR (a folder), --seeds N (a count), --quick (a smoke run), "
                           "--backend/--workers/--threads/--ray-address (where the cells run) and positional Hydra "
                           "overrides (filter.lambda_corr=0.3 filter.compile=true).")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    for name in BENCHMARKS:
        importlib.import_module(name).register(bench_sub)
    probe = sub.add_parser("check-model", help="call every method of your model on a tiny batch and check it",
                           description="Build pkg.module:Class with --model-arg KEY=VALUE and call every method of the "
                           "model protocol on a tiny batch: shapes, dtypes, finiteness and the log-densities' "
                           "gradients in the state. Prints the first problem, naming the method, or that it passes.")
    probe.add_argument("model", help="your model's class, pkg.module:Class (the module on the Python path)")
    probe.add_argument("--model-arg", nargs="+", default=[], metavar="KEY=VALUE", help="keyword arguments of the class")
    cfg = sub.add_parser("config", help="print the composed config",
                         description="Print the config as YAML; with resume=RUN_DIR, the config that "
                         "`escort-rl train resume=RUN_DIR ...` would continue that run with.")
    cfg.add_argument("overrides", nargs="*", help=OVERRIDES_HELP)
    return parser


def _train(overrides: list[str], quiet: bool = False) -> Path:
    from escort_rl.trainers.entry import train

    return train(overrides, progress=not quiet)


def _run(overrides: list[str], quiet: bool = False) -> None:
    """Train, then evaluate the run's final checkpoint and print its summary."""
    from escort_rl.trainers.evaluate import evaluate

    run_dir = _train(overrides, quiet)
    evaluate(run_dir, progress=not quiet)
    out = run_dir.resolve() / "evaluation"
    print((out / "summary.md").read_text())
    print(f"results: {out} (summary.md, metrics.json, learning_curve.png, belief_projection.png)")
    print(f"checkpoints and logs: {run_dir.resolve()}")


def _quiet_compiler_notices() -> None:
    """torch.compile's C++ toolchain logs a CUDA_HOME notice and Inductor a deprecation warning on
    every CPU compile; neither says anything about the user's run."""
    import logging
    import warnings

    logging.getLogger("torch.utils.cpp_extension").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", message=r"`torch\._prims_common\.check` is deprecated", category=FutureWarning)


# Count arguments of the subcommands: each must be a positive int (or a list of them).
POSITIVE_ARGUMENTS = ("episodes", "repeats", "dims", "particles", "batches", "batch_sizes", "workers",
                      "collector_workers", "num_envs", "steps",
                      "seeds", "threads", "num_steps", "training", "training_steps", "seeds_per_cell")


def check_output_argument(args) -> None:
    """Raise ``ValueError`` naming ``--output`` (always a folder) when it cannot hold the results: an
    existing file, a path under a file, or a folder that cannot be created. The folder is created
    here, before any work is done."""
    value = getattr(args, "output", None)
    if value is None:
        return
    from escort_rl.config.schema import check_output_dir

    folder = Path(value).expanduser()
    problem = check_output_dir(str(folder))
    if problem is not None:
        raise ValueError(f"--output: {problem}")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"--output: cannot create '{folder}' ({err.strerror or type(err).__name__}); pass a folder "
                         "you can write to") from None


def interrupted_line(args, err: KeyboardInterrupt) -> str:
    """What a Ctrl-C prints: a training run's iteration and resume command
    (:class:`~escort_rl.trainers.scaffold.TrainingInterrupted`), else what to run again."""
    from escort_rl.trainers.scaffold import TrainingInterrupted

    if isinstance(err, TrainingInterrupted):
        return str(err)
    if args.command == "bench":
        return "interrupted; the same command resumes from the cells it finished"
    return "interrupted"


def parse_args(argv: list[str] | None = None):
    """The command line, with options accepted before or after the overrides (``train a=1 --quiet b=2``):
    argparse stops a positional list at the first option, so the overrides it leaves over are put back
    in order."""
    parser = _parser()
    args, rest = parser.parse_known_args(argv)
    if rest:
        if not hasattr(args, "overrides") or any(token.startswith("-") for token in rest):
            parser.error(f"unrecognized arguments: {' '.join(rest)}")
        args.overrides = [*args.overrides, *rest]
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    _quiet_compiler_notices()
    from escort_rl.bench.methods import check_at_least_one
    from escort_rl.config import ConfigError
    from escort_rl.config.errors import MissingExtra
    from escort_rl.trainers.checkpointing import CheckpointLoadError
    from escort_rl.trainers.scaffold import CollectorWorkerDied

    try:
        check_at_least_one(**{name: getattr(args, name, None) for name in POSITIVE_ARGUMENTS})
        check_output_argument(args)
        if args.command == "config":
            from omegaconf import OmegaConf

            from escort_rl.trainers.resume import train_config

            # with resume=RUN_DIR: the config `escort-rl train` would resume that run with
            print(OmegaConf.to_yaml(train_config(args.overrides)[0]))
        elif args.command == "bench":
            status = args.handler(args)
            if isinstance(status, int):
                return status
        elif args.command == "check-model":
            from escort_rl.bench.frontier.cells import frontier_model as build_user_model
            from escort_rl.models import check_model

            model = build_user_model(f"class:{args.model}", tuple(args.model_arg))
            try:
                check_model(model)
            except TypeError as err:
                print(f"error: {err}", file=sys.stderr)
                return 2
            print(f"{args.model}: every method of the model protocol passes the probe (shapes, dtypes, finiteness, "
                  "gradients)")
        elif args.command == "describe":
            from escort_rl.models.light_dark import describe_correlations

            print(describe_correlations())
        elif args.command in ("train", "run"):
            from escort_rl.config.sweeps import expand_sweep

            sweep = expand_sweep(args.overrides) if args.multirun else [args.overrides]
            for i, overrides in enumerate(sweep):
                if len(sweep) > 1:
                    print(f"[{i + 1}/{len(sweep)}] {' '.join(overrides)}")
                if args.command == "train":
                    run_dir = _train(overrides, args.quiet)
                    print(f"checkpoints and logs: {run_dir.resolve()}")
                else:
                    _run(overrides, args.quiet)
        elif args.command == "evaluate":
            from escort_rl.trainers.evaluate import evaluate

            result = evaluate(args.checkpoint, args.episodes, args.output, args.greedy, progress=not args.quiet)
            from escort_rl.trainers.checkpointing import resolve_checkpoint

            out = Path(args.output) if args.output else resolve_checkpoint(args.checkpoint).parent.parent / "evaluation"
            _ = result
            print((out / "summary.md").read_text())
            print(f"results: {out.resolve()}")
    except (ConfigError, CheckpointLoadError, CollectorWorkerDied, FloatingPointError, MissingExtra) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:  # Ctrl-C: one line, no traceback, the shell's exit status for SIGINT
        print(f"\n{interrupted_line(args, err)}", file=sys.stderr)
        return 130
    except ValueError as err:
        print(f"error: {str(err).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
