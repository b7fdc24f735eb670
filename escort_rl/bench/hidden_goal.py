"""Which belief keeps the hidden goal's modes, and what that is worth to a controller
(``escort-rl bench hidden-goal``).

On the hidden-goal family (:class:`~escort_rl.models.HiddenGoal`, ``env=hidden_goal``) the goal is one of
``M`` candidates and only the beacon reveals which. Each row is a filter configuration (config overrides, as
in ``bench decisions``) and one of the two scripted controllers of
:class:`~escort_rl.planners.scripted.HeaviestModeController`:

- **commit**: toward the heaviest mode's goal at once (``confidence = 0``): right in about ``1/M`` of the
  episodes if the belief keeps the modes equally weighted;
- **look first**: toward the beacon while no mode weighs 0.9 (``confidence = 0.9``), then the goal: right
  every time if the belief still holds the true mode when the beacon speaks.

Every row runs the same seeded episodes (the same starts and goals). Beside success and steps it records
what the belief did with the modes, at a few steps of the episode (over the episodes still running):

- **true mode**: the weight the belief gives the true goal's mode;
- **modes held**: how many modes hold at least 5% of the weight (the prior holds all ``M``);
- **goal error**: ``‖ẑ − z‖`` of the heaviest mode's mean goal (what the controller steers to).

Mean ± s.e. over episodes; each row is a cell of :mod:`escort_rl.bench.core.runner` (saved as it finishes).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch

from escort_rl.bench.core import options
from escort_rl.bench.core.runner import CellStore, ConfigCell, backend_from_args, make_backend, run_cells
from escort_rl.reporting.paths import safe_name, write_results
from escort_rl.reporting.stats import format_mean_se, mean_se

FILTER_ROWS: dict[str, tuple[str, ...]] = {
    "sir": ("filter=sir",),
    "sir N=1000": ("filter=sir", "num_particles=1000"),
    "enkf": ("filter=enkf",),
    "svgd": ("filter=svgd", "filter.num_steps=15", "filter.step_size=0.15", "filter.prior=shrunk",
             "filter.compile=true"),
    "escort_train": ("filter=escort_train",),
}
"""The filters: label -> config overrides on ``env=hidden_goal``. SVGD runs at ``escort_train``'s budget and
prior, so that the two differ in the regularisers only."""
CONTROLLERS = {"commit": 0.0, "look first": 0.9}
"""The controllers: label -> ``HeaviestModeController.confidence``."""
PROBE_STEPS = (1, 5, 10, 20, 40)
"""The steps at which the belief's modes are read."""
QUICK = dict(episodes=4, steps=12, filters=("sir", "escort_train"), particles=30, dims=(3,))


@dataclass(frozen=True, kw_only=True)
class HiddenGoalCell(ConfigCell):
    """One row: a filter configuration and a controller, closed loop, on ``episodes`` seeded episodes."""

    label: str
    overrides: tuple[str, ...]
    confidence: float
    dim: int
    modes: int
    particles: int
    episodes: int
    seed: int
    steps: int | None = None

    def key(self) -> str:
        return f"dim{self.dim}-modes{self.modes}/{safe_name(self.label)}"

    def config(self):
        from escort_rl.config import compose

        extra = [] if self.steps is None else [f"env.max_steps={self.steps}"]
        has_n = any(o.startswith("num_particles=") for o in self.overrides)
        return compose(["env=hidden_goal", f"env.model.dim={self.dim}", f"env.model.modes={self.modes}",
                        *([] if has_n else [f"num_particles={self.particles}"]), *extra, *self.overrides])

    def run(self) -> dict:
        from escort_rl.planners.scripted import HeaviestModeController, ScriptedBeliefController
        from escort_rl.trainers.builders import belief_keys, build_model
        from escort_rl.trainers.evaluate import first_episode_metrics, run_episodes

        cfg = self.config()
        model = build_model(cfg.env, cfg.device)
        controller = HeaviestModeController(model, self.confidence)
        particles_key, log_weights_key = belief_keys(cfg)
        policy = ScriptedBeliefController(model, particles_key=particles_key, log_weights_key=log_weights_key,
                                          controller=controller)
        beliefs, means = {}, []

        def keep(td) -> None:  # a step's belief mean, and its particles at the probe steps
            x, lw = td["next", particles_key], td["next", log_weights_key]
            means.append((torch.softmax(lw, -1).unsqueeze(-1) * x).sum(-2))
            if len(means) in PROBE_STEPS:
                beliefs[len(means)] = (x.clone(), lw.clone())

        def keep_and_drop(t: int, td) -> None:  # not T × E × N particles held until the end
            keep(td)
            for key in (particles_key, log_weights_key):
                td.del_(key)
                td.del_(("next", key))

        t0 = time.perf_counter()
        rollout, step_s = run_episodes(cfg, policy, self.episodes, self.seed, on_step=keep_and_drop)
        seconds = time.perf_counter() - t0
        keep(rollout[:, -1])  # the last step, which the rollout shows no callback
        m = first_episode_metrics(rollout, model, belief_mean=torch.stack(means, 1))
        return {"label": self.label, "overrides": list(self.overrides), "confidence": self.confidence,
                "dim": self.dim, "modes": self.modes, "particles": int(cfg.num_particles),
                "filter": str(cfg.filter.name), "success": m["success"].double().tolist(),
                "steps": m["steps"].double().tolist(), "episode_return": m["episode_return"].double().tolist(),
                **mode_probes(model, controller, beliefs, rollout["next", "true_state"], m["length"]),
                "seconds_per_step": step_s, "seconds": seconds}


def mode_probes(model, controller, beliefs: dict, truth: torch.Tensor, length: torch.Tensor) -> dict:
    """At each step of :data:`PROBE_STEPS` inside the episode, per running episode: the true mode's weight,
    the modes holding at least 5% and the heaviest mode's goal error. Returns ``{"<metric>@<step>": [...]}``
    (``beliefs``: ``{step: (particles [E, N, 2d], log_weights [E, N])}`` after that step, for the steps of
    :data:`PROBE_STEPS` the episodes reached; ``truth`` ``[E, T, 2d]``, ``length`` ``[E]``)."""
    d = model.dim
    out = {}
    for step in PROBE_STEPS:
        t = step - 1
        if step not in beliefs or t >= truth.shape[1]:
            continue
        running = length > t
        particles, log_weights = beliefs[step]
        x, lw, s = particles[running], log_weights[running], truth[:, t][running]
        if x.shape[0] == 0:
            continue
        shares = controller.mode_weights(x, lw)[2]
        goal = controller.heaviest_goal(x, lw)[1]
        true_mode = model.mode_of(s[..., d:])
        out[f"true_mode@{step}"] = shares.gather(-1, true_mode.unsqueeze(-1)).squeeze(-1).double().tolist()
        out[f"modes_held@{step}"] = (shares >= 0.05).sum(-1).double().tolist()
        out[f"goal_error@{step}"] = torch.linalg.vector_norm(goal - s[..., d:], dim=-1).double().tolist()
    return out


def hidden_goal_markdown(result: dict) -> str:
    lines = ["# Beliefs on the hidden goal: which keep its modes, and what that is worth to a controller", "",
             f"`env=hidden_goal`, {result['episodes']} episodes per row (env seeds {result['seed']}.., the same "
             "starts and goals in every row), N = "
             f"{result['particles']} unless a row sets it. *commit*: toward the heaviest mode's goal at once; *look "
             "first*: toward the beacon while no mode weighs 0.9. *true mode*: the belief's weight on the true "
             "goal's mode; *modes held*: modes with at least 5% of the weight; *goal error*: ‖ẑ − z‖ of the heaviest "
             "mode's mean goal; each at step t over the episodes still running. Mean ± s.e. over episodes.", ""]
    for (dim, modes) in sorted({(r["dim"], r["modes"]) for r in result["rows"]}):
        rows = [r for r in result["rows"] if (r["dim"], r["modes"]) == (dim, modes)]
        probes = [k for k in rows[0] if "@" in k]
        head = ["row", "success", "steps", *probes, "ms/step"]
        lines += [f"## dim {dim} (a {2 * dim}-D belief), {modes} modes", "",
                  "| " + " | ".join(head) + " |", "| " + " | ".join("---" for _ in head) + " |"]
        for r in rows:
            cells = [r["label"], format_mean_se(mean_se(r["success"])), format_mean_se(mean_se(r["steps"]), 0)]
            cells += [format_mean_se(mean_se(r[k]), 2) if r.get(k) else "—" for k in probes]
            lines.append("| " + " | ".join([*cells, f"{1e3 * r['seconds_per_step']:.1f}"]) + " |")
        lines.append("")
    lines += ["Filters (config overrides on `env=hidden_goal`):", ""]
    lines += [f"- {label}: `{' '.join(o)}`" for label, o in result["filters"].items()]
    return "\n".join(lines) + "\n"


def run_hidden_goal(dims=(5, 10), modes: int = 4, filters=tuple(FILTER_ROWS), episodes: int = 100,
                    particles: int = 100, seed: int = 30000, steps: int | None = None, overrides=(),
                    output="outputs/bench/hidden_goal", backend=None, threads: int = 1, own_filters=()) -> dict:
    """Every filter of ``filters`` (names of :data:`FILTER_ROWS`) and of ``own_filters`` (``(label,
    overrides)`` pairs) with both :data:`CONTROLLERS` at each of ``dims``; writes ``hidden_goal.md`` and
    ``hidden_goal.json`` into ``output``."""
    unknown = [f for f in filters if f not in FILTER_ROWS]
    if unknown:
        raise ValueError(f"--filters: unknown {', '.join(unknown)}; choose among {', '.join(FILTER_ROWS)}")
    rows = {**{f: FILTER_ROWS[f] for f in filters}, **dict(own_filters)}
    for name, value in (("episodes", episodes), ("particles", particles), ("modes", modes)):
        if value < 1:
            raise ValueError(f"--{name}: must be >= 1, got {value}")
    cells = [HiddenGoalCell(label=f"{f}, {c}", overrides=(*overrides, *rows[f]), confidence=conf, dim=dim,
                            modes=modes, particles=particles, episodes=episodes, seed=seed, steps=steps,
                            threads=threads)
             for dim in dims for f in rows for c, conf in CONTROLLERS.items()]
    for cell in cells:
        cell.config()  # a bad override or size fails here, before anything runs
    t0 = time.perf_counter()
    results = run_cells(cells, backend or make_backend("inprocess"), CellStore(Path(output) / "cells"), desc="rows",
                        on_result=lambda c, r: print(f"dim {r['dim']:>3} {r['label']:>28}: success "
                                                     f"{mean_se(r['success'])[0]:.3f}", flush=True))
    result = {"episodes": episodes, "particles": particles, "seed": seed, "modes": modes, "dims": list(dims),
              "filters": {f: list(o) for f, o in rows.items()}, "rows": results}
    write_results(Path(output), "hidden_goal", result, hidden_goal_markdown(result), time.perf_counter() - t0)
    return result


def register(subparsers) -> None:
    """Add ``bench hidden-goal`` to the ``bench`` subparsers."""
    p = subparsers.add_parser(
        "hidden-goal", help="which filter keeps the hidden goal's modes, and what it is worth to a controller",
        description="On env=hidden_goal, each filter with the controller that commits to the heaviest mode and "
        "the one that looks at the beacon first, on the same seeded episodes: success, steps, and what the "
        "belief did with the modes (the true mode's weight, the modes held, the committed goal's error).")
    options.add_overrides_argument(p, "Hydra overrides under every row, e.g. env.model.beacon_distance=5")
    p.add_argument("--dims", type=int, nargs="+", default=None, help="env.model.dim values (default: 5 10)")
    p.add_argument("--modes", type=int, default=4, help="env.model.modes (default: 4)")
    p.add_argument("--filters", nargs="+", default=None, help=f"filters among {', '.join(FILTER_ROWS)} (default: all, "
                   "or none with --add-filter)")
    options.add_labelled_option(p, "--add-filter", "a filter configuration of your own",
                                "'escort smoothed' filter=escort_train filter.prior=smoothed")
    p.add_argument("--frontier-rows", nargs=2, default=None, metavar=("FRONTIER_JSON", "MS"),
                   help="add each filter's configuration that a frontier.json (bench frontier, at the one "
                   "--dims value) found closest to its reference within MS ms an update: equal filter time")
    p.add_argument("--episodes", type=int, default=None, help="episodes per row (default: 100)")
    p.add_argument("--particles", type=int, default=None, metavar="N", help="N where a row does not set it "
                   "(default: 100)")
    p.add_argument("--seed", type=int, default=30000, help="first env seed (default: 30000)")
    p.add_argument("--steps", type=int, default=None, help="episode length (default: env.max_steps)")
    options.add_quick_option(p, f"dim {QUICK['dims'][0]}, filters {' '.join(QUICK['filters'])}, "
                             f"{QUICK['episodes']} episodes of {QUICK['steps']} steps, N={QUICK['particles']}")
    options.add_runner_options(p, seeds_per_cell=False)
    options.add_output_option(p, "outputs/bench/hidden_goal", "hidden_goal.md, hidden_goal.json and cells/")
    p.set_defaults(handler=main)


def main(args) -> None:
    full = dict(episodes=100, steps=None, particles=100, dims=(5, 10), filters=tuple(FILTER_ROWS))
    pick = QUICK if args.quick else full
    kw = {k: getattr(args, k) if getattr(args, k) is not None else pick[k] for k in full}
    own = options.labelled(args.add_filter, "--add-filter")
    if getattr(args, "frontier_rows", None):
        from escort_rl.bench.frontier.run import budget_configurations

        if len(kw["dims"]) != 1:
            raise ValueError(f"--frontier-rows: a frontier is measured at one dimension; give the frontier's as the "
                             f"only --dims value, got {list(kw['dims'])}")
        path, budget = args.frontier_rows
        own = [*((f"{name} (closest within {float(budget):g} ms)", overrides)
                 for name, overrides in budget_configurations(path, float(budget), "--frontier-rows")), *own]
    if own and args.filters is None:
        kw["filters"] = ()
    run_hidden_goal(modes=args.modes, seed=args.seed, overrides=tuple(args.overrides), output=args.output,
                    backend=backend_from_args(args), threads=args.threads or 1, own_filters=own, **kw)


__all__ = ["CONTROLLERS", "FILTER_ROWS", "HiddenGoalCell", "hidden_goal_markdown", "mode_probes", "run_hidden_goal"]
