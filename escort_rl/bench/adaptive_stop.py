"""The adaptive stop of the particle evolution (``filter.stop_tolerance``): iterations used per
update on each domain, and what it does to the position error and to calibration.

For each domain and tolerance, ESCORT (``filter=escort``, ``K`` the cap) runs on protocol (a)'s
shared trajectories (uniform-random actions, the same seeds for every tolerance); the row gives the
mean iterations per belief update, the final and time-averaged position error (mean ± s.e. over the
seeds) and the filter's seconds per step. The calibration rows run the same tolerances on the
linear-Gaussian episode against the Kalman filter (:func:`escort_rl.bench.calibration.kalman_calibration`).
A tolerance of 0 is the filter without the stop: every update runs ``K`` iterations.
"""

from __future__ import annotations

from escort_rl.bench.calibration import kalman_calibration
from escort_rl.bench.core import options
from escort_rl.bench.methods import build_domain, build_method, check_names
from escort_rl.bench.trajectories import filter_trajectories, generate_trajectories
from escort_rl.reporting.stats import mean_se


def adaptive_stop_rows(domains: list[str], tolerances: list[float], seeds: int = 8, steps: int = 30,
                       n: int = 100, method: str = "escort", progress=None) -> list[dict]:
    """One row per (domain, tolerance): ``iterations``, ``final_error`` and ``mean_error`` (mean, s.e.),
    ``seconds_per_step``; and one row per tolerance with ``domain == "calibration"``: ``mahalanobis``,
    ``variance_ratio`` and ``iterations`` on the Kalman episode."""
    check_names(domains, [method])
    rows = []
    seed_list = list(range(seeds))
    for domain in domains:
        model, _ = build_domain(domain)
        traj = generate_trajectories(model, steps, seed_list)
        for tol in tolerances:
            out = filter_trajectories(domain, method, traj, seed_list, n, filter_set=(("stop_tolerance", str(tol)),))
            if out["failed"]:
                raise RuntimeError(f"{method} on {domain} with stop_tolerance={tol}: {out['failed']['message']}")
            errors = out["errors"]
            row = {"domain": domain, "tolerance": tol, "iterations": out["iterations"],
                   "final_error": mean_se(errors[:, -1].tolist()),
                   "mean_error": mean_se(errors[:, 1:].mean(1).tolist()),
                   "seconds_per_step": out["seconds"] / out["timed_steps"]}
            rows.append(row)
            if progress is not None:
                progress(row)
    for tol in tolerances:
        filt = build_method("lightdark10d", method, (("stop_tolerance", str(tol)),))
        maha, ratio = kalman_calibration(filt)
        row = {"domain": "calibration", "tolerance": tol, "iterations": filt.mean_iterations(),
               "mahalanobis": maha, "variance_ratio": ratio}
        rows.append(row)
        if progress is not None:
            progress(row)
    return rows


def adaptive_stop_markdown(rows: list[dict], method: str = "escort") -> str:
    domain_rows = [r for r in rows if r["domain"] != "calibration"]
    lines = ["# Adaptive stop", "",
             f"`filter={method}` (K = 50 is the cap) on protocol (a)'s shared trajectories; mean ± s.e. over the "
             "seeds. Tolerance 0: no stop.", "",
             "| domain | stop_tolerance | iterations per update | final position error | mean position error | "
             "ms per step |", "| --- | --- | --- | --- | --- | --- |"]
    for r in domain_rows:
        lines.append(f"| {r['domain']} | {r['tolerance']:g} | {r['iterations']:.1f} | "
                     f"{r['final_error'][0]:.3f} ± {r['final_error'][1]:.3f} | "
                     f"{r['mean_error'][0]:.3f} ± {r['mean_error'][1]:.3f} | {1e3 * r['seconds_per_step']:.0f} |")
    lines += ["", "Calibration against the Kalman filter (linear-Gaussian, d = 4, N = 300, 12 steps, 4 episodes; "
              "the calibration bounds: Mahalanobis < 0.6, variance ratio in [0.6, 1.6]):", "",
              "| stop_tolerance | iterations per update | mean Mahalanobis error | variance ratio |",
              "| --- | --- | --- | --- |"]
    for r in rows:
        if r["domain"] == "calibration":
            lines.append(f"| {r['tolerance']:g} | {r['iterations']:.1f} | {r['mahalanobis']:.3f} | "
                         f"{r['variance_ratio']:.3f} |")
    return "\n".join(lines) + "\n"


def register(subparsers) -> None:
    """Add ``bench adaptive-stop`` to the ``bench`` subparsers."""
    from escort_rl.bench.methods import DOMAINS

    stop = subparsers.add_parser("adaptive-stop", help="ESCORT's adaptive stop: iterations used, error, calibration",
                                 description="ESCORT (K = 50 the cap) with each --tolerances value of "
                                 "filter.stop_tolerance on protocol (a)'s trajectories of each domain, and on the "
                                 "Kalman calibration episode; writes adaptive_stop.md and adaptive_stop.json.")
    stop.add_argument("--domains", nargs="+", default=None,
                      help=f"env configs (default: {' '.join(DOMAINS)}; --quick: {QUICK['domains'][0]})")
    stop.add_argument("--tolerances", type=float, nargs="+", default=None,
                      help="values of filter.stop_tolerance; 0: no stop (default: 0 0.05 0.1; --quick: 0 0.1)")
    options.add_seeds_option(stop, None, "seeds 0..N-1 of the shared trajectories", f"8; --quick: {QUICK['seeds']}")
    stop.add_argument("--steps", type=int, default=None,
                      help=f"steps per trajectory (default: 30; --quick: {QUICK['steps']})")
    options.add_quick_option(stop, "lightdark10d, tolerances 0 0.1, 2 seeds, 5 steps")
    options.add_threads_option(stop)
    options.add_output_option(stop, "outputs/bench/adaptive_stop", "adaptive_stop.md and adaptive_stop.json")
    stop.set_defaults(handler=main)


QUICK = dict(domains=["lightdark10d"], tolerances=[0.0, 0.1], seeds=2, steps=5)
"""``--quick``: one domain, two tolerances, 2 seeds of 5 steps."""


def main(args) -> None:
    import math
    from pathlib import Path

    from escort_rl.bench.methods import DOMAINS
    from escort_rl.reporting.paths import write_results

    full = dict(domains=list(DOMAINS), tolerances=[0.0, 0.05, 0.1], seeds=8, steps=30)
    kw = {k: getattr(args, k) if getattr(args, k) is not None else (QUICK if args.quick else full)[k] for k in full}
    if any(not (t >= 0 and math.isfinite(t)) for t in kw["tolerances"]):
        raise ValueError(f"--tolerances: each must be a finite number >= 0, got {kw['tolerances']}")
    options.set_threads(args)
    rows = adaptive_stop_rows(kw["domains"], kw["tolerances"], seeds=kw["seeds"], steps=kw["steps"],
                              progress=lambda r: print(f"{r['domain']:>12} tol={r['tolerance']:g}: "
                                                       f"{r['iterations']:.1f} iterations", flush=True))
    write_results(Path(args.output), "adaptive_stop", rows, adaptive_stop_markdown(rows))
