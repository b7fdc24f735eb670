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


def plot_belief_projection(particles: torch.Tensor, true_positions: torch.Tensor, path: Path,
                           dims: tuple[int, int] = (0, 1), every: int = 50,
                           position_error: torch.Tensor | None = None) -> Path:
    """Belief particles against the true state over one episode, projected on two position dims.

    ``particles``: ``[T, N, d]``, ``true_positions``: ``[T, p]``, ``position_error``: ``[T]``.
    """
    ncols = 2 if position_error is not None else 1
    fig, axes = plt.subplots(1, ncols, figsize=(5.5 * ncols, 4.5), squeeze=False)
    ax = axes[0, 0]
    steps = list(range(0, particles.shape[0], every))
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
