"""Markdown of the frontier: every row, the Pareto front, the closest filter at each time budget, and
one line of advice."""

from __future__ import annotations

from escort_rl.bench.frontier.cells import ITERATIVE
from escort_rl.bench.frontier.run import label
from escort_rl.reporting.stats import format_importance, format_mean_se, mean_se

METRIC_NAMES = {"w1": "sliced W1", "mean": "‖mean − mean_ref‖₂", "cov": "‖cov − cov_ref‖_F", "mmd2": "MMD²"}


def train_command(result: dict, row: dict) -> str:
    """The ``escort-rl train`` command that trains on ``row``'s filter and settings on the frontier's
    model: ``env=NAME`` with its overrides for a package env, ``env=custom`` with the class and its
    keyword arguments for one's own.

    Example:
        >>> train_command({"model": "class:my_pkg.models:Ring", "model_args": ["n=4"], "compile": False},
        ...               {"base": "escort", "settings": ["lambda_corr=0.3"], "particles": 100, "num_steps": 15})
        ... # doctest: +NORMALIZE_WHITESPACE
        'escort-rl train env=custom env.model._target_=my_pkg.models.Ring +env.model.n=4
         filter=escort num_particles=100 filter.num_steps=15 filter.lambda_corr=0.3'
    """
    kind, _, name = result["model"].partition(":")
    if kind == "env":
        model = [f"env={name}", *(f"env.{arg}" for arg in result["model_args"])]  # stored relative to env
    else:
        model = ["env=custom", f"env.model._target_={name.replace(':', '.')}",
                 *(f"+env.model.{arg}" for arg in result["model_args"])]
    base = row["base"] if "base" in row else row["method"]
    filt = [f"filter={base}", f"num_particles={row['particles']}"]
    if base in ITERATIVE:
        filt.append(f"filter.num_steps={row['num_steps']}")
        if result.get("compile"):
            filt.append("filter.compile=true")
    filt += [f"filter.{setting}" for setting in row.get("settings", [])]
    return " ".join(["escort-rl train", *model, *filt])


def reference_ess_line(result: dict) -> str:
    """The report's line on the reference's ESS (:func:`~escort_rl.bench.frontier.run.reference_ess_summary`),
    with a warning in bold where it is below 1% of its particles."""
    ess = result["reference_ess"]
    which = ("the smallest of its tempering stages'" if ess.get("stages") else "before resampling")
    line = (f"The reference's ESS per update ({which}): median {ess['median']:.0f}, min {ess['min']:.0f} of "
            f"{ess.get('particles', 'its')} particles.")
    if ess.get("stages"):
        line += (f" Untempered, as SIR's would be: median {ess['untempered_median']:.0f} (how sharp the likelihood "
                 "is; the stages keep the weights from collapsing).")
    if ess["fraction"] < 0.01:
        line += (" **Below 1% of its particles: the reference is a few points, and distances to it are not a "
                 "posterior's.**")
    return line


def advice(result: dict, budget_ms: float = 10.0) -> str:
    """"At 10 ms per update, use …; train on it with `escort-rl train ...`": the closest filter within
    the budget, or the cheapest row. A reference whose ESS is below 1% of its particles cannot rank
    filters: then the advice says so and how to get one that can."""
    ess = result.get("reference_ess")
    if ess and ess["fraction"] < 0.01:
        fix = ("" if ess.get("stages") else ", or --reference-filter resample_move, whose tempering does not collapse")
        return (f"No advice: the reference kept a median ESS of {ess['median']:.0f} particles, too few to rank the "
                f"filters; rerun with more --reference-particles{fix}, or on a model with fewer steps.")
    fits = [b for b in result["budgets"] if b["ms"] <= budget_ms and b["best"] is not None]
    rows = [r for r in result["rows"] if r["error"] == r["error"]]
    if fits:
        best = fits[-1]
        row = next((r for r in rows if label(r) == best["best"]), None)
        command = "" if row is None else f" Train on it: `{train_command(result, row)}`"
        tied = best.get("not_separated") or []
        caveat = (f" The reference cannot rank it above {', '.join(tied)} (within its own error of it)."
                  if tied else "")
        return (f"At {budget_ms:g} ms per update, use {best['best']} ({METRIC_NAMES[result['metric']]} "
                f"{best['error']:.3g} to the reference).{caveat}{command}")
    if not rows:
        return "No filter kept a finite belief."
    cheapest = min(rows, key=lambda r: r["ms_per_update"])
    return (f"No filter fits {budget_ms:g} ms per update here; the cheapest is {label(cheapest)} at "
            f"{cheapest['ms_per_update']:.3g} ms: `{train_command(result, cheapest)}`.")


def reference_error_lines(result: dict) -> list[str]:
    """The reference's own error (the distance between two independent SIR references of the same
    posterior), per metric, and what it means for the ranking; empty for an exact reference."""
    error = result.get("reference_error")
    if not error:
        return []
    cells = ", ".join(f"{METRIC_NAMES[m]} {format_mean_se(v, 4)}" for m, v in error.items())
    return [f"The reference's own error, measured: two independent runs of it sit at {cells} from each other "
            "(averaged over steps 1..T, mean ± s.e. over seeds). Two rows whose distances to it differ by less "
            "than that, plus twice the s.e. of the difference, are not ranked: the table lists them as not "
            "separated.", ""]


def paired_lines(result: dict, a: str = "escort", b: str = "svgd") -> list[str]:
    """``a`` against ``b`` at the same N and K, paired by seed (the same trajectories and prior draws):
    the mean ± s.e. of the per-seed difference of each distance; the lines of a Markdown table (empty
    when the two share no (N, K))."""
    part = result["part"]
    rows = {(r["method"], r["particles"], r["num_steps"]): r for r in result["rows"] if r.get("failed") is None}
    shared = sorted(k[1:] for k in rows if k[0] == a and (b, *k[1:]) in rows)
    if not shared:
        return []
    lines = ["", f"## {a} − {b} at the same N and K, paired by seed (negative: {a} closer)", "",
             "| N | K | " + " | ".join(METRIC_NAMES[m] for m in ("w1", "mmd2", "mean", "cov")) + " |",
             "| --- | --- | --- | --- | --- | --- |"]
    for n, k in shared:
        cells = []
        for m in ("w1", "mmd2", "mean", "cov"):
            x, y = rows[(a, n, k)]["per_seed"][f"{part}/{m}"], rows[(b, n, k)]["per_seed"][f"{part}/{m}"]
            cells.append(format_mean_se(mean_se([p - q for p, q in zip(x, y)]), 4))
        lines.append(f"| {n} | {k} | " + " | ".join(cells) + " |")
    return lines


def frontier_markdown(result: dict) -> str:
    part, metric = result["part"], result["metric"]
    lines = [
        f"# Accuracy against time per update: {result['model_name']} ({result['model']}"
        + (" " + " ".join(result["model_args"]) if result["model_args"] else "") + ")", "",
        f"d = {result['state_dim']}, obs_dim = {result['obs_dim']}; {result['seeds']} seeds × {result['steps']} steps "
        f"of shared trajectories ({result.get('behaviour_policy', 'uniform random actions')}); reference: "
        f"{result['reference']}. Distances to the "
        f"reference on the state part `{part}`, averaged over steps 1..T, mean ± s.e. over seeds. Time: ms per "
        f"update of one belief (the {result['seeds']} seeds' beliefs updated as one batch, the first update "
        f"excluded), {result['threads']} torch thread(s)"
        + (", SVGD/ESCORT compiled" if result["compile"] else ", eager") + ".", "",
        *([reference_ess_line(result), ""] if result.get("reference_ess") else []),
        *reference_error_lines(result),
        "**" + advice(result) + "**", "",
        "## Closest filter at each time budget", "",
        f"| budget (ms per update) | filter | {METRIC_NAMES[metric]} | not separated from it by the reference |",
        "| --- | --- | --- | --- |",
    ]
    for b in result["budgets"]:
        lines.append(f"| {b['ms']:g} | {b['best'] or '— (none fits)'} | "
                     f"{'—' if b['error'] is None else format(b['error'], '.4g')} | "
                     f"{', '.join(b.get('not_separated') or []) or '—'} |")
    lines += ["", f"Pareto front ({METRIC_NAMES[metric]} against time): " + ", ".join(result["front"]) + ".", "",
              *[f"On {METRIC_NAMES[m]} instead: " + ", ".join(f) + "." for m, f in result.get("fronts", {}).items()
                if m != metric], *paired_lines(result), "",
              "## Every row", "",
              "| filter | ms per update | sliced W1 | mean error | covariance error | MMD² | on the front | "
              "ESS of the importance weights |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in sorted(result["rows"], key=lambda r: (r["method"], r["particles"], r["num_steps"])):
        if r.get("failed"):
            lines.append(f"| {label(r)} | {r['ms_per_update']:.3g} | diverged at step {r['failed']['step']} "
                         "| | | | | |")
            continue
        s = r["summary"]
        lines.append(f"| {label(r)} | {r['ms_per_update']:.3g} | " + " | ".join(
            format_mean_se(s[f"{part}/{m}"], 4) for m in ("w1", "mean", "cov", "mmd2"))
            + f" | {'yes' if label(r) in result['front'] else ''} | {format_importance(r['importance'])} |")
    return "\n".join(lines) + "\n"
