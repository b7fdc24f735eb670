"""``escort-rl bench frontier``: which filter, at which N and K, for a time budget, on any model."""

from __future__ import annotations

import json
from pathlib import Path

from escort_rl.bench.core import options
from escort_rl.bench.frontier.cells import FILTER_METHODS, parse_variant
from escort_rl.bench.frontier.run import DEFAULT_ITERATIONS, DEFAULT_PARTICLES, METRICS, run_frontier

QUICK = {"particles": {"sir": (100, 1000, 10_000), "enkf": (100, 1000, 10_000), "svgd": (50, 200),
                       "escort": (50, 200)},
         "iterations": (5, 15), "seeds": 2, "steps": 5, "reference_particles": 2000}
"""``--quick``: a few points per filter, 2 seeds × 5 steps (a few minutes on two cores)."""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "frontier", help="accuracy against time per update of SIR, EnKF, SVGD and ESCORT on any model",
        description="Sweep each filter over its cost knobs (SIR and EnKF over N, SVGD and ESCORT over N x K) on a "
        "model's shared trajectories; measure the time per update and the distance to the reference posterior "
        "(exact where the model has one, else a large SIR); write the Pareto plot, the closest filter at each "
        "time budget and one line of advice. The model: a package env (env=NAME and env.model.KEY=VALUE "
        "overrides; default env=linear_gaussian) or your own class (--model pkg.module:Class --model-arg KEY=VALUE).")
    p.add_argument("overrides", nargs="*", default=[], metavar="OVERRIDE",
                   help="Hydra overrides: the env and its keys, e.g. env=linear_gaussian env.model.state_dim=100, "
                   "and filter.compile=true (SVGD and ESCORT compiled; the first update, which compiles, is not "
                   "timed) (default: none)")
    p.add_argument("--model", default=None, metavar="pkg.module:Class", help="a model class of your own")
    p.add_argument("--model-arg", nargs="+", default=[], metavar="KEY=VALUE", help="keyword arguments of --model")
    add_method_options(p)
    options.add_seeds_option(p, 5, "shared trajectories")
    p.add_argument("--steps", type=int, default=20, help="updates per trajectory")
    p.add_argument("--metric", choices=METRICS, default="w1", help="the front's distance (w1: sliced W1)")
    p.add_argument("--reference-particles", type=int, default=100_000, metavar="N",
                   help="N of the SIR reference for a model without an exact posterior")
    options.add_quick_option(p, "N of SIR/EnKF 100 1000 10000, of SVGD/ESCORT 50 200, K 5 15, 2 seeds, 5 steps, a "
                     "2000-particle reference")
    options.add_output_option(p, "outputs/bench/frontier", "frontier.json, frontier.md, frontier.png and cells/")
    options.add_runner_options(p, seeds_per_cell=False)
    p.set_defaults(handler=main)


def add_method_options(p) -> None:
    """``--methods``, ``--<method>-particles``, ``--num-steps`` and ``--variant``, shared with
    ``bench regime-map``."""
    p.add_argument("--methods", nargs="+", default=list(FILTER_METHODS), help="the filters swept")
    for m in FILTER_METHODS:
        p.add_argument(f"--{m}-particles", type=int, nargs="+", default=None, metavar="N",
                       help=f"N of {m} (default: {' '.join(map(str, DEFAULT_PARTICLES[m]))})")
    p.add_argument("--num-steps", type=int, nargs="+", default=None, metavar="K",
                   help=f"K of SVGD and ESCORT (default: {' '.join(map(str, DEFAULT_ITERATIONS))})")
    options.add_labelled_option(p, "--variant", "one more row, a filter with its own settings swept over its "
                        "method's N (and K); the overrides are filter=METHOD and filter.KEY=VALUE",
                        "escort_stop filter=escort filter.stop_tolerance=0.05")


def frontier_variants(items) -> dict:
    """``--variant`` as ``name -> (method, ("KEY=VALUE", ...))``, names unique."""
    options.labelled(items, "--variant")
    return {name: (method, settings) for name, method, settings in map(parse_variant, items)}


def model_spec(args) -> tuple[str, tuple]:
    """``(model, model_args)`` of the cells from the positional overrides or ``--model``."""
    env, env_args = None, []
    for item in args.overrides:
        if item.startswith("env="):
            env = item.split("=", 1)[1]
        elif item.startswith("env.") and "=" in item:
            env_args.append(item[len("env."):])
        elif not item.startswith("filter."):
            raise ValueError(f"overrides: '{item}' is neither env=NAME, env.KEY=VALUE nor filter.compile=true|false")
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
    from escort_rl.bench.core.runner import backend_from_args
    from escort_rl.bench.frontier.run import label

    model, model_args = model_spec(args)
    compile = options.compile_override([o for o in args.overrides if o.startswith("filter.")])
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

    variants = frontier_variants(args.variant)
    result = run_frontier(model, model_args, args.methods, particles, iterations, seeds=explicit("seeds", 5),
                          steps=explicit("steps", 20), compile=compile, metric=args.metric,
                          reference_particles=explicit("reference_particles", 100_000),
                          backend=backend_from_args(args), threads=args.threads or 1, output=out, progress=show,
                          variants=variants)
    write_frontier(out, result)
