"""Protocol (a)'s reference posterior, and each belief's distance to it.

**The reference** is a bootstrap particle filter with many particles (the domain benchmark's
``--reference-particles``, default 10⁵): propagate through the model's transition, weight by its
observation likelihood, resample systematically when ESS/N < 0.5, no roughening. It filters the
same shared trajectories as the methods, from its own draw of the same prior, and converges to the
exact filtering posterior as N grows. The benchmark checks that: it runs the reference again at 2N
and reports (i) the distance between the two references (the floor under every figure) and (ii) how
much each method's figures move when the 2N reference replaces the N one.

:func:`reference_posterior` filters a block of seeds in chunks of at most :data:`CHUNK_ROWS` particle
rows (seeds × N), so memory stays bounded whatever N. For every seed, step ``t = 0..T`` and part of
the state (``position``: the model's ``position_dims``; ``velocity``: its ``velocity_dims``) it keeps

- the weighted mean and covariance of all N particles;
- ``sample`` particles drawn from them by systematic resampling (uniform weights), for the
  sample-based distances;
- the MMD bandwidth ``γ = 1 / (2 med²)``, ``med`` the median pairwise distance of that subsample
  (the median heuristic), and the subsample's kernel mean ``(1/M²) Σ_ij k(y_i, y_j)``;
- :data:`PROJECTIONS` unit directions per part, seeded by the domain and the part alone, so every
  reference of a domain slices along the same directions.

The benchmark's reference cell writes them to a tensor file and records a hash of its tensors
(:func:`content_hash`); :meth:`Reference.load` recomputes that hash, so a damaged or replaced file is
detected, not read.

**The distances** (:meth:`Reference.compare`) of a belief (particles ``x``, weights ``w``) at step
``t``, per part:

- ``w1``: sliced W1 along the reference's directions
  (:func:`~escort_rl.metrics.distances.weighted_sliced_wasserstein`);
- ``mmd2``: MMD² with the reference's γ (the biased V-statistic, weighted);
- ``mean``: ``‖E_b[s_part] − E_ref[s_part]‖₂``;
- ``cov``: ``‖Cov_b[s_part] − Cov_ref[s_part]‖_F`` (weighted, normalised by Σw = 1, as the reference's).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch
from torch import Tensor

from escort_rl.belief.resample_move import ResampleMoveFilter
from escort_rl.belief.resampling import effective_sample_size, systematic
from escort_rl.belief.seeding import derived_seed, initial_beliefs, tensor_hash
from escort_rl.belief.sir import SIRFilter
from escort_rl.metrics.distances import kernel_mean, median_gamma, sphere_directions, weighted_sliced_wasserstein
from escort_rl.metrics.moments import weighted_moments
from escort_rl.metrics.rao_blackwell import RaoBlackwellisedSMC

CHUNK_ROWS = 400_000
"""Particle rows (seeds × N) a reference filters at once: 10⁵ particles go 4 seeds at a time. Multi-Target
Tracking's exact likelihood (a mixture over zones and identity swaps) peaks at about 16 KB per row,
so 10⁶ rows took 15.6 GB; 4·10⁵ keeps two references side by side within 16 GB."""
SAMPLE = 500
"""Reference particles kept per step for the sample-based distances (W1, MMD²)."""
PROJECTIONS = 50
"""Directions of the sliced W1, per part."""
METRICS = ("w1", "mmd2", "mean", "cov")
METRIC_LABELS = {"w1": "sliced W1", "mmd2": "MMD²", "mean": "‖mean − mean_ref‖₂", "cov": "‖cov − cov_ref‖_F"}
THIN_SEED = 7_777
"""Seed (plus the step) of the systematic draws that thin a belief larger than M for MMD²."""
COMPARE_ROWS = 40_000_000
"""Kernel entries (seeds × N × max(N, M)) one chunk of :meth:`Reference.compare` may hold."""


def state_parts(model) -> dict[str, tuple[int, ...]]:
    """The model's own ``state_parts`` where it declares them (e.g. the hidden goal's ``goal`` before its
    ``position``), else ``{"position": dims, "velocity": dims}`` (a part with no dims is left out)."""
    from escort_rl.models import position_dims, velocity_dims

    declared = getattr(model, "state_parts", None)
    if isinstance(declared, dict) and declared:
        return {str(k): tuple(int(i) for i in v) for k, v in declared.items()}

    parts = {"position": position_dims(model), "velocity": velocity_dims(model)}
    return {k: v for k, v in parts.items() if v}


def content_hash(data: dict) -> str:
    """SHA-256 (16 hex digits) of every tensor in ``data`` (nested dicts), in key order, with shapes
    and dtypes: the same tensors give the same hash whatever the file's bytes."""
    h = hashlib.sha256()

    def walk(d, prefix=""):
        for k in sorted(d):
            v = d[k]
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}/")
            elif isinstance(v, Tensor):
                h.update(f"{prefix}{k}:{tensor_hash(v)}".encode())
            else:
                h.update(f"{prefix}{k}={v!r}".encode())

    walk(data)
    return h.hexdigest()[:16]


def step_summary(particles: Tensor, log_w: Tensor, parts: dict, sample: int, generator) -> dict:
    """One step of the reference: per part ``mean`` ``[B, dp]``, ``cov`` ``[B, dp, dp]``, ``sample``
    ``[B, M, dp]``, ``gamma`` ``[B]`` and ``kyy`` ``[B]``; and ``ess`` ``[B]``, the effective sample size of
    the weights after the update (and its resampling, when ESS/N fell below 0.5)."""
    w = torch.softmax(log_w.double(), -1)
    idx = systematic(log_w.double(), generator, sample)
    out = {"ess": effective_sample_size(log_w.double())}
    for name, dims in parts.items():
        x = particles[..., list(dims)]
        mean, cov = weighted_moments(x, w)
        out[name] = part_summary(mean, cov, x.gather(-2, idx[..., None].expand(*idx.shape, len(dims))).float())
    return out


def part_summary(mean: Tensor, cov: Tensor, y: Tensor) -> dict:
    """One part of one step of a reference: its ``mean`` ``[B, dp]`` and ``cov`` ``[B, dp, dp]``, the
    equally weighted ``sample`` ``y`` ``[B, M, dp]`` the sample-based distances use, its median-heuristic
    ``gamma`` ``[B]`` and kernel mean ``kyy`` ``[B]``."""
    gamma = median_gamma(y)
    return {"mean": mean.float(), "cov": cov.float(), "sample": y, "gamma": gamma.float(),
            "kyy": kernel_mean(y, y, gamma).float()}


def has_exact_posterior(model) -> bool:
    """Whether ``model`` gives its exact filtering posterior, in one of two forms:

    - **Kalman**: a Gaussian prior ``m0``, ``P0`` and ``kalman_step(mean, cov, action, observation)
      -> (mean, cov)`` (``LinearGaussian``);
    - **Gaussian sum**: ``exact_posterior_init(batch) -> (log_w, means, covs)`` and
      ``exact_posterior_step(log_w, means, covs, action, observation) -> (log_w, means, covs,
      dropped)``, ``log_w`` ``[B, M]``, ``means`` ``[B, M, d]``, ``covs`` ``[B, M, d, d]``, ``dropped``
      ``[B]`` the mass a pruned sum cut away (the synthetic benchmark's ``GMMTracking``).

    A user's model may define either."""
    kalman = callable(getattr(model, "kalman_step", None)) and hasattr(model, "m0") and hasattr(model, "P0")
    mixture = callable(getattr(model, "exact_posterior_init", None)) and callable(
        getattr(model, "exact_posterior_step", None))
    return kalman or mixture


def exact_posterior_start(model, b: int):
    """The exact posterior's prior as a Gaussian sum ``(log_w [B, M], means [B, M, d], covs [B, M, d, d])``,
    float64, whichever form the model gives (:func:`has_exact_posterior`; Kalman: ``M = 1``)."""
    if callable(getattr(model, "exact_posterior_init", None)):
        return model.exact_posterior_init(b)
    d = model.state_dim
    return (torch.zeros(b, 1, dtype=torch.float64), model.m0.double().expand(b, 1, d),
            model.P0.double().expand(b, 1, d, d))


def exact_posterior_update(model, log_w, means, covs, a, o):
    """One exact update of a Gaussian sum ``(log_w, means, covs)`` -> the same and ``dropped`` ``[B]``,
    the mass a pruned sum cut (0 for Kalman)."""
    if callable(getattr(model, "exact_posterior_step", None)):
        log_w, means, covs, dropped = model.exact_posterior_step(log_w, means, covs, a, o)
        return log_w.double(), means.double(), covs.double(), dropped.double()
    mean, cov = model.kalman_step(means[:, 0], covs[:, 0], a, o)
    return log_w, mean.unsqueeze(1), cov.unsqueeze(1), torch.zeros(log_w.shape[0], dtype=torch.float64)


def _exact_steps(model, traj: dict, b: int):
    """The exact posterior at ``t = 0..T`` as Gaussian sums ``(log_w, means, covs, dropped)``."""
    log_w, means, covs = exact_posterior_start(model, b)
    yield log_w, means, covs, torch.zeros(b, dtype=torch.float64)
    for t in range(traj["actions"].shape[1]):
        log_w, means, covs, dropped = exact_posterior_update(model, log_w, means, covs, traj["actions"][:, t],
                                                             traj["observations"][:, t])
        yield log_w, means, covs, dropped


def exact_reference(model, traj: dict, seeds: list[int], sample: int = SAMPLE, base_seed: int = 0,
                    name: str = "") -> dict:
    """The exact posterior of a model with one (:func:`has_exact_posterior`) on the shared trajectories,
    in the format of :func:`reference_posterior`: per part the exact ``mean`` and ``cov`` at every step
    ``t = 0..T`` (of the Gaussian sum: ``Σ w_j m_j`` and ``Σ w_j (C_j + m_j m_jᵀ) − m mᵀ``), and
    ``sample`` exact draws (a component by its weight, then its Gaussian; seeded by the first seed);
    ``ess`` is NaN (no weights) and ``dropped_mass`` ``[S, T+1]`` the mass a pruned sum cut at each step
    (0 for Kalman)."""
    parts = state_parts(model)
    b = len(seeds)
    g = torch.Generator().manual_seed(derived_seed("exact-reference-sample", base_seed, seeds[0]))
    steps = []
    for log_w, means, covs, dropped in _exact_steps(model, traj, b):
        w = torch.softmax(log_w, -1)  # [B, M]
        comp = torch.multinomial(w, sample, replacement=True, generator=g) if w.shape[1] > 1 \
            else torch.zeros(b, sample, dtype=torch.long)
        step = {"ess": torch.full((b,), float("nan"), dtype=torch.float64), "dropped_mass": dropped}
        for part, dims in parts.items():
            idx = list(dims)
            mj, cj = means[..., idx], covs[..., idx, :][..., idx]  # [B, M, p], [B, M, p, p]
            m = (w.unsqueeze(-1) * mj).sum(1)
            second = (w[..., None, None] * (cj + mj.unsqueeze(-1) * mj.unsqueeze(-2))).sum(1)
            c = second - m.unsqueeze(-1) * m.unsqueeze(-2)
            tril = torch.linalg.cholesky(0.5 * (cj + cj.transpose(-1, -2)))  # [B, M, p, p]
            pick = lambda x: x.gather(1, comp.reshape(b, sample, *([1] * (x.dim() - 2))).expand(  # noqa: E731
                b, sample, *x.shape[2:]))
            z = torch.randn(b, sample, len(idx), generator=g, dtype=torch.float64)
            draws = pick(mj) + (pick(tril) @ z.unsqueeze(-1)).squeeze(-1)
            step[part] = part_summary(m, 0.5 * (c + c.transpose(-1, -2)), draws.float())
        steps.append(step)
    out = _stack(steps)
    for part, dims in parts.items():
        gp = torch.Generator().manual_seed(derived_seed(f"reference-projections/{name}/{part}", 0, 0))
        out[part]["projections"] = sphere_directions(PROJECTIONS, len(dims), gp, dtype=torch.float32)
        out[part]["dims"] = torch.tensor(dims, dtype=torch.int64)
    return out


COMPILE_ROWS = 200_000
"""From this many particle rows in a chunk, the model's transition and likelihood run compiled."""


class _CompiledModel:
    """``model`` with ``transition`` and ``observation_log_prob`` compiled by ``torch.compile`` (one
    graph per chunk shape): 2.7× and 3× faster on Multi-Target Tracking at 2 × 10⁵ rows, the same
    values to float rounding. Every other attribute is the model's."""

    def __init__(self, model) -> None:
        self._model = model
        self.transition = torch.compile(model.transition, dynamic=False)
        self.observation_log_prob = torch.compile(model.observation_log_prob, dynamic=False)

    def __getattr__(self, name):
        return getattr(self._model, name)


def _stack(steps: list[dict]) -> dict:
    """Per-step summaries (:func:`step_summary`) -> the same keys with a time dim after the seeds."""
    first = steps[0]
    return {k: (_stack([s[k] for s in steps]) if isinstance(v, dict) else torch.stack([s[k] for s in steps], 1))
            for k, v in first.items()}


REFERENCE_FILTERS = {"sir": lambda: SIRFilter(resample_threshold=0.5), "resample_move": lambda: ResampleMoveFilter()}
"""The filters a reference posterior may run: name -> a new filter."""

RAO_BLACKWELL = "rao_blackwell"
"""The reference that samples only part of the state (:mod:`escort_rl.metrics.rao_blackwell`), for a model
that gives the rest in closed form."""

REFERENCE_METHODS = (*REFERENCE_FILTERS, RAO_BLACKWELL)
"""Every reference a ``--reference-filter`` may name."""

REFERENCE_NAMES = {"sir": "SIR", "resample_move": "resample-move SMC (tempered, with MCMC moves)",
                   RAO_BLACKWELL: "Rao-Blackwellised SMC (part of the state sampled, the rest a Gaussian sum in "
                                  "closed form)"}
"""What each reference filter is called in a report."""


def _update_mean(now: dict, seen: dict, key: str, rows: int) -> float:
    """The mean over the ``rows`` beliefs of one update of the running mean ``key`` of
    :meth:`~escort_rl.belief.base.BeliefFilter.importance_diagnostics`, from its values after (``now``)
    and before (``seen``) the update."""
    return (now[key] * now["count"] - (seen[key] * seen["count"] if seen else 0.0)) / rows


def reference_posterior(model, traj: dict, seeds: list[int], particles: int, base_seed: int = 0,
                        sample: int = SAMPLE, chunk_rows: int = CHUNK_ROWS, name: str = "",
                        replicate: int = 0, method: str = "sir") -> dict:
    """The reference of ``seeds`` on the shared trajectories ``traj`` (see the module docstring).

    Returns per part ``mean`` ``[S, T+1, dp]``, ``cov`` ``[S, T+1, dp, dp]``, ``sample``
    ``[S, T+1, M, dp]``, ``gamma``/``kyy`` ``[S, T+1]``, ``dims`` and ``projections`` ``[L, dp]``;
    ``ess`` ``[S, T+1]`` (after each update's resampling) and ``ess_fraction_before_resampling``
    ``[S, T]`` (ESS / N of each update's weights before it resamples or tempers; the mean over the seeds of
    a chunk, repeated for each); a tempered reference adds ``ess_fraction_of_stages`` ``[S, T]``, the same
    mean of the smallest ESS / N among the weights its stages resampled. Chunks of seeds (at most
    ``chunk_rows // particles`` each) filter one
    after another, each with its own generators seeded by its first seed. ``name`` (the domain's)
    seeds the directions of the sliced W1. A chunk of at least :data:`COMPILE_ROWS` rows runs the
    model compiled. ``replicate = r > 0`` draws an independent reference (its prior draw, its filter's and
    its subsample's random streams are the ``r``-th), on the same trajectories and directions: the distance
    between two replicates measures the reference's own error. ``method``: the reference's filter, one of
    :data:`REFERENCE_METHODS` (``sir``: SIR resampling at ESS/N < 0.5; ``resample_move``: resample-move SMC
    with adaptive tempering, whose weights do not collapse onto a few particles when the likelihood is sharp;
    ``rao_blackwell``: particles on part of the state and the rest in closed form, for a model that gives
    that form, :mod:`escort_rl.metrics.rao_blackwell`).
    """

    parts = state_parts(model)
    if method not in REFERENCE_METHODS:
        raise ValueError(f"--reference-filter: unknown reference filter '{method}'; choose from "
                         f"{', '.join(REFERENCE_METHODS)}")
    rao_blackwell = method == RAO_BLACKWELL
    if rao_blackwell:
        RaoBlackwellisedSMC.check(model)
    per_chunk = max(1, int(chunk_rows) // int(particles))
    if not rao_blackwell and min(per_chunk, len(seeds)) * int(particles) >= COMPILE_ROWS:
        model = _CompiledModel(model)
    chunks = []
    for lo in range(0, len(seeds), per_chunk):
        block = list(seeds[lo:lo + per_chunk])
        run = _rao_blackwellised_chunk if rao_blackwell else _filter_chunk
        chunks.append(run(model, traj, slice(lo, lo + len(block)), block, particles, base_seed, sample, name,
                          replicate, method, parts))
    out = {k: (torch.cat([c[k] for c in chunks]) if not isinstance(v, dict)
               else {kk: torch.cat([c[k][kk] for c in chunks]) for kk in v}) for k, v in chunks[0].items()}
    for part, dims in parts.items():
        g = torch.Generator().manual_seed(derived_seed(f"reference-projections/{name}/{part}", 0, 0))
        out[part]["projections"] = sphere_directions(PROJECTIONS, len(dims), g, dtype=torch.float32)
        out[part]["dims"] = torch.tensor(dims, dtype=torch.int64)
    return out


def _filter_chunk(model, traj: dict, rows: slice, block: list[int], particles: int, base_seed: int, sample: int,
                  name: str, replicate: int, method: str, parts: dict) -> dict:
    """:func:`reference_posterior` of the seeds ``block`` (rows ``rows`` of ``traj``) by a filter of
    :data:`REFERENCE_FILTERS`."""
    filt = REFERENCE_FILTERS[method]()
    tag = f"/{int(replicate)}" if replicate else ""
    belief, _ = initial_beliefs(filt, model, block, particles, base_seed, kind=f"reference-belief{tag}")
    g = torch.Generator().manual_seed(derived_seed(f"reference-filter{tag}", base_seed, block[0]))
    gs = torch.Generator().manual_seed(derived_seed(f"reference-sample{tag}", base_seed, block[0]))
    steps = [step_summary(belief.particles, belief.log_weights, parts, sample, gs)]
    before, staged = [], []  # per update, the mean over the chunk of the ESS fractions (see the docstring)
    for t in range(traj["actions"].shape[1]):
        seen = filt.importance_diagnostics()
        belief = filt.update(model, belief, traj["actions"][rows, t], traj["observations"][rows, t], g)
        now = filt.importance_diagnostics()
        before.append(_update_mean(now, seen, "mean_ess_fraction", len(block)))
        if "mean_stage_ess_fraction" in now:
            staged.append(_update_mean(now, seen, "mean_stage_ess_fraction", len(block)))
        if not bool(torch.isfinite(belief.particles).all()) or bool(torch.isnan(belief.log_weights).any()):
            raise ValueError(f"the reference posterior of '{name}' became non-finite at step {t + 1} "
                             f"(seeds {block}); its particles are not usable")
        steps.append(step_summary(belief.particles, belief.log_weights, parts, sample, gs))
    chunk = _stack(steps)
    chunk["ess_fraction_before_resampling"] = torch.tensor(before, dtype=torch.float64).expand(len(block), -1)
    if staged:
        chunk["ess_fraction_of_stages"] = torch.tensor(staged, dtype=torch.float64).expand(len(block), -1)
    return chunk


def _rao_blackwellised_chunk(model, traj: dict, rows: slice, block: list[int], particles: int, base_seed: int,
                             sample: int, name: str, replicate: int, method: str, parts: dict) -> dict:
    """:func:`reference_posterior` of the seeds ``block`` by :class:`~escort_rl.metrics.rao_blackwell.
    RaoBlackwellisedSMC`: per part the mixture's exact moments given the particles, and ``sample`` draws of it."""
    filt = RaoBlackwellisedSMC()
    tag = f"/{int(replicate)}" if replicate else ""
    g = torch.Generator().manual_seed(derived_seed(f"reference-belief{tag}", base_seed, block[0]))
    gs = torch.Generator().manual_seed(derived_seed(f"reference-sample{tag}", base_seed, block[0]))
    belief = filt.init(model, len(block), particles, g)

    def summary() -> dict:
        mean, cov = filt.moments(model, belief)
        y = filt.draws(model, belief, sample, gs)
        out = {"ess": effective_sample_size(belief.log_weights)}
        for part, dims in parts.items():
            idx = list(dims)
            out[part] = part_summary(mean[..., idx], cov[..., idx, :][..., idx], y[..., idx].float())
        return out

    steps, before = [summary()], []
    for t in range(traj["actions"].shape[1]):
        belief = filt.update(model, belief, traj["actions"][rows, t], traj["observations"][rows, t], g)
        before.append(float(filt.last_ess_fraction.mean()))
        if not bool(torch.isfinite(belief.x).all()) or bool(torch.isnan(belief.log_weights).any()):
            raise ValueError(f"the reference posterior of '{name}' became non-finite at step {t + 1} "
                             f"(seeds {block}); its particles are not usable")
        steps.append(summary())
    chunk = _stack(steps)
    chunk["ess_fraction_before_resampling"] = torch.tensor(before, dtype=torch.float64).expand(len(block), -1)
    return chunk


class DamagedReferenceError(ValueError):
    """A reference file is missing, unreadable or not the one its cell wrote."""


class Reference:
    """A reference posterior loaded from a :class:`ReferenceCell`'s file, for :meth:`compare`."""

    def __init__(self, data: dict) -> None:
        self.data = data
        self.parts = {k: v for k, v in data.items() if isinstance(v, dict)}

    @classmethod
    def load(cls, path: Path, expected_hash: str) -> "Reference":
        """Load ``path`` and check its tensors against ``expected_hash``; raises
        :class:`DamagedReferenceError` naming the file and the fix otherwise."""
        fix = "delete it and the cell's .json beside it under cells/reference/, and rerun the command"
        try:
            data = torch.load(path, weights_only=True)
        except Exception as err:  # a truncated or foreign file: torch raises several types
            raise DamagedReferenceError(f"reference file {path}: unreadable ({type(err).__name__}); {fix}") from None
        if not isinstance(data, dict) or content_hash(data) != expected_hash:
            raise DamagedReferenceError(f"reference file {path}: its contents do not match the hash its cell "
                                        f"recorded ({expected_hash}); {fix}")
        return cls(data)

    def compare(self, particles: Tensor, log_weights: Tensor, t: int, rows: slice | None = None) -> dict:
        """The distances of the belief ``particles`` ``[S, N, d]`` / ``log_weights`` ``[S, N]`` to the
        reference at step ``t`` (of the seeds ``rows`` of the file; default all). Returns
        ``{"<part>/<metric>": [S]}`` for the parts and :data:`METRICS`.

        The mean, covariance and sliced W1 use the whole weighted belief. MMD² does too up to the
        reference's sample size M; a larger belief enters it as M systematic draws from its weights
        (seeded by ``t``, so every backend draws the same), which bounds the cost at M² kernel
        entries per seed and part, as for the reference itself, and adds the same O(1/M) bias as
        the reference's own subsample (the floor of :meth:`compare_reference` has it too)."""
        rows = rows if rows is not None else slice(None)
        w = torch.softmax(log_weights.double(), -1)
        out = {}
        s, n = particles.shape[0], particles.shape[-2]
        m = next(iter(self.parts.values()))["sample"].shape[-2]
        thin = None
        if n > m:  # MMD² of a large belief on m systematic draws (same draws for every part)
            thin = systematic(log_weights.double(), torch.Generator().manual_seed(THIN_SEED + t), m)
        for name, ref in self.parts.items():
            x = particles[..., ref["dims"].tolist()]
            y = ref["sample"][rows, t].to(x.dtype)
            gamma = ref["gamma"][rows, t].to(x.dtype)
            mean, cov = weighted_moments(x, w)
            out[f"{name}/mean"] = (mean - ref["mean"][rows, t].double()).norm(dim=-1)
            out[f"{name}/cov"] = torch.linalg.matrix_norm(cov - ref["cov"][rows, t].double())
            xk, wk = x, w
            if thin is not None:
                xk, wk = x.gather(-2, thin[..., None].expand(*thin.shape, x.shape[-1])), None
            k = xk.shape[-2]  # the MMD kernel's belief side: n, or m when thinned
            step = max(1, COMPARE_ROWS // max(k * max(k, y.shape[-2]), 1))
            w1, mmd = [], []
            for lo in range(0, s, step):  # chunks of seeds bound the N × N kernel's memory
                c = slice(lo, lo + step)
                wx = w[c].to(x.dtype)
                wm = None if wk is None else wk[c].to(x.dtype)
                w1.append(weighted_sliced_wasserstein(x[c], y[c], ref["projections"], wx))
                mmd.append(kernel_mean(xk[c], xk[c], gamma[c], wm, wm) + ref["kyy"][rows, t][c].to(x.dtype)
                           - 2.0 * kernel_mean(xk[c], y[c], gamma[c], wm))
            out[f"{name}/w1"] = torch.cat(w1).double()
            out[f"{name}/mmd2"] = torch.cat(mmd).double().clamp_min(0.0)
        return out

    def compare_reference(self, other: "Reference", t: int) -> dict:
        """The distances of ``other``'s subsample (uniform weights) to this reference at step ``t``,
        with the moments of both full references: the floor under a method's figures."""
        out = {}
        for name, ref in self.parts.items():
            o = other.parts[name]
            y = o["sample"][:, t]
            gamma = ref["gamma"][:, t]
            out[f"{name}/mean"] = (o["mean"][:, t].double() - ref["mean"][:, t].double()).norm(dim=-1)
            out[f"{name}/cov"] = torch.linalg.matrix_norm(o["cov"][:, t].double() - ref["cov"][:, t].double())
            out[f"{name}/w1"] = weighted_sliced_wasserstein(y, ref["sample"][:, t], ref["projections"]).double()
            out[f"{name}/mmd2"] = (kernel_mean(y, y, gamma) + ref["kyy"][:, t]
                                   - 2.0 * kernel_mean(y, ref["sample"][:, t], gamma)).double().clamp_min(0.0)
        return out


def summarize_series(series: dict, steps: int) -> dict:
    """Per key ``[S, T+1]`` series -> ``{"final": [S], "mean": [S]}`` (the last step; the average over
    steps 1..T, or step 0 when T = 0)."""
    out = {}
    for k, v in series.items():
        v = torch.as_tensor(v, dtype=torch.float64)
        out[k] = {"final": v[:, -1].tolist(), "mean": (v[:, 1:].mean(1) if steps > 0 else v[:, 0]).tolist()}
    return out

