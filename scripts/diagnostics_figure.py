"""The figure of docs/diagnostics.md: ESS / N and the running log-evidence over one Light-Dark 10D
episode, SIR and ESCORT (the default job's filter) tracking the same trajectory, driven by the scripted
controller on SIR's belief. Prints what the page quotes.

    python scripts/diagnostics_figure.py [--output docs/figures/diagnostics.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from escort_rl import make_filter
from escort_rl.models import LightDark10D
from escort_rl.planners.scripted import pd_action
from escort_rl.reporting.plots import plot_curve_panels


def track(steps: int = 300, particles: int = 100, seed: int = 0) -> dict:
    """``{filter: {"ess": [T], "log_evidence": [T], "resampled": [T]}}`` on one seeded episode."""
    model, g = LightDark10D(), torch.Generator().manual_seed(seed)
    filters = {name: make_filter(name) for name in ("sir", "escort_train")}
    beliefs = {name: f.init(model, (1,), particles, torch.Generator().manual_seed(seed + 1))
               for name, f in filters.items()}
    generators = {name: torch.Generator().manual_seed(seed + 2) for name in filters}
    out = {name: {"ess": [], "log_evidence": [], "resampled": []} for name in filters}
    s = model.initial_state((1,), g)
    for _ in range(steps):
        mean = beliefs["sir"].mean()
        a = pd_action(mean[..., :5], mean[..., 5:], model.goal, 0.125)
        s = model.transition(s, a, g)
        o = model.observe(s, a, g)
        for name, f in filters.items():
            beliefs[name] = b = f.update(model, beliefs[name], a, o, generators[name])
            out[name]["ess"].append(float(b.ess[0]) / particles)
            out[name]["log_evidence"].append(float(b.log_evidence[0]))
            out[name]["resampled"].append(bool(b.resampled[0]))
        if bool(model.is_terminal(s)[0]):
            break
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default="docs/figures/diagnostics.png")
    args = parser.parse_args()
    runs = track()
    panels = {"ESS / N (before resampling)": {n: (r["ess"], None) for n, r in runs.items()},
              "running log-evidence": {n: (r["log_evidence"], None) for n, r in runs.items()}}
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    plot_curve_panels(panels, Path(args.output), "step", ncols=2,
                      title="One Light-Dark 10D episode, N = 100, the scripted controller on SIR's belief")
    for name, r in runs.items():
        ess = torch.tensor(r["ess"])
        print(f"{name}: {len(ess)} steps, ESS/N median {ess.median():.2f}, min {ess.min():.3f}, "
              f"resampled at {sum(r['resampled'])} steps, log-evidence at the end {r['log_evidence'][-1]:.1f}")
    print(f"figure: {args.output}")


if __name__ == "__main__":
    main()
