"""What a belief is worth to a controller: the domain's scripted controller, closed loop, on several
filters and filter settings, on the same seeded episodes (``escort-rl bench decisions``).

Each row is a list of config overrides (``filter=escort_train filter.jitter=0``, ``num_particles=1000``)
composed on ``env=<domain>``; the scripted PD controller (:mod:`escort_rl.planners.scripted`) acts on
that row's belief mean for ``episodes`` episodes, env seeds ``seed + 0 .. episodes - 1`` in one batch
(the same start states for every row). Besides the task outcome (success, final distance, steps), a
row records what the controller reads from the belief:

- the error of the belief mean in the controller's position and velocity inputs
  (:func:`escort_rl.planners.scripted.controlled_dims`), ``‖x̂ − x‖₂`` and ``‖v̂ − v‖₂``, averaged over
  each episode's steps and over its steps within ``near`` of the goal;
- the belief's spread, the per-coordinate standard deviation of the particles, in the same inputs;
- **action agreement**: the fraction of steps at which the action taken on the belief equals the
  action the same rule takes on the true state, overall and near the goal (the controller is a
  function of its inputs only, so a disagreement is the belief misleading it);
- error over time (mean over the episodes still running at each step), as plots;
- **where the steps go**: the step at which the true state first comes within ``near`` of the goal
  (the episode's length where it never does), and, over the episodes that reach the goal, the steps
  from there to the goal.

``--true-state`` adds the same rule on the simulator's true state (:class:`TrueStateController`), on the
same episodes beside the first row's belief: the full-information reference, whose steps are what the
task's dynamics alone ask; the gap to it is what the belief costs the rule, phase by phase.

Every figure is a mean ± standard error over episodes; the success difference of each row to the
baseline row (``--baseline``, default the first) is paired by episode (same start state), with its
own standard error.
Each row is a cell of :mod:`escort_rl.bench.core.runner`: saved as it finishes, skipped on a rerun.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch

from escort_rl.bench.core import options
from escort_rl.bench.core.runner import CellStore, ConfigCell, backend_from_args, run_cells
from escort_rl.reporting.paths import safe_name, write_results
from escort_rl.reporting.plots import plot_curves
from escort_rl.reporting.stats import format_mean_se, mean_se

ROWS: dict[str, tuple[str, ...]] = {
    "sir": ("filter=sir",),
    "sir N=1000": ("filter=sir", "num_particles=1000"),
    "escort_train": ("filter=escort_train",),
    "escort_train prior=smoothed": ("filter=escort_train", "filter.prior=smoothed"),
    "escort_train prior=smoothed jitter=0": ("filter=escort_train", "filter.prior=smoothed", "filter.jitter=0"),
    "escort_train prior=smoothed lambda_temp=0": ("filter=escort_train", "filter.prior=smoothed",
                                                  "filter.lambda_temp=0"),
    "escort_train prior=smoothed K=50 step=0.1": ("filter=escort_train", "filter.prior=smoothed",
                                                  "filter.num_steps=50", "filter.step_size=0.1"),
    "escort_train K=50 step=0.1": ("filter=escort_train", "filter.num_steps=50", "filter.step_size=0.1"),
}
"""The named rows: label -> config overrides (on ``env=<domain> num_particles=<N>``)."""
DEFAULT_ROWS = tuple(ROWS)
TRUE_STATE_ROW = "the rule on the true state (full information)"
"""``--true-state``'s row: the same controller at the same gain on the simulator's state."""
QUICK = dict(episodes=4, steps=30, rows=("sir", "escort_train"), particles=30)
"""``--quick``: a smoke run."""


def parse_row(name: str) -> tuple[str, tuple[str, ...]]:
    """A named row (:data:`ROWS`) -> ``(label, overrides)``; a row of your own is ``--add-row LABEL
    OVERRIDE ...``."""
    if name not in ROWS:
        raise ValueError(f"--rows: unknown row '{name}'; known: {', '.join(ROWS)}; for a row of your own give "
                         "--add-row LABEL OVERRIDE ...")
    return name, ROWS[name]


@dataclass(frozen=True, kw_only=True)
class DecisionCell(ConfigCell):
    """One row: the scripted controller on one filter configuration, closed loop."""

    label: str
    domain: str
    overrides: tuple[str, ...]
    particles: int
    episodes: int
    seed: int
    steps: int | None = None
    near: float = 1.0
    on_true_state: bool = False

    def key(self) -> str:
        return f"{self.domain}/{safe_name(self.label)}"

    def config(self):
        from escort_rl.config import compose

        extra = [] if self.steps is None else [f"env.max_steps={self.steps}"]
        has_n = any(o.startswith("num_particles=") for o in self.overrides)
        return compose([f"env={self.domain}", *([] if has_n else [f"num_particles={self.particles}"]),
                        *extra, *self.overrides])

    def run(self) -> dict:
        from escort_rl.planners.scripted import belief_mean, controlled_dims
        from escort_rl.trainers.builders import build_model
        from escort_rl.trainers.evaluate import first_episode_metrics, run_episodes, scripted_policy

        cfg = self.config()
        model = build_model(cfg.env, cfg.device)
        policy = scripted_policy(cfg, model, on_true_state=self.on_true_state)
        if policy is None:
            raise ValueError(f"bench decisions: {self.domain} has no scripted controller")
        t0 = time.perf_counter()
        rollout, step_s = run_episodes(cfg, policy, self.episodes, self.seed)
        seconds = time.perf_counter() - t0
        m = first_episode_metrics(rollout, model)
        pos, vel = (list(i) for i in controlled_dims(model))
        est = belief_mean(rollout["next", "particles"], rollout["next", "particle_log_weights"])  # [E, T, d]
        truth = rollout["next", "true_state"]
        e, t = truth.shape[:2]
        inside = torch.arange(t).expand(e, t) <= (m["length"] - 1).unsqueeze(1)
        near = inside & (model.distance_to_goal(truth) < self.near)
        w = torch.softmax(rollout["next", "particle_log_weights"], -1).unsqueeze(-1)
        spread = (w * (rollout["next", "particles"] - est.unsqueeze(-2)) ** 2).sum(-2).sqrt()  # [E, T, d]
        # the action at step t is taken on the belief after step t - 1; compare it with the row's own rule (its gain
        # and options) on the truth
        agree = (rollout["action"] == policy.controller(rollout["true_state"])).double()

        def per_episode(x: torch.Tensor, mask: torch.Tensor) -> list[float]:
            x = torch.where(mask, x.double(), torch.zeros((), dtype=torch.float64))
            count = mask.sum(1)
            return torch.where(count > 0, x.sum(1) / count.clamp_min(1), torch.nan).tolist()

        def over_time(x: torch.Tensor) -> tuple[list[float], list[float]]:
            x = torch.where(inside, x.double(), torch.nan)
            mean = torch.nanmean(x, 0)
            count = inside.sum(0)
            sd = torch.sqrt(torch.nanmean((x - mean) ** 2, 0) * count / (count - 1).clamp_min(1))
            return mean.tolist(), (sd / count.clamp_min(1).sqrt()).tolist()

        distance = model.distance_to_goal(truth)  # [E, T]
        came_near = inside & (distance < self.near)
        steps_to_near = torch.where(came_near.any(1), came_near.double().argmax(1) + 1, m["steps"].double())
        arrived = m["success"].bool()
        near_to_goal = torch.where(arrived, m["steps"].double() - steps_to_near, torch.nan)
        pos_err = torch.linalg.vector_norm(est[..., pos] - truth[..., pos], dim=-1)
        vel_err = torch.linalg.vector_norm(est[..., vel] - truth[..., vel], dim=-1)
        return {
            "label": self.label, "domain": self.domain, "overrides": list(self.overrides),
            "particles": int(cfg.num_particles), "filter": str(cfg.filter.name),
            "success": m["success"].double().tolist(),
            "final_distance": m["final_distance"].double().tolist(),
            "steps": m["steps"].double().tolist(),
            "steps_to_near": steps_to_near.tolist(),
            "steps_near_to_goal": near_to_goal.tolist(),
            "on_true_state": self.on_true_state,
            "position_error": per_episode(pos_err, inside),
            "velocity_error": per_episode(vel_err, inside),
            "position_error_near": per_episode(pos_err, near),
            "velocity_error_near": per_episode(vel_err, near),
            "position_spread": per_episode(spread[..., pos].mean(-1), inside),
            "velocity_spread": per_episode(spread[..., vel].mean(-1), inside),
            "agreement": per_episode(agree, inside),
            "agreement_near": per_episode(agree, near),
            "position_error_over_time": over_time(pos_err),
            "velocity_error_over_time": over_time(vel_err),
            "seconds_per_step": step_s, "seconds": seconds,
        }


COLUMNS = (("success", "success"), ("final_distance", "final distance"), ("steps", "steps"),
           ("steps_to_near", "steps to near"), ("steps_near_to_goal", "steps near → goal"),
           ("position_error", "pos. error"), ("velocity_error", "vel. error"),
           ("position_error_near", "pos. error near"), ("velocity_error_near", "vel. error near"),
           ("position_spread", "pos. spread"), ("velocity_spread", "vel. spread"),
           ("agreement", "action agreement"), ("agreement_near", "agreement near"))


def paired_difference(a: list[float], b: list[float]) -> tuple[float, float]:
    """Mean ± s.e. of ``a − b`` over the episodes (paired: the same start state)."""
    return mean_se([x - y for x, y in zip(a, b)])


def decisions_markdown(result: dict) -> str:
    rows = result["rows"]
    base = next(r for r in rows if r["label"] == result.get("baseline", rows[0]["label"]))
    head = ["row", "N", *(name for _, name in COLUMNS), f"success − {base['label']}", "ms/step"]
    lines = [
        f"# Scripted controller on beliefs: {result['domain']}",
        "",
        f"{result['episodes']} episodes, env seeds {result['seed']}..{result['seed'] + result['episodes'] - 1} "
        "(the same start states in every row); the domain's scripted PD controller acts on each row's belief "
        "mean. Mean ± s.e. over episodes. Errors: ‖x̂ − x‖₂ and ‖v̂ − v‖₂ of the belief mean in the controller's "
        f"position and velocity inputs, averaged over each episode's steps; *near*: over its steps with the true "
        f"state within {result['near']} of the goal. Spread: the belief's per-coordinate standard deviation, "
        "averaged over the inputs and steps. Action agreement: the fraction of steps at which the action "
        "taken on the belief equals the rule's action on the true state. *Steps to near*: the first step with the "
        f"true state within {result['near']} of the goal (the episode's length where it never comes); *steps near → "
        "goal*: from there to the goal, over the episodes that reach it. The success difference to the "
        f"{base['label']} row is paired by episode.",
        "",
        "| " + " | ".join(head) + " |",
        "| " + " | ".join("---" for _ in head) + " |",
    ]
    for r in rows:
        cells = [r["label"], str(r["particles"])]
        for key, _ in COLUMNS:
            digits = {"steps": 0, "steps_to_near": 1, "steps_near_to_goal": 1}.get(key, 3)
            cells.append(format_mean_se(mean_se(r[key]), digits))
        cells.append("—" if r is base else format_mean_se(paired_difference(r["success"], base["success"])))
        cells.append(f"{1e3 * r['seconds_per_step']:.1f}")
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Rows (config overrides on `env=" + result["domain"] + f" num_particles={result['particles']}`):", ""]
    lines += [f"- {r['label']}: `{' '.join(r['overrides'])}`"
              + (" (the rule on the true state; the belief beside it is not read)" if r.get("on_true_state") else "")
              for r in rows]
    return "\n".join(lines) + "\n"


def run_decisions(domain: str = "lightdark10d", rows=DEFAULT_ROWS, episodes: int = 100, particles: int = 100,
                  seed: int | None = None, steps: int | None = None, near: float = 1.0,
                  output="outputs/bench/decisions", backend=None, threads: int = 1,
                  baseline: str | None = None, true_state: bool = False) -> dict:
    """Run the rows (labels of :data:`ROWS` or ``(label, overrides)`` pairs) and write
    ``decisions.md``, ``decisions.json`` and the error-over-time plots into ``output``. ``true_state``: add
    :data:`TRUE_STATE_ROW`, the rule on the true state with the first row's overrides."""
    from escort_rl.bench.core.runner import make_backend
    from escort_rl.config import compose

    specs = [parse_row(r) if isinstance(r, str) else (r[0], tuple(r[1])) for r in rows]
    if true_state and specs:
        specs.append((TRUE_STATE_ROW, specs[0][1]))
    on_state = [true_state and i == len(specs) - 1 for i in range(len(specs))]
    labels = [label for label, _ in specs]
    if len(set(labels)) != len(labels):
        raise ValueError(f"--rows: labels must differ, got {labels}")
    if baseline is not None and baseline not in labels:
        raise ValueError(f"--baseline: '{baseline}' is not one of the rows ({', '.join(labels)})")
    for name, value in (("episodes", episodes), ("particles", particles), ("threads", threads)):
        if value < 1:
            raise ValueError(f"--{name}: must be >= 1, got {value}")
    if not near > 0:
        raise ValueError(f"--near: must be > 0, got {near}")
    if seed is None:
        seed = int(compose([f"env={domain}"]).evaluate.seed)
    out = Path(output)
    cells = [DecisionCell(label=label, domain=domain, overrides=o, particles=particles, episodes=episodes, seed=seed,
                          steps=steps, near=near, threads=threads, on_true_state=state)
             for (label, o), state in zip(specs, on_state)]
    for cell in cells:
        cell.config()  # a bad override fails here, with its one line, before anything runs
    t0 = time.perf_counter()
    results = run_cells(cells, backend or make_backend("inprocess"), CellStore(out / "cells"), desc="rows",
                        on_result=lambda c, r: print(f"{r['label']:>32}: success {mean_se(r['success'])[0]:.3f}, "
                                                     f"velocity error {mean_se(r['velocity_error'])[0]:.3f}",
                                                     flush=True))
    result = {"domain": domain, "episodes": episodes, "particles": particles, "seed": seed, "near": near,
              "steps": steps, "baseline": baseline or labels[0], "rows": results}
    write_results(out, "decisions", result, decisions_markdown(result), time.perf_counter() - t0)
    for key, what in (("position_error_over_time", "position"), ("velocity_error_over_time", "velocity")):
        curves = {r["label"]: tuple(r[key]) for r in results}
        plot_curves(curves, out / f"{key}.png", "step", f"‖E_b[{what}] − {what}‖₂ (episodes still running)",
                    title=f"{domain}: scripted controller, belief-mean {what} error")
    return result


def register(subparsers) -> None:
    """Add ``bench decisions`` to the ``bench`` subparsers."""
    p = subparsers.add_parser(
        "decisions", help="the scripted controller closed loop on several filters and settings, same seeds",
        description="The domain's scripted PD controller acts on each row's belief mean, closed loop, on the same "
        "seeded episodes: success, final distance, the belief mean's position and velocity error (overall and "
        "near the goal), the belief's spread, and how often the action on the belief equals the rule's action on "
        "the true state. Rows are named rows (--rows) or rows of your own (--add-row LABEL OVERRIDE ...).")
    options.add_overrides_argument(p, "Hydra overrides applied to every row before its own, e.g. filter.compile=true")
    p.add_argument("--domains", nargs="+", default=["lightdark10d"],
                   help="env configs with a scripted controller; with more than one, each domain's results go to "
                   "<output>/<domain>")
    p.add_argument("--rows", nargs="+", default=None, metavar="NAME",
                   help=f"named rows: {', '.join(ROWS)} (default: every named row, or none with --add-row)")
    options.add_labelled_option(p, "--add-row", "a row of your own", "mine filter=escort_train filter.jitter=0.05")
    p.add_argument("--episodes", type=int, default=None, help="episodes per row (default: 100)")
    p.add_argument("--particles", type=int, default=None, metavar="N",
                   help="N where a row does not set num_particles (default: 100)")
    p.add_argument("--seed", type=int, default=None, help="first env seed (default: the config's evaluate.seed)")
    p.add_argument("--steps", type=int, default=None, help="episode length (default: env.max_steps)")
    p.add_argument("--baseline", default=None, metavar="LABEL",
                   help="the row each row's success is compared with, paired by episode (default: the first row)")
    p.add_argument("--near", type=float, default=1.0, help="distance to goal that counts as near")
    p.add_argument("--true-state", action="store_true",
                   help="also run the rule on the true state (full information) with the first row's overrides: "
                   "the steps the dynamics alone ask, beside what each belief costs")
    options.add_quick_option(p, f"rows {' '.join(QUICK['rows'])}, {QUICK['episodes']} episodes of "
                     f"{QUICK['steps']} steps, N={QUICK['particles']}")
    options.add_runner_options(p, seeds_per_cell=False)
    options.add_output_option(p, "outputs/bench/decisions", "decisions.md, decisions.json, the plots and cells/")
    p.set_defaults(handler=main)


def decision_rows(args) -> list[tuple[str, tuple[str, ...]]]:
    """The rows of ``--rows`` and ``--add-row``, each with the positional overrides before its own."""
    own = options.labelled(args.add_row, "--add-row")
    names = args.rows if args.rows is not None else (QUICK["rows"] if args.quick else () if own else DEFAULT_ROWS)
    rows = [parse_row(name) for name in names] + own
    if not rows:
        raise ValueError("--rows: give at least one row (a named row, or --add-row LABEL OVERRIDE ...)")
    return [(label, (*args.overrides, *overrides)) for label, overrides in rows]


def main(args) -> None:
    full = dict(episodes=100, steps=None, particles=100)
    pick = QUICK if args.quick else full
    kw = {k: getattr(args, k) if getattr(args, k) is not None else pick[k] for k in full}
    rows = decision_rows(args)
    for domain in args.domains:
        output = args.output if len(args.domains) == 1 else str(Path(args.output) / domain)
        run_decisions(domain=domain, rows=rows, near=args.near, seed=args.seed, output=output,
                      baseline=args.baseline, backend=backend_from_args(args), threads=args.threads or 1,
                      true_state=args.true_state, **kw)


__all__ = ["DEFAULT_ROWS", "DecisionCell", "ROWS", "TRUE_STATE_ROW", "decisions_markdown", "paired_difference",
           "parse_row", "run_decisions"]
