"""The regime map (``escort-rl bench regime-map``): the frontier over dimension × observation
sharpness on the linear-Gaussian family, whose exact posterior is Kalman's.

Each point ``(D, r)`` is a whole frontier (:func:`~escort_rl.bench.frontier.run.run_frontier`) of
``env=linear_gaussian env.model.state_dim=D env.model.obs_std=r`` in its own folder, so a killed map
resumes cell by cell. The map says, per point, which filters are on the Pareto front and which filter
is closest at each time budget; if ESCORT is on no front, it says so.
"""

from __future__ import annotations

from pathlib import Path

from escort_rl.bench.frontier.cli import write_frontier
from escort_rl.bench.frontier.run import BUDGETS_MS, run_frontier


def point_folder(root: Path, dim: int, obs_std: float) -> Path:
    return Path(root) / f"D{dim}_obs{obs_std:g}"


def run_regime_map(dims, obs_stds, root: Path, progress=None, make_backend=None, **frontier) -> dict:
    """The frontier at every ``(D, obs_std)``; ``make_backend()`` gives each point its backend (a
    frontier closes its own), ``frontier`` goes to :func:`run_frontier`."""
    points = []
    for d in dims:
        for r in obs_stds:
            result = run_frontier("env:linear_gaussian", (f"model.state_dim={int(d)}", f"model.obs_std={float(r)}"),
                                  output=point_folder(root, d, r), progress=progress,
                                  backend=make_backend() if make_backend else None, **frontier)
            write_frontier(point_folder(root, d, r), result, echo=False)
            points.append({"dim": int(d), "obs_std": float(r), "front": result["front"],
                           "budgets": result["budgets"], "metric": result["metric"],
                           "methods_on_front": sorted({f.split()[0] for f in result["front"]})})
    return {"dims": [int(d) for d in dims], "obs_stds": [float(r) for r in obs_stds], "points": points,
            "budgets_ms": list(BUDGETS_MS)}


def regime_markdown(result: dict) -> str:
    points = result["points"]
    escort_on = [p for p in points if "escort" in p["methods_on_front"]]
    lines = ["# Regime map: which filter is on the accuracy–time front (linear-Gaussian family)", "",
             "Each cell: the filters on the Pareto front of "
             f"{points[0]['metric'] if points else ''} to the exact (Kalman) posterior against ms per update, "
             "and the closest filter at 1, 10 and 100 ms per update. One frontier per point "
             "(`escort-rl bench frontier env=linear_gaussian env.model.state_dim=D env.model.obs_std=r`).", ""]
    lines.append("**ESCORT is on the front at: " + (", ".join(f"D = {p['dim']}, obs_std = {p['obs_std']:g}"
                                                        for p in escort_on) if escort_on else "no point of this map")
                 + ".**")
    lines += ["", "| D | obs_std | on the front | best at 1 ms | best at 10 ms | best at 100 ms |",
              "| --- | --- | --- | --- | --- | --- |"]
    for p in points:
        best = {b["ms"]: b["best"] or "—" for b in p["budgets"]}
        lines.append(f"| {p['dim']} | {p['obs_std']:g} | {', '.join(p['methods_on_front'])} | {best.get(1.0, '—')} | "
                     f"{best.get(10.0, '—')} | {best.get(100.0, '—')} |")
    return "\n".join(lines) + "\n"


def register(subparsers) -> None:
    from escort_rl.bench.frontier.cells import FILTER_METHODS
    from escort_rl.bench.runner import add_runner_arguments

    p = subparsers.add_parser("regime-map", help="the frontier over dimension x observation sharpness "
                              "(linear-Gaussian, exact reference)",
                              description="Run bench frontier at every (state_dim, obs_std) of the linear-Gaussian "
                              "family and say where each filter is on the accuracy-time front.")
    p.add_argument("--dims", type=int, nargs="+", default=[10, 20, 50, 100, 200], help="default 10 20 50 100 200")
    p.add_argument("--obs-std", type=float, nargs="+", default=[0.1, 1.0], help="default 0.1 1.0")
    p.add_argument("--methods", nargs="+", default=list(FILTER_METHODS))
    for m in FILTER_METHODS:
        p.add_argument(f"--{m}-particles", type=int, nargs="+", default=None, metavar="N")
    p.add_argument("--num-steps", type=int, nargs="+", default=None, metavar="K")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--compile", action="store_true")
    p.add_argument("--output", default="outputs/bench/regime_map")
    add_runner_arguments(p)
    p.set_defaults(handler=main)


def main(args) -> None:
    from escort_rl.bench.frontier.cells import FILTER_METHODS
    from escort_rl.bench.frontier.run import DEFAULT_ITERATIONS, DEFAULT_PARTICLES
    from escort_rl.bench.runner import backend_from_args
    from escort_rl.reporting.paths import write_results

    particles = {m: getattr(args, f"{m}_particles") or DEFAULT_PARTICLES[m] for m in FILTER_METHODS}
    out = Path(args.output)

    def show(row):
        print(f"{row['method']:>7} N={row['particles']:<6} K={row['num_steps']:<3}: {row['ms_per_update']:.3g} ms, "
              f"error {row['error']:.4g}", flush=True)

    from escort_rl.reporting.plots import plot_regime_map

    result = run_regime_map(args.dims, args.obs_std, out, progress=show, methods=args.methods, particles=particles,
                            iterations=args.num_steps or DEFAULT_ITERATIONS, seeds=args.seeds, steps=args.steps,
                            compile=args.compile, make_backend=lambda: backend_from_args(args),
                            threads=args.threads or 1)
    plot_regime_map(result["points"], out / "regime_map.png",
                    title="Linear-Gaussian family: the closest filter to the Kalman posterior per time budget")
    write_results(out, "regime_map", result, regime_markdown(result))
