"""The grids of the synthetic benchmark: Table 2's targets (:func:`run_synthetic`) and the 5-mode
scalability targets against the dimension (:func:`run_scaling`), under the static or the tracking
protocol, on any backend of :mod:`escort_rl.bench.core.runner` (cells saved as they finish)."""

from __future__ import annotations

from pathlib import Path

import torch

from escort_rl.bench.core.runner import CellStore, InProcessBackend, run_groups, seed_blocks
from escort_rl.bench.methods import SCALING_METHODS, SYNTHETIC_METHODS, check_choices
from escort_rl.bench.synthetic.cells import INITS, TRACKING_METHODS, SyntheticCell, TrackingCell
from escort_rl.bench.synthetic.tracking import STEPS
from escort_rl.bench.targets import SCALABILITY_STRUCTURES, load_target
from escort_rl.reporting.stats import mean_se, merge_importance

SYNTHETIC_TARGETS = ("gmm1d", "gmm2d", "gmm3d", "gmm5d", "gmm20d")
SCALING_DIMS = (1, 5, 20, 50, 100, 200)
PROTOCOLS = ("static", "tracking")
"""``static``: fit a fixed target from a start (``--init``); ``tracking``: follow a latent state
through the target-shaped likelihood (:mod:`escort_rl.bench.synthetic.tracking`)."""


def _run_grid(rows: list[dict], cells: dict, backend, cells_dir, progress) -> list[dict]:
    """Run the cells of every row (``cells``: row index -> its cells, in seed order) and fill in
    each row's ``per_seed``, ``summary``, ``importance`` and ``seconds`` as its last cell arrives."""

    def on_group(i, parts):
        per_seed = {k: [v for p in parts for v in p["per_seed"][k]] for k in parts[0]["per_seed"]}
        rows[i].update(seconds=sum(p["timing"]["seconds"] for p in parts), per_seed=per_seed,
                       summary={k: mean_se(v) for k, v in per_seed.items()},
                       importance=merge_importance([p.get("importance") for p in parts]))
        shown = [p["seed0_particles"] for p in parts if "seed0_particles" in p]
        if shown:
            rows[i]["_shown"] = torch.tensor(shown[0])
        if progress is not None:
            progress(rows[i])

    backend = backend or InProcessBackend()
    try:
        run_groups(cells, backend, CellStore(cells_dir) if cells_dir is not None else None, on_group,
                   desc="synthetic cells")
    finally:
        backend.close()
    return rows


def _cells_of(protocol: str, blocks, common: dict, init: str, init_scale: float, steps: int,
              keep_particles: bool = False) -> list:
    if protocol == "tracking":
        return [TrackingCell(seeds=b, steps=steps, **common) for b in blocks]
    return [SyntheticCell(seeds=b, init=init, init_scale=float(init_scale), keep_particles=keep_particles, **common)
            for b in blocks]


def _check(protocol: str, methods, default_methods, init: str) -> None:
    if protocol not in PROTOCOLS:
        raise ValueError(f"--protocol: expected one of {', '.join(PROTOCOLS)}, got {protocol!r}")
    check_choices("--methods", methods, TRACKING_METHODS if protocol == "tracking" else default_methods)
    if init not in INITS:
        raise ValueError(f"--init: expected one of {', '.join(INITS)}, got {init!r}")


def _meta(protocol, n, seeds, num_steps, filter_kwargs, init, init_scale, steps) -> dict:
    meta = {"protocol": protocol, "n": n, "seeds": seeds, "num_steps": num_steps,
            "filter_kwargs": dict(filter_kwargs or {})}
    if protocol == "tracking":
        meta["steps"] = steps
    else:
        meta.update(init=init, init_scale=float(init_scale))
    return meta


def run_synthetic(targets=SYNTHETIC_TARGETS, methods=SYNTHETIC_METHODS, seeds: int = 30, n: int = 1000,
                  num_steps: int = 500, progress=None, plot_dir=None, filter_kwargs: dict | None = None,
                  backend=None, threads: int | None = None, seeds_per_cell: int | None = None,
                  cells_dir=None, init: str = "cloud", init_scale: float = 1.0, protocol: str = "static",
                  steps: int = STEPS) -> dict:
    """Fit (or track) and score every method on every target; per-seed values and mean ± s.e.

    ``backend``, ``threads`` (per cell, default 1), ``seeds_per_cell`` (default all) and
    ``cells_dir`` (saved cells, skipped on a rerun): see :mod:`escort_rl.bench.core.runner`. ``init`` and
    ``init_scale``: the static protocol's start (:func:`~escort_rl.bench.synthetic.cells.fit_particles`);
    ``steps``: the tracking protocol's ``T`` (``num_steps`` is then the iterations per update). With
    ``plot_dir`` (static), writes ``<target>_particles.png`` (seed 0's particles of every method on
    the target's contours, first two coordinates) and ``<metric>_vs_dimension.png``.
    """
    from escort_rl.reporting.plots import plot_metric_against_dimension, plot_particles_on_target

    _check(protocol, methods, SYNTHETIC_METHODS, init)
    blocks = seed_blocks(list(range(seeds)), seeds_per_cell)
    rows, cells = [], {}
    kw = tuple(sorted((filter_kwargs or {}).items()))
    for name in targets:
        dim = load_target(name).dim
        for method in methods:
            common = dict(target=name, method=method, particles=n, num_steps=num_steps, filter_kwargs=kw,
                          threads=threads or 1)
            cells[len(rows)] = _cells_of(protocol, blocks, common, init, init_scale, steps,
                                         keep_particles=plot_dir is not None)
            rows.append({"target": name, "dim": dim, "method": method})
    _run_grid(rows, cells, backend, cells_dir, progress)
    shown = {r["target"]: {} for r in rows}
    for r in rows:
        particles = r.pop("_shown", None)
        if particles is not None:
            shown[r["target"]][r["method"]] = particles
    if plot_dir is not None and protocol == "static":
        for name in targets:
            plot_particles_on_target(load_target(name).log_prob, shown[name], Path(plot_dir) / f"{name}_particles.png",
                                     title=f"{name}: seed 0, N = {n}")
        for metric in ("sliced_w1", "corr_error", "mmd2"):
            plot_metric_against_dimension(rows, metric, Path(plot_dir) / f"{metric}_vs_dimension.png")
    return {**_meta(protocol, n, seeds, num_steps, filter_kwargs, init, init_scale, steps), "rows": rows}


def run_scaling(dims=SCALING_DIMS, structures=SCALABILITY_STRUCTURES, methods=SCALING_METHODS, seeds: int = 5,
                n: int = 1000, num_steps: int = 500, progress=None, plot_dir=None, filter_kwargs: dict | None = None,
                backend=None, threads: int | None = None, seeds_per_cell: int | None = None, cells_dir=None,
                init: str = "cloud", init_scale: float = 1.0, protocol: str = "static", steps: int = STEPS) -> dict:
    """RMSE (and the other metrics) of the 5-mode scalability GMMs against the dimension, under
    ``protocol``; with ``plot_dir``, ``rmse_vs_dimension.png`` (averaged over the correlation
    structures). The other arguments are those of :func:`run_synthetic`."""
    from escort_rl.reporting.plots import plot_metric_against_dimension

    default = SCALING_METHODS + tuple(m for m in SYNTHETIC_METHODS if m not in SCALING_METHODS)
    _check(protocol, methods, default, init)
    check_choices("--structures", structures, SCALABILITY_STRUCTURES, "structure")
    blocks = seed_blocks(list(range(seeds)), seeds_per_cell)
    rows, cells = [], {}
    kw = tuple(sorted((filter_kwargs or {}).items()))
    for d in dims:
        for structure in structures if d > 1 else structures[:1]:
            for method in methods:
                common = dict(target=f"scaling-{structure}-{d}d", method=method, particles=n, num_steps=num_steps,
                              dim=d, structure=structure, filter_kwargs=kw, threads=threads or 1)
                cells[len(rows)] = _cells_of(protocol, blocks, common, init, init_scale, steps)
                rows.append({"dim": d, "structure": structure, "method": method})
    _run_grid(rows, cells, backend, cells_dir, progress)
    if plot_dir is not None:
        plot_metric_against_dimension(rows, "rmse", Path(plot_dir) / "rmse_vs_dimension.png",
                                      ylabel="RMSE (state units)")
        if protocol == "static":
            plot_metric_against_dimension(rows, "mode_coverage", Path(plot_dir) / "coverage_vs_dimension.png")
    return {**_meta(protocol, n, seeds, num_steps, filter_kwargs, init, init_scale, steps), "rows": rows}
