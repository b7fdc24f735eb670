"""The runs of the domain benchmark, each from one :class:`~escort_rl.bench.domains.spec.DomainsSpec`
on any backend of :mod:`escort_rl.bench.core.runner`.

Protocol (a) (:func:`run_domains`), in explicit steps: train the learned beliefs; generate the shared
trajectories (:func:`shared_trajectories`); compute the reference posteriors
(:meth:`~escort_rl.bench.domains.grid.Grid.run_references`), which give the references the method
cells read; run the equal-N rows with them; then the equal wall-clock rows
(:func:`~escort_rl.bench.domains.equal_time.equal_time_rows`). Protocol (b) (:func:`run_closed_loop`):
one cell per (domain, method), see :mod:`escort_rl.bench.domains.closed_loop_cells`.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import torch

from escort_rl.bench import methods as registry
from escort_rl.bench.core.runner import CellStore, InProcessBackend, run_cells
from escort_rl.bench.domains.cells import train_learned_beliefs
from escort_rl.bench.domains.closed_loop_cells import REFERENCE_FILTER, ClosedLoopCell, method_spec, run_config
from escort_rl.bench.domains.equal_time import equal_time_rows
from escort_rl.bench.domains.grid import Grid, References
from escort_rl.bench.domains.spec import DomainsSpec
from escort_rl.bench.methods import RANDOM, SECTIONS, applied_filter_set, build_domain, check_names
from escort_rl.bench.trajectories import BEHAVIOUR_POLICY, generate_trajectories, position_error_label
from escort_rl.reporting.paths import display_path
from escort_rl.reporting.stats import mean_se


def _protocol(spec: DomainsSpec, protocol: str, function: str) -> None:
    if spec.protocol != protocol:
        other = "run_closed_loop" if protocol == "a" else "run_domains"
        raise ValueError(f"protocol: {function} runs protocol ({protocol}), the spec asks for ({spec.protocol}); "
                         f"call {other}")


def shared_trajectories(spec: DomainsSpec) -> tuple[dict, dict]:
    """The seeded trajectories every method filters, and what the report says of each domain:
    ``(domain -> trajectories, domain -> info)``."""
    seeds, trajectories, info = list(range(spec.seeds)), {}, {}
    for d in spec.domains:
        model, max_steps = build_domain(d)
        steps = spec.steps if spec.steps is not None else max_steps
        traj = generate_trajectories(model, steps, seeds, spec.base_seed)
        trajectories[d] = traj
        info[d] = {"steps": steps, "env_max_steps": max_steps, "state_dim": model.state_dim,
                   "obs_dim": model.obs_dim, "n_actions": model.n_actions,
                   "position_error": position_error_label(model), "trajectory_hashes": traj["hashes"]}
        if hasattr(model, "distance_to_goal"):
            info[d]["shared_final_distance_to_goal"] = mean_se(model.distance_to_goal(traj["states"][:, -1]).tolist())
    return trajectories, info


def run_domains(spec: DomainsSpec, backend=None, progress=None) -> dict:
    """Protocol (a) for every method of ``spec`` on every domain; per-seed values and mean ± s.e.

    ``backend``: a runner backend (:func:`escort_rl.bench.core.runner.make_backend`; default
    in-process), closed at the end. ``progress(kind, payload)`` is called with ``("row", row)`` after
    each (domain, method, N), ``("reference", info)`` after the reference posteriors and
    ``("calibration", dict)`` after each equal-time measurement. With ``spec.output``, each cell's
    result is saved under ``<output>/cells`` as it finishes (a rerun skips the finished cells), the
    reference files go to ``<output>/cells/reference-data`` (else a temporary folder) and the learned
    beliefs (``dvrl``; they need it) are trained first in ``<output>/runs/<domain>/<method>``
    (:func:`~escort_rl.bench.domains.cells.train_learned_beliefs`); they have no particle count, so
    they sit out the equal-time table.

    Examples:
        >>> r = run_domains(DomainsSpec(domains=["lightdark10d"], methods=["sir"], seeds=2, particles=10, steps=2,
        ...                             equal_time=False, reference_particles=0))
        >>> r["rows"][0]["per_seed"]["final_error"]  # doctest: +SKIP
        [1.93..., 2.41...]
    """
    _protocol(spec, "a", "run_domains")
    check_names(spec.domains, spec.methods, spec.filter_set)
    learned = [m for m in spec.methods if m in registry.learned_methods()]
    if learned and spec.output is None:
        raise ValueError(f"--output: the learned beliefs {', '.join(learned)} need a folder to train in")
    backend = backend or InProcessBackend()
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(spec.threads)
    try:
        checkpoints = train_learned_beliefs(spec.domains, learned, spec.output / "runs") if learned else {}
        with tempfile.TemporaryDirectory(prefix="escort-rl-reference-") as scratch:
            # absolute, so a Ray worker that starts in another directory finds the files
            cells = spec.output / "cells" if spec.output is not None else None
            folder = (cells / "reference-data" if cells is not None else Path(scratch)).resolve()
            return _run_protocol_a(spec, backend, CellStore(cells) if cells is not None else None, checkpoints,
                                   folder, progress)
    finally:
        torch.set_num_threads(previous_threads)


def _run_protocol_a(spec: DomainsSpec, backend, store, checkpoints: dict, folder: Path, progress) -> dict:
    t_start = time.perf_counter()
    trajectories, info = shared_trajectories(spec)
    grid = Grid(spec, {d: info[d]["steps"] for d in spec.domains}, backend, store, checkpoints, progress)
    filters = [m for m in spec.methods if not any((d, m) in checkpoints for d in spec.domains)]
    try:
        references, reference_info = References(), None
        if spec.reference_particles:
            references, reference_info = grid.run_references(
                folder, {d: info[d]["trajectory_hashes"] for d in spec.domains})
            if progress is not None:
                progress("reference", reference_info)
        rows = grid.run([(d, m, spec.particles) for d in spec.domains for m in spec.methods], references,
                        desc="protocol (a) cells")
        equal = None
        if spec.equal_time and filters:
            equal = equal_time_rows(grid, filters, rows, trajectories, references)
    finally:
        backend.close()
    for row in rows:
        if row["input_hashes"] != info[row["domain"]]["trajectory_hashes"]:
            raise RuntimeError(f"method '{row['method']}' on '{row['domain']}' saw a different trajectory")
    return {
        "protocol": "a: shared trajectories",
        "behaviour_policy": BEHAVIOUR_POLICY,
        "seeds": spec.seeds, "particles": spec.particles, "base_seed": spec.base_seed,
        "backend": backend.name, "workers": getattr(backend, "workers", 1), "cell_threads": spec.threads,
        "seeds_per_cell": len(grid.blocks[0]),
        "methods": list(spec.methods), "domains": list(spec.domains), "domain_info": info,
        "filter_set": {m: applied_filter_set(m, spec.filter_set) for m in filters},
        "learned": {f"{d}/{m}": display_path(Path(c)) for (d, m), c in checkpoints.items()},
        "seconds": time.perf_counter() - t_start,
        "rows": rows, "equal_time": equal, "reference": reference_info,
    }


def _closed_loop_rows(spec: DomainsSpec, settings: dict) -> tuple[dict, int, int]:
    """Protocol (b)'s checked rows: method -> :func:`method_spec` (the random row included), and the
    episodes and N (the spec's, else the yaml's)."""
    methods = list(spec.methods)
    registry.named_rows(settings)  # the sections' names are distinct
    specs = {m: method_spec(m, settings) for m in [*methods, RANDOM]}
    check_names(list(spec.domains), list(dict.fromkeys(specs[m]["filter"] for m in methods)), spec.filter_set)
    if len(set(methods)) != len(methods):
        raise ValueError("--methods: a method is listed twice")
    if RANDOM in methods:
        raise ValueError(f"--methods: '{RANDOM}' is always run; leave it out")
    episodes = int(spec.seeds if spec.seeds is not None else settings["episodes"])
    n = int(spec.particles if spec.particles is not None else settings["particles"])
    registry.check_at_least_one(seeds=episodes, particles=n)
    missing = [d for d in spec.domains if d not in settings["train"]]
    if missing:
        raise ValueError(f"{registry.settings_path().name}: no train entry for {', '.join(missing)}; add one")
    return specs, episodes, n


def run_closed_loop(spec: DomainsSpec, backend=None, progress=None) -> dict:
    """Protocol (b) for every method of ``spec`` on every domain, plus a random-policy row per domain.

    ``spec.methods``: filter configs (trained with the yaml's ``trainer``) and the rows of the yaml's
    sections (:func:`~escort_rl.bench.domains.closed_loop_cells.method_spec`); ``spec.seeds`` (the
    evaluation episodes) and ``spec.particles`` default to ``configs/bench/closed_loop.yaml``'s, the
    budget per domain is the yaml's with :meth:`DomainsSpec.train_overrides` on top. ``backend``:
    where the (domain, method) cells run (default in-process), closed at the end. ``progress(row)`` is
    called per row as it finishes. Writes the runs under ``<output>/runs``; returns the result (rows in
    grid order and settings). A row that fails (a diverged belief) or does not apply (a scripted row
    on a domain without a controller) has ``failed = {"message": ...}`` (with ``"not_applicable":
    True`` for the latter) and no metrics."""
    _protocol(spec, "b", "run_closed_loop")
    if spec.output is None:
        raise ValueError("--output: protocol b needs a folder for its training runs")
    settings = registry.load_settings()
    specs, episodes, n = _closed_loop_rows(spec, settings)
    domains, methods, output = list(spec.domains), list(spec.methods), spec.output
    backend = backend or InProcessBackend()
    t_start = time.perf_counter()
    eval_seed, greedy = int(settings["eval_seed"]), bool(settings["greedy"])
    budgets = {d: {**settings["train"][d], **spec.train_overrides()} for d in domains}
    cells = [ClosedLoopCell(domain=d, method=m, kind=specs[m]["kind"], section=specs[m]["section"],
                            filter=specs[m]["filter"], trainer=specs[m]["trainer"], particles=n, episodes=episodes,
                            steps=spec.steps, budget=tuple(budgets[d].items()), filter_set=spec.filter_set,
                            run_dir=str(output / "runs" / d / m), eval_seed=eval_seed, greedy=greedy,
                            train_progress=spec.train_progress, threads=spec.threads)
             for d in domains for m in [*methods, RANDOM]]
    try:
        rows = run_cells(cells, backend, on_result=None if progress is None else lambda cell, row: progress(row),
                         desc="protocol (b) cells")
    finally:
        backend.close()
    for row in rows:
        row.pop("timing", None)
    trainers = {r["method"]: r["trainer"] for r in rows if r["trainer"] is not None}
    # the filter rows' trainer (resolved: the config's when the yaml has none)
    reference = run_config(domains[0], REFERENCE_FILTER, n, output / "runs" / domains[0] / RANDOM, budgets[domains[0]],
                           (), spec.steps, trainer=specs[RANDOM]["trainer"])
    sections = {section: {m: settings[section][m] for m in methods if specs[m]["section"] == section}
                for section in SECTIONS}
    return {"protocol": "b: closed loop", "domains": domains, "methods": [*methods, RANDOM], "episodes": episodes,
            "particles": n, "eval_seed": eval_seed, "greedy": greedy,
            "trainer": str(reference.trainer.algorithm), "trainers": trainers,
            "train_budget": budgets,
            "filter_set": {m: applied_filter_set(specs[m]["filter"], spec.filter_set)
                           for m in methods if specs[m]["kind"] != "learned"},
            **sections,
            "torch_threads": spec.threads, "backend": backend.name,
            "seconds": time.perf_counter() - t_start, "rows": rows}
