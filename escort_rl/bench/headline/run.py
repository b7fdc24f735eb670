"""The headline table (:func:`run_headline`): every trained row over its seeds, the scripted
controller's gain chosen on held-out episodes and then evaluated, and a random policy."""

from __future__ import annotations

import math

from escort_rl.bench.core.runner import CellStore, run_cells
from escort_rl.bench.headline.cells import (
    BELIEF_KEYS,
    FixedPolicyCell,
    TrainedCell,
    belief_identity,
    dropped_overrides,
    row_overrides,
    safe_name,
)
from escort_rl.bench.headline.spec import HeadlineSpec
from escort_rl.config import compose
from escort_rl.reporting.stats import mean_se


def trained_cells(spec: HeadlineSpec) -> list[TrainedCell]:
    return [TrainedCell(label=label, overrides=tuple(row_overrides(spec.overrides, overrides)), seed=seed,
                        run_dir=str(spec.output / "runs" / f"{safe_name(label)}-seed{seed}"),
                        episodes=spec.episodes, eval_seed=spec.eval_seed, threads=spec.threads,
                        curve_every=spec.curve_every)
            for label, overrides in spec.rows for seed in range(spec.seeds)]


def fixed_cell(spec: HeadlineSpec, filter_name: str, gain: float | None, eval_seed: int,
               episodes: int | None = None) -> FixedPolicyCell:
    """The scripted (``gain``) or random (``None``) policy on ``episodes`` episodes (default: the table's) from
    env seed ``eval_seed``."""
    return FixedPolicyCell(filter=filter_name, gain=gain, overrides=spec.overrides,
                           episodes=spec.episodes if episodes is None else episodes, eval_seed=eval_seed,
                           threads=spec.threads)


PAIRED = ("success", "steps", "episode_return")
"""The metrics a trained row is compared on with the scripted controller, episode by episode."""


def gainless_rule(cfg) -> str | None:
    """What the scripted controller of ``cfg``'s env does, in words, where it has no gain to choose (the hidden
    goal's :class:`~escort_rl.planners.scripted.HeaviestModeController`), else ``None``: a PD rule, whose
    velocity gain the headline searches."""
    from escort_rl.planners.scripted import scripted_controller_for
    from escort_rl.trainers.builders import build_model, scripted_policy

    model = build_model(cfg.env, "cpu")
    policy = scripted_policy(cfg, model)  # with the env's scripted_options
    controller = policy.controller if policy is not None else scripted_controller_for(model)  # raises the reason
    return None if hasattr(controller, "gain_v") else controller.rule


def trained_row(label: str, results: list[dict]) -> dict:
    """A trained row: each metric's mean ± s.e. across the training seeds of the per-seed means, and
    ``per_episode`` (the :data:`PAIRED` metrics, ``[seed][episode]``), from which a paired difference can be
    recomputed."""
    row = {"policy": label, "kind": "trained", "filter": results[0]["filter"], "seeds": len(results),
           "per_seed": {}}
    for key in ("success", "final_distance", "episode_return", "steps"):
        per_seed = [mean_se(r[key])[0] for r in results]
        row["per_seed"][key] = per_seed
        row[key], row[f"{key}_se"] = mean_se(per_seed)
    row["per_episode"] = {key: [list(r[key]) for r in results] for key in PAIRED}
    row["frames"] = results[0]["frames"]
    row["curve"] = mean_curve([r.get("curve", []) for r in results])
    row["train_minutes"], row["train_minutes_se"] = mean_se([r["train_seconds"] / 60 for r in results])
    return row


def mean_curve(curves: list[list[dict]]) -> list[dict]:
    """The seeds' curves (each a list of ``{"frames", "success", "steps", "episode_return", ...}``) as
    one: at every frame count that all the seeds reached, each metric's mean ± s.e. across the seeds.

    Examples:
        >>> a = [{"frames": 10, "success": 0.5}, {"frames": 20, "success": 1.0}]
        >>> b = [{"frames": 10, "success": 0.7}]
        >>> mean_curve([a, b])
        [{'frames': 10, 'seeds': 2, 'success': 0.6, 'success_se': 0.09999999999999998}]
    """
    if not curves or not all(curves):
        return []
    common = sorted(set.intersection(*({p["frames"] for p in c} for c in curves)))
    out = []
    for frames in common:
        points = [next(p for p in c if p["frames"] == frames) for c in curves]
        point = {"frames": frames, "seeds": len(points)}
        for key in (k for k in points[0] if k != "frames"):
            point[key], point[f"{key}_se"] = mean_se([p[key] for p in points])
        out.append(point)
    return out


def paired_difference(results: list[dict], scripted: dict) -> dict:
    """A trained row against the scripted controller on the same episodes and belief: the mean of
    ``d_si = trained_si − scripted_i`` over training seeds ``s`` and episodes ``i`` (success, steps, return),
    with the standard error of both samples, ``{"success": (mean, se, se_seeds, se_episodes), ...}``:

        se = √(se_seeds² + se_episodes²),

    ``se_seeds`` the s.e. across seeds of the per-seed means ``d̄_s·`` (the training's spread), and
    ``se_episodes`` the s.e. across episodes of the per-episode means ``d̄_·i`` (the episodes' spread, the
    controller's one run on them included: every seed is compared with the same run, so the spread across
    seeds cannot see it). Both carry the seed × episode residual, so the sum is conservative. Pairing by
    episode removes what the two policies share (a far start takes longer for both)."""
    out = {}
    for key in PAIRED:
        out[key] = two_part_mean_se([dict(enumerate(t - c for t, c in zip(r[key], scripted[key]))) for r in results])
    out["steps_both_succeed"] = steps_where_both_succeed(results, scripted)
    return out


def two_part_mean_se(pairs: list[dict[int, float]]) -> tuple[float, float, float, float]:
    """``(mean, se, se_seeds, se_episodes)`` of paired differences ``pairs[s][i] = d_si`` (seed ``s``, episode ``i``;
    a seed may hold a subset of the episodes): the mean and s.e. across seeds of the per-seed means, the s.e.
    across episodes of the per-episode means (over the seeds that hold the episode), and
    ``se = √(se_seeds² + se_episodes²)`` (:func:`paired_difference`)."""
    mean, se_seeds = mean_se([mean_se(list(p.values()))[0] for p in pairs if p])
    episodes = sorted(set().union(*pairs))
    se_episodes = mean_se([mean_se([p[i] for p in pairs if i in p])[0] for i in episodes])[1]
    return (mean, math.hypot(se_seeds, se_episodes), se_seeds, se_episodes)


def steps_where_both_succeed(results: list[dict], scripted: dict) -> tuple[float, float, float, float] | None:
    """:func:`paired_difference`'s steps on the episodes that the seed's policy and the controller both finish:
    ``d_si = steps_si − steps_i`` over the pairs ``(s, i)`` where both succeed, as ``(mean, se, se_seeds,
    se_episodes)`` with the same two s.e. (:func:`two_part_mean_se`). An episode that one policy misses costs it the
    time-out's ``max_steps`` in the mean steps, and which episodes each misses is largely chance (a belief gone wrong
    near the goal); this difference is the speed of the two where both arrive, with that chance out. ``None`` where
    fewer than two seeds or two episodes hold a pair."""
    pairs = [{i: t - c for i, (t, c, ok, ok_c) in enumerate(zip(r["steps"], scripted["steps"], r["success"],
                                                                 scripted["success"])) if ok and ok_c}
             for r in results]
    if sum(1 for p in pairs if p) < 2 or len(set().union(*pairs)) < 2:
        return None
    return two_part_mean_se(pairs)


def fixed_row(label: str, result: dict, kind: str) -> dict:
    """A scripted or random row: each metric's mean ± s.e. over the episodes, and ``per_episode`` (the
    :data:`PAIRED` metrics)."""
    row = {"policy": label, "kind": kind, "filter": result["filter"], "gain": result["gain"]}
    for key in ("success", "final_distance", "episode_return", "steps"):
        row[key], row[f"{key}_se"] = mean_se(result[key])
    row["per_episode"] = {key: list(result[key]) for key in PAIRED}
    return row


def best_gain(results: list[dict]) -> float:
    """The gain of the highest mean success; ties (every gain reaching the goal, say) go to the higher
    mean return, which rewards reaching it sooner, then to the lower mean final distance, then to the
    lower gain."""
    def score(r):
        distance = mean_se(r["final_distance"])[0]
        ret = mean_se(r["episode_return"])[0]
        return (-mean_se(r["success"])[0], -ret if not math.isnan(ret) else 0.0,
                distance if not math.isnan(distance) else 0.0, r["gain"])

    return min(results, key=score)["gain"]


def _plain(cfg) -> dict:
    from omegaconf import OmegaConf

    return OmegaConf.to_container(cfg, resolve=True)


def policy_reads(config: dict) -> str | None:
    """What a trained row's policy acts on when it is not a filter's belief (its trainer's
    ``belief_label``, e.g. the GRU's raw observations), or ``None``: the belief of its config."""
    from escort_rl.config import registry

    return registry.resolve("trainer", config["trainer"].get("algorithm", "reinforce")).belief_label


def row_beliefs(spec: HeadlineSpec) -> tuple[str, ...]:
    """The beliefs the trained rows act on, each once, in the rows' order: a row's own overrides that pick
    its belief (``filter=``, ``filter.KEY=``, ``num_particles=``), space-separated, or its filter's config
    name where it sets none. A row whose policy reads no belief (the GRU) has none."""
    beliefs, seen = [], set()
    for _, overrides in spec.rows:
        cfg = _plain(compose(row_overrides(spec.overrides, overrides)))
        if policy_reads(cfg) is not None:
            continue
        own = [o for o in overrides if o.split("=", 1)[0].split(".", 1)[0] in BELIEF_KEYS]
        identity = belief_identity(cfg)
        if identity not in seen:
            seen.add(identity)
            beliefs.append(" ".join(own) if own else str(cfg["filter"]["name"]))
    return tuple(beliefs)


def run_headline(spec: HeadlineSpec, backend) -> dict:
    """Run every cell (finished ones are loaded from ``spec.output / "cells"``) and return
    ``{"rows", "selection", "spec"}``: the table's rows in order (trained rows, the scripted
    controller on each filter at its selected gain, random) and the gain search's success rates."""
    store = CellStore(spec.output / "cells")
    beliefs = spec.scripted_filters if spec.scripted_filters is not None else row_beliefs(spec)
    if not beliefs:
        raise ValueError("--scripted-on: no trained row acts on a filter's belief; name the beliefs the scripted "
                         "controller runs on (a filter config name, or its overrides in one quoted word)")
    dropped = {label: dropped_overrides(spec.overrides, overrides) for label, overrides in spec.rows}
    for label, lost in dropped.items():
        if lost:
            print(f"headline: row '{label}' picks the group of the run's {' '.join(lost)}, which it drops; give them "
                  "again in the row to keep them")
    rule = gainless_rule(compose(row_overrides(spec.overrides, ())))
    gains = () if rule else spec.gains  # nothing to search for a controller without a gain
    selection = [fixed_cell(spec, f, g, spec.selection_seed, spec.selection_size) for f in beliefs for g in gains]
    trained = trained_cells(spec)
    results = run_cells([*selection, *trained], backend, store, desc="headline")
    chosen = {f: spec.gains[0] if rule else best_gain([r for c, r in zip(selection, results) if c.filter == f])
              for f in beliefs}
    final = [fixed_cell(spec, f, chosen[f], spec.eval_seed) for f in beliefs]
    final.append(fixed_cell(spec, beliefs[-1], None, spec.eval_seed))
    fixed = run_cells(final, backend, store, desc="headline evaluation")
    by_row: dict[str, list[dict]] = {}
    for cell, result in zip(trained, results[len(selection):]):
        by_row.setdefault(cell.label, []).append(result)
    rows = [trained_row(label, by_row[label]) for label, _ in spec.rows]
    scripted_on: dict[str, tuple[str, dict]] = {}
    for cell, result in zip(final[:-1], fixed[:-1]):  # the last cell is random's
        # several controllers on one belief (e.g. env.scripted_options in --scripted-on): the first is the pair
        scripted_on.setdefault(belief_identity(_plain(cell.config())), (cell.filter, result))
    for row in rows:
        config = by_row[row["policy"]][0]["config"]
        reads = policy_reads(config)
        match = scripted_on.get(belief_identity(config)) if reads is None else None
        row["filter"] = reads or (match[0] if match else row["filter"])
        if dropped[row["policy"]]:
            row["dropped_overrides"] = dropped[row["policy"]]
        if match:
            row["vs_scripted"] = paired_difference(by_row[row["policy"]], match[1])
    rules = {f: gainless_rule(cell.config()) for f, cell in zip(beliefs, final)} if rule else {}
    rows += [fixed_row(f"scripted controller ({rules.get(f) or f'gain {chosen[f]:g}'})", {**r, "filter": f}, "scripted")
             for f, r in zip(beliefs, fixed)]
    rows.append(fixed_row("random", fixed[-1], "random"))
    env = str(compose(row_overrides(spec.overrides, ())).env.name)
    return {"rows": rows, "spec": {"env": env, "seeds": spec.seeds, "episodes": spec.episodes,
                                   "eval_seed": spec.eval_seed, "selection_seed": spec.selection_seed,
                                   "selection_episodes": spec.selection_size,
                                   "gains": list(gains), "scripted_rule": rule,
                                   "overrides": list(spec.overrides), "threads": spec.threads,
                                   "curve_every": spec.curve_every},
            "selection": [{"filter": c.filter, "gain": c.gain, "success": mean_se(r["success"])[0],
                           "episode_return": mean_se(r["episode_return"])[0], "steps": mean_se(r["steps"])[0]}
                          for c, r in zip(selection, results)],
            "runs": [{"label": c.label, "seed": c.seed, "run_dir": c.run_dir} for c in trained]}
