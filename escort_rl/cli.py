"""The ``escort-rl`` command.

    escort-rl run [KEY=VALUE ...]        train, then evaluate (the default job)
    escort-rl train [KEY=VALUE ...]      train; resume with resume=RUN_DIR
    escort-rl evaluate --checkpoint PATH evaluate a checkpoint against a random policy
    escort-rl config [KEY=VALUE ...]     print the composed config
    escort-rl describe                   print the Light-Dark process-noise correlations
    escort-rl bench throughput           collector frames/s with the belief transform
"""

from __future__ import annotations

import argparse
import json
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
                    help="take the most probable action instead of sampling (default: evaluate.greedy)")
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
    cfg = sub.add_parser("config", help="print the composed config", description="Print the config as YAML.")
    cfg.add_argument("overrides", nargs="*", help=OVERRIDES_HELP)
    return parser


def _train(overrides: list[str], quiet: bool = False) -> Path:
    from omegaconf import OmegaConf

    from escort_rl.config import compose, merge_overrides
    from escort_rl.trainers.checkpointing import load_checkpoint, resolve_checkpoint
    from escort_rl.trainers.reinforce import train

    resume = [o.split("=", 1)[1] for o in overrides if o.startswith("resume=")]
    rest = [o for o in overrides if not o.startswith("resume=")]
    if resume and resume[0] not in ("", "null", "None"):
        path = resolve_checkpoint(resume[0])
        saved = load_checkpoint(path)
        cfg = merge_overrides(OmegaConf.create(saved["config"]), rest)
        cfg.resume = str(path)
        print(f"resuming from {path} (iteration {saved['trainer_state']['iteration']})")
        return train(cfg, resume_state=saved, progress=not quiet)
    cfg = compose(rest)
    return train(cfg, progress=not quiet)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from escort_rl.config import ConfigError
    from escort_rl.trainers.checkpointing import CheckpointLoadError

    try:
        if args.command == "config":
            from omegaconf import OmegaConf

            from escort_rl.config import compose

            print(OmegaConf.to_yaml(compose(args.overrides)))
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
            out = Path(args.output) if args.output else Path(result["checkpoint"]).parent.parent / "evaluation"
            print(json.dumps({k: result[k] for k in ("trained", "random")}, indent=1))
            print(f"results: {out.resolve()}")
    except (ConfigError, CheckpointLoadError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except ValueError as err:
        print(f"error: {str(err).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
