"""``escort-rl bench headline``: the default job over several training seeds beside PPO on SIR
beliefs only, the scripted controller at its best gain and random, with error bars."""

from __future__ import annotations

import json
from pathlib import Path

from escort_rl.bench.core import options
from escort_rl.bench.core.runner import backend_from_args
from escort_rl.bench.headline.spec import DEFAULT_OUTPUT, ROW_SETS, HeadlineSpec, frontier_rows
from escort_rl.reporting.metadata import with_metadata


def register(subparsers) -> None:
    full, quick = HeadlineSpec(), HeadlineSpec.quick()
    p = subparsers.add_parser(
        "headline", help="the default job over several training seeds beside SIR-only PPO, scripted and random",
        description="Train the default job (PPO, SIR warm start then ESCORT beliefs) and PPO on SIR beliefs only "
        "for each training seed, evaluate every final policy on the same episodes, beside the scripted controller "
        "at its best gain (chosen on other episodes) and a random policy; mean ± s.e. across training seeds. "
        "A killed run resumes: finished cells are loaded and a training cell continues from its last checkpoint.")
    options.add_overrides_argument(p, "overrides under every row, e.g. env=lightdark10d_continuous (a force vector "
                                   "for an action)")
    options.add_seeds_option(p, None, "training seeds 0..N-1 per trained row", str(full.seeds))
    p.add_argument("--episodes", type=int, default=None, help=f"evaluation episodes (default: {full.episodes})")
    p.add_argument("--selection-episodes", type=int, default=None,
                   help="the gain search's episodes (default: as many as --episodes)")
    p.add_argument("--gains", type=float, nargs="+", default=None,
                   help="the scripted controller's velocity gains searched (default: "
                   f"{' '.join(f'{g:g}' for g in full.gains)})")
    p.add_argument("--rows", choices=sorted(ROW_SETS), default="headline",
                   help="the trained rows: headline (the default job and PPO on SIR beliefs), default (the default job "
                   "alone), ablation (the "
                   "learner's changes one at a time), starts (the default job with half its training starts "
                   "in the evaluation's box), half (half the frames on ESCORT beliefs), frames (PPO on SIR beliefs "
                   "for 1.44M frames), coordinates (the policy's outputs per action group), own_filter (all 16 "
                   "iterations on ESCORT beliefs), horizon (a longer discount, a smaller entropy bonus), teacher "
                   "(the default job's teacher for the warm start only, or none), reinforce (REINFORCE, tuned, "
                   "at 4x the frames) or mtt (PPO on SIR beliefs as first run on env=mtt20d)")
    options.add_labelled_option(p, "--row", "a trained row of your own instead of --rows' set, on top of the "
                                "default job, paired with the scripted controller on its belief",
                                '"PPO on SIR N=3000" filter=sir num_particles=3000 trainer.warm_start_iterations=0')
    p.add_argument("--frontier-rows", nargs=2, default=None, metavar=("FRONTIER_JSON", "MS"),
                   help="instead of --rows' set: PPO on each filter's configuration that a frontier.json (bench "
                   "frontier) found closest to its reference within MS ms an update; --row adds rows beside them")
    p.add_argument("--scripted-on", nargs="+", default=None, metavar="BELIEF",
                   help="the beliefs the scripted controller runs on: filter config names, or a belief's overrides "
                   "in one quoted word ('filter=sir num_particles=3000'), which may add the controller's options "
                   "for a second rule on the same belief ('filter=sir env.scripted_options={confidence:0.999}'; a "
                   "trained row meets the first controller on its belief) (default: escort_train sir_rough for the "
                   "named row sets; with --row, each row's belief)")
    p.add_argument("--curve-every", type=int, default=None, metavar="K",
                   help="also evaluate every trained seed's checkpoint of every K-th iteration on the same episodes: "
                   "success against training frames beside the controller's line, in curve.png (default: 0, no curve)")
    options.add_quick_option(p, f"{quick.seeds} seeds of a 2-iteration job, {quick.episodes} episodes of 20 steps")
    options.add_output_option(p, DEFAULT_OUTPUT, "headline.md, headline.json, headline.png, cells/ and runs/")
    options.add_runner_options(p, seeds_per_cell=False)
    p.set_defaults(handler=main)


def spec_from_args(args) -> HeadlineSpec:
    base = HeadlineSpec.quick() if args.quick else HeadlineSpec()
    changes = options.given(args, "seeds", "episodes", "selection_episodes", "threads", "curve_every")
    if args.gains is not None:
        changes["gains"] = tuple(args.gains)
    overrides = (*base.overrides, *getattr(args, "overrides", ()))
    own = options.labelled(getattr(args, "row", None), "--row")
    if getattr(args, "frontier_rows", None):
        path, budget = args.frontier_rows
        try:
            budget = float(budget)
        except ValueError:
            raise ValueError(f"--frontier-rows: MS must be a number of milliseconds, got '{budget}'") from None
        own = [*frontier_rows(path, budget), *own]
    changes["rows"] = tuple(own) if own else ROW_SETS[args.rows]
    if own or getattr(args, "scripted_on", None):
        changes["scripted_filters"] = tuple(args.scripted_on) if getattr(args, "scripted_on", None) else None
    return base.replace(output=Path(args.output), overrides=overrides, **changes)


def write_headline(result: dict, out: Path) -> str:
    """``headline.md``, ``headline.json`` and ``headline.png`` in ``out``; returns the Markdown."""
    from escort_rl.bench.headline.report import env_name, headline_markdown
    from escort_rl.reporting.plots import plot_against_frames, plot_rows_with_seeds

    out.mkdir(parents=True, exist_ok=True)
    md = headline_markdown(result)
    (out / "headline.md").write_text(md)
    (out / "headline.json").write_text(json.dumps(with_metadata(result), indent=1))
    spec = result["spec"]
    plot_rows_with_seeds(result["rows"], "success", out / "headline.png", "success rate (mean ± s.e.; dots: seeds)",
                         title=f"{env_name(spec)}, {spec['episodes']} evaluation episodes")
    curves = {r["policy"]: ([p["frames"] for p in r["curve"]], [p["success"] for p in r["curve"]],
                            [p["success_se"] for p in r["curve"]]) for r in result["rows"] if r.get("curve")}
    if curves:
        lines = {f"{r['policy']} on {r['filter']}": (r["success"], r["success_se"])
                 for r in result["rows"] if r["kind"] == "scripted"}
        plot_against_frames(curves, lines, out / "curve.png", "success rate (mean ± s.e. across seeds)",
                            title=f"{env_name(spec)}: greedy success against training frames, "
                            f"{spec['episodes']} evaluation episodes")
    return md


def main(args) -> None:
    from escort_rl.bench.headline.run import run_headline

    spec = spec_from_args(args)
    result = run_headline(spec, backend_from_args(args))
    print(write_headline(result, spec.output))
    print(f"results: {spec.output.resolve()}")
