"""The report of ``escort-rl bench atari`` (``atari.md``, ``atari.json``, ``learning_curves.png``).

Per game and agent: the mean of the last :data:`LAST_GAMES` games' returns (unclipped game scores)
of each seed, their mean ± s.e. across seeds (the pooled games' where there is one seed), how many
standard errors it lies above the random policy's, the same at equal wall-clock (the games each run
had ended by the time the fastest agent finished its frames), the frames and the training frames/s;
beside it, the paper's Table 4 where the game is one of its. The curves show the returns against
frames and against training seconds.
"""

from __future__ import annotations

import math
from pathlib import Path

from omegaconf import DictConfig

from escort_rl.reporting.stats import format_mean_se, mean_se

LAST_GAMES = 100  # the returns of the last games of each seed that the table averages
PAPER_METHOD = {"escort_latent": "escort", "dvrl": "dvrl"}  # our agent -> the paper's Table 4 column
RANDOM = "random"


def last_games(result: dict, by_seconds: float | None = None) -> list[float]:
    """The returns of the last :data:`LAST_GAMES` games of one run, or of those that had ended by
    ``by_seconds`` of its training."""
    returns = result["game_returns"]
    if by_seconds is not None:
        returns = [r for r, s in zip(returns, result["game_seconds"]) if s <= by_seconds]
    return returns[-LAST_GAMES:]


def margin(a: tuple[float, float], b: tuple[float, float]) -> float:
    """``(m_a − m_b) / sqrt(se_a² + se_b²)``: how many combined standard errors ``a`` lies above ``b``
    (NaN when either is missing or both are exact)."""
    scale = math.hypot(a[1], b[1])
    return (a[0] - b[0]) / scale if scale > 0 else float("nan")


def equal_seconds(results: list[dict], game: str) -> float | None:
    """The wall-clock of equal time on ``game``: the smallest, over the trained agents, of their
    seeds' mean training seconds (``None`` without a trained agent)."""
    per_agent: dict[str, list[float]] = {}
    for r in results:
        if r["game"] == game and r["agent"] != RANDOM:
            per_agent.setdefault(r["agent"], []).append(r["seconds"])
    return min(sum(s) / len(s) for s in per_agent.values()) if per_agent else None


def seed_level(row: dict, key: str = "return") -> tuple[float, float]:
    """The row's mean ± s.e. with the training seeds as the samples (``<key>_seeds``) where it has two
    or more seeds, else that of its pooled games (``<key>``): the figure every comparison uses."""
    return row[f"{key}_seeds"] if row["seeds"] >= 2 else row[key]


def summarise(results: list[dict]) -> list[dict]:
    """One row per (game, agent), in the order met: ``return`` (the last games of each seed pooled,
    mean ± s.e.), ``seed_means`` (each seed's mean) and ``return_seeds`` (their mean ± s.e.),
    ``above_random`` (:func:`margin` of :func:`seed_level` figures over the random row of the game, if
    any), ``return_equal_time`` and ``return_equal_time_seeds`` at ``equal_seconds``, the frames
    (smallest over seeds), the frames/s and the training seconds (means over seeds)."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in results:
        groups.setdefault((r["game"], r["agent"]), []).append(r)
    rows = []
    for (game, agent), runs in groups.items():
        t_equal = equal_seconds(results, game)
        pooled = [x for r in runs for x in last_games(r)]
        timed = agent != RANDOM and t_equal is not None
        at_time = [x for r in runs for x in last_games(r, t_equal)] if timed else []
        seed_means = [mean_se(last_games(r))[0] for r in runs]
        seed_means_at_time = [mean_se(last_games(r, t_equal))[0] for r in runs] if timed else []
        rows.append({"game": game, "agent": agent, "seeds": len(runs), "games": len(pooled),
                     "return": mean_se(pooled), "seed_means": seed_means, "return_seeds": mean_se(seed_means),
                     "equal_seconds": t_equal, "return_equal_time": mean_se(at_time), "games_equal_time": len(at_time),
                     "return_equal_time_seeds": mean_se(seed_means_at_time),
                     "frames": min(r["frames"] for r in runs), "fps": sum(r["fps"] for r in runs) / len(runs),
                     "seconds": sum(r["seconds"] for r in runs) / len(runs)})
    randoms = {row["game"]: seed_level(row) for row in rows if row["agent"] == RANDOM}
    for row in rows:
        base = randoms.get(row["game"])
        row["above_random"] = margin(seed_level(row), base) if base is not None and row["agent"] != RANDOM else None
    return rows


def _number(x: float | None, digits: int = 1) -> str:
    return "—" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:,.{digits}f}"


def markdown_table(rows: list[dict], paper: DictConfig | None) -> str:
    """Ours beside the random policy and the paper's Table 4 (where ``paper`` has the game), each with
    its budget in frames (agent steps)."""
    lines = ["| game | agent | last 100 games: mean ± s.e. | per seed | above random (s.e.) | at equal wall-clock (s) "
             "| games (seeds) | frames | frames/s | paper (same method) | paper frames | paper's budget at our rate "
             "(hours per seed) |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in rows:
        method = PAPER_METHOD.get(row["agent"])
        ref = paper.table4.get(row["game"], {}).get(method) if method and paper is not None else None
        paper_text, paper_frames = ((f"{ref[0]} ± {ref[1]} ({method.upper()})", f"{int(paper.frames):,}")
                                    if ref is not None else ("—", "—"))
        in_paper = paper is not None and row["game"] in paper.table4 and row["agent"] != RANDOM
        hours = _number(int(paper.frames) / row["fps"] / 3600.0) if in_paper and row["fps"] > 0 else "—"
        equal = ("—" if row["agent"] == RANDOM or row["equal_seconds"] is None else
                 f"{format_mean_se(seed_level(row, 'return_equal_time'), 2)} ({row['equal_seconds']:.0f})")
        per_seed = ", ".join(_number(m, 2) for m in row["seed_means"])
        lines.append(f"| {row['game']} | {row['agent']} | {format_mean_se(seed_level(row), 2)} | {per_seed} | "
                     f"{_number(row['above_random'])} | {equal} | {row['games']} ({row['seeds']}) | "
                     f"{row['frames']:,} | {_number(row['fps'])} | {paper_text} | {paper_frames} | {hours} |")
    return "\n".join(lines) + "\n"


def seed_curve(xs: list[float], returns: list[float], grid, window: int, upto: float):
    """One run's learning curve on ``grid``: the running mean of its last ``window`` games' returns,
    ``xs`` the frame (or second) at which each game ended, read at each grid point from the games
    ended by then (NaN before its first game and after the run's end, ``upto``)."""
    import numpy as np

    if not returns:
        return np.full(len(grid), np.nan)
    r = np.asarray(returns, dtype=float)
    sums = np.concatenate([[0.0], np.cumsum(r)])
    idx = np.arange(1, len(r) + 1)
    smooth = (sums[idx] - sums[np.maximum(idx - window, 0)]) / np.minimum(idx, window)
    ended = np.searchsorted(np.asarray(xs, dtype=float), grid, side="right")  # games ended by each point
    out = np.where(ended > 0, smooth[np.maximum(ended - 1, 0)], np.nan)
    return np.where(grid <= upto, out, np.nan)


def plot_curves(results: list[dict], path: Path, window: int = 20, points: int = 200) -> Path:
    """Learning curves, one column per game: each agent's return against frames (top) and training
    seconds (bottom): each seed's running mean over its last ``window`` games, then the mean over
    seeds (shaded: ± one s.e. across seeds where two or more have data); the random policy's mean as a
    dashed line."""
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    games = sorted({r["game"] for r in results})
    fig, axes = plt.subplots(2, len(games), figsize=(5 * len(games), 7), squeeze=False)
    for col, game in enumerate(games):
        top, bottom = axes[0][col], axes[1][col]
        for agent in sorted({r["agent"] for r in results if r["game"] == game}):
            runs = [r for r in results if r["game"] == game and r["agent"] == agent]
            if agent == RANDOM:
                mean = mean_se([x for r in runs for x in last_games(r)])[0]
                for ax in (top, bottom):
                    if not math.isnan(mean):
                        ax.axhline(mean, color="grey", linestyle="--", label=f"random ({len(runs)} seeds)")
                continue
            for ax, key in ((top, "game_frames"), (bottom, "game_seconds")):
                extent = "frames" if key == "game_frames" else "seconds"
                if not any(r[key] for r in runs):
                    continue
                grid = np.linspace(0.0, max(r[extent] for r in runs), points)
                curves = np.stack([seed_curve(r[key], r["game_returns"], grid, window, r[extent]) for r in runs])
                have = np.isfinite(curves).sum(0)
                mean = np.where(have > 0, np.nanmean(np.where(have > 0, curves, 0.0), 0), np.nan)
                line, = ax.plot(grid, mean, label=f"{agent} ({len(runs)} seeds)")
                if len(runs) > 1:
                    spread = np.nanstd(np.where(have > 1, curves, 0.0), 0, ddof=1) / np.sqrt(np.maximum(have, 1))
                    band = have > 1
                    ax.fill_between(grid[band], (mean - spread)[band], (mean + spread)[band], alpha=0.2,
                                    color=line.get_color())
        top.set_title(f"Flickering {game}")
        top.set_xlabel("frames (agent steps)")
        bottom.set_xlabel("training seconds")
        for ax in (top, bottom):
            ax.set_ylabel(f"game return (running mean of {window} games)")
            if ax.lines:
                ax.legend(fontsize=8)
            else:
                ax.text(0.5, 0.5, "no game has ended yet", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
