"""The regime map (``escort-rl bench regime-map``): the frontier over dimension × observation
sharpness of a model family; by default the linear-Gaussian family, whose exact posterior is Kalman's.

Each point ``(D, r)`` is a whole frontier (:func:`~escort_rl.bench.frontier.run.run_frontier`) of
``env=<env> env.<dim_key>=D env.<sharpness_key>=r`` in its own folder, so a killed map resumes cell
by cell. Another family is another env and its two keys, e.g. Light-Dark in more dimensions:
``--env lightdark10d --dim-key model.n_pos --sharpness-key model.sigma_base``. The map says, per point,
which filters are on the Pareto front and which filter
is closest at each time budget; if ESCORT is on no front, it says so.
"""

from __future__ import annotations

from pathlib import Path

from escort_rl.bench.core import options
from escort_rl.bench.frontier.cli import write_frontier
from escort_rl.bench.frontier.report import METRIC_NAMES
from escort_rl.bench.frontier.run import BUDGETS_MS, label, run_frontier


def point_folder(root: Path, dim: int, obs_std: float) -> Path:
    return Path(root) / f"D{dim}_obs{obs_std:g}"


def run_regime_map(dims, obs_stds, root: Path, progress=None, make_backend=None, env: str = "linear_gaussian",
                   dim_key: str = "model.state_dim", sharpness_key: str = "model.obs_std", model: str | None = None,
                   **frontier) -> dict:
    """The frontier at every ``(D, r)``: ``env.<dim_key>=D env.<sharpness_key>=r``, or with ``model``
    (``pkg.module:Class``, a user's class or factory) its keyword arguments ``<dim_key>=D
    <sharpness_key>=r``; ``make_backend()`` gives each point its backend (a frontier closes its own),
    ``frontier`` goes to :func:`run_frontier`."""
    spec = f"class:{model}" if model else f"env:{env}"
    points = []
    for d in dims:
        for r in obs_stds:
            result = run_frontier(spec, (f"{dim_key}={int(d)}", f"{sharpness_key}={float(r)}"),
                                  output=point_folder(root, d, r), progress=progress,
                                  backend=make_backend() if make_backend else None, **frontier)
            write_frontier(point_folder(root, d, r), result, echo=False)
            points.append({"dim": int(d), "obs_std": float(r), "state_dim": result["state_dim"],
                           "front": result["front"], "budgets": result["budgets"], "metric": result["metric"],
                           "reference": result["reference"], "reference_ess": result.get("reference_ess"),
                           "methods_on_front": sorted({f.split()[0] for f in result["front"]}),
                           "filters_on_front": sorted({r.get("base", r["method"]) for r in result["rows"]
                                                       if label(r) in result["front"]}),
                           "filters_on_fronts": {m: sorted({r.get("base", r["method"]) for r in result["rows"]
                                                            if label(r) in f}) for m, f in result["fronts"].items()}})
    return {"env": env, "model": model, "dim_key": dim_key, "sharpness_key": sharpness_key,
            "dims": [int(d) for d in dims], "obs_stds": [float(r) for r in obs_stds], "points": points,
            "budgets_ms": list(BUDGETS_MS)}


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
    lines.append("**ESCORT (or a variant of it) is on the "
                 f"{METRIC_NAMES.get(points[0]['metric'], '') if points else ''} "
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


QUICK = dict(dims=[2, 4], obs_std=[1.0])
"""``--quick``: two dimensions, one sharpness, and ``bench frontier --quick``'s points at each."""


def register(subparsers) -> None:
    from escort_rl.bench.frontier.cli import QUICK as FRONTIER_QUICK
    from escort_rl.bench.frontier.cli import add_method_options

    quick = {**FRONTIER_QUICK, **QUICK}

    p = subparsers.add_parser("regime-map", help="the frontier over dimension x observation sharpness "
                              "(default: linear-Gaussian, exact reference)",
                              description="Run bench frontier at every (dimension, sharpness) of a model family "
                              "(default: the linear-Gaussian family's state_dim x obs_std) and say where each "
                              "filter is on the accuracy-time front.")
    options.add_overrides_argument(p, "filter.compile=true: SVGD and ESCORT compiled (the first update is not timed)")
    p.add_argument("--env", default="linear_gaussian", help="the family's env config")
    p.add_argument("--model", default=None, metavar="pkg.module:Class", help="a model class or factory of your "
                   "own instead of --env; --dim-key and --sharpness-key name its keyword arguments (e.g. "
                   "--model escort_rl.bench.synthetic.tracking:gmm_tracking --dim-key dim --sharpness-key noise_scale)")
    p.add_argument("--dim-key", default="model.state_dim", help="the env key of the dimension axis "
                   "(Light-Dark: model.n_pos)")
    p.add_argument("--sharpness-key", default="model.obs_std", help="the env key of the sharpness axis "
                   "(Light-Dark: model.sigma_base)")
    p.add_argument("--dims", type=int, nargs="+", default=None, metavar="D",
                   help=f"the dimension axis (default: 10 20 50 100 200; --quick: {' '.join(map(str, QUICK['dims']))})")
    p.add_argument("--obs-std", type=float, nargs="+", default=None,
                   help=f"the sharpness axis (default: 0.1 1.0; --quick: {' '.join(map(str, QUICK['obs_std']))})")
    add_method_options(p)
    options.add_seeds_option(p, None, "shared trajectories per point", f"5; --quick: {quick['seeds']}")
    p.add_argument("--steps", type=int, default=None,
                   help=f"updates per trajectory (default: 20; --quick: {quick['steps']})")
    p.add_argument("--reference-particles", type=int, default=None, metavar="N",
                   help="N of the SIR reference where the family has no exact posterior (default: 100000; --quick: "
                   f"{quick['reference_particles']})")
    options.add_quick_option(p, "dimensions 2 4, obs_std 1.0, and bench frontier's --quick points at each")
    options.add_output_option(p, "outputs/bench/regime_map", "regime_map.md, regime_map.json, regime_map.png and a "
                      "folder per point")
    options.add_runner_options(p, seeds_per_cell=False)
    p.set_defaults(handler=main)


def main(args) -> None:
    from escort_rl.bench.core.runner import backend_from_args
    from escort_rl.bench.frontier.cells import FILTER_METHODS
    from escort_rl.bench.frontier.cli import QUICK as FRONTIER_QUICK
    from escort_rl.bench.frontier.cli import frontier_variants
    from escort_rl.bench.frontier.run import DEFAULT_ITERATIONS, DEFAULT_PARTICLES
    from escort_rl.reporting.paths import write_results

    quick = {**FRONTIER_QUICK, **QUICK} if args.quick else {}
    full = dict(dims=[10, 20, 50, 100, 200], obs_std=[0.1, 1.0], seeds=5, steps=20, reference_particles=100_000)
    kw = {k: getattr(args, k) if getattr(args, k) is not None else quick.get(k, full[k]) for k in full}
    particles = {m: getattr(args, f"{m}_particles") or quick.get("particles", DEFAULT_PARTICLES)[m]
                 for m in FILTER_METHODS}
    variants = frontier_variants(args.variant)
    out = Path(args.output)

    def show(row):
        print(f"{row['method']:>7} N={row['particles']:<6} K={row['num_steps']:<3}: {row['ms_per_update']:.3g} ms, "
              f"error {row['error']:.4g}", flush=True)

    from escort_rl.reporting.plots import plot_regime_map

    result = run_regime_map(kw["dims"], kw["obs_std"], out, progress=show, env=args.env, model=args.model,
                            dim_key=args.dim_key,
                            sharpness_key=args.sharpness_key, methods=args.methods, particles=particles,
                            iterations=args.num_steps or quick.get("iterations", DEFAULT_ITERATIONS),
                            seeds=kw["seeds"], steps=kw["steps"], compile=options.compile_override(args.overrides),
                            make_backend=lambda: backend_from_args(args),
                            reference_particles=kw["reference_particles"], variants=variants,
                            threads=args.threads or 1)
    plot_regime_map(result["points"], out / "regime_map.png",
                    title=f"{args.model or 'env=' + args.env}: the closest filter to the reference per time budget")
    write_results(out, "regime_map", result, regime_markdown(result))
