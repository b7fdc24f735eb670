"""The Markdown of ``bench headline``."""

from __future__ import annotations

import math


def _selection_cell(s: dict) -> str:
    """One gain's result in the gain search: success, and return and steps where recorded."""
    if "episode_return" not in s:
        return f"{s['success']:.3f}"
    return f"{s['success']:.3f} ({s['episode_return']:.1f}, {s['steps']:.0f} steps)"


def _cell(mean: float, se: float, digits: int) -> str:
    if math.isnan(mean):
        return "—"
    return f"{mean:.{digits}f} ± {se:.{digits}f}"


def env_name(spec: dict) -> str:
    """The env the table ran on (a result written before the table named it ran on Light-Dark 10D)."""
    return spec.get("env", "lightdark10d")


def curve_markdown(rows: list[dict]) -> list[str]:
    """The lines of the success-against-frames table: one row per evaluated checkpoint of each trained
    row that has a curve (none: no lines)."""
    curved = [r for r in rows if r.get("curve")]
    if not curved:
        return []
    lines = ["", "Greedy success, steps and return against training frames (each seed's checkpoint on the same "
             "episodes; mean ± s.e. across seeds; `curve.png`):", "",
             "| policy | frames | success | steps | return |", "| --- | --- | --- | --- | --- |"]
    for r in curved:
        for p in r["curve"]:
            ret = _cell(p["episode_return"], p["episode_return_se"], 1)
            lines.append(f"| {r['policy']} | {p['frames']} | {_cell(p['success'], p['success_se'], 3)} | "
                         f"{_cell(p['steps'], p['steps_se'], 0)} | {ret} |")
    return lines


def _controller_sentence(spec: dict, rows: list[dict]) -> str:
    """How the scripted controller was set: the gain search, or the rule of a controller without a gain (and
    where other rows run another rule, that they do)."""
    if spec.get("scripted_rule"):
        own = f"scripted controller ({spec['scripted_rule']})"
        others = any(r["kind"] == "scripted" and r["policy"] != own for r in rows)
        return (f"The scripted controller has no gain to choose: it pushes {spec['scripted_rule']}."
                + (" Rows naming another rule run it with the options in their belief's overrides "
                   "(`env.scripted_options`); a trained row is compared with the first controller on its belief."
                   if others else ""))
    return ("The scripted controller's velocity gain was chosen among "
            f"{', '.join(f'{g:g}' for g in spec['gains'])} by success on {spec['selection_episodes']} other episodes "
            f"(env seeds {spec['selection_seed']}..), ties by return.")


def headline_markdown(result: dict) -> str:
    """The table: each row's success, final distance, return and steps (mean ± s.e.), its belief,
    its training frames and minutes; then the gain search and how to read the table."""
    spec = result["spec"]
    lines = [f"# Headline: PPO on particle beliefs, {env_name(spec)}", "",
             f"Trained rows: {spec['seeds']} training seeds each, every seed's final policy greedy on the same "
             f"{spec['episodes']} episodes (env seeds {spec['eval_seed']}..); mean ± s.e. **across training seeds** "
             "of the per-seed means. Scripted and random rows: the same episodes, mean ± s.e. **over episodes**. "
             + _controller_sentence(spec, result["rows"]), "",
             "| policy | belief | success | final distance | return | steps | frames | training minutes |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in result["rows"]:
        trained = r["kind"] == "trained"
        belief = r["filter"] if r["kind"] != "random" else "—"
        lines.append(
            f"| {r['policy']} | {belief} | {_cell(r['success'], r['success_se'], 3)} | "
            f"{_cell(r['final_distance'], r['final_distance_se'], 2)} | "
            f"{_cell(r['episode_return'], r['episode_return_se'], 1)} | {_cell(r['steps'], r['steps_se'], 0)} | "
            f"{r['frames'] if trained else '—'} | "
            f"{_cell(r['train_minutes'], r['train_minutes_se'], 1) if trained else '—'} |")
    compared = [r for r in result["rows"] if r.get("vs_scripted")]
    if compared:
        scripted = {r["filter"]: r["policy"] for r in result["rows"] if r["kind"] == "scripted"}
        lines += ["", "Each trained row against the scripted controller on its belief, episode by episode "
                  "(trained − scripted on the same episodes, averaged over seeds and episodes). The s.e. counts "
                  "both samples, √(s.e. across seeds² + s.e. across episodes²): every seed meets the same run of "
                  "the controller, whose own spread over the episodes the seeds cannot see. Positive success and "
                  "return, negative steps: the learner is ahead. *Δ steps where both arrive*: the same on the "
                  "episodes that both the seed's policy and the controller finish, so that which episodes each "
                  "misses, largely chance, stays out of it.", "",
                  "| policy | against | Δ success | Δ steps | Δ return | Δ steps where both arrive |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for r in compared:
            d = r["vs_scripted"]
            both = d["steps_both_succeed"]
            lines.append(f"| {r['policy']} | {scripted.get(r['filter'], r['filter'])} on {r['filter']} | "
                         f"{_cell(*d['success'][:2], 3)} | {_cell(*d['steps'][:2], 1)} | "
                         f"{_cell(*d['episode_return'][:2], 1)} | {_cell(*both[:2], 1) if both else '—'} |")
    lines += ["", "Per-seed success of the trained rows:", ""]
    for r in result["rows"]:
        if r["kind"] == "trained":
            lines.append(f"- {r['policy']}: " + ", ".join(f"{v:.2f}" for v in r["per_seed"]["success"]))
    lines += curve_markdown(result["rows"])
    if result["selection"]:
        lines += ["", "Gain search (success on the selection episodes; return and steps beside it where recorded):",
                  "", "| belief | " + " | ".join(f"gain {g:g}" for g in spec["gains"]) + " |",
                  "| --- |" + " --- |" * len(spec["gains"])]
    for f in dict.fromkeys(s["filter"] for s in result["selection"]):
        cells = {s["gain"]: _selection_cell(s) for s in result["selection"] if s["filter"] == f}
        lines.append(f"| {f} | " + " | ".join(cells[g] for g in spec["gains"]) + " |")
    if spec["overrides"]:
        lines += ["", "Overrides on every row: `" + " ".join(spec["overrides"]) + "`."]
        lines += [f"Row *{r['policy']}* drops `{' '.join(r['dropped_overrides'])}`: it picks their group."
                  for r in result["rows"] if r.get("dropped_overrides")]
    lines += ["", "Training minutes: each seed's training wall-clock (collection and updates), "
              f"{spec['threads']} torch thread(s) per cell."]
    return "\n".join(lines) + "\n"
