"""Protocol (a)'s equal wall-clock table: each method's time per step is measured, one method at a
time with the cells' thread count, on a few steps of the same batch at each ``N'`` of the grid
(capped by ``max_particles``) plus the base ``N``; the method gets the largest ``N'`` whose time is
not above the reference method's time at the base ``N``, and its row is rerun at that ``N'`` as a
second grid of cells. The reference keeps the base ``N``; a method whose ``N'`` equals ``N`` reuses
its equal-N row."""

from __future__ import annotations

from escort_rl.bench.domains.grid import Grid, References
from escort_rl.bench.trajectories import NonFiniteBeliefError, time_per_step


def calibrate(grid: Grid, methods: list[str], trajectories: dict, sizes: list[int], reference: str,
              failed: dict) -> dict:
    """Per domain: the reference's seconds per step at ``N`` (the budget), each other method's
    seconds per step at each of ``sizes`` (stopping at the first over the budget), and the ``N'``
    chosen: the largest within the budget, or the smallest of ``sizes`` (listed in ``over_budget``)
    if none is. ``failed``: domain -> methods whose equal-N run failed; they are not timed."""
    spec, out = grid.spec, {}
    n, seeds = spec.particles, grid.seeds

    def timed(d, m, k):
        return time_per_step(d, m, trajectories[d], seeds, k, spec.calibration_steps, spec.base_seed, spec.filter_set)

    for d in spec.domains:
        budget = timed(d, reference, n)
        calib, chosen = {}, {}
        for m in methods:
            if m == reference or m in failed.get(d, ()):  # a failed method keeps N (its failed row is reused)
                calib[m], chosen[m] = {str(n): (budget if m == reference else float("nan"))}, n
                continue
            times = {}
            for k in sizes:
                times[str(k)] = timed(d, m, k)
                if times[str(k)] > budget:
                    break  # time grows with N: larger N' cannot fit either
            fits = [int(k) for k, t in times.items() if t <= budget]
            calib[m], chosen[m] = times, (max(fits) if fits else sizes[0])
            if grid.progress is not None:
                grid.progress("calibration", {"domain": d, "method": m, "times": times, "budget": budget,
                                              "chosen": chosen[m]})
        out[d] = {"budget_seconds_per_step": budget, "calibration": calib, "chosen": chosen,
                  "over_budget": [m for m in methods if calib[m][str(chosen[m])] > budget]}
        if failed.get(d) and reference in failed[d]:
            raise NonFiniteBeliefError(f"the equal-time reference '{reference}' failed on '{d}'; pass --no-equal-time")
    return out


def equal_time_rows(grid: Grid, methods: list[str], rows: list[dict], trajectories: dict,
                    references: References) -> dict:
    """The equal wall-clock table of ``methods`` (the filter methods), given their equal-N ``rows``:
    the calibration per domain and the rows at each method's ``N'``."""
    spec = grid.spec
    n = spec.particles
    ref = spec.time_reference if spec.time_reference in methods else methods[0]
    sizes = sorted({int(k) for k in spec.particle_grid if k <= spec.max_particles} | {n})
    out = {"reference": ref, "reference_particles": n, "grid": sizes, "calibration_steps": spec.calibration_steps,
           "domains": {}, "rows": []}
    failed = {d: {r["method"] for r in rows if r["domain"] == d and r["failed"]} for d in spec.domains}
    choices = calibrate(grid, methods, trajectories, sizes, ref, failed)
    jobs = []
    for d in spec.domains:
        out["domains"][d] = choices[d]
        jobs += [(d, m, choices[d]["chosen"][m]) for m in methods if choices[d]["chosen"][m] != n]
    rerun = {(r["domain"], r["method"]): r for r in grid.run(jobs, references, desc="equal-time cells")}
    for d in spec.domains:
        for m in methods:
            if (d, m) in rerun:
                row = dict(rerun[(d, m)], reused_equal_n=False)
            else:  # N' equals the base N: the equal-N run is that row
                row = dict(next(r for r in rows if r["domain"] == d and r["method"] == m), reused_equal_n=True)
            row["calibrated_seconds_per_step"] = out["domains"][d]["calibration"][m][str(row["particles"])]
            out["rows"].append(row)
    return out
