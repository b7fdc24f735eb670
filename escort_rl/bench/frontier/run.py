"""The frontier's grid: every filter over its cost knobs on one model, the reference first where the
model has no exact posterior, then one cell per (filter, N, K), on any backend of
:mod:`escort_rl.bench.core.runner` (saved as they finish; a rerun skips them)."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from escort_rl.bench.core.runner import CellStore, InProcessBackend, run_cells
from escort_rl.bench.frontier.cells import (
    ITERATIVE,
    FrontierCell,
    FrontierReferenceCell,
    frontier_model,
    model_label,
)
from escort_rl.bench.frontier.pareto import best_at_budgets, pareto_front
from escort_rl.bench.frontier.spec import METRICS, FrontierSpec
from escort_rl.bench.trajectories import behaviour_policy
from escort_rl.metrics.reference import REFERENCE_NAMES, Reference, has_exact_posterior
from escort_rl.reporting.stats import mean_se

BUDGETS_MS = (0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)
"""The time budgets (ms per update of one belief) of the "closest filter at each budget" table."""


def frontier_cells(spec: FrontierSpec, reference: tuple = (), reference_folder: str = "") -> list[FrontierCell]:
    """One cell per (filter, N) for SIR and EnKF and per (filter, N, K) for SVGD and ESCORT; a variant
    is swept over its method's N (and K)."""
    rows = [(m, m, ()) for m in spec.methods] + list(spec.variants)
    cells = []
    for name, method, args in rows:
        for n in spec.particles[method]:
            for k in (spec.iterations if method in ITERATIVE else (0,)):
                cells.append(FrontierCell(model=spec.model, model_args=spec.model_args, method=method,
                                          particles=int(n), num_steps=int(k), seeds=tuple(range(spec.seeds)),
                                          steps=spec.steps, compile=spec.compile and method in ITERATIVE,
                                          base_seed=spec.base_seed, reference=reference,
                                          reference_folder=reference_folder, threads=spec.threads,
                                          variant="" if name == method else name, filter_args=tuple(args)))
    return cells


def reference_ess_summary(path: Path, digest: str, particles: int) -> dict:
    """How far a reference's weights can be trusted: the effective sample size of the weights it
    resampled at each update (the mean over a chunk of seeds), as ``min`` and ``median`` over the
    updates, and ``fraction`` (the median over ``N``). A reference whose ESS is a handful of particles
    is a few points, not a posterior. For SIR these are its weights before resampling; for a tempered
    reference, the smallest of its stages' (``stages``: true), with SIR's untempered ESS beside them
    (``untempered_median``), which says how sharp the likelihood was, not how the reference fared."""
    data = Reference.load(path, digest).data
    before = data["ess_fraction_before_resampling"].double()
    frac = data.get("ess_fraction_of_stages")
    out = {"stages": frac is not None}
    if frac is None:
        frac = before
    else:
        out["untempered_median"] = float(before.median()) * particles
    frac = frac.double()
    return {**out, "particles": particles, "min": float(frac.min()) * particles,
            "median": float(frac.median()) * particles, "fraction": float(frac.median())}


def _row(cell: FrontierCell, result: dict, metric: str, part: str) -> dict:
    row = {"method": cell.variant or cell.method, "base": cell.method, "settings": list(cell.filter_args),
           "particles": cell.particles, "num_steps": cell.num_steps,
           "ms_per_update": 1e3 * result["timing"]["seconds_per_update"], "failed": result.get("failed"),
           "importance": result.get("importance") or {}}
    if result.get("failed") is None:
        row["per_seed"] = result["per_seed"]
        row["summary"] = {k: mean_se(v) for k, v in result["per_seed"].items()}
        row["error"] = row["summary"][f"{part}/{metric}"][0]
    else:
        row["error"] = float("nan")
    return row


def _error(row: dict, part: str, metric: str) -> float:
    """A row's time-averaged ``metric`` to the reference (NaN for a diverged row)."""
    return row["summary"][f"{part}/{metric}"][0] if row.get("failed") is None else float("nan")


def label(row: dict) -> str:
    """``escort N=100 K=15``."""
    iterative = row.get("base", row["method"]) in ITERATIVE
    return f"{row['method']} N={row['particles']}" + (f" K={row['num_steps']}" if iterative else "")


def closest_at_budget(result: dict, budget_ms: float) -> list[dict]:
    """Each filter's row closest to the reference among those that update within ``budget_ms`` ms, from a
    frontier ``result`` (:func:`run_frontier`, or its ``frontier.json``), in the order the filters first
    appear; a filter with no finite row within the budget is left out.

    Example:
        >>> rows = [dict(method="sir", base="sir", particles=100, num_steps=0, ms_per_update=0.3, error=2.0),
        ...         dict(method="sir", base="sir", particles=1000, num_steps=0, ms_per_update=3.0, error=1.0),
        ...         dict(method="escort", base="escort", particles=100, num_steps=15, ms_per_update=9.0, error=0.5)]
        >>> [label(r) for r in closest_at_budget({"rows": rows}, 5.0)]
        ['sir N=1000']
    """
    best: dict[str, dict] = {}
    for row in result["rows"]:
        error = row.get("error")
        if row.get("failed") or error is None or not math.isfinite(error) or row["ms_per_update"] > budget_ms:
            continue
        base = row.get("base", row["method"])
        if base not in best or error < best[base]["error"]:
            best[base] = row
    order = list(dict.fromkeys(r.get("base", r["method"]) for r in result["rows"]))
    return [best[b] for b in order if b in best]


def budget_configurations(path, budget_ms: float, option: str) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """Each filter's configuration that a frontier (the ``frontier.json`` at ``path``) found closest to its
    reference within ``budget_ms`` ms an update (:func:`closest_at_budget`), as ``(label, Hydra overrides)``:
    the rows of a comparison at equal filter time. ``option`` (the command's flag) names the mistake in an
    error."""
    import json
    from pathlib import Path

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{option}: no frontier result at '{path}'; give the frontier.json of a bench frontier run")
    picked = closest_at_budget(json.loads(path.read_text()), float(budget_ms))
    if not picked:
        raise ValueError(f"{option}: no filter of '{path}' updates within {budget_ms:g} ms; raise the budget")
    return tuple((label(r), (f"filter={r.get('base', r['method'])}", f"num_particles={r['particles']}",
                             *([f"filter.num_steps={r['num_steps']}"] if r.get("num_steps") else []),
                             *(f"filter.{s}" for s in r.get("settings", []))))
                 for r in picked)


def run_frontier(spec: FrontierSpec, backend=None, progress=None) -> dict:
    """Every filter of ``spec`` over its costs on its model; each row's distances to the reference
    (mean ± s.e. over seeds, time-averaged over the steps), its ms per update, and the Pareto front on
    ``spec.metric`` of the model's first state part against time (``fronts``: the front on each of
    :data:`~escort_rl.bench.frontier.spec.METRICS`). ``spec.output``: where the cells (and the SIR
    reference) are kept. ``backend``: where the cells run (default in-process), closed at the end;
    ``progress(row)`` is called per row as it finishes."""
    from escort_rl.metrics.reference import state_parts

    built = frontier_model(spec.model, spec.model_args)
    part = next(iter(state_parts(built)))
    store = CellStore(spec.output / "cells") if spec.output is not None else None
    backend = backend or InProcessBackend()
    try:
        reference, folder, reference_kind, reference_ess, ref_error = _reference(spec, built, part, backend, store)
        cells = frontier_cells(spec, reference, folder)
        on_result = (lambda c, r: progress(_row(c, r, spec.metric, part))) if progress else None
        results = run_cells(cells, backend, store, desc="frontier cells", on_result=on_result)
    finally:
        backend.close()
    rows = [_row(c, r, spec.metric, part) for c, r in zip(cells, results)]
    points = [(label(r), r["ms_per_update"], r["error"]) for r in rows]
    front = pareto_front(points)
    fronts = {m: [p[0] for p in pareto_front([(label(r), r["ms_per_update"], _error(r, part, m)) for r in rows])]
              for m in METRICS}
    best = best_at_budgets(points, BUDGETS_MS)
    floor = ref_error[spec.metric][0] if ref_error else 0.0
    return {"model": spec.model, "model_args": list(spec.model_args), "model_name": type(built).__name__,
            "state_dim": built.state_dim, "obs_dim": built.obs_dim, "reference": reference_kind, "part": part,
            "reference_ess": reference_ess, "reference_error": ref_error, "behaviour_policy": behaviour_policy(built),
            "variants": {k: [m, list(a)] for k, m, a in spec.variants}, "metric": spec.metric,
            "seeds": spec.seeds, "steps": spec.steps, "compile": spec.compile, "threads": spec.threads,
            "rows": rows, "front": [p[0] for p in front], "fronts": fronts,
            "budgets": [{"ms": b, "best": None if p is None else p[0], "error": None if p is None else p[2],
                         "not_separated": [] if p is None else not_separated(rows, p[0], b, floor, part, spec.metric)}
                        for b, p in zip(BUDGETS_MS, best)]}


def not_separated(rows: list[dict], best: str, budget_ms: float, floor: float, part: str, metric: str) -> list[str]:
    """The rows within ``budget_ms`` that the reference cannot rank below ``best``: a row whose distance
    exceeds the best's by at most the reference's own error ``floor`` plus twice the s.e. of the difference
    (seeds unpaired), ``|e_r − e_b| ≤ floor + 2·√(se_r² + se_b²)``.

    Example:
        >>> row = lambda name, ms, e, se: {"method": name, "particles": 10, "num_steps": 0, "ms_per_update": ms,
        ...                                "failed": None, "summary": {"x/w1": (e, se)}}
        >>> rows = [row("sir", 1.0, 0.10, 0.01), row("enkf", 1.0, 0.12, 0.01), row("svgd", 1.0, 0.30, 0.01)]
        >>> not_separated(rows, "sir N=10", 5.0, floor=0.01, part="x", metric="w1")
        ['enkf N=10']
    """
    by_label = {label(r): r for r in rows if r.get("failed") is None}
    if best not in by_label:
        return []
    e_best, se_best = by_label[best]["summary"][f"{part}/{metric}"][:2]
    out = []
    for name, r in by_label.items():
        e, se = r["summary"][f"{part}/{metric}"][:2]
        if name != best and r["ms_per_update"] <= budget_ms and math.isfinite(e) \
                and e - e_best <= floor + 2.0 * math.hypot(se, se_best):
            out.append(name)
    return out


def _reference_cell(spec: FrontierSpec, folder: str, gaussian_sum: bool, replicate: int = 0) -> FrontierReferenceCell:
    return FrontierReferenceCell(domain=model_label(spec.model, spec.model_args),
                                 particles=0 if gaussian_sum else int(spec.reference_particles),
                                 steps=spec.steps, seeds=tuple(range(spec.seeds)), base_seed=spec.base_seed,
                                 folder=folder, model_spec=spec.model, model_args=spec.model_args,
                                 threads=spec.threads, exact=gaussian_sum, replicate=replicate,
                                 method=spec.reference_filter)


def _computed(cell: FrontierReferenceCell, backend, store) -> dict:
    """``cell``'s saved result, or its result computed now (also where the saved file is missing or damaged)."""
    ref = store.load(cell) if store is not None else None
    if ref is None or not cell.valid(ref):
        [ref] = run_cells([cell], backend, None, desc="frontier reference")
        if store is not None:
            store.save(cell, ref)
    return ref


def reference_error(first: Reference, second: Reference, steps: int, part: str) -> dict:
    """The distance between two independent references of the same posterior, per metric: averaged over
    steps 1..T per seed, then ``[mean, s.e.]`` over seeds. Two rows whose distances to the reference differ
    by less than this cannot be told apart by it."""
    per_step = [first.compare_reference(second, t) for t in range(1, steps + 1)]
    return {m: list(mean_se(torch.stack([d[f"{part}/{m}"] for d in per_step], 1).mean(1).tolist()))
            for m in METRICS}


def _reference(spec: FrontierSpec, built, part: str, backend,
               store) -> tuple[tuple, str, str, dict | None, dict | None]:
    """The reference the cells read, where the model has no exact posterior (a SIR one, or the exact
    Gaussian sum of a model that has one): ``(reference, folder, what it is, its ESS or None, its own error or
    None)``. A SIR reference is computed twice, independently, and its error is the distance between the two
    (:func:`reference_error`) on the front's state ``part``; the cells read the first."""
    gaussian_sum = callable(getattr(built, "exact_posterior_init", None))
    if has_exact_posterior(built) and not gaussian_sum:
        return (), "", "exact", None, None
    folder = str((spec.output if spec.output is not None else Path(".")) / "reference")
    ref = _computed(_reference_cell(spec, folder, gaussian_sum), backend, store)
    reference = (ref["file"], ref["hash"])
    if gaussian_sum:
        dropped = Reference.load(Path(folder) / ref["file"], ref["hash"]).data["dropped_mass"]
        kind = (f"exact (a Gaussian sum of up to {getattr(built, 'max_components', '?')} components; "
                f"mass pruned per update: max {float(dropped.max()):.2g}, mean {float(dropped[:, 1:].mean()):.2g})")
        return reference, folder, kind, None, None
    ess = reference_ess_summary(Path(folder) / ref["file"], ref["hash"], spec.reference_particles)
    twin = _computed(_reference_cell(spec, folder, gaussian_sum, replicate=1), backend, store)
    error = reference_error(Reference.load(Path(folder) / ref["file"], ref["hash"]),
                            Reference.load(Path(folder) / twin["file"], twin["hash"]), spec.steps, part)
    return reference, folder, f"{REFERENCE_NAMES[spec.reference_filter]} with {spec.reference_particles} particles", \
        ess, error
