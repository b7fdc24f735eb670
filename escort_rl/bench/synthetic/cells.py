"""The cells of the synthetic benchmark: one method on one target and a block of seeds, fitted (the
static protocol) or tracking (the tracking protocol), and scored.

**Static protocol.** Each method fits N particles to a fixed GMM target from a start drawn from a
start distribution ``q`` (:func:`start_distribution`):

* ``cloud``: the broad isotropic Gaussian of the config (the paper gives none); SVGD cannot move mass
  between separated modes, so from it the figures mostly report which basin each starting particle
  fell in;
* ``overlap``: the target's own components with their spread doubled, at the target's weights, so
  that every mode starts with its share and the figures measure the fit within the modes;
* ``resampled`` (ESCORT and SVGD only; the others start from ``cloud``): the cloud importance-resampled
  to the target and spread by a Silverman kernel (:func:`initial_particles`).

Rows: ESCORT, ESCORT-NoCorr, SVGD (:meth:`ESCORTFilter.fit`; no time axis, so F_temp is off), SIR
(systematic importance resampling of the start by ``p/q``), a DVRL-style parametric fit
(:mod:`escort_rl.bench.parametric`) and an oracle of N exact samples. Every metric compares the
particles with a fresh set of N exact samples (:func:`score_particles`).

**Tracking protocol** (:mod:`escort_rl.bench.synthetic.tracking`): the target's mixture is the noise
of an observed random walk, and each filter's error is taken against the true state over ``T`` steps.

The random streams depend only on a cell's fields (the start, the oracle and the reference samples on
each seed; the filters' noise on the cell's first seed), so every backend gives the same numbers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from escort_rl import metrics
from escort_rl.belief.prior import silverman_factor
from escort_rl.belief.resampling import effective_sample_size, systematic
from escort_rl.bench.core.runner import Cell
from escort_rl.bench.targets import (
    GaussianMixture,
    initial_distribution,
    load_target,
    scalability_initial,
    scalability_target,
)
from escort_rl.config import registry

INITS = ("cloud", "overlap", "resampled")
"""The starts of the static protocol (:func:`start_distribution`, :func:`initial_particles`)."""
OVERLAP_SPREAD = 2.0
"""The ``overlap`` start: the target's components with their standard deviations times this."""
TRACKING_METHODS = ("escort", "escort_nocorr", "svgd", "sir")
"""The rows of the tracking protocol: the filters (no oracle: the exact posterior is not at hand)."""


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


def start_distribution(target: GaussianMixture, cloud: GaussianMixture, init: str,
                       scale: float = 1.0) -> GaussianMixture:
    """The distribution ``q`` the starting particles are drawn from: the broad ``cloud`` (``init`` is
    ``cloud`` or ``resampled``) or, for ``overlap``, the target's components at its weights with
    their spread times :data:`OVERLAP_SPREAD`; either spread times ``scale``."""
    if init not in INITS:
        raise ValueError(f"init: expected one of {', '.join(INITS)}, got {init!r}")
    if init == "overlap":
        return scaled(GaussianMixture(target.weights, target.means, target.covariances * OVERLAP_SPREAD ** 2,
                                      name=f"{target.name}/overlap"), scale)
    return scaled(cloud, scale)


def initial_particles(x0: torch.Tensor, target: GaussianMixture, initial: GaussianMixture, init: str,
                      generator: torch.Generator) -> torch.Tensor:
    r"""Where ESCORT and SVGD start, from particles ``x0`` ``[S, n, d]`` drawn from ``initial`` (q).

    * ``cloud`` and ``overlap``: ``x0`` itself.
    * ``resampled``: ``x0`` resampled systematically by the importance weights ``p/q`` (so the modes
      start with about their target mass, which SVGD cannot move between modes later), then each copy
      moved by ``N(0, h² diag(σ̂²))``, the regularised particle filter's kernel: σ̂² the per-dimension
      variance of the resampled set and ``h = (4 / (n (d + 2)))^{1/(d+4)}`` (Silverman). The kernel
      separates the copies, which SVGD's repulsion could not (the kernel's gradient vanishes between
      equal points). Where the weights degenerate (high ``d``), most copies share a few ancestors.
    """
    if init not in INITS:
        raise ValueError(f"init: expected one of {', '.join(INITS)}, got {init!r}")
    if init != "resampled":
        return x0
    log_w = (target.log_prob(x0) - initial.log_prob(x0)).to(torch.float64)
    idx = systematic(log_w, generator)
    x = torch.gather(x0, -2, idx.unsqueeze(-1).expand_as(x0))
    h = silverman_factor(x.shape[-2], x.shape[-1])
    std = x.std(-2, keepdim=True).clamp_min(1e-6)
    return x + h * std * torch.randn(x.shape, generator=generator, dtype=x.dtype)


ROW_FILTERS: dict[str, tuple[str, dict, tuple[str, ...]]] = {
    "escort": ("escort", {}, ()),
    "escort_nocorr": ("escort", {"lambda_corr": 0.0}, ("lambda_corr",)),
    "svgd": ("svgd", {}, ("lambda_corr", "lambda_temp")),
    "sir": ("sir", {}, None),
}
"""Each filter row: the registered filter family (``filter.kind``), the row's own settings, and the
keys of a sweep's ``filter_kwargs`` it ignores (``None``: all of them)."""


def row_filter(method: str, filter_kwargs: dict | None = None):
    """The filter of row ``method`` (:data:`ROW_FILTERS`). ``filter_kwargs`` go to the ESCORT and SVGD
    constructors; the row's own settings win: ESCORT-NoCorr keeps ``lambda_corr = 0`` and SVGD both
    ``λ = 0`` (a sweep of ``lambda_corr`` moves ESCORT alone). SIR takes none."""
    if method not in ROW_FILTERS:
        raise ValueError(f"method: expected one of {', '.join(ROW_FILTERS)}, got {method!r}")
    kind, own, ignored = ROW_FILTERS[method]
    kw = {} if ignored is None else {k: v for k, v in (filter_kwargs or {}).items() if k not in ignored}
    return registry.resolve("filter", kind)(**{**kw, **own})


def fit_particles(method: str, target: GaussianMixture, initial: GaussianMixture, seeds: list[int], n: int,
                  num_steps: int, filter_kwargs: dict | None = None, init: str = "cloud",
                  init_scale: float = 1.0) -> tuple[torch.Tensor, float, dict]:
    """Particles ``[S, n, d]`` of ``method`` for each seed, the wall-clock seconds it took, and the
    importance weights it formed: ``{"ess_fraction": [per seed]}`` for SIR and the ``resampled`` start
    (ESS/N of ``p/q``), ESCORT's :meth:`~escort_rl.belief.base.BeliefFilter.importance_diagnostics`
    (its correlation projections' target samples), ``{}`` otherwise.

    ``initial`` is the broad cloud; the start is :func:`start_distribution` of ``init`` and
    ``init_scale``, which SIR and the DVRL fit use as well."""
    start = start_distribution(target, initial, init, init_scale)
    x0 = _sample_batch(start, seeds, n, offset=0)
    importance: dict = {}
    t0 = time.perf_counter()
    if method == "oracle":
        x = _sample_batch(target, seeds, n, offset=10_000)
    elif method == "dvrl":
        from escort_rl.bench.parametric import fit_parametric

        cov = start.covariance()
        x = fit_parametric(lambda z: target.log_prob(z), target.dim, seeds, n, num_steps=num_steps,
                           init_mean=float(start.mean().mean()),
                           init_std=float(torch.diagonal(cov).mean()) ** 0.5)
    elif method == "sir":
        log_w = (target.log_prob(x0) - start.log_prob(x0)).to(torch.float64)
        importance = {"ess_fraction": (effective_sample_size(log_w) / n).tolist()}
        g = torch.Generator().manual_seed(seeds[0])
        idx = systematic(log_w, g)
        x = torch.gather(x0, -2, idx.unsqueeze(-1).expand_as(x0))
    else:
        filt = row_filter(method, filter_kwargs)
        g = torch.Generator().manual_seed(seeds[0])
        if init == "resampled":
            log_w = (target.log_prob(x0) - start.log_prob(x0)).to(torch.float64)
            importance["start_ess_fraction"] = (effective_sample_size(log_w) / n).tolist()
        x0 = initial_particles(x0, target, start, init, g)
        # the start's density, for the projections' weights p/q; a resampled start samples the target
        proposal = target.log_prob if init == "resampled" else start.log_prob
        x = filt.fit(lambda z: target.log_prob(z), x0, num_steps=num_steps, generator=g,
                     proposal_log_prob=lambda z: proposal(z).to(z.dtype))
        importance.update(filt.importance_diagnostics())
    return x, time.perf_counter() - t0, importance


def score_particles(x: torch.Tensor, target: GaussianMixture, seeds: list[int], num_projections: int = 100) -> dict:
    """Per-seed metrics of particles ``[S, N, d]`` against fresh exact samples of the target:
    ``mmd2``, ``w1`` (1-D), ``sliced_w1``, ``mode_coverage`` (Mahalanobis, valid at every dimension),
    ``mode_coverage_ball`` (the paper's τ = 1 ball), ``corr_error`` and ``rmse`` (``‖x̄ − μ‖₂``, the
    paper's units)."""
    n, d = x.shape[-2], x.shape[-1]
    ref = _sample_batch(target, seeds, n, offset=20_000).to(torch.float64)
    x = x.to(torch.float64)
    c_true = target.correlation()
    keys = ("mmd2", "w1", "sliced_w1", "mode_coverage", "mode_coverage_ball", "corr_error", "rmse")
    out: dict[str, list[float]] = {k: [] for k in keys}
    proj = metrics.sphere_directions(num_projections, d, torch.Generator().manual_seed(12345)).to(torch.float64)
    coverage = metrics.mode_coverage_mahalanobis(x, target.means, target.covariances)
    for s in range(x.shape[0]):
        out["mmd2"].append(float(metrics.mmd_squared(x[s], ref[s], gamma=0.5)))
        out["w1"].append(float(metrics.wasserstein_1d(x[s, :, 0], ref[s, :, 0])) if d == 1 else float("nan"))
        out["sliced_w1"].append(float(metrics.sliced_wasserstein(x[s], ref[s], projections=proj)))
        out["mode_coverage"].append(float(coverage[s]))
        out["mode_coverage_ball"].append(float(metrics.mode_coverage(x[s], target.means)))
        out["corr_error"].append(float(metrics.correlation_error(c_true, x[s])) if d > 1 else float("nan"))
        out["rmse"].append(float(metrics.rmse_of_mean(x[s], target.mean(), per_coordinate=False)))
    return out


@dataclass(frozen=True)
class _TargetCell(Cell):
    """The fields every synthetic cell has: a named GMM of ``configs/bench/synthetic.yaml``
    (``target``), or, with ``structure``, the 5-mode scalability GMM of dimension ``dim``."""

    target: str
    method: str
    seeds: tuple
    particles: int
    num_steps: int
    filter_kwargs: tuple = ()
    dim: int | None = None
    structure: str | None = None

    def distributions(self) -> tuple[GaussianMixture, GaussianMixture]:
        """The target and the broad initial cloud's distribution."""
        if self.structure is None:
            return load_target(self.target), initial_distribution(self.target)
        return scalability_target(self.dim, self.structure, 0), scalability_initial(self.dim)


@dataclass(frozen=True)
class SyntheticCell(_TargetCell):
    """One method fitted to one static target on ``seeds`` (one batch ``[S, N, d]``) and scored.
    ``init``/``init_scale``: the start (:func:`fit_particles`). With ``keep_particles`` the result also
    holds seed 0's particles (for the figures).

    Examples:
        >>> cell = SyntheticCell(target="gmm1d", method="oracle", seeds=(0, 1), particles=20, num_steps=1)
        >>> sorted(cell.run()["per_seed"])
        ['corr_error', 'mmd2', 'mode_coverage', 'mode_coverage_ball', 'rmse', 'sliced_w1', 'w1']
    """

    init: str = "cloud"
    init_scale: float = 1.0
    keep_particles: bool = False

    def key(self) -> str:
        start = "" if self.init == "cloud" else f"{self.init}-"
        return (f"synthetic/{self.target}/{self.method}/{start}N{self.particles}-K{self.num_steps}-"
                f"seeds{self.seeds[0]}-{self.seeds[-1]}")

    def run(self) -> dict:
        target, initial = self.distributions()
        seeds = list(self.seeds)
        x, seconds, importance = fit_particles(self.method, target, initial, seeds, self.particles, self.num_steps,
                                               dict(self.filter_kwargs), self.init, self.init_scale)
        out = {"per_seed": score_particles(x, target, seeds), "timing": {"seconds": seconds},
               "importance": importance}
        if self.keep_particles and 0 in seeds:
            out["seed0_particles"] = x[seeds.index(0)].tolist()
        return out


@dataclass(frozen=True)
class TrackingCell(_TargetCell):
    """One filter tracking the random walk observed through the target's mixture
    (:class:`~escort_rl.bench.synthetic.tracking.GMMTracking`) for ``steps`` updates of ``num_steps``
    iterations each, on ``seeds`` at once; the error against the true state
    (:func:`~escort_rl.bench.synthetic.tracking.track`).

    Examples:
        >>> cell = TrackingCell(target="gmm2d", method="sir", seeds=(0, 1), particles=50, num_steps=1, steps=3)
        >>> sorted(cell.run()["per_seed"])
        ['final_error', 'rmse']
    """

    steps: int = 10

    def key(self) -> str:
        return (f"tracking/{self.target}/{self.method}/N{self.particles}-K{self.num_steps}-T{self.steps}-"
                f"seeds{self.seeds[0]}-{self.seeds[-1]}")

    def run(self) -> dict:
        from escort_rl.bench.synthetic.tracking import GMMTracking, track

        if self.method not in TRACKING_METHODS:
            raise ValueError(f"method: the tracking protocol runs {', '.join(TRACKING_METHODS)}, got {self.method!r}")
        target, _ = self.distributions()
        kw = dict(self.filter_kwargs)
        if self.method != "sir":
            kw["num_steps"] = self.num_steps
        filt = row_filter(self.method, kw)
        t0 = time.perf_counter()
        result = track(filt, GMMTracking(target), list(self.seeds), self.particles, self.steps)
        importance = result.pop("importance")
        return {"per_seed": result, "timing": {"seconds": time.perf_counter() - t0}, "importance": importance}
