"""Paired ablation tables across benchmark runs (``escort-rl bench ablation``).

An ablation compares one method's rows in several runs (a sweep of ``filter.lambda_corr=…``
writes one run per value) or several methods of one run, against a reference row, seed by seed. The
runs must share their seeds and inputs (the same benchmark with the same seeds, particles, starts and
trajectories): each seed's difference is then paired, and a difference counts when it exceeds
:data:`~escort_rl.bench.synthetic.report.SIGNIFICANCE` standard errors of the paired differences.

It reads the ``synthetic.json``, ``scaling.json`` or ``domains.json`` of each run folder; rows are
matched by target (synthetic), dimension and structure (scaling) or domain (domains).

Example:
    ``escort-rl bench ablation outputs/a:escort_nocorr lambda=0.1=outputs/a:escort
    lambda=0.3=outputs/b:escort --metric rmse`` prints, per target, each row's mean ± s.e. and its
    paired difference from ESCORT-NoCorr of run ``a``.
"""

from __future__ import annotations

import json
from pathlib import Path

from escort_rl.bench.core import options
from escort_rl.reporting.stats import format_mean_se, mean_se

RESULT_FILES = ("synthetic.json", "scaling.json", "domains.json")


def load_run(folder: str | Path) -> dict:
    """The result JSON of a benchmark run folder (the first of :data:`RESULT_FILES` it holds)."""
    for name in RESULT_FILES:
        path = Path(folder) / name
        if path.exists():
            return json.loads(path.read_text())
    raise ValueError(f"{folder}: no {', '.join(RESULT_FILES)} in this folder; give a benchmark's --output folder")


def row_key(row: dict) -> str:
    """Where a row sits: its target, ``d=<dim> <structure>`` or its domain."""
    if "structure" in row:
        return f"d={row['dim']} {row['structure']}"
    return row.get("target") or row["domain"]


def rows_of(result: dict, method: str, metric: str) -> dict[str, list[float]]:
    """``row_key -> per-seed values of metric`` for ``method``'s rows of a run."""
    out = {}
    for row in result["rows"]:
        if row["method"] == method and "per_seed" in row:
            if metric not in row["per_seed"]:
                raise ValueError(f"--metric: the rows have no '{metric}'; choose from "
                                 f"{', '.join(sorted(row['per_seed']))}")
            out[row_key(row)] = row["per_seed"][metric]
    return out


def parse_run(spec: str) -> tuple[str, str, str]:
    """``[LABEL=]DIR[:METHOD]`` -> ``(label, dir, method)``; the method defaults to ``escort`` and the
    label to ``DIR:METHOD``."""
    label, _, rest = spec.rpartition("=") if "=" in spec else ("", "", spec)
    folder, _, method = rest.partition(":")
    method = method or "escort"
    return label or f"{folder}:{method}", folder, method


def ablation_markdown(reference: str, runs: list[str], metric: str, lower_is_better: bool = True) -> str:
    """The paired table: a column per run (``[LABEL=]DIR[:METHOD]``) and, for each, its difference
    from ``reference`` (same form) with the verdict."""
    from escort_rl.bench.synthetic.report import compare

    ref_label, ref_dir, ref_method = parse_run(reference)
    ref = rows_of(load_run(ref_dir), ref_method, metric)
    parsed = [parse_run(r) for r in runs]
    data = [(label, rows_of(load_run(folder), method, metric)) for label, folder, method in parsed]
    header = f"| row | {ref_label} | " + " | ".join(f"{label} | vs {ref_label}" for label, _ in data) + " |"
    lines = [f"Metric `{metric}` ({'lower' if lower_is_better else 'higher'} is better), mean ± s.e. over seeds; "
             "each run's paired difference from the reference row.", "", header,
             "| --- | --- | " + " | ".join("--- | ---" for _ in data) + " |"]
    for key, base in ref.items():
        cells = [format_mean_se(mean_se(base))]
        for label, rows in data:
            if key not in rows:
                cells += ["—", "—"]
                continue
            cells += [format_mean_se(mean_se(rows[key])), compare(label, rows[key], ref_label, base, lower_is_better)]
        lines.append(f"| {key} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def register(subparsers) -> None:
    """Add ``bench ablation`` to the ``bench`` subparsers."""
    p = subparsers.add_parser("ablation", help="paired differences of rows across runs (e.g. a lambda_corr sweep)",
                              description="Compare one method's rows in several runs, or several methods, with a "
                              "reference row seed by seed (the runs must share seeds and inputs). Each run is "
                              "[LABEL=]DIR[:METHOD], METHOD defaulting to escort.")
    p.add_argument("reference", help="the reference row: [LABEL=]DIR[:METHOD]")
    p.add_argument("runs", nargs="+", help="the rows to compare with it: [LABEL=]DIR[:METHOD] ...")
    p.add_argument("--metric", default="rmse", help="per-seed metric (domains: final_error, mean_error)")
    p.add_argument("--higher-is-better", action="store_true", help="for coverage-like metrics")
    options.add_output_option(p, None, "ablation.md, the table also printed (default: print only)")
    p.set_defaults(handler=main)


def main(args) -> None:
    md = ablation_markdown(args.reference, args.runs, args.metric, lower_is_better=not args.higher_is_better)
    print(md)
    if args.output:
        out = Path(args.output)
        out.mkdir(parents=True, exist_ok=True)
        (out / "ablation.md").write_text(md)
