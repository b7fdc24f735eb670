"""``escort-rl bench synthetic`` and ``escort-rl bench scaling``: the options, and what they write
(``<output>/<bench>.md|json``, the "paper against ours" table, plots, and ``cells/``)."""

from __future__ import annotations

from pathlib import Path

from escort_rl.belief import ESCORTFilter
from escort_rl.bench.core import options
from escort_rl.bench.methods import SCALING_METHODS, SYNTHETIC_METHODS, check_choices
from escort_rl.bench.synthetic.cells import INITS, TRACKING_METHODS
from escort_rl.bench.synthetic.run import PROTOCOLS, SCALING_DIMS, SYNTHETIC_TARGETS, run_scaling, run_synthetic
from escort_rl.bench.synthetic.tracking import STEPS


def register(subparsers) -> None:
    """Add ``bench synthetic`` and ``bench scaling`` to the ``bench`` subparsers."""
    from escort_rl.bench.targets import SCALABILITY_STRUCTURES

    syn = subparsers.add_parser("synthetic", help="the paper's GMM targets (Table 2): ESCORT, NoCorr, SVGD, SIR, "
                                "DVRL, oracle", description="The paper's Table 2 targets: MMD², W1, sliced W1, mode "
                                "coverage, correlation error and RMSE, mean ± s.e. over seeds, under the static or "
                                "the tracking protocol, beside the paper's figures.")
    syn.add_argument("--targets", nargs="+", default=list(SYNTHETIC_TARGETS), help="the GMM targets")
    options.add_seeds_option(syn, 30)
    options.add_quick_option(syn, "gmm1d, gmm2d, gmm3d, 2 seeds, N=100, 30 steps")
    options.add_output_option(syn, "outputs/bench/synthetic", "synthetic.md, synthetic.json, the plots and cells/")
    sca = subparsers.add_parser("scaling", help="RMSE of ESCORT against ESCORT-NoCorr on 5-mode GMMs, 1D-200D",
                                description="The paper's RMSE-against-dimension table, with the paired NoCorr gap, "
                                "under the static or the tracking protocol, beside the paper's figures.")
    sca.add_argument("--dims", type=int, nargs="+", default=list(SCALING_DIMS), metavar="D", help="dimensions")
    sca.add_argument("--structures", nargs="+", default=list(SCALABILITY_STRUCTURES),
                     help="the correlation structures of the targets")
    options.add_seeds_option(sca, 5)
    options.add_quick_option(sca, "d 1 5, block, 2 seeds, N=100, 30 steps")
    options.add_output_option(sca, "outputs/bench/scaling", "scaling.md, scaling.json, the plots and cells/")
    for p, methods in ((syn, SYNTHETIC_METHODS), (sca, SCALING_METHODS)):
        p.set_defaults(handler=main)
        options.add_overrides_argument(p, "ESCORT/SVGD arguments as filter overrides, e.g. filter.lambda_corr=0.3 "
                               "filter.corr_form=position filter.compile=true (a row's own setting wins: NoCorr keeps "
                               "lambda_corr=0, SVGD both lambdas 0)")
        p.add_argument("--methods", nargs="+", default=None,
                       help=f"rows (default: {' '.join(methods)}; with --protocol tracking: "
                       f"{' '.join(TRACKING_METHODS)})")
        p.add_argument("--protocol", choices=PROTOCOLS, default="static",
                       help="static: fit the fixed target from --init; tracking: follow a random walk "
                       "observed through noise shaped as the target")
        p.add_argument("--particles", type=int, default=1000, metavar="N", help="particles of every method")
        p.add_argument("--num-steps", type=int, default=None, metavar="K",
                       help="iterations of ESCORT and SVGD: of the fit, or per update under --protocol tracking "
                       "(default: 500 for the fit, 50 per update)")
        p.add_argument("--steps", type=int, default=STEPS, metavar="T", help="steps of the tracking protocol")
        p.add_argument("--bandwidth-scale", type=float, default=1.0,
                       help="multiply ESCORT's and SVGD's median-heuristic bandwidth")
        p.add_argument("--init", choices=INITS, default="cloud",
                       help="the static protocol's start: the broad cloud, overlap (the target's "
                       "components at its weights, spread doubled), or resampled (ESCORT and SVGD from the cloud "
                       "importance-resampled to the target)")
        p.add_argument("--init-scale", type=float, default=1.0,
                       help="multiply the start's spread, for every method but the oracle")
        options.add_runner_options(p)


def filter_arguments(overrides) -> dict:
    """Positional ``filter.KEY=VALUE ...`` overrides as ESCORT/SVGD constructor arguments, each value
    read as OmegaConf reads a dotlist value (``4`` an int, ``0.5`` a float, ``true`` a bool); a key
    the constructor does not take is an error naming it and the keys it does take, and a bad value
    is the constructor's error naming the key."""
    import dataclasses

    from omegaconf import OmegaConf

    known = [f.name for f in dataclasses.fields(ESCORTFilter.Params)]
    out = {}
    for key, value in options.filter_overrides(overrides):
        if key not in known:
            raise ValueError(f"overrides: ESCORT has no argument '{key}' (filter.{key}); choose from "
                             f"{', '.join(known)}")
        out[key] = OmegaConf.from_dotlist([f"value={value}"])["value"]
    if out:
        ESCORTFilter(**{k: v for k, v in out.items()})  # a bad value fails here, naming its key
    return out


def main(args) -> None:
    """``bench synthetic`` and ``bench scaling``."""
    from escort_rl.bench.core.runner import backend_from_args
    from escort_rl.bench.synthetic.report import (
        rmse_against_paper,
        scaling_markdown,
        synthetic_markdown,
        table2_against_paper,
    )
    from escort_rl.bench.targets import synthetic_config
    from escort_rl.reporting.paths import write_results

    tracking = args.protocol == "tracking"
    default_methods = TRACKING_METHODS if tracking else (SYNTHETIC_METHODS if args.bench == "synthetic"
                                                          else SCALING_METHODS)
    methods = list(args.methods or default_methods)
    if args.bench == "synthetic":
        check_choices("--targets", args.targets, sorted(synthetic_config()["targets"]))
    filter_kwargs = {}
    if args.bandwidth_scale != 1.0:
        filter_kwargs["bandwidth_scale"] = args.bandwidth_scale
    filter_kwargs.update(filter_arguments(args.overrides))
    num_steps = args.num_steps if args.num_steps is not None else (50 if tracking else 500)

    def show(row):
        where = row.get("target") or f"d={row['dim']} {row['structure']}"
        s = row["summary"]
        shown = ("mmd2", "sliced_w1", "mode_coverage", "corr_error", "rmse") if "mmd2" in s else ("rmse", "final_error")
        print(f"{where:>18} {row['method']:>14}: " + " ".join(f"{k} {s[k][0]:.4g}" for k in shown)
              + f" ({row['seconds']:.1f} s)", flush=True)

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    runner = dict(backend=backend_from_args(args), threads=args.threads, seeds_per_cell=args.seeds_per_cell,
                  cells_dir=out / "cells", filter_kwargs=filter_kwargs, progress=show, plot_dir=out,
                  init=args.init, init_scale=args.init_scale, protocol=args.protocol, steps=args.steps,
                  methods=methods, seeds=args.seeds, n=args.particles, num_steps=num_steps)
    if args.bench == "synthetic":
        kw = dict(targets=args.targets)
        if args.quick:
            kw["targets"] = ["gmm1d", "gmm2d", "gmm3d"]
            runner.update(seeds=2, n=100, num_steps=30, steps=min(args.steps, 3))
        result = run_synthetic(**kw, **runner)
        md, paper = synthetic_markdown(result), table2_against_paper(result) if not tracking else None
        paper_name = "table2_paper"
    else:
        kw = dict(dims=args.dims, structures=args.structures)
        if args.quick:
            kw.update(dims=[1, 5], structures=["block"])
            runner.update(seeds=2, n=100, num_steps=30, steps=min(args.steps, 3))
        result = run_scaling(**kw, **runner)
        md, paper = scaling_markdown(result), rmse_against_paper(result)
        paper_name = "rmse_paper"
    if paper is not None:
        (out / f"{paper_name}.md").write_text(paper)
        md = md + "\n" + paper
    write_results(out, args.bench, result, md)
