"""The grids of the synthetic benchmark: Table 2's targets (:func:`run_synthetic`) and the 5-mode
scalability targets against the dimension (:func:`run_scaling`), under the static or the tracking
protocol, on any backend of :mod:`escort_rl.bench.core.runner` (cells saved as they finish)."""

from __future__ import annotations

from pathlib import Path

import torch

from escort_rl.bench.core.runner import CellStore, InProcessBackend, run_groups, seed_blocks
from escort_rl.bench.methods import check_choices
from escort_rl.bench.synthetic.cells import SyntheticCell, TrackingCell
from escort_rl.bench.synthetic.spec import GridSpec, ScalingSpec, SyntheticSpec
from escort_rl.bench.targets import load_target, synthetic_config
from escort_rl.reporting.stats import mean_se, merge_importance


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


def _cells_of(spec: GridSpec, common: dict, keep_particles: bool = False) -> list:
    """The cells of one row (``common``: its target, method and settings), one per seed block."""
    blocks = seed_blocks(list(range(spec.seeds)), spec.seeds_per_cell)
    common = dict(common, particles=spec.particles, num_steps=spec.num_steps,
                  filter_kwargs=tuple(sorted(spec.filter_arguments().items())), threads=spec.threads)
    if spec.protocol == "tracking":
        return [TrackingCell(seeds=b, steps=spec.steps, **common) for b in blocks]
    return [SyntheticCell(seeds=b, init=spec.init, init_scale=float(spec.init_scale), keep_particles=keep_particles,
                          **common) for b in blocks]


def _meta(spec: GridSpec) -> dict:
    meta = {"protocol": spec.protocol, "n": spec.particles, "seeds": spec.seeds, "num_steps": spec.num_steps,
            "filter_kwargs": spec.filter_arguments()}
    if spec.protocol == "tracking":
        meta["steps"] = spec.steps
    else:
        meta.update(init=spec.init, init_scale=float(spec.init_scale))
    return meta


def run_synthetic(spec: SyntheticSpec, backend=None, progress=None) -> dict:
    """Fit (or track) and score every method of ``spec`` on every target; per-seed values and mean ±
    s.e.

    ``backend``: where the cells run (default in-process, see :mod:`escort_rl.bench.core.runner`),
    closed at the end; ``progress(row)`` is called per row as it finishes. With ``spec.output``, the
    cells are saved in ``<output>/cells`` (skipped on a rerun) and, under the static protocol, the
    plots written there: ``<target>_particles.png`` (seed 0's particles of every method on the
    target's contours, first two coordinates) and ``<metric>_vs_dimension.png``.
    """
    from escort_rl.reporting.plots import plot_metric_against_dimension, plot_particles_on_target

    check_choices("--targets", spec.targets, sorted(synthetic_config()["targets"]))
    plot_dir = spec.output
    rows, cells = [], {}
    for name in spec.targets:
        dim = load_target(name).dim
        for method in spec.methods:
            cells[len(rows)] = _cells_of(spec, dict(target=name, method=method), keep_particles=plot_dir is not None)
            rows.append({"target": name, "dim": dim, "method": method})
    _run_grid(rows, cells, backend, _cells_dir(spec), progress)
    shown = {r["target"]: {} for r in rows}
    for r in rows:
        particles = r.pop("_shown", None)
        if particles is not None:
            shown[r["target"]][r["method"]] = particles
    if plot_dir is not None and spec.protocol == "static":
        for name in spec.targets:
            plot_particles_on_target(load_target(name).log_prob, shown[name], plot_dir / f"{name}_particles.png",
                                     title=f"{name}: seed 0, N = {spec.particles}")
        for metric in ("sliced_w1", "corr_error", "mmd2"):
            plot_metric_against_dimension(rows, metric, plot_dir / f"{metric}_vs_dimension.png")
    return {**_meta(spec), "rows": rows}


def _cells_dir(spec: GridSpec) -> Path | None:
    return spec.output / "cells" if spec.output is not None else None


def run_scaling(spec: ScalingSpec, backend=None, progress=None) -> dict:
    """RMSE (and the other metrics) of the 5-mode scalability GMMs against the dimension, under
    ``spec.protocol``; with ``spec.output``, ``rmse_vs_dimension.png`` (averaged over the correlation
    structures) and, under the static protocol, ``coverage_vs_dimension.png``. ``backend`` and
    ``progress``: those of :func:`run_synthetic`."""
    from escort_rl.reporting.plots import plot_metric_against_dimension

    rows, cells = [], {}
    for d in spec.dims:
        for structure in spec.structures if d > 1 else spec.structures[:1]:
            for method in spec.methods:
                common = dict(target=f"scaling-{structure}-{d}d", method=method, dim=d, structure=structure)
                cells[len(rows)] = _cells_of(spec, common)
                rows.append({"dim": d, "structure": structure, "method": method})
    _run_grid(rows, cells, backend, _cells_dir(spec), progress)
    if spec.output is not None:
        plot_metric_against_dimension(rows, "rmse", spec.output / "rmse_vs_dimension.png",
                                      ylabel="RMSE (state units)")
        if spec.protocol == "static":
            plot_metric_against_dimension(rows, "mode_coverage", spec.output / "coverage_vs_dimension.png")
    return {**_meta(spec), "rows": rows}
