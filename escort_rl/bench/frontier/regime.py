"""The regime map (``escort-rl bench regime-map``): the frontier over dimension × observation
sharpness of a model family; by default the linear-Gaussian family, whose exact posterior is Kalman's.

Each point ``(D, r)`` is a whole frontier (:func:`~escort_rl.bench.frontier.run.run_frontier`) of
``env=<env> env.<dim_key>=D env.<sharpness_key>=r`` in its own folder, so a killed map resumes cell
by cell. Another family is another env and its two keys, e.g. Light-Dark in more dimensions:
``--env lightdark10d --dim-key model.n_pos --sharpness-key model.sigma_base``. The map says, per
point, which filters are on the Pareto front and which filter is closest at each time budget; if
ESCORT is on no front, it says so.
"""

from __future__ import annotations

from pathlib import Path

from escort_rl.bench.core import options
from escort_rl.bench.frontier.cli import write_frontier
from escort_rl.bench.frontier.report import METRIC_NAMES
from escort_rl.bench.frontier.run import BUDGETS_MS, label, run_frontier
from escort_rl.bench.frontier.spec import REGIME_OUTPUT, FrontierSpec, RegimeSpec


def run_regime_map(spec: RegimeSpec, progress=None, make_backend=None) -> dict:
    """The frontier at every ``(D, r)`` of ``spec``: ``env.<dim_key>=D env.<sharpness_key>=r``, or
    with ``spec.model`` (``pkg.module:Class``, a user's class or factory) its keyword arguments
    ``<dim_key>=D <sharpness_key>=r``, each with ``spec.frontier``'s settings in its own folder
    (:meth:`~escort_rl.bench.frontier.spec.RegimeSpec.point`); ``make_backend()`` gives each point
    its backend (a frontier closes its own), ``progress(row)`` is called per row."""
    if spec.output is None:
        raise ValueError("--output: the regime map needs a folder, with a folder per point in it")
    points = []
    for d in spec.dims:
        for r in spec.obs_stds:
            point = spec.point(d, r)
            result = run_frontier(point, make_backend() if make_backend else None, progress=progress)
            write_frontier(point.output, result, echo=False)
            points.append(_point(d, r, result))
    return {"env": spec.env, "model": spec.model, "dim_key": spec.dim_key, "sharpness_key": spec.sharpness_key,
            "dims": list(spec.dims), "obs_stds": list(spec.obs_stds), "points": points,
            "budgets_ms": list(BUDGETS_MS)}


def _point(dim: int, obs_std: float, result: dict) -> dict:
    """What the map keeps of the frontier ``result`` at ``(dim, obs_std)``."""
    def filters_on(front) -> list:
        return sorted({r.get("base", r["method"]) for r in result["rows"] if label(r) in front})

    return {"dim": int(dim), "obs_std": float(obs_std), "state_dim": result["state_dim"],
            "front": result["front"], "budgets": result["budgets"], "metric": result["metric"],
            "reference": result["reference"], "reference_ess": result.get("reference_ess"),
            "methods_on_front": sorted({f.split()[0] for f in result["front"]}),
            "filters_on_front": filters_on(result["front"]),
            "filters_on_fronts": {m: filters_on(f) for m, f in result["fronts"].items()}}


def regime_markdown(result: dict) -> str:
    points = result["points"]
    escort_on = [p for p in points if "escort" in p.get("filters_on_front", p["methods_on_front"])]
    env, dk, sk = (result.get("env", "linear_gaussian"), result.get("dim_key", "model.state_dim"),
                   result.get("sharpness_key", "model.obs_std"))
    model = result.get("model")
    family = f"--model {model}" if model else f"env={env}"
    command = (f"escort-rl bench frontier --model {model} --model-arg {dk}=D {sk}=r" if model
               else f"escort-rl bench frontier env={env} env.{dk}=D env.{sk}=r")
    kinds = sorted({p["reference"].split(" (")[0] for p in points})
    lines = [f"# Regime map: which filter is on the accuracy–time front ({family})", "",
             "Each row: the filters on the Pareto front of "
             f"{points[0]['metric'] if points else ''} to the reference posterior ({', '.join(kinds)}; each "
             "point's `frontier.md` says more) against ms per update, and the closest filter at 1, 10 and "
             f"100 ms per update. One frontier per point (`{command}`).", ""]
    metric_name = METRIC_NAMES.get(points[0]["metric"], "") if points else ""
    lines.append(f"**ESCORT (or a variant of it) is on the {metric_name} "
                 "front at: " + (", ".join(f"D = {p['dim']}, r = {p['obs_std']:g}"
                                                        for p in escort_on) if escort_on else "no point of this map")
                 + ".**")
    with_ess = any(p.get("reference_ess") for p in points)
    others = [m for m in ("mmd2", "mean", "cov") if all("filters_on_fronts" in p for p in points) and points]
    escort_other = {m: [p for p in points if "escort" in p["filters_on_fronts"][m]] for m in others}
    for m, on in escort_other.items():
        lines.append(f"On the {METRIC_NAMES[m]} front: " + (", ".join(
            f"D = {p['dim']}, r = {p['obs_std']:g}" for p in on) if on else "no point") + ".")
    lines += ["", f"| {dk} = D | {sk} = r | state dim | on the front | best at 1 ms | best at 10 ms | best at 100 ms |"
              + "".join(f" on the {METRIC_NAMES[m]} front |" for m in others)
              + (" reference ESS (median) |" if with_ess else ""),
              "| --- | --- | --- | --- | --- | --- | --- |" + " --- |" * len(others) + (" --- |" if with_ess else "")]
    for p in points:
        best = {b["ms"]: b["best"] or "—" for b in p["budgets"]}
        ess = p.get("reference_ess")
        lines.append(f"| {p['dim']} | {p['obs_std']:g} | {p.get('state_dim', p['dim'])} | "
                     f"{', '.join(p['methods_on_front'])} "
                     f"| {best.get(1.0, '—')} | {best.get(10.0, '—')} | {best.get(100.0, '—')} |"
                     + "".join(f" {', '.join(p['filters_on_fronts'][m])} |" for m in others)
                     + (f" {ess['median']:.0f} |" if with_ess and ess else (" — |" if with_ess else "")))
    return "\n".join(lines) + "\n"


def register(subparsers) -> None:
    from escort_rl.bench.frontier.cli import add_method_options, add_reference_filter_option

    full, quick = RegimeSpec(), RegimeSpec.quick()
    p = subparsers.add_parser("regime-map", help="the frontier over dimension x observation sharpness "
                              "(default: linear-Gaussian, exact reference)",
                              description="Run bench frontier at every (dimension, sharpness) of a model family "
                              "(default: the linear-Gaussian family's state_dim x obs_std) and say where each "
                              "filter is on the accuracy-time front.")
    options.add_overrides_argument(p, "filter.compile=true: SVGD and ESCORT compiled (the first update is not timed)")
    p.add_argument("--env", default=full.env, help="the family's env config")
    p.add_argument("--model", default=full.model, metavar="pkg.module:Class", help="a model class or factory of "
                   "your own instead of --env; --dim-key and --sharpness-key name its keyword arguments (e.g. "
                   "--model escort_rl.bench.synthetic.tracking:gmm_tracking --dim-key dim --sharpness-key "
                   "noise_scale)")
    p.add_argument("--dim-key", default=full.dim_key, help="the env key of the dimension axis "
                   "(Light-Dark: model.n_pos)")
    p.add_argument("--sharpness-key", default=full.sharpness_key, help="the env key of the sharpness axis "
                   "(Light-Dark: model.sigma_base)")
    p.add_argument("--dims", type=int, nargs="+", default=None, metavar="D",
                   help=f"the dimension axis (default: {_numbers(full.dims)}; --quick: {_numbers(quick.dims)})")
    p.add_argument("--obs-std", type=float, nargs="+", default=None,
                   help=f"the sharpness axis (default: {_numbers(full.obs_stds)}; --quick: "
                   f"{_numbers(quick.obs_stds)})")
    add_method_options(p)
    point, quick_point = full.frontier, quick.frontier
    options.add_seeds_option(p, None, "shared trajectories per point", f"{point.seeds}; --quick: {quick_point.seeds}")
    p.add_argument("--steps", type=int, default=None,
                   help=f"updates per trajectory (default: {point.steps}; --quick: {quick_point.steps})")
    p.add_argument("--reference-particles", type=int, default=None, metavar="N",
                   help="N of the SIR reference where the family has no exact posterior (default: "
                   f"{point.reference_particles}; --quick: {quick_point.reference_particles})")
    add_reference_filter_option(p)
    options.add_quick_option(p, f"dimensions {_numbers(quick.dims)}, obs_std {_numbers(quick.obs_stds)}, and bench "
                             "frontier's --quick points at each")
    options.add_output_option(p, REGIME_OUTPUT, "regime_map.md, regime_map.json, regime_map.png and a folder per "
                              "point")
    options.add_runner_options(p, seeds_per_cell=False)
    p.set_defaults(handler=main)


def _numbers(values) -> str:
    return " ".join(map(str, values))


def spec_from_args(args) -> RegimeSpec:
    """The map ``args`` ask for: each setting given explicitly, else ``--quick``'s, else the default
    (:meth:`RegimeSpec.quick`, :meth:`RegimeSpec.full`); each point's settings likewise."""
    from escort_rl.bench.frontier.cli import method_settings

    explicit = {name: getattr(args, name) for name in ("seeds", "steps", "reference_particles", "reference_filter",
                                                       "threads")
                if getattr(args, name) is not None}
    point = dict(compile=options.compile_override(args.overrides), **method_settings(args), **explicit)
    axes = {name: getattr(args, flag) for name, flag in (("dims", "dims"), ("obs_stds", "obs_std"))
            if getattr(args, flag) is not None}
    if args.quick:
        return RegimeSpec.quick(FrontierSpec.quick(**point), env=args.env, model=args.model, dim_key=args.dim_key,
                                sharpness_key=args.sharpness_key, output=Path(args.output), **axes)
    return RegimeSpec.full(FrontierSpec.full(**point), env=args.env, model=args.model, dim_key=args.dim_key,
                           sharpness_key=args.sharpness_key, output=Path(args.output), **axes)


def main(args) -> None:
    from escort_rl.bench.core.runner import backend_from_args
    from escort_rl.reporting.paths import write_results
    from escort_rl.reporting.plots import plot_regime_map

    spec = spec_from_args(args)

    def show(row):
        print(f"{row['method']:>7} N={row['particles']:<6} K={row['num_steps']:<3}: {row['ms_per_update']:.3g} ms, "
              f"error {row['error']:.4g}", flush=True)

    result = run_regime_map(spec, progress=show, make_backend=lambda: backend_from_args(args))
    plot_regime_map(result["points"], spec.output / "regime_map.png",
                    title=f"{args.model or 'env=' + args.env}: the closest filter to the reference per time budget")
    write_results(spec.output, "regime_map", result, regime_markdown(result))
