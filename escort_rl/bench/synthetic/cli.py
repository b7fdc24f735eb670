"""``escort-rl bench synthetic`` and ``escort-rl bench scaling``: the options, and what they write
(``<output>/<bench>.md|json``, the "paper against ours" table, plots, and ``cells/``)."""

from __future__ import annotations

from pathlib import Path

from escort_rl.belief import ESCORTFilter
from escort_rl.bench.core import options
from escort_rl.bench.synthetic.cells import INITS, TRACKING_METHODS
from escort_rl.bench.synthetic.run import run_scaling, run_synthetic
from escort_rl.bench.synthetic.spec import (
    FIT_STEPS,
    PROTOCOLS,
    SCALING_OUTPUT,
    SYNTHETIC_OUTPUT,
    GridSpec,
    ScalingSpec,
    SyntheticSpec,
)


def _quick_help(spec: GridSpec, axes: str) -> str:
    return f"{axes}, {spec.seeds} seeds, N={spec.particles}, {spec.num_steps} steps"


def register(subparsers) -> None:
    """Add ``bench synthetic`` and ``bench scaling`` to the ``bench`` subparsers."""
    syn_full, syn_quick = SyntheticSpec(), SyntheticSpec.quick()
    sca_full, sca_quick = ScalingSpec(), ScalingSpec.quick()
    syn = subparsers.add_parser("synthetic", help="the paper's GMM targets (Table 2): ESCORT, NoCorr, SVGD, SIR, "
                                "DVRL, oracle", description="The paper's Table 2 targets: MMD², W1, sliced W1, mode "
                                "coverage, correlation error and RMSE, mean ± s.e. over seeds, under the static or "
                                "the tracking protocol, beside the paper's figures.")
    syn.add_argument("--targets", nargs="+", default=None, help=f"the GMM targets (default: {list(syn_full.targets)})")
    options.add_seeds_option(syn, None, shown=str(syn_full.seeds))
    options.add_quick_option(syn, _quick_help(syn_quick, ", ".join(syn_quick.targets)))
    options.add_output_option(syn, SYNTHETIC_OUTPUT, "synthetic.md, synthetic.json, the plots and cells/")
    sca = subparsers.add_parser("scaling", help="RMSE of ESCORT against ESCORT-NoCorr on 5-mode GMMs, 1D-200D",
                                description="The paper's RMSE-against-dimension table, with the paired NoCorr gap, "
                                "under the static or the tracking protocol, beside the paper's figures.")
    sca.add_argument("--dims", type=int, nargs="+", default=None, metavar="D",
                     help=f"dimensions (default: {list(sca_full.dims)})")
    sca.add_argument("--structures", nargs="+", default=None,
                     help=f"the correlation structures of the targets (default: {list(sca_full.structures)})")
    options.add_seeds_option(sca, None, shown=str(sca_full.seeds))
    options.add_quick_option(sca, _quick_help(sca_quick, f"d {' '.join(map(str, sca_quick.dims))}, "
                                              f"{', '.join(sca_quick.structures)}"))
    options.add_output_option(sca, SCALING_OUTPUT, "scaling.md, scaling.json, the plots and cells/")
    for p, full in ((syn, syn_full), (sca, sca_full)):
        p.set_defaults(handler=main)
        _add_grid_options(p, full)


def _add_grid_options(p, full: GridSpec) -> None:
    """The options ``bench synthetic`` and ``bench scaling`` share."""
    options.add_overrides_argument(p, "ESCORT/SVGD arguments as filter overrides, e.g. filter.lambda_corr=0.3 "
                                   "filter.corr_form=position filter.compile=true (a row's own setting wins: NoCorr "
                                   "keeps lambda_corr=0, SVGD both lambdas 0)")
    p.add_argument("--methods", nargs="+", default=None,
                   help=f"rows (default: {' '.join(full.default_methods)}; with --protocol tracking: "
                   f"{' '.join(TRACKING_METHODS)})")
    p.add_argument("--protocol", choices=PROTOCOLS, default=full.protocol,
                   help="static: fit the fixed target from --init; tracking: follow a random walk "
                   "observed through noise shaped as the target")
    p.add_argument("--particles", type=int, default=None, metavar="N",
                   help=f"particles of every method (default: {full.particles})")
    p.add_argument("--num-steps", type=int, default=None, metavar="K",
                   help="iterations of ESCORT and SVGD: of the fit, or per update under --protocol tracking "
                   f"(default: {FIT_STEPS['static']} for the fit, {FIT_STEPS['tracking']} per update)")
    p.add_argument("--steps", type=int, default=None, metavar="T",
                   help=f"steps of the tracking protocol (default: {full.steps})")
    p.add_argument("--bandwidth-scale", type=float, default=full.bandwidth_scale,
                   help="multiply ESCORT's and SVGD's median-heuristic bandwidth")
    p.add_argument("--init", choices=INITS, default=full.init,
                   help="the static protocol's start: the broad cloud, overlap (the target's "
                   "components at its weights, spread doubled), or resampled (ESCORT and SVGD from the cloud "
                   "importance-resampled to the target)")
    p.add_argument("--init-scale", type=float, default=full.init_scale,
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


FLAGS = ("methods", "seeds", "particles", "num_steps", "steps", "threads", "seeds_per_cell")
"""The options that set the spec's field of the same name when given (else ``--quick``'s or the default)."""
AXES = {"synthetic": ("targets",), "scaling": ("dims", "structures")}
"""Each bench's own options, fields of its spec."""


def spec_from_args(args) -> GridSpec:
    """The run ``args`` ask for (``args.bench``: ``synthetic`` or ``scaling``): each option of
    :data:`FLAGS` and :data:`AXES` given explicitly, else ``--quick``'s setting, else the default."""
    cls = SyntheticSpec if args.bench == "synthetic" else ScalingSpec
    explicit = {name: getattr(args, name) for name in FLAGS + AXES[args.bench] if getattr(args, name) is not None}
    make = cls.quick if args.quick else cls.full
    return make(protocol=args.protocol, bandwidth_scale=args.bandwidth_scale, init=args.init,
                init_scale=args.init_scale, filter_kwargs=filter_arguments(args.overrides), output=Path(args.output),
                **explicit)


def show_progress(row: dict) -> None:
    """The line of a finished row."""
    where = row.get("target") or f"d={row['dim']} {row['structure']}"
    s = row["summary"]
    shown = ("mmd2", "sliced_w1", "mode_coverage", "corr_error", "rmse") if "mmd2" in s else ("rmse", "final_error")
    print(f"{where:>18} {row['method']:>14}: " + " ".join(f"{k} {s[k][0]:.4g}" for k in shown)
          + f" ({row['seconds']:.1f} s)", flush=True)


def main(args) -> None:
    """``bench synthetic`` and ``bench scaling``."""
    from escort_rl.bench.core.runner import backend_from_args
    from escort_rl.bench.synthetic.report import (
        rmse_against_paper,
        scaling_markdown,
        synthetic_markdown,
        table2_against_paper,
    )
    from escort_rl.reporting.paths import write_results

    spec = spec_from_args(args)
    out = spec.output
    out.mkdir(parents=True, exist_ok=True)
    if args.bench == "synthetic":
        result = run_synthetic(spec, backend_from_args(args), progress=show_progress)
        md = synthetic_markdown(result)
        paper = table2_against_paper(result) if spec.protocol != "tracking" else None
        paper_name = "table2_paper"
    else:
        result = run_scaling(spec, backend_from_args(args), progress=show_progress)
        md, paper = scaling_markdown(result), rmse_against_paper(result)
        paper_name = "rmse_paper"
    if paper is not None:
        (out / f"{paper_name}.md").write_text(paper)
        md = md + "\n" + paper
    write_results(out, args.bench, result, md)
