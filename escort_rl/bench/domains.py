"""The domain benchmark, protocol (a) "shared trajectories", as a grid of cells.

Every method (a filter config name, so a new config is a new row; or a learned belief) filters the
same seeded action/observation sequences from the same seeded priors
(:mod:`escort_rl.bench.trajectories`). The grid's cells are (domain × method × block of seeds)
(:class:`FilterCell`, :class:`LearnedCell`): a cell regenerates its seeds' trajectories (the hashes
prove they are the driver's) and filters them as one batch ``[S, N, d]``. ``seeds_per_cell``
(default: all seeds of a row in one cell) is part of the cell, so the numbers do not depend on the
backend or the number of workers (:mod:`escort_rl.bench.core.runner`); each finished cell is saved under
``<output>/cells/`` and a rerun skips it.

Metrics, each mean ± standard error over seeds: the position error ``‖E_b[pos] − pos_true‖₂`` of the
weighted belief mean at every step (Light-Dark: the 5 position coordinates; Kidnapped Robot: dims
(0, 1); Multi-Target Tracking: ``model.position_error``, the mean over the four targets), its value
at the final step and its average over steps 1..T, and the wall-clock seconds per filter update
(summed over a row's cells). With ``reference_particles`` (the command's default 10⁵) every filter row
also gets its distances to a reference posterior at every step, for the position and the velocity
(:mod:`escort_rl.metrics.reference`): the reference cells run first, as their own grid phase.

Equal wall-clock table: each method's time per step is measured here, one method at a time with the
cells' thread count, on a few steps of the same batch at each ``N'`` of a grid (capped by
``max_particles``) plus the base ``N``; the method gets the largest ``N'`` whose time is not above the
reference method's (``escort``, or the first method when escort is not listed) time at the base
``N``, and protocol (a) is rerun at that ``N'`` as a second grid of cells. The reference keeps the
base ``N``; a method whose ``N'`` equals ``N`` reuses its equal-N row.
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from escort_rl.bench import methods as registry
from escort_rl.bench.core.options import (
    add_output_option,
    add_overrides_argument,
    add_quick_option,
    add_runner_options,
    add_seeds_option,
    filter_overrides,
)
from escort_rl.bench.core.runner import Cell, CellStore, backend_from_args, run_groups, seed_blocks
from escort_rl.bench.methods import applied_filter_set, build_domain, check_at_least_one, check_names
from escort_rl.bench.reference_cell import ReferenceCell
from escort_rl.bench.trajectories import (
    BEHAVIOUR_POLICY,
    NonFiniteBeliefError,
    filter_trajectories,
    generate_trajectories,
    learned_trajectories,
    position_error_label,
    time_per_step,
)
from escort_rl.metrics.reference import METRIC_LABELS, METRICS, SAMPLE, Reference, state_parts, summarize_series
from escort_rl.reporting.paths import display_path, write_results
from escort_rl.reporting.plots import plot_curve_panels, plot_curves
from escort_rl.reporting.stats import format_importance, format_mean_se, mean_se, merge_importance
from escort_rl.reporting.tables import method_table

PARTICLE_GRID = (50, 100, 200, 500, 1000, 2000, 5000, 10_000, 20_000, 50_000, 100_000)


# ---------------------------------------------------------------------------------------- cells
def _part(out: dict) -> dict:
    """A filtering output (:func:`filter_trajectories`) as a cell result: plain lists, and the
    wall-clock figures under ``timing`` (the only entries that differ between runs)."""
    part = {k: v for k, v in out.items() if k not in ("seconds", "first_seconds", "errors", "accuracy")}
    part["errors"] = out["errors"].tolist()
    accuracy = out.get("accuracy") or []
    if accuracy:  # the first reference's whole series; the doubled reference's per-seed summaries
        part["accuracy"] = {"series": {k: v.tolist() for k, v in accuracy[0].items()},
                            "checks": [summarize_series(a, out["steps"]) for a in accuracy[1:]]}
    part["timing"] = {"seconds": out["seconds"], "first_seconds": out["first_seconds"]}
    return part


@dataclass(frozen=True)
class FilterCell(Cell):
    """One filter method on one domain's shared trajectories of ``seeds`` (one batch).

    Examples:
        >>> cell = FilterCell(domain="lightdark10d", method="sir", particles=10, steps=2, seeds=(0, 1))
        >>> cell.key()
        'domains/lightdark10d/sir/N10-T2-seeds0-1'
        >>> len(cell.run()["errors"][0])  # [S, T + 1] position errors, index 0 the prior's
        3
    """

    domain: str
    method: str
    particles: int
    steps: int
    seeds: tuple
    base_seed: int = 0
    filter_set: tuple = ()
    references: tuple = ()
    """``((particles, file, hash), ...)``: the reference posteriors of these seeds
    (:class:`~escort_rl.bench.reference_cell.ReferenceCell` results) to compare the belief with."""
    reference_folder: str = ""
    """Where the reference files are; left out of :meth:`spec` (it is where, not what)."""

    def key(self) -> str:
        return (f"domains/{self.domain}/{self.method}/N{self.particles}-T{self.steps}-"
                f"seeds{self.seeds[0]}-{self.seeds[-1]}")

    def spec(self) -> dict:
        spec = super().spec()
        spec.pop("reference_folder")
        return spec

    def run(self) -> dict:
        model, _ = build_domain(self.domain)
        seeds = list(self.seeds)
        traj = generate_trajectories(model, self.steps, seeds, self.base_seed)
        refs = tuple(Reference.load(Path(self.reference_folder) / file, digest) for _, file, digest in self.references)
        for ref in refs:
            if ref.data["input_hashes"] != list(traj["hashes"]):
                raise RuntimeError(f"{self.key()}: its reference posterior was computed on other trajectories")
        part = _part(filter_trajectories(self.domain, self.method, traj, seeds, self.particles, self.base_seed,
                                         self.filter_set, refs))
        if "accuracy" in part:
            part["accuracy"]["references"] = [int(n) for n, _, _ in self.references]
        return part


@dataclass(frozen=True)
class LearnedCell(Cell):
    """A learned belief (DVRL, from ``checkpoint``) on one domain's shared trajectories of ``seeds``.
    Not stored: the checkpoint may be trained further between runs."""

    domain: str
    method: str
    steps: int
    seeds: tuple
    checkpoint: str
    base_seed: int = 0
    stored = False

    def key(self) -> str:
        return f"domains/{self.domain}/{self.method}/T{self.steps}-seeds{self.seeds[0]}-{self.seeds[-1]}"

    def run(self) -> dict:
        model, _ = build_domain(self.domain)
        seeds = list(self.seeds)
        traj = generate_trajectories(model, self.steps, seeds, self.base_seed)
        return _part(learned_trajectories(self.domain, self.method, traj, seeds, self.checkpoint, self.base_seed))


def train_learned_beliefs(domains, methods, runs_dir: Path, progress: bool = False) -> dict:
    """Train (or resume, or reuse) each learned-belief method of ``methods`` on each domain in
    ``runs_dir/<domain>/<method>``, with protocol (b)'s run config and budget (the same folder layout,
    so ``--output`` of a protocol (b) run can share its runs). Returns ``{(domain, method): checkpoint}``."""
    from escort_rl.bench.closed_loop import run_config, train_run

    settings = registry.load_settings()
    learned = registry.learned_methods(settings)
    out = {}
    for d in domains:
        for m in methods:
            if m in learned:
                cfg = run_config(d, "sir", int(settings["particles"]), Path(runs_dir) / d / m,
                                 settings["train"][d], trainer=learned[m]["trainer"])
                out[(d, m)] = train_run(cfg, progress=progress)["checkpoint"]
    return out


# ---------------------------------------------------------------------------------------- rows
def _accuracy(parts: list[dict], steps: int) -> dict | None:
    """The distances to the reference posterior of a row (its cells' ``accuracy``, in seed order):
    per key ``<part>/<metric>`` the per-seed final and time-averaged values, their mean ± s.e., the
    mean ± s.e. over seeds at every step, and ``checks``: the same summaries against the doubled
    reference."""
    acc = [p.get("accuracy") for p in parts]
    if not acc or any(a is None for a in acc):
        return None
    series = {k: torch.tensor([row for a in acc for row in a["series"][k]], dtype=torch.float64)
              for k in acc[0]["series"]}
    if not all(bool(torch.isfinite(v).all()) for v in series.values()):
        raise NonFiniteBeliefError("a distance to the reference posterior is NaN or Inf")
    per_seed = summarize_series(series, steps)
    b = next(iter(series.values())).shape[0]
    checks = []
    for i in range(len(acc[0]["checks"])):
        checks.append({k: {w: mean_se([x for a in acc for x in a["checks"][i][k][w]]) for w in ("final", "mean")}
                       for k in series})
    return {"references": acc[0]["references"], "per_seed": per_seed,
            "summary": {k: {w: mean_se(v[w]) for w in ("final", "mean")} for k, v in per_seed.items()},
            "over_time": {k: {"mean": v.mean(0).tolist(),
                              "se": (v.std(0, unbiased=True) / math.sqrt(b) if b > 1 else torch.zeros(v.shape[1])).tolist()}
                          for k, v in series.items()},
            "checks": checks}


def _row(domain: str, method: str, n: int, parts: list[dict], seeds: list[int]) -> dict:
    """A table row from the results of the row's cells (in seed order)."""
    failed = [p["failed"] for p in parts if p.get("failed")]
    if failed:  # a diverged belief: no error figures, the earliest failure is reported
        first = min(failed, key=lambda f: f["step"])
        nan = (float("nan"), float("nan"))
        return {"domain": domain, "method": method, "filter": parts[0]["filter"], "particles": n, "seeds": seeds,
                "steps": parts[0]["steps"], "failed": first, "summary": {"final_error": nan, "mean_error": nan},
                "input_hashes": [h for p in parts for h in p["input_hashes"]],
                "initial_belief_hashes": [h for p in parts for h in p["belief_hashes"]]}
    errors = torch.tensor([e for p in parts for e in p["errors"]], dtype=torch.float64)  # [B, T+1]
    b = errors.shape[0]
    steps = parts[0]["steps"]
    seconds = sum(p["timing"]["seconds"] for p in parts)
    timed = parts[0]["timed_steps"]
    first = sum(p["timing"]["first_seconds"] for p in parts)
    final = errors[:, -1]
    avg = errors[:, 1:].mean(1) if steps > 0 else errors[:, 0]
    se_t = errors.std(0, unbiased=True) / math.sqrt(b) if b > 1 else torch.zeros(errors.shape[1])
    if not torch.isfinite(errors).all() or (errors < 0).any():
        raise NonFiniteBeliefError(f"method '{method}' on domain '{domain}': the position error is NaN, Inf "
                                   "or negative")
    return {
        "domain": domain, "method": method, "filter": parts[0]["filter"], "particles": n, "seeds": seeds,
        "steps": steps, "failed": None,
        "per_seed": {"final_error": final.tolist(), "mean_error": avg.tolist()},
        "summary": {"final_error": mean_se(final.tolist()), "mean_error": mean_se(avg.tolist())},
        "error_over_time": {"mean": errors.mean(0).tolist(), "se": se_t.tolist()},
        "filter_seconds": seconds + first,
        "first_step_seconds": first,
        "seconds_per_step": seconds / timed,
        "seconds_per_step_per_env": seconds / timed / b,
        "input_hashes": [h for p in parts for h in p["input_hashes"]],
        "initial_belief_hashes": [h for p in parts for h in p["belief_hashes"]],
        "accuracy": _accuracy(parts, steps),
        "importance": merge_importance([p.get("importance") for p in parts]),
    }


class _Grid:
    """Runs (domain, method, N) rows as cells on a backend and assembles the rows."""

    def __init__(self, backend, store, seeds: list[int], per_cell, base_seed: int, horizon: dict, filter_set: tuple,
                 threads: int, learned: dict, progress) -> None:
        self.backend, self.store, self.seeds, self.base_seed = backend, store, seeds, base_seed
        self.blocks = seed_blocks(seeds, per_cell)
        self.horizon, self.filter_set, self.threads, self.learned = horizon, filter_set, threads, learned
        self.progress = progress
        self.references, self.reference_folder = {}, ""  # (domain, seed block) -> ((N, file, hash), ...)

    def cells(self, d: str, m: str, n: int) -> list[Cell]:
        common = dict(domain=d, method=m, steps=self.horizon[d], base_seed=self.base_seed, threads=self.threads)
        if (d, m) in self.learned:
            return [LearnedCell(seeds=b, checkpoint=str(self.learned[(d, m)]), **common) for b in self.blocks]
        return [FilterCell(particles=n, seeds=b, filter_set=self.filter_set, references=self.references.get((d, b), ()),
                           reference_folder=self.reference_folder, **common) for b in self.blocks]

    def run_references(self, domains: list[str], particles: int, sample: int, folder: Path,
                       trajectory_hashes: dict) -> dict:
        """Compute (or load) the reference posteriors at ``particles`` and ``2 × particles`` of every
        domain and seed block, point the method cells at them, and return per domain: the sizes,
        seconds, and the distance between the two references (the floor under the figures)."""
        sizes = (particles, 2 * particles)
        cells = {(d, b, n): ReferenceCell(domain=d, particles=n, steps=self.horizon[d], seeds=b, base_seed=self.base_seed,
                                          sample=sample, folder=str(folder), threads=self.threads)
                 for d in domains for b in self.blocks for n in sizes}
        if self.store is not None:  # a saved result whose file is gone or damaged is computed again
            for cell in cells.values():
                saved = self.store.load(cell)
                if saved is not None and not cell.valid(saved):
                    self.store.path(cell).unlink()
        results = {k: v[0] for k, v in run_groups({k: [c] for k, c in cells.items()}, self.backend, self.store,
                                                  desc="reference cells").items()}
        self.reference_folder = str(folder)
        self.references = {(d, b): tuple((n, results[(d, b, n)]["file"], results[(d, b, n)]["hash"]) for n in sizes)
                           for d in domains for b in self.blocks}
        out = {}
        for d in domains:
            hashes = [h for b in self.blocks for h in results[(d, b, particles)]["input_hashes"]]
            if hashes != trajectory_hashes[d]:
                raise RuntimeError(f"the reference posterior of '{d}' saw a different trajectory")
            floor = []
            for b in self.blocks:
                ref, ref2 = (Reference.load(folder / results[(d, b, n)]["file"], results[(d, b, n)]["hash"])
                             for n in sizes)
                steps = [ref.compare_reference(ref2, t) for t in range(self.horizon[d] + 1)]
                floor.append({k: torch.stack([s[k] for s in steps], 1) for k in steps[0]})
            series = {k: torch.cat([f[k] for f in floor]) for k in floor[0]}
            per_seed = summarize_series(series, self.horizon[d])
            out[d] = {"particles": list(sizes), "sample": sample,
                      "seconds": {str(n): sum(results[(d, b, n)]["timing"]["seconds"] for b in self.blocks)
                                  for n in sizes},
                      "floor": {k: {w: mean_se(v[w]) for w in ("final", "mean")} for k, v in per_seed.items()}}
        return out

    def run(self, jobs: list[tuple[str, str, int]], desc: str) -> list[dict]:
        """``jobs``: (domain, method, N). Rows in job order; each is reported to ``progress`` as
        soon as its last cell is in."""
        rows = {}

        def on_group(job, parts):
            rows[job] = _row(*job, parts, self.seeds)
            if self.progress is not None:
                self.progress("row", rows[job])

        run_groups({job: self.cells(*job) for job in jobs}, self.backend, self.store, on_group, desc)
        return [rows[job] for job in jobs]


# ---------------------------------------------------------------------------------------- protocol (a)
def run_domains(domains=registry.DOMAINS, methods=registry.PROTOCOL_A_METHODS, seeds: int = 30, n: int = 100,
                steps: int | None = None, backend=None, equal_time: bool = True, max_particles: int = 100_000,
                particle_grid=PARTICLE_GRID, reference: str = "escort", calibration_steps: int = 3,
                base_seed: int = 0, filter_set=(), threads: int | None = None, seeds_per_cell: int | None = None,
                progress=None, plot_dir=None, runs_dir=None, cells_dir=None, reference_particles: int = 0,
                reference_sample: int = SAMPLE) -> dict:
    """Protocol (a) for every method on every domain; per-seed values and mean ± s.e.

    ``steps``: the horizon (default: each domain's ``env.max_steps``). ``backend``: a runner backend
    (:func:`escort_rl.bench.core.runner.make_backend`; default in-process). ``threads``: torch threads in
    every cell and in the equal-time measurement (default 1: small batched updates are often fastest
    on one thread). ``seeds_per_cell``: seeds per cell (default all). ``filter_set``: (key, value)
    pairs set on every method's filter config that has the key (e.g. ``("num_steps", "10")``).
    ``progress(kind, payload)`` is called with ``("row", row)`` after each (domain, method) and
    ``("calibration", dict)`` after each equal-time measurement. With ``plot_dir``, writes
    ``error_over_time_<domain>.png``; with ``cells_dir``, each cell's result is saved there as it
    finishes and a rerun skips the finished cells. Learned-belief methods (``dvrl``) are trained
    first in ``runs_dir/<domain>/<method>`` (required for them; see :func:`train_learned_beliefs`);
    they have no particle count, so they sit out the equal-time table.

    ``reference_particles`` (0: none): the size N of the reference posterior
    (:mod:`escort_rl.metrics.reference`), computed at N and 2N on the same trajectories; every filter
    row then gets ``accuracy``, its distances to it at every step (``reference_sample`` reference
    particles per step for the sample-based ones). The reference files live under ``cells_dir``
    (a temporary folder without it).

    Examples:
        >>> r = run_domains(["lightdark10d"], ["sir"], seeds=2, n=10, steps=2, equal_time=False)
        >>> r["rows"][0]["per_seed"]["final_error"]  # doctest: +SKIP
        [1.93..., 2.41...]
    """
    from escort_rl.bench.core.runner import InProcessBackend

    domains, methods = list(domains), list(methods)
    filter_set = tuple(tuple(kv) for kv in filter_set)
    check_names(domains, methods, filter_set)
    check_at_least_one(seeds=seeds, particles=n, steps=steps, threads=threads, seeds_per_cell=seeds_per_cell)
    if isinstance(reference_particles, bool) or not isinstance(reference_particles, int) or reference_particles < 0:
        raise ValueError(f"--reference-particles: must be a whole number >= 0 (0: no reference), got "
                         f"{reference_particles!r}")
    if reference_particles and (isinstance(reference_sample, bool) or not isinstance(reference_sample, int)
                                or not 2 <= reference_sample <= reference_particles):
        raise ValueError(f"--reference-sample: must be a whole number from 2 to --reference-particles "
                         f"({reference_particles}), got {reference_sample!r}")
    learned = [m for m in methods if m in registry.learned_methods()]
    if learned and runs_dir is None:
        raise ValueError(f"--output: the learned beliefs {', '.join(learned)} need a folder to train in")
    threads = threads or 1
    backend = backend or InProcessBackend()
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        checkpoints = train_learned_beliefs(domains, learned, Path(runs_dir)) if learned else {}
        with tempfile.TemporaryDirectory(prefix="escort-rl-reference-") as scratch:
            # absolute, so a Ray worker that starts in another directory finds the files
            folder = (Path(cells_dir) / "reference-data" if cells_dir is not None else Path(scratch)).resolve()
            return _run_domains(domains, methods, seeds, n, steps, backend, equal_time, max_particles, particle_grid,
                                reference, calibration_steps, base_seed, filter_set, threads, seeds_per_cell, progress,
                                plot_dir, checkpoints, CellStore(cells_dir) if cells_dir is not None else None,
                                (reference_particles, reference_sample, folder))
    finally:
        torch.set_num_threads(previous_threads)


def _run_domains(domains, methods, seeds, n, steps, backend, equal_time, max_particles, particle_grid, reference,
                 calibration_steps, base_seed, filter_set, threads, seeds_per_cell, progress, plot_dir, checkpoints,
                 store, posterior) -> dict:
    seed_list = list(range(seeds))
    horizon = {d: (steps if steps is not None else build_domain(d)[1]) for d in domains}
    t_start = time.perf_counter()

    domain_info, trajs = {}, {}
    for d in domains:
        model, max_steps = build_domain(d)
        traj = generate_trajectories(model, horizon[d], seed_list, base_seed)
        trajs[d] = traj
        info = {"steps": horizon[d], "env_max_steps": max_steps, "state_dim": model.state_dim,
                "obs_dim": model.obs_dim, "n_actions": model.n_actions,
                "position_error": position_error_label(model), "trajectory_hashes": traj["hashes"]}
        if hasattr(model, "distance_to_goal"):
            dist = model.distance_to_goal(traj["states"][:, -1]).tolist()
            info["shared_final_distance_to_goal"] = mean_se(dist)
        domain_info[d] = info

    grid = _Grid(backend, store, seed_list, seeds_per_cell, base_seed, horizon, filter_set, threads, checkpoints,
                 progress)
    filters = [m for m in methods if not any((d, m) in checkpoints for d in domains)]
    try:
        reference_info = None
        if posterior[0]:
            reference_info = grid.run_references(domains, posterior[0], posterior[1], posterior[2],
                                                 {d: domain_info[d]["trajectory_hashes"] for d in domains})
            if progress is not None:
                progress("reference", reference_info)
        rows = grid.run([(d, m, n) for d in domains for m in methods], desc="protocol (a) cells")
        equal = None
        if equal_time and filters:
            equal = _equal_time(domains, filters, rows, trajs, seed_list, n, grid, max_particles, particle_grid,
                                reference, calibration_steps, base_seed, progress)
    finally:
        backend.close()
    for row in rows:
        if row["input_hashes"] != domain_info[row["domain"]]["trajectory_hashes"]:
            raise RuntimeError(f"method '{row['method']}' on '{row['domain']}' saw a different trajectory")

    result = {
        "protocol": "a: shared trajectories",
        "behaviour_policy": BEHAVIOUR_POLICY,
        "seeds": seeds, "particles": n, "base_seed": base_seed,
        "backend": backend.name, "workers": getattr(backend, "workers", 1), "cell_threads": threads,
        "seeds_per_cell": len(grid.blocks[0]),
        "methods": methods, "domains": domains, "domain_info": domain_info,
        "filter_set": {m: applied_filter_set(m, filter_set) for m in filters},
        "learned": {f"{d}/{m}": display_path(Path(c)) for (d, m), c in checkpoints.items()},
        "seconds": time.perf_counter() - t_start,
        "rows": rows, "equal_time": equal, "reference": reference_info,
    }
    if plot_dir is not None:
        for d in domains:
            plot_error_over_time(result, d, Path(plot_dir) / f"error_over_time_{d}.png")
            if reference_info:
                plot_accuracy_over_time(result, d, Path(plot_dir) / f"accuracy_over_time_{d}.png")
    return result


def _calibrate(domains, methods, trajs, seed_list, n, filter_set, grid, ref, calibration_steps, base_seed,
               progress, failed: dict) -> dict:
    """Per domain: the reference's seconds per step at ``n`` (the budget), each other method's seconds
    per step on the grid (stopping at the first ``N'`` over the budget), and the ``N'`` chosen: the
    largest within the budget, or the smallest of the grid (listed in ``over_budget``) if none is.
    ``failed``: domain -> methods whose equal-N run failed; they are not timed."""
    out = {}
    for d in domains:
        budget = time_per_step(d, ref, trajs[d], seed_list, n, calibration_steps, base_seed, filter_set)
        calib, chosen = {}, {}
        for m in methods:
            if m == ref or m in failed.get(d, ()):  # a failed method keeps N (its failed row is reused)
                calib[m], chosen[m] = {str(n): (budget if m == ref else float("nan"))}, n
                continue
            times = {}
            for k in grid:
                times[str(k)] = time_per_step(d, m, trajs[d], seed_list, k, calibration_steps, base_seed,
                                              filter_set)
                if times[str(k)] > budget:
                    break  # time grows with N: larger N' cannot fit either
            fits = [int(k) for k, t in times.items() if t <= budget]
            calib[m], chosen[m] = times, (max(fits) if fits else grid[0])
            if progress is not None:
                progress("calibration", {"domain": d, "method": m, "times": times, "budget": budget,
                                         "chosen": chosen[m]})
        out[d] = {"budget_seconds_per_step": budget, "calibration": calib, "chosen": chosen,
                  "over_budget": [m for m in methods if calib[m][str(chosen[m])] > budget]}
        if failed.get(d) and ref in failed[d]:
            raise NonFiniteBeliefError(f"the equal-time reference '{ref}' failed on '{d}'; pass --no-equal-time")
    return out


def _equal_time(domains, methods, rows, trajs, seed_list, n, grid, max_particles, particle_grid, reference,
                calibration_steps, base_seed, progress) -> dict:
    ref = reference if reference in methods else methods[0]
    sizes = sorted({int(k) for k in particle_grid if k <= max_particles} | {n})
    out = {"reference": ref, "reference_particles": n, "grid": sizes, "calibration_steps": calibration_steps,
           "domains": {}, "rows": []}
    failed = {d: {r["method"] for r in rows if r["domain"] == d and r["failed"]} for d in domains}
    choices = _calibrate(domains, methods, trajs, seed_list, n, grid.filter_set, sizes, ref, calibration_steps,
                         base_seed, progress, failed)
    jobs = []
    for d in domains:
        out["domains"][d] = choices[d]
        jobs += [(d, m, choices[d]["chosen"][m]) for m in methods if choices[d]["chosen"][m] != n]
    rerun = {(r["domain"], r["method"]): r for r in grid.run(jobs, desc="equal-time cells")}
    for d in domains:
        for m in methods:
            if (d, m) in rerun:
                row = dict(rerun[(d, m)], reused_equal_n=False)
            else:  # N' equals the base N: the equal-N run is that row
                row = dict(next(r for r in rows if r["domain"] == d and r["method"] == m), reused_equal_n=True)
            row["calibrated_seconds_per_step"] = out["domains"][d]["calibration"][m][str(row["particles"])]
            out["rows"].append(row)
    return out


# ---------------------------------------------------------------------------------------- reporting
def plot_error_over_time(result: dict, domain: str, path: Path) -> Path:
    """Mean position error against the step, one line per method, shaded ± s.e."""
    curves = {r["method"]: (r["error_over_time"]["mean"], r["error_over_time"]["se"])
              for r in result["rows"] if r["domain"] == domain and not r["failed"]}
    return plot_curves(curves, path, "step (0: prior)", "position error ‖E_b[pos] − pos_true‖₂",
                       f"{domain}: protocol (a), N = {result['particles']}, {result['seeds']} seeds (mean ± s.e.)")


def plot_accuracy_over_time(result: dict, domain: str, path: Path) -> Path:
    """The distances to the reference posterior against the step: one panel per (part, metric), one
    line per method, shaded ± s.e. over seeds (log scale)."""
    rows = [r for r in result["rows"] if r["domain"] == domain and not r["failed"] and r.get("accuracy")]
    keys = sorted(rows[0]["accuracy"]["over_time"], key=lambda k: (k.split("/")[0] != "position",
                                                                  METRICS.index(k.split("/")[1]))) if rows else []
    panels = {f"{k.split('/')[0]}: {METRIC_LABELS[k.split('/')[1]]}":
              {r["method"]: (r["accuracy"]["over_time"][k]["mean"], r["accuracy"]["over_time"][k]["se"]) for r in rows}
              for k in keys}
    ref = result["reference"][domain]
    return plot_curve_panels(panels, path, "step (0: prior)", ncols=len(METRICS), log_y=True,
                             title=f"{domain}: distance to the reference posterior (SIR, N_ref = {ref['particles'][0]}), "
                                   f"N = {result['particles']}, {result['seeds']} seeds (mean ± s.e.)")


def _table(result: dict, rows: list[dict], cell) -> list[str]:
    """One row per method, one column per domain; a failed run's cell says at which step it failed."""
    learned = {key.split("/", 1)[1] for key in result.get("learned", {})}
    cells = {(r["domain"], r["method"]): f"failed at step {r['failed']['step']}" if r["failed"] else cell(r)
             for r in rows}
    return method_table(result["domains"], result["methods"], cells,
                        label=lambda m: f"{m.upper()} (learned belief, readout)" if m in learned else m)


def _parts_cell(row: dict, metric: str, which: str = "mean") -> str:
    """``position / velocity`` of one metric's time-averaged (``mean``) or final distance, mean ± s.e."""
    acc = row.get("accuracy")
    if not acc:
        return "—"
    return " / ".join(format_mean_se(v[which]) for k, v in acc["summary"].items() if k.endswith(f"/{metric}"))


def _accuracy_sections(result: dict) -> list[str]:
    """The distances to the reference posterior, the reference itself, and its convergence check."""
    ref = result.get("reference")
    if not ref:
        return []
    domains = result["domains"]
    n_ref = ref[domains[0]]["particles"]
    lines = [
        "## Distance to the reference posterior",
        "",
        f"The reference is a bootstrap particle filter with N_ref = {n_ref[0]} particles on the same trajectories, "
        "from its own draw of the same prior (resampling when ESS/N < 0.5); it converges to the exact posterior as "
        "N_ref grows. Each belief is compared with it at every step, on the position and the velocity separately "
        "(" + "; ".join(f"{d}: {_parts_label(d)}" for d in domains) + "): sliced W1 (50 fixed directions), MMD² "
        "(RBF kernel at the median-heuristic bandwidth of the reference), the distance between the means and the "
        "Frobenius distance between the covariances. The sample-based distances use "
        f"{ref[domains[0]]['sample']} particles drawn from the reference at each step. Cells: position / velocity, "
        "time-averaged over steps 1..T, mean ± s.e. over seeds; lower is closer. Learned beliefs have no particles "
        "and no figures here. `accuracy_over_time_<domain>.png` plots every step.",
        "",
    ]
    for metric in METRICS:
        lines += [f"### {METRIC_LABELS[metric]}", "", *_table(result, result["rows"], lambda r: _parts_cell(r, metric)),
                  ""]
    lines += [
        "### The reference and its convergence",
        "",
        f"Each reference ran at N_ref and at 2 N_ref = {n_ref[1]}. *Floor*: the distance of the 2 N_ref reference "
        "to the N_ref one (position / velocity, time-averaged), the part of every figure above that is the "
        "reference's own error. *Change*: per method, the largest relative change of its time-averaged figures "
        "(all parts and metrics) when the 2 N_ref reference replaces the N_ref one.",
        "",
        "| domain | seconds (N_ref / 2 N_ref) | " + " | ".join(f"floor: {METRIC_LABELS[m]}" for m in METRICS) + " |",
        "| --- | --- | " + " | ".join("---" for _ in METRICS) + " |",
    ]
    for d in domains:
        info = ref[d]
        secs = " / ".join(f"{info['seconds'][str(n)]:.0f}" for n in info["particles"])
        floors = [" / ".join(format_mean_se(v["mean"]) for k, v in info["floor"].items() if k.endswith(f"/{m}"))
                  for m in METRICS]
        lines.append(f"| {d} | {secs} | " + " | ".join(floors) + " |")
    lines += ["", "Change of each method's figures when N_ref doubles (the largest over parts and metrics):", "",
              *_table(result, result["rows"], _reference_change), ""]
    return lines


def _parts_label(domain: str) -> str:
    model, _ = build_domain(domain)
    return ", ".join(f"{k} = dims {list(v)}" for k, v in state_parts(model).items())


def _reference_change(row: dict) -> str:
    acc = row.get("accuracy")
    if not acc or not acc["checks"]:
        return "—"
    change = max(abs(acc["checks"][0][k]["mean"][0] - v["mean"][0]) / max(abs(v["mean"][0]), 1e-300)
                 for k, v in acc["summary"].items())
    return f"{100 * change:.1f}%"


def domains_markdown(result: dict) -> str:
    info = result["domain_info"]
    horizon = ", ".join(f"{d} {info[d]['steps']}" for d in result["domains"])
    lines = [
        "# Domain benchmark, protocol (a): shared trajectories (paper Table 1 layout)",
        "",
        f"N = {result['particles']} particles for every method, {result['seeds']} seeds (mean ± standard error "
        f"over seeds), steps per trajectory: {horizon}. Behaviour policy: {result['behaviour_policy']}. Every "
        "method filters the same seeded action/observation sequence from the same seeded prior particles, so "
        "the tables measure belief accuracy alone. Position error: ‖E_b[pos] − pos_true‖₂ of the weighted "
        "belief mean, on " + "; ".join(f"{d}: {info[d]['position_error']}" for d in result["domains"]) + ".",
        "",
        *([("Filter settings changed from the configs: " + "; ".join(
            f"{m}: " + ", ".join(f"{k}={v}" for k, v in kv.items()) for m, kv in result["filter_set"].items() if kv)
            + "."), ""] if any(result.get("filter_set", {}).values()) else []),
        *([("Learned-belief rows (DVRL) were trained closed-loop with protocol (b)'s budget (checkpoints: "
            + ", ".join(f"{k}: `{v}`" for k, v in result["learned"].items()) + "); they read the same "
            "action/observation sequences, and their position error is that of a readout head from the belief "
            "summary to the state, fitted to the training trajectories' true states. They have no particle "
            "count and are not in the equal-time table."), ""] if result.get("learned") else []),
        "## Final position error (after the last step)",
        "",
        *_table(result, result["rows"], lambda r: format_mean_se(r["summary"]["final_error"])),
        "",
        "## Time-averaged position error (steps 1..T)",
        "",
        *_table(result, result["rows"], lambda r: format_mean_se(r["summary"]["mean_error"])),
        "",
        *_accuracy_sections(result),
        "## Importance weights",
        "",
        "The effective sample size of the importance weights each filter formed, over every update: SIR's weights "
        "before resampling; ESCORT's target samples of the correlation projections (the predicted particles "
        "weighted by the likelihood), tempered where ESS/N falls below `ess_floor`. ESS/N averaged over beliefs "
        "and steps, its minimum, the share of tempered updates and the mean tempering exponent β.",
        "",
        *_table(result, result["rows"], lambda r: format_importance(r.get("importance"))),
        "",
        "## Wall-clock per filter update",
        "",
        f"Milliseconds per step for the whole batch of {result['seeds']} beliefs / per belief (the sum over "
        f"the row's cells of {result['seeds_per_cell']} seeds, each with {result['cell_threads']} torch threads; "
        f"backend {result['backend']}" + (f", {result['workers']} workers" if result["workers"] > 1 else "") + "), "
        "over steps 2..T; the first update is a warm-up (it compiles, for `compile=true`) and its "
        "seconds are in brackets.",
        "",
        *_table(result, result["rows"],
                lambda r: f"{1e3 * r['seconds_per_step']:.1f} / {1e3 * r['seconds_per_step_per_env']:.2f} "
                          f"({r.get('first_step_seconds', float('nan')):.1f} s)"),
        "",
    ]
    eq = result.get("equal_time")
    if eq:
        lines += [
            "## Equal wall-clock per step",
            "",
            f"Each method gets the largest N' in {eq['grid']} whose measured time per batched update (one "
            f"warm-up, then the mean of {eq['calibration_steps']} updates on the same trajectories) is not "
            f"above {eq['reference']}'s at N = {eq['reference_particles']}; {eq['reference']} keeps N = "
            f"{eq['reference_particles']}. Cells: final error mean ± s.e. (N', ms per step in the timing "
            "measurement / in the run itself). A row at N' = N reuses the equal-N run. The runs' own times are sums "
            "over the row's cells, which may have run side by side; the choice of N' uses the timing "
            "measurement, one method at a time in one process.",
            "",
            *_table(result, eq["rows"], lambda r: f"{format_mean_se(r['summary']['final_error'])} "
                                                  f"(N'={r['particles']}, {1e3 * r['calibrated_seconds_per_step']:.1f}"
                                                  f" / {1e3 * r['seconds_per_step']:.1f} ms)"),
            "",
            *([line for metric in METRICS for line in (
                f"Distance to the reference posterior at equal wall-clock: {METRIC_LABELS[metric]} of the position "
                "/ velocity, time-averaged over steps 1..T.", "",
                *_table(result, eq["rows"], lambda r, metric=metric: _parts_cell(r, metric)), "")]
              if result.get("reference") else []),
            "Budgets (ms per step of the reference): " + ", ".join(
                f"{d} {1e3 * v['budget_seconds_per_step']:.1f}" for d, v in eq["domains"].items()) + ".",
        ]
        capped = [f"{m} on {d}" for d, v in eq["domains"].items() for m in v["chosen"]
                  if m != eq["reference"] and v["chosen"][m] == eq["grid"][-1]
                  and v["calibration"][m][str(eq["grid"][-1])] <= v["budget_seconds_per_step"]]
        if capped:
            lines.append(f"The grid's largest N' ({eq['grid'][-1]}) is still within the budget for: "
                         + ", ".join(capped) + "; a larger --max-particles would give them more.")
        over = [f"{m} on {d}" for d, v in eq["domains"].items() for m in v["over_budget"]]
        if over:
            lines.append("Even the smallest N' is over the budget for: " + ", ".join(over) + ".")
        lines.append("")
    failures = [r for r in result["rows"] + (eq["rows"] if eq else []) if r["failed"]]
    if failures:
        lines += ["## Failed runs", "",
                  "A failed run's belief diverged on at least one seed; the run stops there and has no error figures.",
                  ""]
        seen = set()
        for r in failures:
            if (r["domain"], r["method"], r["particles"]) not in seen:
                seen.add((r["domain"], r["method"], r["particles"]))
                lines.append(f"- {r['method']} on {r['domain']} (N = {r['particles']}): step {r['failed']['step']}: "
                             f"{r['failed']['message']}")
        lines.append("")
    lines += [
        "## Task outcome",
        "",
        "Under protocol (a) the actions come from the behaviour policy, not from the belief, so the true "
        "trajectory, and with it the final distance to goal, success and return, is the same for every "
        "method; only the error metrics above differ between methods. The closed-loop task outcome "
        "(each filter driving its own trained policy, or POMCPOW) is protocol (b), reported separately.",
    ]
    shared = [f"{d} {format_mean_se(info[d]['shared_final_distance_to_goal'])}" for d in result["domains"]
              if "shared_final_distance_to_goal" in info[d]]
    if shared:
        lines.append("Shared trajectories' final true distance to goal (the same for all methods): "
                     + ", ".join(shared) + ".")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------- command line
QUICK = dict(domains=list(registry.DOMAINS), methods=list(registry.QUICK_METHODS), seeds=2, particles=30, steps=20,
             max_particles=60, threads=1, reference_particles=2000, reference_sample=200)
"""``bench domains --quick`` (flags given explicitly win)."""


def register(subparsers) -> None:
    """Add ``bench domains`` (protocols (a) and (b)) to the ``bench`` subparsers."""
    dom = subparsers.add_parser(
        "domains", help="filters on Light-Dark, Kidnapped Robot, MTT: shared trajectories",
        description="Protocol (a) (paper Table 1 layout): every method filters the same seeded "
        "trajectories (uniform random actions) from the same seeded priors; final and time-averaged position "
        "error (mean ± s.e. over seeds), ms per step, and a table at equal wall-clock per step. Methods are "
        "filter config names. The grid's cells (domain × method × seeds) run on --backend; each is saved in "
        "<output>/cells as it finishes and a rerun skips it.")
    add_overrides_argument(dom, "filter overrides, each set on every method whose config has the key, e.g. "
                           "filter.num_steps=10 filter.compile=true")
    dom.add_argument("--domains", nargs="+", default=None,
                     help=f"env configs (default: {' '.join(registry.DOMAINS)})")
    dom.add_argument("--methods", nargs="+", default=None, help=registry.methods_help())
    add_seeds_option(dom, None, "seeds 0..N-1 (protocol b: evaluation episodes)", "30")
    dom.add_argument("--particles", type=int, default=None, metavar="N", help="N for every method (default: 100)")
    dom.add_argument("--steps", type=int, default=None, help="steps per trajectory (default: env.max_steps)")
    add_runner_options(dom, threads_help="torch threads in each cell and in the equal-time measurement; small "
                       "updates are often fastest with 1 (default: 1)")
    dom.add_argument("--max-particles", type=int, default=None,
                     help="largest N' for the equal wall-clock table; the timing stops at the first N' over the "
                     "budget (default: 100000)")
    dom.add_argument("--no-equal-time", action="store_true", help="skip the equal wall-clock table")
    dom.add_argument("--reference-particles", type=int, default=None, metavar="N",
                     help="particles of the reference posterior (an SIR filter, run at N and 2N to check it has "
                     "converged) that every belief is compared with at every step; 0: none (default: 100000)")
    dom.add_argument("--reference-sample", type=int, default=None, metavar="M",
                     help=f"reference particles kept per step for sliced W1 and MMD² (default: {SAMPLE})")
    add_quick_option(dom, f"all three domains, {' '.join(registry.QUICK_METHODS)}, 2 seeds, 20 steps, N=30, 1 torch "
                     "thread, equal-time grid up to N'=60 with 1 timed step, a reference of 2000 particles (200 kept "
                     "per step); protocol b: 10 steps, N=20, 1 training iteration of 2 envs")
    dom.add_argument("--protocol", choices=("a", "b"), default="a",
                     help="a: shared trajectories; b: closed loop, each method trains its own DeepSets "
                     "policy (budget per domain in configs/bench/closed_loop.yaml) and drives it on --seeds "
                     "evaluation episodes; a rerun with the same --output resumes from the checkpoints")
    dom.add_argument("--train-iterations", type=int, default=None,
                     help="protocol b: trainer.iterations for every domain (default: the yaml's)")
    dom.add_argument("--train-envs", type=int, default=None,
                     help="protocol b: trainer.num_envs for every domain (default: the yaml's)")
    add_output_option(dom, "outputs/bench/domains", "domains.json, domains.md, PNGs and cells/ (protocol b: "
                      "closed_loop.json, closed_loop.md, PNGs and runs/)")
    dom.set_defaults(handler=main)


def main(args) -> None:
    """``bench domains``: protocol (a) here, protocol (b) in :func:`escort_rl.bench.closed_loop.main`."""
    if args.protocol == "b":
        from escort_rl.bench import closed_loop

        return closed_loop.main(args)
    if args.train_iterations is not None or args.train_envs is not None:
        raise ValueError("--train-iterations/--train-envs: only for --protocol b")
    full = dict(domains=list(registry.DOMAINS), methods=list(registry.PROTOCOL_A_METHODS), seeds=30, particles=100,
                steps=None, max_particles=100_000, threads=None, reference_particles=100_000,
                reference_sample=SAMPLE)
    kw = {k: getattr(args, k) if getattr(args, k) is not None else (QUICK if args.quick else full)[k] for k in full}
    backend = backend_from_args(args)

    def show(kind, payload):
        if kind == "row" and payload["failed"]:
            f = payload["failed"]
            print(f"{payload['domain']:>13} {payload['method']:>14} N={payload['particles']:<5} FAILED at step "
                  f"{f['step']}: {f['message']}", flush=True)
        elif kind == "row":
            s = payload["summary"]
            w1 = (f"  W1 to ref (pos/vel) {_parts_cell(payload, 'w1')}" if payload.get("accuracy") else "")
            print(f"{payload['domain']:>13} {payload['method']:>14} N={payload['particles']:<5} final error "
                  f"{format_mean_se(s['final_error'])}  mean error {format_mean_se(s['mean_error'])}  "
                  f"{1e3 * payload['seconds_per_step']:.1f} ms/step{w1}", flush=True)
        elif kind == "reference":
            for d, info in payload.items():
                floor = ", ".join(f"{k} {v['mean'][0]:.4g}" for k, v in info["floor"].items() if k.endswith("/w1"))
                print(f"{d:>13} reference N_ref={info['particles'][0]}/{info['particles'][1]}: "
                      f"{info['seconds'][str(info['particles'][0])]:.0f} + {info['seconds'][str(info['particles'][1])]:.0f}"
                      f" s; floor (sliced W1) {floor}", flush=True)
        else:
            times = ", ".join(f"N'={k}: {1e3 * v:.1f} ms" for k, v in payload["times"].items())
            print(f"{payload['domain']:>13} {payload['method']:>14} equal-time: budget "
                  f"{1e3 * payload['budget']:.1f} ms; {times} -> N'={payload['chosen']}", flush=True)

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    result = run_domains(kw["domains"], kw["methods"], seeds=kw["seeds"], n=kw["particles"], steps=kw["steps"],
                         backend=backend, equal_time=not args.no_equal_time, max_particles=kw["max_particles"],
                         calibration_steps=1 if args.quick else 3, filter_set=filter_overrides(args.overrides),
                         threads=kw["threads"], seeds_per_cell=args.seeds_per_cell, progress=show, plot_dir=out,
                         runs_dir=out / "runs", cells_dir=out / "cells", reference_particles=kw["reference_particles"],
                         reference_sample=kw["reference_sample"])
    write_results(out, "domains", result, domains_markdown(result), time.perf_counter() - t0)
