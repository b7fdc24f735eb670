"""``escort-rl bench frontier-decisions``: what a belief at a given cost is worth to a controller.

A frontier row (a filter at its N and K) drives the **greedy regulator** in closed loop: at each step
the action that brings the belief mean closest to the origin after the noise-free move,

    a_t = argmin_a ‖transition_mean(m̂_t, a)‖²,    m̂_t the belief mean,

which, for a reward ``−‖s_{t+1}‖`` and additive noise, is the myopic choice on the belief's first
moment: the expected squared distance ``E‖s + u_a‖² = ‖m̂ + u_a‖² + tr Σ`` depends on the belief
only through its mean. The rows differ by their beliefs alone. Where the model has an exact
posterior (:func:`~escort_rl.metrics.reference.has_exact_posterior`), an ``exact`` row acts on its mean:
the best any filter can do with this rule.

The ``E`` episodes of a row run as one batch, their starts and noise drawn from one generator seeded
the same for every row; the number of draws per step does not depend on the actions, so every row
meets the same starts and the same noise draws, and the difference of two rows' returns is paired
by episode. The table gives the
mean return ± s.e. over episodes, each row's paired difference to the first, the ms per update (one
belief; the batch's time over ``E``, the first update excluded) and the error of the mean.

Meant for the action-taking models of the frontier, e.g. the regulation form of the synthetic tracking
family: ``--model escort_rl.bench.synthetic.tracking:gmm_tracking --model-arg dim=10 control=1``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch

from escort_rl.bench.core import options
from escort_rl.bench.core.runner import Cell, CellStore, InProcessBackend, run_cells
from escort_rl.bench.frontier.cells import ITERATIVE, frontier_filter, frontier_model, model_label
from escort_rl.bench.frontier.spec import DECISIONS_OUTPUT, DecisionsSpec
from escort_rl.metrics.reference import exact_posterior_start, exact_posterior_update
from escort_rl.reporting.paths import write_results
from escort_rl.reporting.stats import format_mean_se, mean_se


def greedy_action(model, mean: torch.Tensor) -> torch.Tensor:
    """``argmin_a ‖transition_mean(mean, a)‖²`` for ``mean`` ``[B, d]`` -> actions int64 ``[B]``."""
    b, d = mean.shape
    actions = torch.arange(model.n_actions).expand(b, -1)  # [B, A]
    nxt = model.transition_mean(mean.unsqueeze(1).expand(b, model.n_actions, d), actions)
    return (nxt * nxt).sum(-1).argmin(-1)


@dataclass(frozen=True)
class DecisionCell(Cell):
    """One row: ``method`` at ``particles`` (and ``num_steps``), ``episodes`` closed-loop episodes of
    ``steps`` steps on ``model``; returns per-episode ``return`` and ``mean_error`` and the timing."""

    model: str
    method: str
    particles: int
    episodes: int
    steps: int
    num_steps: int = 0
    model_args: tuple = ()

    def key(self) -> str:
        k = f"-K{self.num_steps}" if self.method in ITERATIVE else ""
        return (f"decisions/{model_label(self.model, self.model_args)}/{self.method}/N{self.particles}{k}-"
                f"E{self.episodes}-T{self.steps}")

    def run(self) -> dict:
        model = frontier_model(self.model, tuple(self.model_args))
        e, exact = self.episodes, self.method == "exact"
        env = torch.Generator().manual_seed(10_007)  # the same starts and noise draws for every row
        s = model.initial_state((e,), env)
        if exact:
            log_w, means, covs = exact_posterior_start(model, e)
            mean = _mixture_mean(log_w, means)
        else:
            filt = frontier_filter(self.method, self.num_steps)
            g = torch.Generator().manual_seed(54_321)
            belief = filt.init(model, (e,), self.particles, g)
            mean = belief.mean()
        returns, errors, seconds = torch.zeros(e, dtype=torch.float64), [], 0.0
        for t in range(self.steps):
            a = greedy_action(model, mean)
            s = model.transition(s, a, env)
            o = model.observe(s, a, env)
            returns += model.reward(s, a, s).double()
            t0 = time.perf_counter()
            if exact:
                log_w, means, covs, _ = exact_posterior_update(model, log_w, means, covs, a, o)
                mean = _mixture_mean(log_w, means)
            else:
                belief = filt.update(model, belief, a, o, g)
                mean = belief.mean()
            if t > 0:
                seconds += time.perf_counter() - t0
            errors.append(torch.linalg.vector_norm(mean - s, dim=-1).double())
        return {"return": returns.tolist(), "mean_error": torch.stack(errors, 1).mean(1).tolist(),
                "timing": {"seconds_per_update": seconds / max(self.steps - 1, 1) / e}}


def _mixture_mean(log_w: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
    return (torch.softmax(log_w, -1).unsqueeze(-1) * means).sum(1).float()


def run_decisions(spec: DecisionsSpec, backend=None) -> dict:
    """Every row of ``spec`` driving the greedy regulator; each row's returns (mean ± s.e. over
    episodes), their paired difference to the first row's, the error of the mean and the ms per
    update. ``backend``: where the cells run (default in-process), closed at the end."""
    built = frontier_model(spec.model, spec.model_args)
    if getattr(built, "n_actions", 1) < 2:
        raise ValueError(f"--model: {type(built).__name__} has {getattr(built, 'n_actions', 1)} action; the regulator "
                         "needs a choice (gmm_tracking: pass --model-arg control=1)")
    cells = [DecisionCell(model=spec.model, model_args=spec.model_args, method=m, particles=n, num_steps=k,
                          episodes=spec.episodes, steps=spec.steps, threads=spec.threads) for m, n, k in spec.rows]
    store = CellStore(spec.output / "cells") if spec.output is not None else None
    backend = backend or InProcessBackend()
    try:
        results = run_cells(cells, backend, store, desc="decision cells")
    finally:
        backend.close()
    base = results[0]["return"]
    out_rows = []
    for c, r in zip(cells, results):
        name = "exact posterior" if c.method == "exact" else (
            f"{c.method} N={c.particles}" + (f" K={c.num_steps}" if c.method in ITERATIVE else ""))
        out_rows.append({"row": name, "method": c.method, "particles": c.particles, "num_steps": c.num_steps,
                         "return": mean_se(r["return"]), "mean_error": mean_se(r["mean_error"]),
                         "difference": mean_se([x - y for x, y in zip(r["return"], base)]),
                         "ms_per_update": 1e3 * r["timing"]["seconds_per_update"]})
    return {"model": spec.model, "model_args": list(spec.model_args), "episodes": spec.episodes,
            "steps": spec.steps, "rows": out_rows}


def decisions_markdown(result: dict) -> str:
    first = result["rows"][0]["row"]
    lines = [f"# Decisions on beliefs: the greedy regulator ({result['model']} {' '.join(result['model_args'])})", "",
             f"{result['episodes']} closed-loop episodes of {result['steps']} steps per row, the same starts and noise "
             "draws for every row; return = Σ_t −‖s_t‖ (higher is better), mean ± s.e. over episodes; the "
             f"difference to `{first}` is paired by episode; error = ‖m̂ − s‖ averaged over the steps.", "",
             f"| row | ms per update | return | difference to {first} | error of the mean |",
             "| --- | --- | --- | --- | --- |"]
    for r in result["rows"]:
        ms = "—" if r["method"] == "exact" else f"{r['ms_per_update']:.3g}"
        lines.append(f"| {r['row']} | {ms} | {format_mean_se(r['return'], 2)} | {format_mean_se(r['difference'], 2)} "
                     f"| {format_mean_se(r['mean_error'], 3)} |")
    return "\n".join(lines) + "\n"


def register(subparsers) -> None:
    full, quick = DecisionsSpec.full(model="", rows=["exact"]), DecisionsSpec.quick(model="", rows=["exact"])
    p = subparsers.add_parser("frontier-decisions", help="the greedy regulator, closed loop, on chosen frontier rows",
                              description="Drive the greedy regulator (argmin_a |transition_mean(belief mean, a)|^2) "
                              "on each row's belief in closed loop, on the same seeded episodes, and report the "
                              "returns with paired differences.")
    p.add_argument("--model", required=True, metavar="pkg.module:Class", help="a model with actions and reward -|s|, "
                   "e.g. escort_rl.bench.synthetic.tracking:gmm_tracking")
    p.add_argument("--model-arg", nargs="+", default=[], metavar="KEY=VALUE", help="e.g. dim=10 control=1")
    p.add_argument("--rows", nargs="+", required=True, metavar="METHOD:N[:K] | exact",
                   help="the rows, the first the baseline of the differences, e.g. sir:10000 enkf:1000 escort:300:50")
    p.add_argument("--episodes", type=int, default=None,
                   help=f"closed-loop episodes per row (default: {full.episodes}; --quick: {quick.episodes})")
    p.add_argument("--steps", type=int, default=None,
                   help=f"steps per episode (default: {full.steps}; --quick: {quick.steps})")
    options.add_quick_option(p, f"{quick.episodes} episodes of {quick.steps} steps")
    options.add_output_option(p, DECISIONS_OUTPUT, "frontier_decisions.md and frontier_decisions.json")
    options.add_runner_options(p, seeds_per_cell=False)
    p.set_defaults(handler=main)


def spec_from_args(args) -> DecisionsSpec:
    """The run ``args`` ask for: each setting given explicitly, else ``--quick``'s, else the default."""
    explicit = {name: getattr(args, name) for name in ("episodes", "steps", "threads")
                if getattr(args, name) is not None}
    make = DecisionsSpec.quick if args.quick else DecisionsSpec.full
    return make(model=f"class:{args.model}", model_args=args.model_arg, rows=args.rows, output=Path(args.output),
                **explicit)


def main(args) -> None:
    from escort_rl.bench.core.runner import backend_from_args

    spec = spec_from_args(args)
    result = run_decisions(spec, backend_from_args(args))
    write_results(spec.output, "frontier_decisions", result, decisions_markdown(result))
