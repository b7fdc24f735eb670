"""A protocol (a) row (one method at one N on one domain) from its cells' results: the position
error per seed and over time, the time per step, the distances to the reference posterior and the
importance-weight diagnostics, each mean ± s.e. over seeds; a diverged belief gives a failed row."""

from __future__ import annotations

import math

import torch

from escort_rl.bench.trajectories import NonFiniteBeliefError
from escort_rl.metrics.reference import summarize_series
from escort_rl.reporting.stats import mean_se, merge_importance


def over_seeds(values: torch.Tensor) -> dict:
    """``{"mean", "se"}`` over seeds (the first dimension) at every step of ``values`` ``[B, T+1]``;
    a standard error of 0 for a single seed.

    Examples:
        >>> over_seeds(torch.tensor([[1.0, 2.0], [3.0, 2.0]], dtype=torch.float64))
        {'mean': [2.0, 2.0], 'se': [1.0, 0.0]}
    """
    b = values.shape[0]
    se = values.std(0, unbiased=True) / math.sqrt(b) if b > 1 else torch.zeros(values.shape[1])
    return {"mean": values.mean(0).tolist(), "se": se.tolist()}


def row_accuracy(parts: list[dict], steps: int) -> dict | None:
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
    checks = []
    for i in range(len(acc[0]["checks"])):
        checks.append({k: {w: mean_se([x for a in acc for x in a["checks"][i][k][w]]) for w in ("final", "mean")}
                       for k in series})
    return {"references": acc[0]["references"], "per_seed": per_seed,
            "summary": {k: {w: mean_se(v[w]) for w in ("final", "mean")} for k, v in per_seed.items()},
            "over_time": {k: over_seeds(v) for k, v in series.items()},
            "checks": checks}


def assemble_row(domain: str, method: str, n: int, parts: list[dict], seeds: list[int]) -> dict:
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
    if not torch.isfinite(errors).all() or (errors < 0).any():
        raise NonFiniteBeliefError(f"method '{method}' on domain '{domain}': the position error is NaN, Inf "
                                   "or negative")
    return {
        "domain": domain, "method": method, "filter": parts[0]["filter"], "particles": n, "seeds": seeds,
        "steps": steps, "failed": None,
        "per_seed": {"final_error": final.tolist(), "mean_error": avg.tolist()},
        "summary": {"final_error": mean_se(final.tolist()), "mean_error": mean_se(avg.tolist())},
        "error_over_time": over_seeds(errors),
        "filter_seconds": seconds + first,
        "first_step_seconds": first,
        "seconds_per_step": seconds / timed,
        "seconds_per_step_per_env": seconds / timed / b,
        "input_hashes": [h for p in parts for h in p["input_hashes"]],
        "initial_belief_hashes": [h for p in parts for h in p["belief_hashes"]],
        "accuracy": row_accuracy(parts, steps),
        "importance": merge_importance([p.get("importance") for p in parts]),
    }
