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
from escort_rl.bench.domains import (build_domain, build_method, check_names, filter_trajectories, generate_trajectories,
                                     mean_se)


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
              "bounds of SPEC §4: Mahalanobis < 0.6, variance ratio in [0.6, 1.6]):", "",
              "| stop_tolerance | iterations per update | mean Mahalanobis error | variance ratio |",
              "| --- | --- | --- | --- |"]
    for r in rows:
        if r["domain"] == "calibration":
            lines.append(f"| {r['tolerance']:g} | {r['iterations']:.1f} | {r['mahalanobis']:.3f} | "
                         f"{r['variance_ratio']:.3f} |")
    return "\n".join(lines) + "\n"
