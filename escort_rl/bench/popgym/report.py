"""``bench popgym``'s table: POPGym's MMER per row and task, mean ± s.e. over training seeds, beside
a random policy's episodes.

MMER (POPGym's score): an episode's return lies in ``[−1, 1]`` by POPGym's reward scaling; a run's
score is the maximum, over its training iterations, of the iteration's mean episode return; the
row's is the mean of its runs' scores. The table also gives the last iteration's mean return (what
the run ends at), the frames and the training minutes."""

from __future__ import annotations

import math

from escort_rl.reporting.stats import format_mean_se, mean_se

RANDOM = "random"


def mmer(returns: list[float]) -> float:
    """The maximum of a run's per-iteration mean episode returns (NaN where an iteration ended none).

    Example:
        >>> mmer([0.1, float("nan"), 0.4, 0.3])
        0.4
    """
    finite = [r for r in returns if not math.isnan(r)]
    return max(finite) if finite else math.nan


def summarise(trained: list[dict], randoms: list[dict]) -> list[dict]:
    """One row per (task, label) of the trained runs and one random row per task."""
    rows = []
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in trained:
        groups.setdefault((r["task"], r["label"]), []).append(r)
    for (task, label), runs in groups.items():
        scores = [mmer(r["episode_return"]) for r in runs]
        last = [r["episode_return"][-1] if r["episode_return"] else math.nan for r in runs]
        minutes = [sum(r["seconds"]) / 60 for r in runs]
        rows.append({"task": task, "policy": label, "seeds": len(runs), "per_seed": scores,
                     "mmer": mean_se(scores), "last": mean_se(last), "frames": runs[0]["frames"][-1],
                     "minutes": mean_se(minutes)})
    for r in randoms:
        rows.append({"task": r["task"], "policy": RANDOM, "seeds": 0, "per_seed": [],
                     "mmer": mean_se(r["episode_return"]), "last": mean_se(r["episode_return"]),
                     "frames": 0, "minutes": (math.nan, math.nan)})
    return sorted(rows, key=lambda row: row["task"])


def markdown_table(rows: list[dict]) -> str:
    lines = ["| task | policy | MMER (mean ± s.e.) | per seed | last iteration | frames | training minutes |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        seeds = ", ".join(f"{s:.3f}" for s in r["per_seed"]) or "—"
        frames = f"{r['frames']:,}" if r["frames"] else "—"
        lines.append(f"| {r['task']} | {r['policy']} | {format_mean_se(r['mmer'])} | {seeds} | "
                     f"{format_mean_se(r['last'])} | {frames} | {format_mean_se(r['minutes'], 1)} |")
    return "\n".join(lines) + "\n"
