"""Matplotlib figures written as PNG files (headless backend)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402


def plot_learning_curve(history: list[dict], path: Path) -> Path:
    """Mean episode return and final distance to goal per training iteration."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
    it = [h["iteration"] for h in history]
    axes[0].plot(it, [h["episode_return"] for h in history])
    axes[0].set_xlabel("iteration")
    axes[0].set_ylabel("mean episode return")
    axes[1].plot(it, [h["final_distance"] for h in history])
    axes[1].set_xlabel("iteration")
    axes[1].set_ylabel("final distance to goal")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def snapshot_steps(length: int, snapshots: int) -> list[int]:
    """``snapshots`` evenly spaced steps of an episode of ``length`` steps, its first and its last
    among them (every step of a shorter episode).

    Example:
        >>> snapshot_steps(500, 5), snapshot_steps(3, 8)
        ([0, 125, 250, 374, 499], [0, 1, 2])
    """
    last = length - 1
    return sorted({round(k * last / max(snapshots - 1, 1)) for k in range(snapshots)})


def plot_belief_projection(particles: torch.Tensor, true_positions: torch.Tensor, path: Path,
                           dims: tuple[int, int] = (0, 1), snapshots: int = 8,
                           position_error: torch.Tensor | None = None) -> Path:
    """Belief particles against the true state over one episode, projected on two position dims:
    ``snapshots`` evenly spaced steps from the first to the last (every step of a shorter episode).

    ``particles``: ``[T, N, d]``, ``true_positions``: ``[T, p]``, ``position_error``: ``[T]``.
    """
    ncols = 2 if position_error is not None else 1
    fig, axes = plt.subplots(1, ncols, figsize=(5.5 * ncols, 4.5), squeeze=False)
    ax = axes[0, 0]
    steps = snapshot_steps(particles.shape[0], snapshots)
    cmap = plt.get_cmap("viridis")
    for k, t in enumerate(steps):
        color = cmap(k / max(len(steps) - 1, 1))
        ax.scatter(particles[t, :, dims[0]], particles[t, :, dims[1]], s=4, alpha=0.35, color=color,
                   label=f"t={t}" if k in (0, len(steps) - 1) else None)
    ax.plot(true_positions[:, dims[0]], true_positions[:, dims[1]], "r-", lw=1.2, label="true position")
    ax.set_xlabel(f"x{dims[0] + 1}")
    ax.set_ylabel(f"x{dims[1] + 1}")
    ax.set_title("belief particles (colour: time) and the true path")
    ax.legend(loc="best", fontsize=8)
    if position_error is not None:
        axes[0, 1].plot(position_error)
        axes[0, 1].set_xlabel("step")
        axes[0, 1].set_ylabel("‖E_b[pos] − pos_true‖₂ (mean over episodes)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_particles_on_target(log_prob, particles: dict, path: Path, dims: tuple[int, int] = (0, 1),
                             center: torch.Tensor | None = None, title: str = "") -> Path:
    """Particles of several methods projected on two coordinates over the target's log-density
    contours (the other coordinates held at ``center``, default 0). ``particles``: name -> ``[N, d]``.
    One panel per method. For d = 1 a histogram over the density is drawn instead."""
    names = list(particles)
    d = next(iter(particles.values())).shape[-1]
    fig, axes = plt.subplots(1, len(names), figsize=(3.2 * len(names), 3.2), squeeze=False)
    allx = torch.cat([p.reshape(-1, d) for p in particles.values()]).double()
    if d == 1:
        grid = torch.linspace(float(allx.min()) - 1, float(allx.max()) + 1, 400, dtype=torch.float64)
        dens = torch.exp(log_prob(grid[:, None]))
        for ax, name in zip(axes[0], names):
            ax.hist(particles[name][:, 0].double().numpy(), bins=60, density=True, alpha=0.6)
            ax.plot(grid.numpy(), dens.numpy(), "k-", lw=1)
            ax.set_title(name, fontsize=9)
    else:
        i, j = dims
        lo, hi = allx.min(0).values - 1, allx.max(0).values + 1
        gx = torch.linspace(float(lo[i]), float(hi[i]), 120, dtype=torch.float64)
        gy = torch.linspace(float(lo[j]), float(hi[j]), 120, dtype=torch.float64)
        xx, yy = torch.meshgrid(gx, gy, indexing="xy")
        base = torch.zeros(d, dtype=torch.float64) if center is None else center.double()
        pts = base.expand(xx.numel(), d).clone()
        pts[:, i], pts[:, j] = xx.reshape(-1), yy.reshape(-1)
        z = log_prob(pts).reshape(xx.shape)
        for ax, name in zip(axes[0], names):
            ax.contour(xx.numpy(), yy.numpy(), z.clamp_min(z.max() - 20).numpy(), levels=12, linewidths=0.6)
            p = particles[name].double()
            ax.scatter(p[:, i].numpy(), p[:, j].numpy(), s=2, alpha=0.4, color="tab:orange")
            ax.set_title(name, fontsize=9)
            ax.set_xlabel(f"x{i + 1}")
            ax.set_ylabel(f"x{j + 1}")
    return _finish(fig, path, title, title_size=10, dpi=100)


def plot_metric_against_dimension(rows: list[dict], metric: str, path: Path, group_key: str = "method",
                                  dim_key: str = "dim", ylabel: str | None = None) -> Path:
    """Mean ± s.e. of ``metric`` against the dimension, one line per ``group_key`` value (averaged over
    any other keys at the same dimension)."""
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    groups: dict = {}
    for r in rows:
        m, se = r["summary"][metric]
        if m != m:  # NaN: the metric does not apply
            continue
        groups.setdefault(r[group_key], {}).setdefault(r[dim_key], []).append((m, se))
    for name, by_dim in groups.items():
        dims = sorted(by_dim)
        means = [sum(v[0] for v in by_dim[k]) / len(by_dim[k]) for k in dims]
        ses = [sum(v[1] for v in by_dim[k]) / len(by_dim[k]) for k in dims]
        ax.errorbar(dims, means, yerr=ses, marker="o", ms=3, capsize=2, label=name)
    ax.set_xscale("log")
    ax.set_xlabel("dimension")
    ax.set_ylabel(ylabel or metric)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _finish(fig, path: Path, title: str = "", title_size: int = 9, dpi: int = 110) -> Path:
    """Give ``fig`` its overall ``title`` (if any), lay it out, write it to ``path`` and close it."""
    if title:
        fig.suptitle(title, fontsize=title_size)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _draw_curves(ax, curves: dict, start: int = 0) -> None:
    """``curves`` (name -> ``(mean, se)``) on ``ax``: one line each, shaded ± s.e.; all-NaN left out."""
    for name, (mean, se) in curves.items():
        m = torch.tensor(mean, dtype=torch.float64)
        if torch.isnan(m).all():
            continue
        t = torch.arange(start, start + m.shape[0])
        ax.plot(t.numpy(), m.numpy(), label=name, lw=1.2)
        if se is not None:
            s = torch.tensor(se, dtype=torch.float64)
            ax.fill_between(t.numpy(), (m - s).numpy(), (m + s).numpy(), alpha=0.2)


def plot_curves(curves: dict, path: Path, xlabel: str, ylabel: str, title: str = "", start: int = 0) -> Path:
    """One line per name against the step, shaded ± s.e. where given.

    ``curves``: name -> ``(mean, se)``, each a list of length ``T`` (``se`` may be ``None``); the
    x axis runs ``start .. start + T - 1``. A curve that is all NaN (a method without the metric) is
    left out.
    """
    fig, ax = plt.subplots(figsize=(6.5, 4))
    _draw_curves(ax, curves, start)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_curve_panels(panels: dict, path: Path, xlabel: str, ncols: int, title: str = "", log_y: bool = False) -> Path:
    """A grid of :func:`plot_curves` panels: ``panels`` maps a panel's y label to its curves
    (name -> ``(mean, se)``), filled row by row, ``ncols`` per row; one legend, on the first panel."""
    nrows = max(1, -(-len(panels) // ncols))
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.6 * ncols, 2.9 * nrows), squeeze=False)
    for ax, (ylabel, curves) in zip(axes.flat, panels.items()):
        _draw_curves(ax, curves)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        if log_y:
            ax.set_yscale("log")
    for ax in list(axes.flat)[len(panels):]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=7)
    return _finish(fig, path, title)


def plot_frontier(rows: list[dict], front: list[str], path: Path, xlabel: str, ylabel: str, title: str = "",
                  label=None) -> Path:
    """Accuracy against cost on log–log axes: one marker series per ``row["method"]`` (``ms_per_update``
    against ``error``), the points of ``front`` (their ``label(row)``) joined by a line."""
    fig, ax = plt.subplots(figsize=(6.0, 4.2))
    by_method: dict = {}
    for r in rows:
        if r["error"] == r["error"] and r["error"] > 0:
            by_method.setdefault(r["method"], []).append(r)
    for method, rs in by_method.items():
        ax.scatter([r["ms_per_update"] for r in rs], [r["error"] for r in rs], label=method, s=22)
    on = sorted((r for r in rows if label is not None and label(r) in front), key=lambda r: r["ms_per_update"])
    if on:
        ax.plot([r["ms_per_update"] for r in on], [r["error"] for r in on], color="black", lw=1, ls="--",
                label="Pareto front")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=8)
    return _finish(fig, path, title)


def plot_regime_map(points: list[dict], path: Path, budgets=(1.0, 10.0, 100.0), title: str = "") -> Path:
    """One panel per time budget: a grid of (dimension, observation std) points, each coloured and
    labelled by the filter closest to the reference within that budget (``point["budgets"]``)."""
    dims = sorted({p["dim"] for p in points})
    stds = sorted({p["obs_std"] for p in points})
    methods = sorted({(b["best"] or "none").split()[0] for p in points for b in p["budgets"]})
    colours = {m: plt.cm.tab10(i) for i, m in enumerate(methods)}
    fig, axes = plt.subplots(1, len(budgets), figsize=(3.4 * len(budgets), 0.5 + 0.55 * len(dims) + 1.2),
                             squeeze=False)
    for ax, budget in zip(axes[0], budgets):
        for p in points:
            best = next((b["best"] for b in p["budgets"] if b["ms"] == budget), None) or "none"
            x, y = stds.index(p["obs_std"]), dims.index(p["dim"])
            ax.add_patch(plt.Rectangle((x - 0.5, y - 0.5), 1, 1, color=colours[best.split()[0]], alpha=0.55))
            ax.text(x, y, best.replace(" K=", "\nK=").replace(" N=", "\nN="), ha="center", va="center", fontsize=6)
        ax.set_xlim(-0.5, len(stds) - 0.5)
        ax.set_ylim(-0.5, len(dims) - 0.5)
        ax.set_xticks(range(len(stds)), [f"{s:g}" for s in stds])
        ax.set_yticks(range(len(dims)), [str(d) for d in dims])
        ax.set_xlabel("observation std")
        ax.set_ylabel("dimension D")
        ax.set_title(f"closest within {budget:g} ms", fontsize=8)
    return _finish(fig, path, title)


def plot_rows_with_seeds(rows: list[dict], metric: str, path: Path, ylabel: str, title: str = "") -> Path:
    """One horizontal bar per row at ``row[metric]`` with its ``row[metric + "_se"]`` as an error bar,
    and, where a row has them, its per-seed values (``row["per_seed"][metric]``) as dots."""
    fig, ax = plt.subplots(figsize=(7, 0.6 * len(rows) + 1.2))
    ys = list(range(len(rows)))[::-1]
    for y, row in zip(ys, rows):
        ax.barh(y, row[metric], xerr=row.get(f"{metric}_se", 0.0), color="C0" if row.get("per_seed") else "C7",
                alpha=0.8, capsize=4)
        seeds = row.get("per_seed", {}).get(metric, [])
        ax.scatter(seeds, [y] * len(seeds), color="k", s=12, zorder=3)
    ax.set_yticks(ys, [row["policy"] for row in rows], fontsize=8)
    ax.set_xlabel(ylabel)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_against_frames(curves: dict, lines: dict, path: Path, ylabel: str, title: str = "") -> Path:
    """Each of ``curves`` (label -> ``(frames, mean, se)``, three lists) as a line with ± s.e. bars
    against training frames, and each of ``lines`` (label -> ``(value, se)``) as a horizontal line
    with its ± s.e. band: a learner's success against frames beside a fixed policy's."""
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for i, (label, (frames, mean, se)) in enumerate(curves.items()):
        ax.errorbar(frames, mean, yerr=se, label=label, color=f"C{i}", lw=1.2, capsize=3, marker="o", ms=3)
    for j, (label, (value, se)) in enumerate(lines.items()):
        color = f"C{len(curves) + j}"
        ax.axhline(value, color=color, ls="--", lw=1.0, label=label)
        ax.axhspan(value - se, value + se, color=color, alpha=0.12)
    ax.set_xlabel("training frames")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7)
    return _finish(fig, path, title)
