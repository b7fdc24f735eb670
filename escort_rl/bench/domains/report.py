"""The reports of the domain benchmark: protocol (a)'s Markdown (:func:`domains_markdown`) and plots
(:func:`plot_domains`), protocol (b)'s (:func:`closed_loop_markdown`, :func:`plot_closed_loop`)."""

from __future__ import annotations

from pathlib import Path

from escort_rl.bench.domains.closed_loop_cells import REFERENCE_FILTER
from escort_rl.bench.methods import RANDOM, build_domain
from escort_rl.metrics.reference import METRIC_LABELS, METRICS, state_parts
from escort_rl.reporting.plots import plot_curve_panels, plot_curves
from escort_rl.reporting.stats import format_importance, format_mean_se
from escort_rl.reporting.tables import changed_settings, key_values, method_table, section


# ---------------------------------------------------------------------------------------- protocol (a) plots
def plot_error_over_time(result: dict, domain: str, path: Path) -> Path:
    """Mean position error against the step, one line per method, shaded ± s.e."""
    curves = {r["method"]: (r["error_over_time"]["mean"], r["error_over_time"]["se"])
              for r in result["rows"] if r["domain"] == domain and not r["failed"]}
    return plot_curves(curves, path, "step (0: prior)", "position error ‖E_b[pos] − pos_true‖₂",
                       f"{domain}: protocol (a), N = {result['particles']}, {result['seeds']} seeds (mean ± s.e.)")


def plot_accuracy_over_time(result: dict, domain: str, path: Path) -> Path:
    """The distances to the reference posterior against the step: one panel per (part, metric), one
    line per method, shaded ± s.e. over seeds (log scale)."""
    rows = [r for r in result["rows"] if r["domain"] == domain and not r["failed"] and r.get("accuracy")]
    keys = sorted(rows[0]["accuracy"]["over_time"], key=lambda k: (k.split("/")[0] != "position",
                                                                  METRICS.index(k.split("/")[1]))) if rows else []
    panels = {f"{k.split('/')[0]}: {METRIC_LABELS[k.split('/')[1]]}":
              {r["method"]: (r["accuracy"]["over_time"][k]["mean"], r["accuracy"]["over_time"][k]["se"]) for r in rows}
              for k in keys}
    n_ref = result["reference"][domain]["particles"][0]
    return plot_curve_panels(panels, path, "step (0: prior)", ncols=len(METRICS), log_y=True,
                             title=f"{domain}: distance to the reference posterior (SIR, N_ref = {n_ref}), "
                                   f"N = {result['particles']}, {result['seeds']} seeds (mean ± s.e.)")


def plot_domains(result: dict, folder: Path) -> None:
    """``error_over_time_<domain>.png`` (and, with a reference, ``accuracy_over_time_<domain>.png``)
    of every domain in ``folder``."""
    for d in result["domains"]:
        plot_error_over_time(result, d, Path(folder) / f"error_over_time_{d}.png")
        if result.get("reference"):
            plot_accuracy_over_time(result, d, Path(folder) / f"accuracy_over_time_{d}.png")


# ---------------------------------------------------------------------------------------- protocol (a) cells
def table(result: dict, rows: list[dict], cell) -> list[str]:
    """One row per method, one column per domain; a failed run's cell says at which step it failed."""
    learned = {key.split("/", 1)[1] for key in result.get("learned", {})}
    cells = {(r["domain"], r["method"]): f"failed at step {r['failed']['step']}" if r["failed"] else cell(r)
             for r in rows}
    return method_table(result["domains"], result["methods"], cells,
                        label=lambda m: f"{m.upper()} (learned belief, readout)" if m in learned else m)


def parts_cell(row: dict, metric: str, which: str = "mean") -> str:
    """``position / velocity`` of one metric's time-averaged (``mean``) or final distance, mean ± s.e."""
    acc = row.get("accuracy")
    if not acc:
        return "—"
    return " / ".join(format_mean_se(v[which]) for k, v in acc["summary"].items() if k.endswith(f"/{metric}"))


def _parts_label(domain: str) -> str:
    model, _ = build_domain(domain)
    return ", ".join(f"{k} = dims {list(v)}" for k, v in state_parts(model).items())


def _reference_change(row: dict) -> str:
    acc = row.get("accuracy")
    if not acc or not acc["checks"]:
        return "—"
    change = max(abs(acc["checks"][0][k]["mean"][0] - v["mean"][0]) / max(abs(v["mean"][0]), 1e-300)
                 for k, v in acc["summary"].items())
    return f"{100 * change:.1f}%"


# ---------------------------------------------------------------------------------------- protocol (a) sections
def _intro(result: dict) -> list[str]:
    info = result["domain_info"]
    horizon = ", ".join(f"{d} {info[d]['steps']}" for d in result["domains"])
    lines = [
        "# Domain benchmark, protocol (a): shared trajectories (paper Table 1 layout)",
        "",
        f"N = {result['particles']} particles for every method, {result['seeds']} seeds (mean ± standard error "
        f"over seeds), steps per trajectory: {horizon}. Behaviour policy: {result['behaviour_policy']}. Every "
        "method filters the same seeded action/observation sequence from the same seeded prior particles, so "
        "the tables measure belief accuracy alone. Position error: ‖E_b[pos] − pos_true‖₂ of the weighted "
        "belief mean, on " + "; ".join(f"{d}: {info[d]['position_error']}" for d in result["domains"]) + ".",
        "",
        *changed_settings(result.get("filter_set", {})),
    ]
    if result.get("learned"):
        lines += ["Learned-belief rows (DVRL) were trained closed-loop with protocol (b)'s budget (checkpoints: "
                  + ", ".join(f"{k}: `{v}`" for k, v in result["learned"].items()) + "); they read the same "
                  "action/observation sequences, and their position error is that of a readout head from the belief "
                  "summary to the state, fitted to the training trajectories' true states. They have no particle "
                  "count and are not in the equal-time table.", ""]
    return lines


def _accuracy_sections(result: dict) -> list[str]:
    """The distances to the reference posterior, the reference itself, and its convergence check."""
    ref = result.get("reference")
    if not ref:
        return []
    domains, rows = result["domains"], result["rows"]
    n_ref = ref[domains[0]]["particles"]
    lines = section(
        "## Distance to the reference posterior",
        f"The reference is a bootstrap particle filter with N_ref = {n_ref[0]} particles on the same trajectories, "
        "from its own draw of the same prior (resampling when ESS/N < 0.5); it converges to the exact posterior as "
        "N_ref grows. Each belief is compared with it at every step, on the position and the velocity separately "
        "(" + "; ".join(f"{d}: {_parts_label(d)}" for d in domains) + "): sliced W1 (50 fixed directions), MMD² "
        "(RBF kernel at the median-heuristic bandwidth of the reference), the distance between the means and the "
        "Frobenius distance between the covariances. The sample-based distances use "
        f"{ref[domains[0]]['sample']} particles drawn from the reference at each step. Cells: position / velocity, "
        "time-averaged over steps 1..T, mean ± s.e. over seeds; lower is closer. Learned beliefs have no particles "
        "and no figures here. `accuracy_over_time_<domain>.png` plots every step.")
    for metric in METRICS:
        lines += section(f"### {METRIC_LABELS[metric]}", table(result, rows, lambda r: parts_cell(r, metric)))
    floor_table = ["| domain | seconds (N_ref / 2 N_ref) | "
                   + " | ".join(f"floor: {METRIC_LABELS[m]}" for m in METRICS) + " |",
                   "| --- | --- | " + " | ".join("---" for _ in METRICS) + " |"]
    for d in domains:
        info = ref[d]
        secs = " / ".join(f"{info['seconds'][str(n)]:.0f}" for n in info["particles"])
        floors = [" / ".join(format_mean_se(v["mean"]) for k, v in info["floor"].items() if k.endswith(f"/{m}"))
                  for m in METRICS]
        floor_table.append(f"| {d} | {secs} | " + " | ".join(floors) + " |")
    return lines + section(
        "### The reference and its convergence",
        f"Each reference ran at N_ref and at 2 N_ref = {n_ref[1]}. *Floor*: the distance of the 2 N_ref reference "
        "to the N_ref one (position / velocity, time-averaged), the part of every figure above that is the "
        "reference's own error. *Change*: per method, the largest relative change of its time-averaged figures "
        "(all parts and metrics) when the 2 N_ref reference replaces the N_ref one.",
        floor_table,
        "Change of each method's figures when N_ref doubles (the largest over parts and metrics):",
        table(result, rows, _reference_change))


def _cost_sections(result: dict) -> list[str]:
    """The importance weights and the wall-clock per update."""
    rows = result["rows"]
    workers = f", {result['workers']} workers" if result["workers"] > 1 else ""
    return section(
        "## Importance weights",
        "The effective sample size of the importance weights each filter formed, over every update: SIR's weights "
        "before resampling; ESCORT's target samples of the correlation projections (the predicted particles "
        "weighted by the likelihood), tempered where ESS/N falls below `ess_floor`. ESS/N averaged over beliefs "
        "and steps, its minimum, the share of tempered updates and the mean tempering exponent β.",
        table(result, rows, lambda r: format_importance(r.get("importance")))) + section(
        "## Wall-clock per filter update",
        f"Milliseconds per step for the whole batch of {result['seeds']} beliefs / per belief (the sum over "
        f"the row's cells of {result['seeds_per_cell']} seeds, each with {result['cell_threads']} torch threads; "
        f"backend {result['backend']}{workers}), over steps 2..T; the first update is a warm-up (it compiles, "
        "for `compile=true`) and its seconds are in brackets.",
        table(result, rows, lambda r: f"{1e3 * r['seconds_per_step']:.1f} / {1e3 * r['seconds_per_step_per_env']:.2f} "
                                      f"({r.get('first_step_seconds', float('nan')):.1f} s)"))


def _equal_time_cell(row: dict) -> str:
    return (f"{format_mean_se(row['summary']['final_error'])} (N'={row['particles']}, "
            f"{1e3 * row['calibrated_seconds_per_step']:.1f} / {1e3 * row['seconds_per_step']:.1f} ms)")


def _equal_time_section(result: dict, eq: dict) -> list[str]:
    lines = section(
        "## Equal wall-clock per step",
        f"Each method gets the largest N' in {eq['grid']} whose measured time per batched update (one "
        f"warm-up, then the mean of {eq['calibration_steps']} updates on the same trajectories) is not "
        f"above {eq['reference']}'s at N = {eq['reference_particles']}; {eq['reference']} keeps N = "
        f"{eq['reference_particles']}. Cells: final error mean ± s.e. (N', ms per step in the timing "
        "measurement / in the run itself). A row at N' = N reuses the equal-N run. The runs' own times are sums "
        "over the row's cells, which may have run side by side; the choice of N' uses the timing "
        "measurement, one method at a time in one process.",
        table(result, eq["rows"], _equal_time_cell))
    if result.get("reference"):
        for metric in METRICS:
            lines += [f"Distance to the reference posterior at equal wall-clock: {METRIC_LABELS[metric]} of the "
                      "position / velocity, time-averaged over steps 1..T.", "",
                      *table(result, eq["rows"], lambda r, metric=metric: parts_cell(r, metric)), ""]
    lines.append("Budgets (ms per step of the reference): " + ", ".join(
        f"{d} {1e3 * v['budget_seconds_per_step']:.1f}" for d, v in eq["domains"].items()) + ".")
    capped = [f"{m} on {d}" for d, v in eq["domains"].items() for m in v["chosen"]
              if m != eq["reference"] and v["chosen"][m] == eq["grid"][-1]
              and v["calibration"][m][str(eq["grid"][-1])] <= v["budget_seconds_per_step"]]
    if capped:
        lines.append(f"The grid's largest N' ({eq['grid'][-1]}) is still within the budget for: "
                     + ", ".join(capped) + "; a larger --max-particles would give them more.")
    over = [f"{m} on {d}" for d, v in eq["domains"].items() for m in v["over_budget"]]
    if over:
        lines.append("Even the smallest N' is over the budget for: " + ", ".join(over) + ".")
    return lines + [""]


def _failures_section(rows: list[dict]) -> list[str]:
    failures, seen = [], set()
    for r in rows:
        if r["failed"] and (r["domain"], r["method"], r["particles"]) not in seen:
            seen.add((r["domain"], r["method"], r["particles"]))
            failures.append(f"- {r['method']} on {r['domain']} (N = {r['particles']}): step {r['failed']['step']}: "
                            f"{r['failed']['message']}")
    if not failures:
        return []
    return section("## Failed runs", "A failed run's belief diverged on at least one seed; the run stops there and "
                   "has no error figures.", failures)


def _outcome_section(result: dict) -> list[str]:
    info = result["domain_info"]
    lines = [
        "## Task outcome",
        "",
        "Under protocol (a) the actions come from the behaviour policy, not from the belief, so the true "
        "trajectory, and with it the final distance to goal, success and return, is the same for every "
        "method; only the error metrics above differ between methods. The closed-loop task outcome "
        "(each filter driving its own trained policy, or POMCPOW) is protocol (b), reported separately.",
    ]
    shared = [f"{d} {format_mean_se(info[d]['shared_final_distance_to_goal'])}" for d in result["domains"]
              if "shared_final_distance_to_goal" in info[d]]
    if shared:
        lines.append("Shared trajectories' final true distance to goal (the same for all methods): "
                     + ", ".join(shared) + ".")
    return lines


def domains_markdown(result: dict) -> str:
    """Protocol (a)'s report: the error tables, the distances to the reference posterior, the cost,
    the equal wall-clock table, the failed runs and the task outcome."""
    eq = result.get("equal_time")
    rows = result["rows"]
    lines = [
        *_intro(result),
        *section("## Final position error (after the last step)",
                 table(result, rows, lambda r: format_mean_se(r["summary"]["final_error"]))),
        *section("## Time-averaged position error (steps 1..T)",
                 table(result, rows, lambda r: format_mean_se(r["summary"]["mean_error"]))),
        *_accuracy_sections(result),
        *_cost_sections(result),
        *(_equal_time_section(result, eq) if eq else []),
        *_failures_section(rows + (eq["rows"] if eq else [])),
        *_outcome_section(result),
    ]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------- protocol (b)
def _failed_cell(row: dict) -> str:
    return "n/a" if row["failed"].get("not_applicable") else "failed"


def _summary_cell(row: dict, key: str, digits: int = 3) -> str:
    if row["failed"]:
        return _failed_cell(row)
    return format_mean_se((row["summary"][key], row["summary"][f"{key}_se"]), digits)


def _label(result: dict, m: str) -> str:
    """A protocol (b) row's name in the tables."""
    planner, scripted = result.get("planners", {}).get(m), result.get("scripted", {}).get(m)
    recurrent = result.get("recurrent", {}).get(m)
    if m == RANDOM:
        return f"random policy ({REFERENCE_FILTER} belief)"
    if planner:
        return f"POMCPOW ({planner['filter']} belief)"
    if scripted:
        return f"scripted PD ({scripted['filter']} belief mean)"
    if m in result.get("learned", {}):
        return f"{m.upper()} (learned belief, readout)"
    if recurrent:
        return f"{m} (GRU on observations, no belief)"
    return m


def _closed_loop_table(result: dict, cell) -> list[str]:
    return method_table(result["domains"], result["methods"],
                        {(r["domain"], r["method"]): cell(r) for r in result["rows"]},
                        label=lambda m: _label(result, m))


def _time_cell(row: dict) -> str:
    if row["failed"]:
        return _failed_cell(row)
    cell = f"{1e3 * row['seconds_per_step']:.1f} ({row['first_step_seconds']:.1f} s)"
    if "seconds_per_decision" in row:
        cell += f"; {1e3 * row['seconds_per_decision']:.1f} ms per decision"
    return cell


def train_cell(row: dict) -> str:
    """A protocol (b) row's training cost: frames, minutes and frames per second."""
    t = row.get("train")
    if not t:
        return "—"
    return f"{t['frames']} frames, {t['seconds'] / 60:.1f} min ({t['frames'] / max(t['seconds'], 1e-9):.0f} frames/s)"


def _closed_loop_intro(result: dict) -> list[str]:
    budgets = "; ".join(f"{d}: {key_values(b)}" for d, b in result["train_budget"].items())
    trainer = result.get("trainer") or "reinforce"
    trainer = {"ppo": "PPO", "reinforce": "REINFORCE"}.get(trainer, trainer)
    others = [f"- {text}" for key, text in (
        ("planners", "POMCPOW rows train nothing: the planner decides on its filter's belief."),
        ("scripted", "Scripted rows train nothing: the domain's PD controller drives its filter's belief mean "
                     "toward the goal (n/a where the domain has no controller: no goal)."),
        ("learned", "The DVRL row trains DVRL, a learned belief, by A2C plus its ELBO at the same frames; its "
                    "position error is that of a readout head fitted to the training trajectories' true states."),
        ("recurrent", "Recurrent rows train a GRU policy on the raw observations (recurrent PPO) at the same "
                      "frames: no belief, so no position error (—).")) if result.get(key)]
    return [
        "# Domain benchmark, protocol (b): closed loop",
        "",
        f"Each filter method trains its own DeepSets policy ({trainer}) on its own beliefs, N = "
        f"{result['particles']} particles, then drives it on {result['episodes']} evaluation episodes (env seeds "
        f"{result['eval_seed']} + 0..{result['episodes'] - 1}, the same for every method; policy "
        f"{'greedy' if result['greedy'] else 'sampled'}). Mean ± standard error over the episodes. Training budget "
        f"per domain (trainer keys, equal for every method): {budgets}.",
        "",
        *others, *([""] if others else []),
        *changed_settings(result["filter_set"]),
    ]


def closed_loop_markdown(result: dict) -> str:
    """Protocol (b)'s report: error, return, distance and success tables, the wall-clock and training
    cost, the failed and the not applicable rows."""
    lines = _closed_loop_intro(result)
    for heading, key, digits in (("## Final position error", "final_position_error", 3),
                                 ("## Time-averaged position error", "mean_position_error", 3),
                                 ("## Return", "episode_return", 1),
                                 ("## Final distance to goal (domains with a goal)", "final_distance", 3),
                                 ("## Success rate", "success_rate", 3)):
        lines += section(heading, _closed_loop_table(result, lambda r, k=key, g=digits: _summary_cell(r, k, g)))
    lines += section(
        "## Wall-clock",
        "Milliseconds per evaluation step for the whole batch of episodes (policy + env + belief update, steps "
        "2..T; the first step's seconds, which include compiling for `compile=true`, in brackets), torch threads: "
        f"{result['torch_threads']}. Planner rows also give the mean wall-clock of one POMCPOW decision (one "
        "belief; the batch's decisions run one after another).",
        _closed_loop_table(result, _time_cell),
        "Training cost (frames, minutes over all sessions of the run, frames per second):",
        _closed_loop_table(result, train_cell))
    failed = [r for r in result["rows"] if r["failed"] and not r["failed"].get("not_applicable")]
    if failed:
        lines += section("## Failed runs", [f"- {r['method']} on {r['domain']}: {r['failed']['message']}"
                                            for r in failed])
    skipped = [r for r in result["rows"] if r["failed"] and r["failed"].get("not_applicable")]
    if skipped:
        lines += section("## Not applicable (n/a)", [
            f"- {r['method']} on {r['domain']}: {r['failed']['message'].removeprefix('not applicable: ')}"
            for r in skipped])
    return "\n".join(lines)


def plot_closed_loop_error(result: dict, domain: str, path: Path) -> Path:
    """Mean position error over the evaluation episodes against the step, one line per method (a
    row without a belief, the recurrent policy, has no curve)."""
    curves = {r["method"]: (r["error_over_time"], None)
              for r in result["rows"] if r["domain"] == domain and not r["failed"]}
    return plot_curves(curves, path, "step", "position error ‖E_b[pos] − pos_true‖₂",
                       f"{domain}: protocol (b), N = {result['particles']}, {result['episodes']} episodes (mean)",
                       start=1)


def plot_closed_loop(result: dict, folder: Path) -> None:
    """``closed_loop_error_<domain>.png`` of every domain in ``folder``."""
    for d in result["domains"]:
        plot_closed_loop_error(result, d, Path(folder) / f"closed_loop_error_{d}.png")
