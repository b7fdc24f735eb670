"""``escort-rl bench frontier``: which filter, at which N and K, for a time budget, on any model."""

from __future__ import annotations

import json
from pathlib import Path

from escort_rl.bench.core import options
from escort_rl.bench.frontier.cells import FILTER_METHODS, parse_variant
from escort_rl.bench.frontier.spec import DEFAULT_OUTPUT, METRICS, FrontierSpec
from escort_rl.reporting.metadata import with_metadata

FLAGS = ("seeds", "steps", "reference_particles", "reference_filter", "threads")
"""The options that set the spec's field of the same name when given (else ``--quick``'s or the default)."""


def _numbers(values) -> str:
    return " ".join(map(str, values))


def quick_help() -> str:
    """What ``bench frontier --quick`` runs (a few minutes on two cores)."""
    q = FrontierSpec.quick()
    return (f"N of SIR/EnKF {_numbers(q.particles['sir'])}, of SVGD/ESCORT {_numbers(q.particles['svgd'])}, K "
            f"{_numbers(q.iterations)}, {q.seeds} seeds, {q.steps} steps, a {q.reference_particles}-particle "
            "reference")


def register(subparsers) -> None:
    full = FrontierSpec()
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
    options.add_seeds_option(p, None, "shared trajectories", str(full.seeds))
    p.add_argument("--steps", type=int, default=None, help=f"updates per trajectory (default: {full.steps})")
    p.add_argument("--metric", choices=METRICS, default=full.metric, help="the front's distance (w1: sliced W1)")
    p.add_argument("--reference-particles", type=int, default=None, metavar="N",
                   help="N of the SIR reference for a model without an exact posterior (default: "
                   f"{full.reference_particles})")
    add_reference_filter_option(p)
    options.add_quick_option(p, quick_help())
    options.add_output_option(p, DEFAULT_OUTPUT, "frontier.json, frontier.md, frontier.png and cells/")
    options.add_runner_options(p, seeds_per_cell=False)
    p.set_defaults(handler=main)


def add_reference_filter_option(p) -> None:
    """``--reference-filter``, shared with ``bench regime-map``."""
    from escort_rl.metrics.reference import REFERENCE_METHODS

    p.add_argument("--reference-filter", choices=sorted(REFERENCE_METHODS), default=None,
                   help="the reference's filter where the model has no exact posterior: sir, resample_move "
                   "(tempered stages that keep ESS/N at 0.5, random-walk Metropolis moves after each; about 10x "
                   "SIR's cost), or rao_blackwell (particles on part of the state, the rest a Gaussian sum in "
                   "closed form, for a model that gives that form, e.g. env=hidden_goal) (default: sir)")


def add_method_options(p) -> None:
    """``--methods``, ``--<method>-particles``, ``--num-steps`` and ``--variant``, shared with
    ``bench regime-map``."""
    full = FrontierSpec()
    p.add_argument("--methods", nargs="+", default=list(full.methods), help="the filters swept")
    for m in FILTER_METHODS:
        p.add_argument(f"--{m}-particles", type=int, nargs="+", default=None, metavar="N",
                       help=f"N of {m} (default: {_numbers(full.particles[m])})")
    p.add_argument("--num-steps", type=int, nargs="+", default=None, metavar="K",
                   help=f"K of SVGD and ESCORT (default: {_numbers(full.iterations)})")
    options.add_labelled_option(p, "--variant", "one more row, a filter with its own settings swept over its method's "
                                "N (and K); the overrides are filter=METHOD and filter.KEY=VALUE",
                                "escort_stop filter=escort filter.stop_tolerance=0.05")


def frontier_variants(items) -> tuple:
    """``--variant`` as ``((name, method, ("KEY=VALUE", ...)), ...)``, names unique."""
    options.labelled(items, "--variant")
    return tuple(map(parse_variant, items))


def method_settings(args) -> dict:
    """The settings of :func:`add_method_options` given explicitly, as :class:`FrontierSpec` fields
    (``particles``: the filters whose N was given)."""
    out = {"methods": args.methods, "variants": frontier_variants(args.variant),
           "particles": {m: getattr(args, f"{m}_particles") for m in FILTER_METHODS
                         if getattr(args, f"{m}_particles") is not None}}
    if args.num_steps is not None:
        out["iterations"] = args.num_steps
    return out


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
    return (f"env:{env}" if env else FrontierSpec().model), tuple(env_args)


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
    (out / "frontier.json").write_text(json.dumps(with_metadata(result), indent=1))
    (out / "frontier.md").write_text(md)
    if echo:
        print(md)
        print(f"results: {out.resolve()}")


def spec_from_args(args) -> FrontierSpec:
    """The run ``args`` ask for: each setting given explicitly, else ``--quick``'s, else the default
    (:meth:`FrontierSpec.quick`, :meth:`FrontierSpec.full`)."""
    model, model_args = model_spec(args)
    explicit = {name: getattr(args, name) for name in FLAGS if getattr(args, name) is not None}
    make = FrontierSpec.quick if args.quick else FrontierSpec.full
    compile = options.compile_override([o for o in args.overrides if o.startswith("filter.")])
    return make(model=model, model_args=model_args, compile=compile, metric=args.metric, output=Path(args.output),
                **method_settings(args), **explicit)


def main(args) -> None:
    from escort_rl.bench.core.runner import backend_from_args
    from escort_rl.bench.frontier.run import label, run_frontier

    spec = spec_from_args(args)
    spec.output.mkdir(parents=True, exist_ok=True)

    def show(row):
        err = "diverged" if row.get("failed") else f"{row['error']:.4g}"
        print(f"{label(row):>24}: {row['ms_per_update']:.3g} ms, {spec.metric} {err}", flush=True)

    result = run_frontier(spec, backend_from_args(args), progress=show)
    write_frontier(spec.output, result)
