"""Learning curves of several training runs side by side (e.g. DVRL against ESCORT + DeepSets).

Each run's history is read from its latest checkpoint (the per-iteration records the trainers keep:
frames, mean episode return, final distance to goal, and for DVRL the mean ELBO term per step).
``escort-rl bench curves RUN [RUN ...]`` writes ``learning_curves.png`` (against frames) and
``learning_curves.md`` (each run's first and last iterations and its training frames per second).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from escort_rl.bench.core import options
from escort_rl.config import registry
from escort_rl.reporting.metadata import with_metadata
from escort_rl.reporting.paths import display_path
from escort_rl.trainers.checkpointing import load_checkpoint, resolve_checkpoint


def run_label(config: dict) -> str:
    """``"<filter> + DeepSets (<algorithm>)"`` for a policy on a filter's beliefs; for a trainer whose
    policy reads something else, what it reads (its class's ``belief_label``, e.g. ``"dvrl (learned
    belief)"``)."""
    algorithm = config.get("trainer", {}).get("algorithm", "reinforce")
    label = registry.resolve("trainer", algorithm).belief_label
    if label is not None:
        return label
    return f"{config.get('filter', {}).get('name', '?')} + DeepSets ({algorithm})"


def load_history(run: str | Path) -> dict:
    """``{"run", "label", "env", "history"}`` of a run directory (or checkpoint)."""
    path = resolve_checkpoint(run)
    saved = load_checkpoint(path)
    history = list(saved["trainer_state"]["history"])
    if not history:
        raise ValueError(f"runs: '{run}' has no training history yet")
    return {"run": display_path(Path(run)), "label": run_label(saved["config"]),
            "env": saved["config"]["env"]["name"], "history": history}


def legend_labels(runs: list[dict]) -> list[str]:
    """Each run's label, with its directory name added only where two runs share a label."""
    labels = [run["label"] for run in runs]
    return [f"{label} ({Path(run['run']).name})" if labels.count(label) > 1 else label
            for label, run in zip(labels, runs)]


def plot_learning_curves(runs: list[dict], path: Path) -> Path:
    """Return, final distance to goal and (where recorded) ELBO per step against frames, one line per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("episode_return", "mean episode return"), ("final_distance", "final distance to goal"),
              ("elbo", "ELBO per step (DVRL)")]
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    labels = legend_labels(runs)
    for i, run in enumerate(runs):
        frames = [h["frames"] for h in run["history"]]
        for ax, (key, _) in zip(axes, panels):
            values = [h.get(key, math.nan) for h in run["history"]]
            if any(not math.isnan(v) for v in values):
                ax.plot([f / 1000 for f in frames], values, marker=".", label=labels[i], color=f"C{i}")
    for ax, (_, name) in zip(axes, panels):
        ax.set_xlabel("frames (thousands)")
        ax.set_ylabel(name)
        if ax.lines:
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def curves_markdown(runs: list[dict]) -> str:
    lines = ["# Learning curves", "",
             "Per-iteration training records of each run (mean over the iteration's finished episodes). "
             "Frames per second: frames over the iterations' wall-clock (collection and update).", "",
             "| run | label | env | frames | first return | last return | first distance | last distance | "
             "last ELBO | frames/s |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for run in runs:
        h = run["history"]
        seconds = sum(r["seconds"] for r in h)
        elbo = h[-1].get("elbo")
        lines.append(f"| `{run['run']}` | {run['label']} | {run['env']} | {h[-1]['frames']} | "
                     f"{h[0]['episode_return']:.1f} | {h[-1]['episode_return']:.1f} | {h[0]['final_distance']:.2f} | "
                     f"{h[-1]['final_distance']:.2f} | {'—' if elbo is None else f'{elbo:.2f}'} | "
                     f"{h[-1]['frames'] / max(seconds, 1e-9):.0f} |")
    return "\n".join(lines) + "\n"


def write_curves(run_dirs: list[str], output: str | Path) -> list[dict]:
    """Load the runs and write ``learning_curves.png``, ``.md`` and ``.json`` into ``output``."""
    if not run_dirs:
        raise ValueError("runs: give at least one run directory")
    runs = [load_history(r) for r in run_dirs]
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    plot_learning_curves(runs, out / "learning_curves.png")
    (out / "learning_curves.md").write_text(curves_markdown(runs))
    (out / "learning_curves.json").write_text(json.dumps(with_metadata(runs), indent=1))
    return runs


def register(subparsers) -> None:
    """Add ``bench curves`` to the ``bench`` subparsers."""
    cur = subparsers.add_parser("curves", help="learning curves of training runs side by side",
                                description="Return, final distance to goal and (DVRL) ELBO against frames for "
                                "each run directory; writes learning_curves.png, .md and .json.")
    cur.add_argument("runs", nargs="+",
                     help="run directories (or checkpoints), e.g. outputs/lightdark10d/escort_train-ppo-seed0")
    options.add_output_option(cur, "outputs/bench/curves", "learning_curves.png, .md and .json")
    cur.set_defaults(handler=main)


def main(args) -> None:
    print(curves_markdown(write_curves(args.runs, args.output)))
    print(f"results: {Path(args.output).resolve()}")
