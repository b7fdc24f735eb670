"""How POMCPOW's return changes with its simulation budget (``escort-rl bench planner-budget``).

For one domain, POMCPOW plans every decision on an SIR belief (the paper's baseline) with ``n_sim``
simulations per decision, for each ``n_sim`` in a list, on the same seeded episodes: env seed
``seed`` for a batch of ``episodes`` envs (so every row starts from the same true states and the
same priors), planner seed ``seed``. A uniform-random policy on the same episodes is the reference
row. Reported, mean ± standard error over the episodes: the return of each env's first episode, the
final distance to goal (when the model has ``distance_to_goal``), the fraction of episodes that
ended in a terminal state, and the mean wall-clock of one POMCPOW decision (one belief).

Domains: ``lightdark1d`` (the 1-D Light-Dark test problem, :class:`escort_rl.models.LightDark1D`, with
:data:`escort_rl.planners.planner_config.LIGHTDARK1D_PLANNER`) and every domain with a planner config
(``configs/planner/<domain>.yaml``, e.g. ``lightdark10d``, with ``configs/env/<domain>.yaml``).
The episodes run through :func:`escort_rl.trainers.evaluate.run_episodes` and are scored by its
:func:`first_episode_metrics` and :func:`summarise_episodes`, as in ``escort-rl evaluate`` and the
closed-loop benchmark.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from escort_rl.bench.core import options
from escort_rl.bench.methods import RANDOM
from escort_rl.reporting.paths import write_results
from escort_rl.reporting.stats import format_mean_se

LIGHTDARK1D = "lightdark1d"
FILTER = "sir"  # the paper's POMCPOW baseline plans on an SIR belief

# Defaults per domain (other planner-config domains use the lightdark10d ones).
DEFAULT_BUDGETS = {LIGHTDARK1D: [10, 30, 100, 300], "lightdark10d": [10, 50, 200]}
DEFAULT_EPISODES = {LIGHTDARK1D: 30, "lightdark10d": 10}
DEFAULT_STEPS = {LIGHTDARK1D: 15, "lightdark10d": 100}
DEFAULT_PARTICLES = {LIGHTDARK1D: 200, "lightdark10d": 100}
QUICK = dict(budgets=[2, 5], episodes=2, steps=3, particles=20)


def budget_domains() -> list[str]:
    """The domains this benchmark runs on: ``lightdark1d`` and those with a planner config."""
    from escort_rl.planners import planner_domains

    return [LIGHTDARK1D, *planner_domains()]


def _defaults(domain: str, table: dict):
    return table.get(domain, table["lightdark10d"])


def _check_int(flag: str, value, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{flag}: must be an int >= {minimum}, got {value!r}")
    return value


def check_inputs(domain: str, budgets, episodes: int, steps: int, particles: int) -> list[int]:
    """Raise ``ValueError`` naming the flag for a bad input; return the budgets as a list."""
    if domain not in budget_domains():
        raise ValueError(f"--domains: unknown domain '{domain}'; choose from {', '.join(budget_domains())}")
    budgets = list(budgets)
    if not budgets:
        raise ValueError("--budgets: give at least one simulation budget (n_sim per decision)")
    for b in budgets:
        if isinstance(b, bool) or not isinstance(b, int) or b < 1:
            raise ValueError(f"--budgets: every budget must be an int >= 1 (simulations per decision), got {b!r}")
    if len(set(budgets)) != len(budgets):
        raise ValueError(f"--budgets: a budget is listed twice: {budgets}")
    _check_int("--episodes", episodes)
    _check_int("--steps", steps)
    _check_int("particles", particles)
    return budgets


def episode_config(domain: str, steps: int, particles: int):
    """The config the episodes run under: ``domain``'s env (``lightdark1d``: a stand-in env node,
    since it has no env config) with ``steps`` steps, the SIR filter config, ``particles`` particles."""
    from escort_rl.config import compose

    if domain == LIGHTDARK1D:
        cfg = compose([f"filter={FILTER}", f"num_particles={particles}"])
        return OmegaConf.create({"env": {"name": LIGHTDARK1D, "max_steps": steps, "model": {}},
                                 "filter": OmegaConf.to_container(cfg.filter, resolve=True),
                                 "num_particles": particles, "device": cfg.device})
    return compose([f"env={domain}", f"filter={FILTER}", f"num_particles={particles}", f"env.max_steps={steps}"])


def _model_and_maker(domain: str, cfg):
    """The domain's model and the env maker ``make(cfg, num_envs, seed)`` for ``run_episodes``."""
    from escort_rl.trainers.builders import build_model, make_env

    return build_model(cfg.env, cfg.device), make_env


def planner_settings(domain: str) -> dict:
    """POMCPOW's keyword arguments for ``domain`` (without ``n_sim``), as plain JSON: a callable
    ``leaf_value`` is given by its name."""
    if domain == LIGHTDARK1D:
        from escort_rl.planners.planner_config import LIGHTDARK1D_PLANNER as settings
    else:
        from escort_rl.planners import load_planner_config

        settings = load_planner_config(domain)
    return {k: (getattr(v, "__name__", repr(v)) if callable(v) else v) for k, v in settings.items() if k != "n_sim"}


def build_budget_planner(domain: str, n_sim: int):
    """POMCPOW for ``domain`` with ``n_sim`` simulations per decision and no time budget."""
    from escort_rl.planners import POMCPOW, build_planner

    if domain == LIGHTDARK1D:
        from escort_rl.planners.planner_config import LIGHTDARK1D_PLANNER

        return POMCPOW(n_sim=n_sim, **LIGHTDARK1D_PLANNER)
    return build_planner(domain, n_sim=n_sim, time_budget_s=None)


def _score(rollout, model) -> dict:
    from escort_rl.trainers.evaluate import first_episode_metrics, summarise_episodes

    metrics = first_episode_metrics(rollout, model)
    return {"summary": summarise_episodes(metrics),
            "per_episode": {"episode_return": metrics["episode_return"].tolist(),
                            "final_distance": metrics["final_distance"].tolist(),
                            "length": metrics["length"].tolist()}}


def run_planner_budget(domain: str = LIGHTDARK1D, budgets=None, episodes: int | None = None,
                       steps: int | None = None, seed: int = 0, particles: int | None = None,
                       progress=None) -> dict:
    """POMCPOW with each ``n_sim`` in ``budgets`` and a uniform-random policy, on the same seeded
    episodes of ``domain`` with an SIR belief of ``particles`` particles.

    ``None`` takes the domain's default (``DEFAULT_*``). ``steps``: the episode length (each env's
    first episode is scored; an env whose episode ends early is reset by the rollout and its later
    decisions are timed but not scored). ``progress(row)`` is called after each row. Raises
    ``ValueError`` naming the flag for a bad input. Returns the settings and one row per policy.
    """
    from escort_rl.planners import POMCPOWPolicy
    from escort_rl.trainers.evaluate import run_episodes

    budgets = list(budgets) if budgets is not None else list(_defaults(domain, DEFAULT_BUDGETS))
    episodes = episodes if episodes is not None else _defaults(domain, DEFAULT_EPISODES)
    steps = steps if steps is not None else _defaults(domain, DEFAULT_STEPS)
    particles = particles if particles is not None else _defaults(domain, DEFAULT_PARTICLES)
    _check_int("seed", seed, minimum=0)
    budgets = check_inputs(domain, budgets, episodes, steps, particles)
    cfg = episode_config(domain, steps, particles)
    model, make = _model_and_maker(domain, cfg)
    t_start = time.perf_counter()
    rows = []
    for n_sim in [*budgets, None]:
        policy = None if n_sim is None else POMCPOWPolicy(model, build_budget_planner(domain, n_sim), seed=seed)
        t0 = time.perf_counter()
        rollout, per_step = run_episodes(cfg, policy, episodes, seed, make=make)
        row = {"policy": RANDOM if n_sim is None else "pomcpow", "n_sim": n_sim, **_score(rollout, model),
               "seconds_per_step": per_step, "seconds": time.perf_counter() - t0,
               "decisions": policy.decisions if policy is not None else 0,
               "seconds_per_decision": (policy.planning_seconds / policy.decisions
                                        if policy is not None and policy.decisions else None)}
        rows.append(row)
        if progress is not None:
            progress(row)
    return {"benchmark": "planner budget", "domain": domain, "budgets": budgets, "episodes": episodes,
            "steps": steps, "particles": particles, "filter": FILTER, "seed": seed,
            "planner": planner_settings(domain), "has_distance": hasattr(model, "distance_to_goal"),
            "torch_threads": torch.get_num_threads(), "seconds": time.perf_counter() - t_start, "rows": rows}


# ---------------------------------------------------------------------------------------- reporting
def _pair(summary: dict, key: str) -> tuple:
    """``(mean, standard error)`` of ``key`` in a row's summary."""
    return summary[key], summary[f"{key}_se"]


def row_cells(row: dict, has_distance: bool) -> list[str]:
    s = row["summary"]
    label = "random policy" if row["policy"] == RANDOM else f"POMCPOW n_sim={row['n_sim']}"
    ms = "—" if row["seconds_per_decision"] is None else f"{1e3 * row['seconds_per_decision']:.1f}"
    return [label, format_mean_se(_pair(s, "episode_return"), 1),
            format_mean_se(_pair(s, "final_distance"), 3) if has_distance else "—",
            format_mean_se(_pair(s, "success_rate"), 2), f"{s['mean_length']:.1f}", ms, f"{row['seconds']:.1f}"]


HEADER = ["policy", "return", "final distance to goal", "ended (terminal)", "steps", "ms per decision",
          "row wall-clock (s)"]


def planner_budget_markdown(result: dict) -> str:
    planner = ", ".join(f"{k}={v}" for k, v in result["planner"].items())
    lines = [
        f"# POMCPOW return against the simulation budget: {result['domain']}",
        "",
        f"{result['episodes']} episodes of {result['steps']} steps (env seed {result['seed']} for the batch, the "
        f"same for every row; planner seed {result['seed']}), belief: {result['filter'].upper()} with "
        f"{result['particles']} particles. Mean ± standard error over the episodes of each env's first "
        "episode. POMCPOW settings other than n_sim: " + planner + ".",
        "",
        "| " + " | ".join(HEADER) + " |",
        "| " + " | ".join("---" for _ in HEADER) + " |",
        *("| " + " | ".join(row_cells(r, result["has_distance"])) + " |" for r in result["rows"]),
        "",
        "Return: undiscounted sum of the rewards of the first episode. Ended (terminal): the fraction of "
        "episodes that reached a terminal state within the steps (for lightdark1d: declared, rightly or "
        "wrongly). ms per decision: mean wall-clock of one POMCPOW plan (one belief), over every decision of the "
        f"rollout, torch threads: {result['torch_threads']}. Total wall-clock {result['seconds']:.0f} s.",
        "",
    ]
    return "\n".join(lines)


def cli(args) -> list[dict]:
    """``escort-rl bench planner-budget``: flags given explicitly win over ``--quick``; with more than
    one domain, each domain's results go to ``<output>/<domain>``."""
    quick = QUICK if args.quick else {}
    budgets = args.budgets if args.budgets is not None else quick.get("budgets")
    episodes = args.episodes if args.episodes is not None else quick.get("episodes")
    steps = args.steps if args.steps is not None else quick.get("steps")
    for domain in args.domains:  # every name is checked before any runs
        if domain not in budget_domains():
            raise ValueError(f"--domains: unknown domain '{domain}'; choose from {', '.join(budget_domains())}")
    options.set_threads(args)

    def show(row):
        print(" | ".join(row_cells(row, True)), flush=True)

    results = []
    for domain in args.domains:
        result = run_planner_budget(domain, budgets, episodes, steps, particles=quick.get("particles"),
                                    progress=show)
        out = Path(args.output) if len(args.domains) == 1 else Path(args.output) / domain
        write_results(out, "planner_budget", result, planner_budget_markdown(result), result["seconds"])
        results.append(result)
    return results


def register(subparsers) -> None:
    """Add ``bench planner-budget`` to the ``bench`` subparsers."""
    pb = subparsers.add_parser("planner-budget", help="POMCPOW return against simulations per decision",
                               description="POMCPOW on an SIR belief with each n_sim in --budgets, plus a "
                               "uniform-random policy, on the same seeded episodes: return, final distance to goal "
                               "and ms per decision (mean ± s.e.); writes planner_budget.json and planner_budget.md.")
    pb.add_argument("--domains", nargs="+", default=[LIGHTDARK1D],
                    help="lightdark1d or configs/planner domains; with more than one, each domain's results go to "
                    "<output>/<domain>")
    pb.add_argument("--budgets", type=int, nargs="+", default=None,
                    help="n_sim values (default: lightdark1d 10 30 100 300, others 10 50 200)")
    pb.add_argument("--episodes", type=int, default=None,
                    help="episodes, one seeded batch (default: 30 on lightdark1d, 10 on others)")
    pb.add_argument("--steps", type=int, default=None,
                    help="steps per episode (default: 15 on lightdark1d, 100 on others)")
    options.add_quick_option(pb, "budgets 2 5, 2 episodes, 3 steps, 20 particles")
    options.add_threads_option(pb)
    options.add_output_option(pb, "outputs/bench/planner_budget", "planner_budget.json and planner_budget.md")
    pb.set_defaults(handler=cli)
