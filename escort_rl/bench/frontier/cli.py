"""``escort-rl bench frontier``: which filter, at which N and K, for a time budget, on any model."""

from __future__ import annotations

import json
from pathlib import Path

from escort_rl.bench.frontier.cells import FILTER_METHODS, parse_variant
from escort_rl.bench.frontier.run import DEFAULT_ITERATIONS, DEFAULT_PARTICLES, METRICS, run_frontier

QUICK = {"particles": {"sir": (100, 1000, 10_000), "enkf": (100, 1000, 10_000), "svgd": (50, 200),
                       "escort": (50, 200)},
         "iterations": (5, 15), "seeds": 2, "steps": 5, "reference_particles": 2000}
"""``--quick``: a few points per filter, 2 seeds × 5 steps (a few minutes on two cores)."""


def register(subparsers) -> None:
    from escort_rl.bench.runner import add_runner_arguments

    p = subparsers.add_parser(
        "frontier", help="accuracy against time per update of SIR, EnKF, SVGD and ESCORT on any model",
        description="Sweep each filter over its cost knobs (SIR and EnKF over N, SVGD and ESCORT over N x K) on a "
        "model's shared trajectories; measure the time per update and the distance to the reference posterior "
        "(exact where the model has one, else a large SIR); write the Pareto plot, the closest filter at each "
        "time budget and one line of advice. The model: a package env (env=NAME and env.model.KEY=VALUE "
        "overrides; default env=linear_gaussian) or your own class (--model pkg.module:Class --model-arg KEY=VALUE).")
    p.add_argument("overrides", nargs="*", metavar="env=NAME | env.KEY=VALUE",
                   help="the env and its overrides, e.g. env=linear_gaussian env.model.state_dim=100")
    p.add_argument("--model", default=None, metavar="pkg.module:Class", help="a model class of your own")
    p.add_argument("--model-arg", nargs="+", default=[], metavar="KEY=VALUE", help="keyword arguments of --model")
    p.add_argument("--methods", nargs="+", default=list(FILTER_METHODS), help="default: sir enkf svgd escort")
    for m in FILTER_METHODS:
        p.add_argument(f"--{m}-particles", type=int, nargs="+", default=None, metavar="N",
                       help=f"N of {m} (default {' '.join(map(str, DEFAULT_PARTICLES[m]))})")
    p.add_argument("--num-steps", type=int, nargs="+", default=None, metavar="K",
                   help=f"K of SVGD and ESCORT (default {' '.join(map(str, DEFAULT_ITERATIONS))})")
    p.add_argument("--variant", nargs="+", default=[], metavar="NAME=METHOD:KEY=VALUE[,KEY=VALUE]",
                   help="more rows: a filter with its own settings, swept over METHOD's N (and K), e.g. "
                   "escort_stop=escort:stop_tolerance=0.05 enkf_loc=enkf:localisation_radius=2")
    p.add_argument("--seeds", type=int, default=5, help="shared trajectories (default 5)")
    p.add_argument("--steps", type=int, default=20, help="updates per trajectory (default 20)")
    p.add_argument("--metric", choices=METRICS, default="w1", help="the front's distance (default w1: sliced W1)")
    p.add_argument("--compile", action="store_true", help="SVGD and ESCORT compiled (the first update, which "
                   "compiles, is not timed)")
    p.add_argument("--reference-particles", type=int, default=100_000,
                   help="N of the SIR reference for a model without an exact posterior (default 100000)")
    p.add_argument("--quick", action="store_true", help="smoke run: N of SIR/EnKF 100 1000 10000, of SVGD/ESCORT "
                   "50 200, K 5 15, 2 seeds, 5 steps, a 2000-particle reference (flags given explicitly win)")
    p.add_argument("--output", default="outputs/bench/frontier", help="folder (default outputs/bench/frontier)")
    add_runner_arguments(p)
    p.set_defaults(handler=main)


def model_spec(args) -> tuple[str, tuple]:
    """``(model, model_args)`` of the cells from the positional overrides or ``--model``."""
    env, env_args = None, []
    for item in args.overrides:
        if item.startswith("env="):
            env = item.split("=", 1)[1]
        elif item.startswith("env.") and "=" in item:
            env_args.append(item[len("env."):])
        else:
            raise ValueError(f"overrides: '{item}' is neither env=NAME nor env.KEY=VALUE")
    if args.model is not None:
        if env is not None or env_args:
            raise ValueError("--model: give either your own class or env=NAME overrides, not both")
        return f"class:{args.model}", tuple(args.model_arg)
    if args.model_arg:
        raise ValueError("--model-arg: needs --model")
    return f"env:{env or 'linear_gaussian'}", tuple(env_args)


def write_frontier(out: Path, result: dict, echo: bool = True) -> None:
    """``frontier.json``, ``frontier.md`` and ``frontier.png`` of one frontier in ``out``."""
    from escort_rl.bench.frontier.report import frontier_markdown
    from escort_rl.bench.frontier.run import label
    from escort_rl.reporting.plots import plot_frontier

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    plot_frontier(result["rows"], result["front"], out / "frontier.png", xlabel="ms per update (one belief)",
                  ylabel=f"{result['metric']} to the reference ({result['part']})",
                  title=f"{result['model_name']} " + " ".join(result["model_args"]), label=label)
    md = frontier_markdown(result)
    (out / "frontier.json").write_text(json.dumps(result, indent=1))
    (out / "frontier.md").write_text(md)
    if echo:
        print(md)
        print(f"results: {out.resolve()}")


def main(args) -> None:
    from escort_rl.bench.frontier.run import label
    from escort_rl.bench.runner import backend_from_args

    model, model_args = model_spec(args)
    quick = QUICK if args.quick else {}
    particles = {m: getattr(args, f"{m}_particles") or quick.get("particles", DEFAULT_PARTICLES)[m]
                 for m in FILTER_METHODS}
    for m, ns in particles.items():
        if any(n < 1 for n in ns):
            raise ValueError(f"--{m}-particles: must be >= 1, got {list(ns)}")
    iterations = args.num_steps or quick.get("iterations", DEFAULT_ITERATIONS)
    explicit = lambda flag, default: getattr(args, flag) if getattr(args, flag) != default else quick.get(flag, default)  # noqa: E731
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)

    def show(row):
        err = "diverged" if row.get("failed") else f"{row['error']:.4g}"
        print(f"{label(row):>24}: {row['ms_per_update']:.3g} ms, {args.metric} {err}", flush=True)

    variants = {name: (method, items) for name, method, items in map(parse_variant, args.variant)}
    result = run_frontier(model, model_args, args.methods, particles, iterations, seeds=explicit("seeds", 5),
                          steps=explicit("steps", 20), compile=args.compile, metric=args.metric,
                          reference_particles=explicit("reference_particles", 100_000),
                          backend=backend_from_args(args), threads=args.threads or 1, output=out, progress=show,
                          variants=variants)
    write_frontier(out, result)
