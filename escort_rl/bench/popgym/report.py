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
GRU = "GRU (recurrent PPO)"


def mmer(returns: list[float]) -> float:
    """The maximum of a run's per-iteration mean episode returns (NaN where an iteration ended none).

    Example:
        >>> mmer([0.1, float("nan"), 0.4, 0.3])
        0.4
    """
    finite = [r for r in returns if not math.isnan(r)]
    return max(finite) if finite else math.nan


def summarise(trained: list[dict], randoms: list[dict]) -> list[dict]:
    """One row per (task, label) of the trained runs and one random row per task, grouped by task in
    the order the trained runs name them (the spec's: Easy, Medium, Hard)."""
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
    order: dict[str, int] = {}
    for row in rows:
        order.setdefault(row["task"], len(order))
    return sorted(rows, key=lambda row: order[row["task"]])  # the tasks in the order the runs came


def markdown_table(rows: list[dict]) -> str:
    lines = ["| task | policy | MMER (mean ± s.e.) | per seed | last iteration | frames | training minutes |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        seeds = ", ".join(f"{s:.3f}" for s in r["per_seed"]) or "—"
        frames = f"{r['frames']:,}" if r["frames"] else "—"
        lines.append(f"| {r['task']} | {r['policy']} | {format_mean_se(r['mmer'])} | {seeds} | "
                     f"{format_mean_se(r['last'])} | {frames} | {format_mean_se(r['minutes'], 1)} |")
    return "\n".join(lines) + "\n"


def versus(rows: list[dict], reference: str = GRU) -> list[dict]:
    """Each trained row's MMER less the ``reference`` row's on the same task: the difference of the
    means, its standard error ``sqrt(se_a² + se_b²)`` (the two rows' seeds are independent runs), and
    the difference in those standard errors (``z``).

    Example:
        >>> rows = [{"task": "T", "policy": "GRU (recurrent PPO)", "mmer": (0.5, 0.03)},
        ...         {"task": "T", "policy": "PPO on SIR beliefs", "mmer": (0.8, 0.04)}]
        >>> [(r["policy"], round(r["difference"], 3), round(r["se"], 3), round(r["z"], 1)) for r in versus(rows)]
        [('PPO on SIR beliefs', 0.3, 0.05, 6.0)]
    """
    base = {r["task"]: r["mmer"] for r in rows if r["policy"] == reference}
    out = []
    for r in rows:
        if r["policy"] in (reference, RANDOM) or r["task"] not in base:
            continue
        (m, se), (m0, se0) = r["mmer"], base[r["task"]]
        spread = math.hypot(se, se0)
        out.append({"task": r["task"], "policy": r["policy"], "difference": m - m0, "se": spread,
                    "z": (m - m0) / spread if spread > 0 else math.nan})
    return out


def versus_table(rows: list[dict], reference: str = GRU) -> str:
    """:func:`versus` as a Markdown table."""
    lines = [f"| task | policy | MMER − {reference}'s | in s.e. |", "| --- | --- | --- | --- |"]
    for r in versus(rows, reference):
        z = "—" if math.isnan(r["z"]) else f"{r['z']:+.1f}"
        lines.append(f"| {r['task']} | {r['policy']} | {format_mean_se((r['difference'], r['se']))} | {z} |")
    return "\n".join(lines) + "\n"
