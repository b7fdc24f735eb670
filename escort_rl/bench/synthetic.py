"""The synthetic benchmark (SPEC §7): fit particles to fixed GMM targets and score them.

Rows: ESCORT, ESCORT-NoCorr, SVGD (static fits by :meth:`ESCORTFilter.fit`; no time axis, so
F_temp is off), SIR (importance resampling of the initial cloud by ``p/q``), a DVRL-style
parametric fit (DVRL's diagonal-Gaussian proposal family fitted by the importance-weighted ELBO with
K = 100, then sampled; :mod:`escort_rl.bench.parametric`), and an oracle of N exact i.i.d. samples of
the target (the floor N particles can reach). Every metric compares the
particles with a fresh set of N exact samples.

The grid's cells are (target × method × block of seeds) (:class:`SyntheticCell`), run on any backend
of :mod:`escort_rl.bench.runner` and saved under ``<output>/cells/`` as they finish; the seeds of a
cell are fitted in one ``[S, N, d]`` call, and the random streams depend only on the cell's fields
(the initial cloud, the oracle and the reference samples on each seed; the filters' noise on the
cell's first seed), so every backend gives the same numbers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch

from escort_rl.belief import ESCORTFilter, SVGDFilter
from escort_rl.belief.prior import silverman_factor
from escort_rl.belief.sir import systematic_resample_indices
from escort_rl.bench import metrics
from escort_rl.bench.methods import SCALING_METHODS, SYNTHETIC_METHODS, check_choices, parse_filter_set
from escort_rl.bench.runner import Cell, CellStore, InProcessBackend, run_groups, seed_blocks
from escort_rl.reporting.stats import format_mean_se, mean_se
from escort_rl.bench.targets import (
    GaussianMixture,
    initial_distribution,
    load_target,
    scalability_initial,
    scalability_target,
)

SYNTHETIC_TARGETS = ("gmm1d", "gmm2d", "gmm3d", "gmm5d", "gmm20d")
INITS = ("cloud", "resampled")
"""How ESCORT and SVGD start: the initial cloud itself, or the cloud importance-resampled to the target
(:func:`initial_particles`)."""
SCALING_DIMS = (1, 5, 20, 50, 100, 200)


def _sample_batch(dist: GaussianMixture, seeds: list[int], n: int, offset: int) -> torch.Tensor:
    """One set of ``n`` samples per seed: ``[S, n, d]`` float32."""
    out = [dist.sample(n, torch.Generator().manual_seed(offset + s)) for s in seeds]
    return torch.stack(out).to(torch.float32)


def scaled(initial: GaussianMixture, scale: float) -> GaussianMixture:
    """``initial`` with every component's spread multiplied by ``scale`` (covariances by ``scale²``)."""
    if not (isinstance(scale, (int, float)) and not isinstance(scale, bool) and 0 < scale < float("inf")):
        raise ValueError(f"init_scale: expected a positive finite number, got {scale!r}")
    if scale == 1.0:
        return initial
    return GaussianMixture(initial.weights, initial.means, initial.covariances * float(scale) ** 2,
                           name=f"{initial.name}*{scale}")


def initial_particles(x0: torch.Tensor, target: GaussianMixture, initial: GaussianMixture, init: str,
                      generator: torch.Generator) -> torch.Tensor:
    r"""Where ESCORT and SVGD start, from the initial cloud ``x0`` ``[S, n, d]`` drawn from ``initial`` (q).

    * ``cloud``: ``x0`` itself.
    * ``resampled``: ``x0`` resampled systematically by the importance weights ``p/q`` (so the modes
      start with about their target mass, which SVGD cannot move between modes later), then each copy
      moved by ``N(0, h² diag(σ̂²))``, the regularised particle filter's kernel: σ̂² the per-dimension
      variance of the resampled set and ``h = (4 / (n (d + 2)))^{1/(d+4)}`` (Silverman). The kernel
      separates the copies, which SVGD's repulsion could not (the kernel's gradient vanishes between
      equal points). Where the weights degenerate (high ``d``), most copies share a few ancestors.
    """
    if init not in INITS:
        raise ValueError(f"init: expected one of {', '.join(INITS)}, got {init!r}")
    if init == "cloud":
        return x0
    log_w = (target.log_prob(x0) - initial.log_prob(x0)).to(torch.float64)
    idx = systematic_resample_indices(log_w, generator)
    x = torch.gather(x0, -2, idx.unsqueeze(-1).expand_as(x0))
    h = silverman_factor(x.shape[-2], x.shape[-1])
    std = x.std(-2, keepdim=True).clamp_min(1e-6)
    return x + h * std * torch.randn(x.shape, generator=generator, dtype=x.dtype)


def fit_particles(method: str, target: GaussianMixture, initial: GaussianMixture, seeds: list[int], n: int,
                  num_steps: int, filter_kwargs: dict | None = None, init: str = "cloud",
                  init_scale: float = 1.0) -> tuple[torch.Tensor, float]:
    """Particles ``[S, n, d]`` of ``method`` for each seed, and the wall-clock seconds it took.
    ``filter_kwargs`` (e.g. ``bandwidth_scale``) go to the ESCORT and SVGD constructors; ``init`` and
    ``init_scale`` set ESCORT's and SVGD's start (:func:`initial_particles`, of the initial cloud with
    its spread times ``init_scale``; SIR and the DVRL fit use that cloud as well)."""
    initial = scaled(initial, init_scale)
    x0 = _sample_batch(initial, seeds, n, offset=0)
    t0 = time.perf_counter()
    if method == "oracle":
        x = _sample_batch(target, seeds, n, offset=10_000)
    elif method == "dvrl":
        from escort_rl.bench.parametric import fit_parametric

        x = fit_parametric(lambda z: target.log_prob(z), target.dim, seeds, n, num_steps=num_steps,
                           init_mean=float(initial.means[0, 0]), init_std=float(initial.covariances[0, 0, 0]) ** 0.5)
    elif method == "sir":
        log_w = target.log_prob(x0) - initial.log_prob(x0)
        g = torch.Generator().manual_seed(seeds[0])
        idx = systematic_resample_indices(log_w.to(torch.float64), g)
        x = torch.gather(x0, -2, idx.unsqueeze(-1).expand_as(x0))
    else:
        kw = dict(filter_kwargs or {})
        filt = {"escort": lambda: ESCORTFilter(**kw), "escort_nocorr": lambda: ESCORTFilter(lambda_corr=0.0, **kw),
                "svgd": lambda: SVGDFilter(**kw)}[method]()
        g = torch.Generator().manual_seed(seeds[0])
        x0 = initial_particles(x0, target, initial, init, g)
        x = filt.fit(lambda z: target.log_prob(z), x0, num_steps=num_steps, generator=g)
    return x, time.perf_counter() - t0


def score_particles(x: torch.Tensor, target: GaussianMixture, seeds: list[int], num_projections: int = 100) -> dict:
    """Per-seed metrics of particles ``[S, N, d]`` against fresh exact samples of the target."""
    n, d = x.shape[-2], x.shape[-1]
    ref = _sample_batch(target, seeds, n, offset=20_000).to(torch.float64)
    x = x.to(torch.float64)
    c_true = target.correlation()
    out: dict[str, list[float]] = {k: [] for k in ("mmd2", "w1", "sliced_w1", "mode_coverage", "corr_error", "rmse")}
    proj = metrics.random_projections(num_projections, d, torch.Generator().manual_seed(12345)).to(torch.float64)
    for s in range(x.shape[0]):
        out["mmd2"].append(float(metrics.mmd_squared(x[s], ref[s], gamma=0.5)))
        out["w1"].append(float(metrics.wasserstein_1d(x[s, :, 0], ref[s, :, 0])) if d == 1 else float("nan"))
        out["sliced_w1"].append(float(metrics.sliced_wasserstein(x[s], ref[s], projections=proj)))
        out["mode_coverage"].append(float(metrics.mode_coverage(x[s], target.means)))
        out["corr_error"].append(float(metrics.correlation_error(c_true, x[s])) if d > 1 else float("nan"))
        out["rmse"].append(float(metrics.rmse_of_mean(x[s], target.mean())))
    return out


@dataclass(frozen=True)
class SyntheticCell(Cell):
    """One method fitted to one static target on ``seeds`` (one batch ``[S, N, d]``) and scored.

    The target is a named GMM of ``configs/bench/synthetic.yaml`` (``target``), or, with
    ``structure``, the 5-mode scalability GMM of dimension ``dim``. With ``keep_particles`` the
    result also holds seed 0's particles (for the figures).

    Examples:
        >>> cell = SyntheticCell(target="gmm1d", method="oracle", seeds=(0, 1), particles=20, num_steps=1)
        >>> sorted(cell.run()["per_seed"])
        ['corr_error', 'mmd2', 'mode_coverage', 'rmse', 'sliced_w1', 'w1']
    """

    target: str
    method: str
    seeds: tuple
    particles: int
    num_steps: int
    filter_kwargs: tuple = ()
    init: str = "cloud"
    init_scale: float = 1.0
    dim: int | None = None
    structure: str | None = None
    keep_particles: bool = False

    def key(self) -> str:
        return (f"synthetic/{self.target}/{self.method}/N{self.particles}-K{self.num_steps}-"
                f"seeds{self.seeds[0]}-{self.seeds[-1]}")

    def distributions(self) -> tuple[GaussianMixture, GaussianMixture]:
        """The target and the initial cloud's distribution."""
        if self.structure is None:
            return load_target(self.target), initial_distribution(self.target)
        return scalability_target(self.dim, self.structure, 0), scalability_initial(self.dim)

    def run(self) -> dict:
        target, initial = self.distributions()
        seeds = list(self.seeds)
        x, seconds = fit_particles(self.method, target, initial, seeds, self.particles, self.num_steps,
                                   dict(self.filter_kwargs), self.init, self.init_scale)
        out = {"per_seed": score_particles(x, target, seeds), "timing": {"seconds": seconds}}
        if self.keep_particles and 0 in seeds:
            out["seed0_particles"] = x[seeds.index(0)].tolist()
        return out


def _run_grid(rows: list[dict], cells: dict, backend, cells_dir, progress) -> list[dict]:
    """Run the cells of every row (``cells``: row index -> its cells, in seed order) and fill in
    each row's ``per_seed``, ``summary`` and ``seconds`` as its last cell arrives."""

    def on_group(i, parts):
        per_seed = {k: [v for p in parts for v in p["per_seed"][k]] for k in parts[0]["per_seed"]}
        rows[i].update(seconds=sum(p["timing"]["seconds"] for p in parts), per_seed=per_seed,
                       summary={k: mean_se(v) for k, v in per_seed.items()})
        shown = [p["seed0_particles"] for p in parts if "seed0_particles" in p]
        if shown:
            rows[i]["_shown"] = torch.tensor(shown[0])
        if progress is not None:
            progress(rows[i])

    backend = backend or InProcessBackend()
    try:
        run_groups(cells, backend, CellStore(cells_dir) if cells_dir is not None else None, on_group,
                   desc="synthetic cells")
    finally:
        backend.close()
    return rows


def run_synthetic(targets=SYNTHETIC_TARGETS, methods=SYNTHETIC_METHODS, seeds: int = 30, n: int = 1000,
                  num_steps: int = 500, progress=None, plot_dir=None, filter_kwargs: dict | None = None,
                  backend=None, threads: int | None = None, seeds_per_cell: int | None = None,
                  cells_dir=None, init: str = "cloud", init_scale: float = 1.0) -> dict:
    """Fit and score every method on every target; per-seed values and mean ± s.e.

    ``backend``, ``threads`` (per cell, default 1), ``seeds_per_cell`` (default all) and
    ``cells_dir`` (saved cells, skipped on a rerun): see :mod:`escort_rl.bench.runner`. ``init`` and
    ``init_scale``: the start of ESCORT and SVGD (:func:`fit_particles`). With
    ``plot_dir``, writes ``<target>_particles.png``: seed 0's particles of every method on the
    target's contours (first two coordinates), and ``<metric>_vs_dimension.png``.
    """
    from escort_rl.reporting.plots import plot_metric_against_dimension, plot_particles_on_target

    check_choices("--methods", methods, SYNTHETIC_METHODS)
    blocks = seed_blocks(list(range(seeds)), seeds_per_cell)
    rows, cells = [], {}
    for name in targets:
        dim = load_target(name).dim
        for method in methods:
            cells[len(rows)] = [SyntheticCell(target=name, method=method, seeds=b, particles=n, num_steps=num_steps,
                                              filter_kwargs=tuple(sorted((filter_kwargs or {}).items())),
                                              init=init, init_scale=float(init_scale), keep_particles=plot_dir is not None, threads=threads or 1)
                                for b in blocks]
            rows.append({"target": name, "dim": dim, "method": method})
    _run_grid(rows, cells, backend, cells_dir, progress)
    shown = {r["target"]: {} for r in rows}
    for r in rows:
        particles = r.pop("_shown", None)
        if particles is not None:
            shown[r["target"]][r["method"]] = particles
    if plot_dir is not None:
        for name in targets:
            plot_particles_on_target(load_target(name).log_prob, shown[name], Path(plot_dir) / f"{name}_particles.png",
                                     title=f"{name}: seed 0, N = {n}")
        for metric in ("sliced_w1", "corr_error", "mmd2"):
            plot_metric_against_dimension(rows, metric, Path(plot_dir) / f"{metric}_vs_dimension.png")
    return {"n": n, "seeds": seeds, "num_steps": num_steps, "filter_kwargs": dict(filter_kwargs or {}),
            "init": init, "init_scale": float(init_scale), "rows": rows}


def run_scaling(dims=SCALING_DIMS, structures=("block", "banded", "long_range", "sparse"),
                methods=SCALING_METHODS, seeds: int = 5, n: int = 1000, num_steps: int = 500, progress=None,
                plot_dir=None, filter_kwargs: dict | None = None, backend=None, threads: int | None = None,
                seeds_per_cell: int | None = None, cells_dir=None, init: str = "cloud",
                init_scale: float = 1.0) -> dict:
    """RMSE (and the other metrics) of the 5-mode scalability GMMs against the dimension; with
    ``plot_dir``, ``rmse_vs_dimension.png`` (averaged over the correlation structures). The runner
    arguments are those of :func:`run_synthetic`."""
    from escort_rl.reporting.plots import plot_metric_against_dimension

    blocks = seed_blocks(list(range(seeds)), seeds_per_cell)
    rows, cells = [], {}
    for d in dims:
        for structure in structures if d > 1 else structures[:1]:
            for method in methods:
                cells[len(rows)] = [SyntheticCell(target=f"scaling-{structure}-{d}d", method=method, seeds=b,
                                                  particles=n, num_steps=num_steps, dim=d, structure=structure,
                                                  filter_kwargs=tuple(sorted((filter_kwargs or {}).items())),
                                                  init=init, init_scale=float(init_scale),
                                                  threads=threads or 1) for b in blocks]
                rows.append({"dim": d, "structure": structure, "method": method})
    _run_grid(rows, cells, backend, cells_dir, progress)
    if plot_dir is not None:
        plot_metric_against_dimension(rows, "rmse", Path(plot_dir) / "rmse_vs_dimension.png",
                                      ylabel="RMSE of the mean")
        plot_metric_against_dimension(rows, "mode_coverage", Path(plot_dir) / "coverage_vs_dimension.png")
    return {"n": n, "seeds": seeds, "num_steps": num_steps, "filter_kwargs": dict(filter_kwargs or {}),
            "init": init, "init_scale": float(init_scale), "rows": rows}


def _filter_kwargs_note(result: dict) -> str:
    kw = dict(result.get("filter_kwargs") or {})
    if result.get("init", "cloud") != "cloud":
        kw["init"] = result["init"]
    if result.get("init_scale", 1.0) != 1.0:
        kw["init_scale"] = result["init_scale"]
    return (" ESCORT and SVGD settings changed from their defaults: "
            + ", ".join(f"`{k}={v}`" for k, v in kw.items()) + ".") if kw else ""


def synthetic_markdown(result: dict) -> str:
    lines = [
        "# Synthetic benchmark (paper Table 2 layout)",
        "",
        f"N = {result['n']} particles, {result['seeds']} seeds, mean ± standard error; static targets, so "
        f"ESCORT's temporal term is off. ESCORT and SVGD: {result['num_steps']} iterations from the initial "
        "cloud. SIR: importance resampling of the initial cloud. DVRL (the DVRL-style parametric fit): DVRL's "
        f"diagonal-Gaussian proposal family fitted by the importance-weighted ELBO (K = 100, {result['num_steps']} "
        "Adam steps, DReG gradients), then sampled. Oracle: N exact samples. Metrics against N "
        "fresh exact samples: MMD² (biased V-statistic, RBF γ = 0.5, squared, not its root), W1 (1-D only), "
        "sliced W1 (100 fixed seeded directions), mode coverage (τ = 1, > 0.05/K of the particles), "
        "correlation error ‖C_true − C_hat‖_F (d ≥ 2) and RMSE of the mean (‖mean − μ‖₂/√d)."
        + _filter_kwargs_note(result),
        "",
        "| target | method | MMD² | W1 | sliced W1 | mode coverage | correlation error | RMSE | seconds |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in result["rows"]:
        s = r["summary"]
        lines.append(f"| {r['target']} | {r['method']} | {format_mean_se(s['mmd2'], 4)} | {format_mean_se(s['w1'])} | "
                     f"{format_mean_se(s['sliced_w1'])} | {format_mean_se(s['mode_coverage'], 2)} | {format_mean_se(s['corr_error'])} | "
                     f"{format_mean_se(s['rmse'])} | {r['seconds']:.1f} |")
    return "\n".join(lines) + "\n"


def scaling_markdown(result: dict) -> str:
    methods = sorted({r["method"] for r in result["rows"]}, key=lambda m: SYNTHETIC_METHODS.index(m) if m in SYNTHETIC_METHODS else 99)
    lines = [
        "# Scalability: RMSE of the mean against the dimension (paper's RMSE table layout)",
        "",
        f"5-mode GMMs, N = {result['n']}, {result['seeds']} seeds, mean ± s.e., {result['num_steps']} iterations. "
        "RMSE = ‖mean − μ‖₂/√d. The NoCorr gap is ESCORT-NoCorr's RMSE minus ESCORT's.",
        "",
        "| d | structure | " + " | ".join(methods) + " | NoCorr gap |",
        "| --- | --- | " + " | ".join("---" for _ in methods) + " | --- |",
    ]
    keys = []
    for r in result["rows"]:
        if (r["dim"], r["structure"]) not in keys:
            keys.append((r["dim"], r["structure"]))
    for d, st in keys:
        by = {r["method"]: r for r in result["rows"] if (r["dim"], r["structure"]) == (d, st)}
        cells = [format_mean_se(by[m]["summary"]["rmse"]) if m in by else "—" for m in methods]
        gap = (by["escort_nocorr"]["summary"]["rmse"][0] - by["escort"]["summary"]["rmse"][0]
               if "escort" in by and "escort_nocorr" in by else float("nan"))
        lines.append(f"| {d} | {st} | " + " | ".join(cells) + f" | {gap:+.4f} |")
    return "\n".join(lines) + "\n"


def register(subparsers) -> None:
    """Add ``bench synthetic`` and ``bench scaling`` to the ``bench`` subparsers."""
    from escort_rl.bench.runner import add_runner_arguments
    from escort_rl.bench.targets import SCALABILITY_STRUCTURES

    syn = subparsers.add_parser("synthetic", help="fit the paper's GMM targets: ESCORT, NoCorr, SVGD, SIR, oracle",
                                description="Static-target benchmark (paper Table 2 layout): MMD², W1, sliced W1, "
                                "mode coverage, correlation error and RMSE, mean ± s.e. over seeds.")
    syn.add_argument("--targets", nargs="+", default=list(SYNTHETIC_TARGETS))
    syn.add_argument("--methods", nargs="+", default=list(SYNTHETIC_METHODS))
    syn.add_argument("--seeds", type=int, default=30)
    syn.add_argument("--particles", type=int, default=1000)
    syn.add_argument("--num-steps", type=int, default=500)
    syn.add_argument("--quick", action="store_true", help="smoke run: gmm1d, gmm2d, gmm3d, 2 seeds, N=100, 30 steps")
    syn.add_argument("--output", default="outputs/bench/synthetic")
    syn.set_defaults(handler=main)
    sca = subparsers.add_parser("scaling", help="RMSE of ESCORT vs ESCORT-NoCorr vs SVGD on 5-mode GMMs, 1D-200D",
                                description="The paper's RMSE-vs-dimension table, with the NoCorr gap.")
    sca.add_argument("--dims", type=int, nargs="+", default=list(SCALING_DIMS))
    sca.add_argument("--structures", nargs="+", default=list(SCALABILITY_STRUCTURES))
    sca.add_argument("--seeds", type=int, default=5)
    sca.add_argument("--particles", type=int, default=1000)
    sca.add_argument("--num-steps", type=int, default=500)
    sca.add_argument("--quick", action="store_true", help="smoke run: d 1 5, block, 2 seeds, N=100, 30 steps")
    sca.add_argument("--output", default="outputs/bench/scaling")
    sca.set_defaults(handler=main)
    for p in (syn, sca):
        p.add_argument("--bandwidth-scale", type=float, default=1.0,
                       help="multiply ESCORT's and SVGD's median-heuristic bandwidth (default 1)")
        p.add_argument("--compile", action="store_true", help="ESCORT and SVGD with compile=True")
        p.add_argument("--filter-set", nargs="+", default=None, metavar="KEY=VALUE",
                       help="other ESCORT/SVGD arguments, e.g. anneal_cycles=4 bandwidth_start=4")
        p.add_argument("--init", choices=INITS, default="cloud",
                       help="ESCORT's and SVGD's start: the initial cloud (default) or the cloud importance-"
                       "resampled to the target and spread by a Silverman kernel")
        p.add_argument("--init-scale", type=float, default=1.0,
                       help="multiply the initial cloud's spread, for every method but the oracle (default 1)")
        add_runner_arguments(p)


def filter_arguments(items) -> dict:
    """``--filter-set KEY=VALUE ...`` as ESCORT/SVGD constructor arguments, each value read as OmegaConf reads a dotlist value
    (``4`` an int, ``0.5`` a float, ``true`` a bool); a key the constructor does not take is an error
    naming it and the keys it does take, and a bad value is the constructor's error naming the key."""
    import inspect

    from omegaconf import OmegaConf

    known = [k for k in inspect.signature(ESCORTFilter.__init__).parameters if k != "self"]
    out = {}
    for key, value in parse_filter_set(items):
        if key not in known:
            raise ValueError(f"--filter-set: ESCORT has no argument '{key}'; choose from {', '.join(known)}")
        out[key] = OmegaConf.from_dotlist([f"value={value}"])["value"]
    if out:
        ESCORTFilter(**{k: v for k, v in out.items()})  # a bad value fails here, naming its key
    return out


def main(args) -> None:
    """``bench synthetic`` and ``bench scaling``."""
    from escort_rl.bench.runner import backend_from_args
    from escort_rl.bench.targets import SCALABILITY_STRUCTURES, synthetic_config
    from escort_rl.reporting.paths import write_results

    if args.bench == "synthetic":
        check_choices("--methods", args.methods, SYNTHETIC_METHODS)
        check_choices("--targets", args.targets, sorted(synthetic_config()["targets"]))
    else:
        check_choices("--structures", args.structures, SCALABILITY_STRUCTURES, "structure")
    filter_kwargs = {}
    if args.bandwidth_scale != 1.0:
        filter_kwargs["bandwidth_scale"] = args.bandwidth_scale
    if args.compile:
        filter_kwargs["compile"] = True
    filter_kwargs.update(filter_arguments(args.filter_set))

    def show(row):
        where = row.get("target") or f"d={row['dim']} {row['structure']}"
        s = row["summary"]
        print(f"{where:>18} {row['method']:>14}: MMD2 {s['mmd2'][0]:.4f} SW1 {s['sliced_w1'][0]:.3f} "
              f"cover {s['mode_coverage'][0]:.2f} corr {s['corr_error'][0]:.3f} RMSE {s['rmse'][0]:.3f} "
              f"({row['seconds']:.1f} s)", flush=True)

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    runner = dict(backend=backend_from_args(args), threads=args.threads, seeds_per_cell=args.seeds_per_cell,
                  cells_dir=out / "cells", filter_kwargs=filter_kwargs, progress=show, plot_dir=out,
                  init=args.init, init_scale=args.init_scale)
    if args.bench == "synthetic":
        kw = dict(targets=args.targets, methods=args.methods, seeds=args.seeds, n=args.particles,
                  num_steps=args.num_steps)
        if args.quick:
            kw.update(targets=["gmm1d", "gmm2d", "gmm3d"], seeds=2, n=100, num_steps=30)
        result = run_synthetic(**kw, **runner)
        md = synthetic_markdown(result)
    else:
        kw = dict(dims=args.dims, structures=args.structures, seeds=args.seeds, n=args.particles,
                  num_steps=args.num_steps)
        if args.quick:
            kw.update(dims=[1, 5], structures=["block"], seeds=2, n=100, num_steps=30)
        result = run_scaling(**kw, **runner)
        md = scaling_markdown(result)
    write_results(out, args.bench, result, md)
