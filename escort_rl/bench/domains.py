"""The domain benchmark (SPEC §6), protocol (a) "shared trajectories".

For each domain and seed one trajectory is drawn with a seeded generator: the true start state from
``model.initial_state``, actions from a fixed behaviour policy (uniform random actions, seeded per
seed), states from ``model.transition`` and observations from ``model.observe``. Episodes are not cut
at terminal states: every trajectory has the same horizon. Every method (a filter config name under
``configs/filter/``, so a new config is a new row with no code change) then filters the *same*
action/observation sequence from the *same* prior particles: seed ``s``'s prior is drawn by
``filt.init`` with a generator of its own, and the per-seed priors are stacked into one batch.

All seeds of a (domain, method) run as one batch ``B = seeds`` (filters are batched over
``[B, N, d]``); the only Python loop in the filtering is over time steps.

Metrics, each mean ± standard error over seeds: the position error ``‖E_b[pos] − pos_true‖₂`` of the
weighted belief mean at every step (Light-Dark: the 5 position coordinates; Kidnapped Robot: dims
(0, 1); Multi-Target Tracking: ``model.target_position_error``, the mean over the four targets), its
value at the final step and its average over steps 1..T, and the wall-clock seconds per filter update.

Reproducibility across ``workers``: seeds are split into ``workers`` contiguous chunks, one process
each. The trajectory of seed ``s`` and its prior particles depend only on ``(base_seed, s)``, so they
are identical for any worker count (the JSON stores their hashes). The filters' own noise (SIR's
resampling offsets, ESCORT's propagation and jitter) comes from one generator per batch, seeded by
the chunk's first seed, so with ``workers > 1`` that noise differs from ``workers = 1`` and the
per-seed errors agree in distribution, not bit for bit. For a fixed worker count a run is
deterministic.

Equal wall-clock table: each method's time per step is measured on a few steps of the same batch at
each ``N'`` of a grid (capped by ``max_particles``) plus the base ``N``; the method gets the largest
``N'`` whose time is not above the reference method's (``escort``, or the first method when escort
is not listed) time at the base ``N``, and protocol (a) is rerun at that ``N'``. The reference keeps
the base ``N``; a method whose ``N'`` equals ``N`` reuses its equal-N run.

Threads: the timings depend strongly on torch's thread count. Small batched updates are often fastest
on one thread, and several threads on a busy 2-core machine can be ten times slower; ``threads``
(``--threads``) fixes the count, and is recorded in the output with the timings.
"""

from __future__ import annotations

import hashlib
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from functools import lru_cache
from pathlib import Path

import torch

from escort_rl.models import position_dims, position_error
from escort_rl.trainers.evaluate import display_path

DEFAULT_METHODS = ("escort", "escort_nocorr", "escort_notemp", "escort_noproj", "svgd", "sir")
DEFAULT_DOMAINS = ("lightdark10d", "kidnapped20d", "mtt20d")
PARTICLE_GRID = (50, 100, 200, 500, 1000, 2000)
BEHAVIOUR_POLICY = ("uniform random actions: a_t ~ U{0, ..., n_actions - 1}, drawn from the seed's "
                    "trajectory generator (the same actions for every method)")


class NonFiniteBeliefError(ValueError):
    """A filter produced NaN or Inf particles or weights; the message names the method and domain."""


def _belief_failures() -> tuple[type[Exception], ...]:
    """The errors that mean a filter's belief diverged on a trajectory: the run records a failed row
    (with the step and the message) and goes on with the other methods."""
    from escort_rl.belief import NonFiniteError
    from escort_rl.belief.prior import PriorCovarianceError

    return NonFiniteBeliefError, PriorCovarianceError, NonFiniteError


# ---------------------------------------------------------------------------------------- seeds
def derived_seed(kind: str, base_seed: int, seed: int) -> int:
    """A 63-bit seed for ``kind`` (``trajectory``, ``belief``, ``filter``) of one seed: the streams
    never overlap, so no prior particle copies the true start state."""
    digest = hashlib.sha256(f"escort-rl/domains/{kind}/{base_seed}/{seed}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def tensor_hash(*tensors: torch.Tensor) -> str:
    """SHA-256 (first 16 hex digits) of the tensors' bytes, shapes and dtypes."""
    h = hashlib.sha256()
    for t in tensors:
        t = t.detach().cpu().contiguous()
        h.update(f"{tuple(t.shape)}{t.dtype}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()[:16]


# ---------------------------------------------------------------------------------------- building
def available_methods() -> list[str]:
    from escort_rl.config import config_dir

    return sorted(p.stem for p in (config_dir() / "filter").glob("*.yaml"))


def available_domains() -> list[str]:
    from escort_rl.config import config_dir

    return sorted(p.stem for p in (config_dir() / "env").glob("*.yaml"))


def check_names(domains, methods, filter_set: tuple = ()) -> None:
    """Raise ``ValueError`` naming ``--domains``, ``--methods`` or ``--filter-set`` for a bad name."""
    if not domains:
        raise ValueError("--domains: give at least one domain")
    if not methods:
        raise ValueError("--methods: give at least one method")
    known_d, known_m, learned = available_domains(), available_methods(), learned_methods()
    for d in domains:
        if d not in known_d:
            raise ValueError(f"--domains: unknown domain '{d}'; choose from {', '.join(known_d)}")
    for m in methods:
        if m not in known_m and m not in learned:
            raise ValueError(f"--methods: unknown method '{m}'; the methods are the filter configs "
                             f"{', '.join(known_m)} and the learned beliefs {', '.join(learned)}")
    if len(set(methods)) != len(methods):
        raise ValueError("--methods: a method is listed twice")
    filters = [m for m in methods if m not in learned]
    for key, _ in filter_set:
        if not any(key in applied_filter_set(m, ((key, ""),)) for m in filters):
            raise ValueError(f"--filter-set: no method in --methods has the filter key '{key}'")


def learned_methods() -> dict:
    """The learned-belief methods (``learned`` in ``configs/bench/closed_loop.yaml``, e.g. ``dvrl``):
    name -> ``{"trainer": ...}``."""
    from escort_rl.bench.closed_loop import load_settings

    return dict(load_settings().get("learned") or {})


def check_at_least_one(**flags) -> None:
    """Raise ``ValueError`` naming the flag (``particles`` -> ``--particles``) of the first value
    below 1; ``None`` (not given) passes."""
    for name, value in flags.items():
        if value is not None and value < 1:
            raise ValueError(f"--{name.replace('_', '-')}: must be >= 1, got {value}")


def parse_filter_set(items) -> tuple[tuple[str, str], ...]:
    """``["num_steps=10", ...]`` -> ``(("num_steps", "10"), ...)``; the ``filter.`` prefix is optional."""
    out = []
    for item in items or ():
        if "=" not in item:
            raise ValueError(f"--filter-set: '{item}' is not of the form KEY=VALUE (e.g. num_steps=10)")
        key, value = item.split("=", 1)
        key = key.removeprefix("filter.")
        if key in ("name", "kind") or not key:
            raise ValueError(f"--filter-set: cannot set '{key}'; pick the filter with --methods")
        out.append((key, value))
    return tuple(out)


@lru_cache(maxsize=None)
def _config(domain: str, method: str, filter_set: tuple = ()):
    """The composed config for ``filter=method env=domain``, with each ``filter_set`` (key, value)
    applied where the method's config has that key (``num_steps`` changes ESCORT and SVGD, not SIR)."""
    from escort_rl.config import compose

    base = [f"filter={method}", f"env={domain}"]
    if not filter_set:
        return compose(base)
    keys = set(compose(base).filter.keys())
    return compose(base + [f"filter.{k}={v}" for k, v in filter_set if k in keys])


def applied_filter_set(method: str, filter_set: tuple) -> dict:
    """The subset of ``filter_set`` that applies to ``method``."""
    keys = set(_config(DEFAULT_DOMAINS[0], method).filter.keys())
    return {k: v for k, v in filter_set if k in keys}


@lru_cache(maxsize=None)
def build_domain(domain: str):
    """The model of ``configs/env/<domain>.yaml`` and its ``max_steps``."""
    from escort_rl.trainers.builders import build_model

    cfg = _config(domain, "sir")
    return build_model(cfg.env), int(cfg.env.max_steps)


def build_method(domain: str, method: str, filter_set: tuple = ()):
    from escort_rl.trainers.builders import build_filter

    return build_filter(_config(domain, method, tuple(filter_set)).filter)


def position_error_label(model) -> str:
    if callable(getattr(model, "position_error", None)):
        return f"{type(model).__name__}.position_error (see its docstring)"
    dims = list(position_dims(model))
    return f"‖E_b[s[{dims}]] − s_true[{dims}]‖₂"


# ---------------------------------------------------------------------------------------- protocol (a)
def generate_trajectory(model, steps: int, seed: int, base_seed: int = 0) -> dict:
    """One seeded trajectory under the behaviour policy (uniform random actions).

    Returns ``states`` ``[T+1, d]`` (index 0 is the start), ``actions`` ``[T]`` (int64) and
    ``observations`` ``[T, obs_dim]`` (``observations[t]`` is seen after ``actions[t]``).
    """
    g = torch.Generator().manual_seed(derived_seed("trajectory", base_seed, seed))
    s = model.initial_state((), g)
    states, actions, observations = [s], [], []
    for _ in range(steps):
        a = torch.randint(model.n_actions, (), generator=g)
        s = model.transition(s, a, g)
        o = model.observe(s, a, g)
        states.append(s)
        actions.append(a)
        observations.append(o)
    return {"states": torch.stack(states), "actions": torch.stack(actions).long(),
            "observations": torch.stack(observations)}


def generate_trajectories(model, steps: int, seeds: list[int], base_seed: int = 0) -> dict:
    """:func:`generate_trajectory` of every seed, stacked: ``states`` ``[B, T+1, d]``, ``actions``
    ``[B, T]``, ``observations`` ``[B, T, obs_dim]``, and ``hashes``: one per seed."""
    trajs = [generate_trajectory(model, steps, s, base_seed) for s in seeds]
    out = {k: torch.stack([t[k] for t in trajs]) for k in ("states", "actions", "observations")}
    out["hashes"] = [tensor_hash(t["states"], t["actions"], t["observations"]) for t in trajs]
    return out


def initial_beliefs(filt, model, seeds: list[int], n: int, base_seed: int = 0):
    """The prior of each seed, drawn by ``filt.init`` with the seed's own generator, stacked into one
    ``ParticleBelief`` with particles ``[B, n, d]``; and the per-seed hashes of the particles."""
    from escort_rl.belief import ParticleBelief

    parts = []
    for s in seeds:
        g = torch.Generator().manual_seed(derived_seed("belief", base_seed, s))
        b = filt.init(model, (), n, g)
        parts.append((b.particles, b.log_weights))
    particles = torch.stack([p for p, _ in parts])
    log_w = torch.stack([w for _, w in parts])
    return ParticleBelief(particles, log_w), [tensor_hash(p) for p, _ in parts]


def _check_finite(belief, method: str, domain: str, step: int, seeds: list[int]) -> None:
    x, lw = belief.particles, belief.log_weights
    bad = ~torch.isfinite(x).all(-1).all(-1) | torch.isnan(lw).any(-1) | torch.isposinf(lw).any(-1)
    if bad.any():
        which = [seeds[i] for i in bad.nonzero().flatten().tolist()]
        raise NonFiniteBeliefError(f"method '{method}' on domain '{domain}': the belief became non-finite "
                                   f"(NaN/Inf particles or weights) at step {step}, seeds {which[:8]}")


def filter_trajectories(domain: str, method: str, traj: dict, seeds: list[int], n: int, base_seed: int = 0,
                        filter_set: tuple = ()) -> dict:
    """Run ``method`` on the shared trajectories ``traj`` of ``seeds`` (one batch), from the seeds'
    priors. Returns per-seed errors ``errors`` ``[B, T+1]`` (index 0: the prior), the filter seconds,
    and the per-seed hashes of the inputs it was fed and of its priors."""
    model, _ = build_domain(domain)
    filt = build_method(domain, method, filter_set)
    states, actions, obs = traj["states"], traj["actions"], traj["observations"]
    steps = actions.shape[1]
    belief, belief_hashes = initial_beliefs(filt, model, seeds, n, base_seed)
    g = torch.Generator().manual_seed(derived_seed("filter", base_seed, seeds[0]))
    errors = [position_error(model, belief.mean(), states[:, 0])]
    input_hashes = [tensor_hash(states[i], actions[i], obs[i]) for i in range(len(seeds))]
    out = {"seconds": 0.0, "first_seconds": 0.0, "timed_steps": max(steps - 1, 1), "steps": steps,
           "input_hashes": input_hashes, "belief_hashes": belief_hashes, "filter": repr(filt), "failed": None}
    for t in range(steps):
        t0 = time.perf_counter()
        try:
            belief = filt.update(model, belief, actions[:, t], obs[:, t], g)
            _check_finite(belief, method, domain, t + 1, seeds)
        except _belief_failures() as e:
            out["failed"] = {"step": t + 1, "message": str(e)}
            break
        # the first update is a warm-up (and, with compile=True, compiles): timed on its own
        if t == 0 and steps > 1:
            out["first_seconds"] = time.perf_counter() - t0
        else:
            out["seconds"] += time.perf_counter() - t0
        errors.append(position_error(model, belief.mean().detach(), states[:, t + 1]))
    out["errors"] = torch.stack(errors, dim=1).detach()
    # particle-evolution iterations per update (K, or fewer with the adaptive stop); NaN for SIR
    out["iterations"] = filt.mean_iterations() if hasattr(filt, "mean_iterations") else float("nan")
    return out


def train_learned_beliefs(domains, methods, runs_dir: Path, progress: bool = False) -> dict:
    """Train (or resume, or reuse) each learned-belief method of ``methods`` on each domain in
    ``runs_dir/<domain>/<method>``, with protocol (b)'s run config and budget (the same folder layout,
    so ``--output`` of a protocol (b) run can share its runs). Returns ``{(domain, method): checkpoint}``."""
    from escort_rl.bench.closed_loop import load_settings, run_config, train_run

    settings, learned = load_settings(), learned_methods()
    out = {}
    for d in domains:
        for m in methods:
            if m in learned:
                cfg = run_config(d, "sir", int(settings["particles"]), Path(runs_dir) / d / m,
                                 settings["train"][d], trainer=learned[m]["trainer"])
                out[(d, m)] = train_run(cfg, progress=progress)["checkpoint"]
    return out


@torch.no_grad()
def learned_trajectories(domain: str, method: str, traj: dict, seeds: list[int], checkpoint: str,
                         base_seed: int = 0) -> dict:
    """A learned belief (DVRL) on the shared trajectories: the same output as :func:`filter_trajectories`.

    The belief starts fresh (``h = z = 0``, the readout of that summary is the step-0 estimate) and
    takes ``(actions[t], observations[t])`` at each step, as in its training (``a_{t-1}``, ``o_t``); the
    position error is that of its readout's state estimate. It has no particles in state space, so
    there is no prior hash (``belief_hashes`` are empty strings)."""
    from escort_rl.trainers.dvrl_a2c import load_dvrl_policy

    model, _ = build_domain(domain)
    _, policy = load_dvrl_policy(checkpoint)
    dvrl, readout = policy.dvrl, policy.readout
    states, actions, obs = traj["states"], traj["actions"], traj["observations"]
    b, steps = actions.shape
    g = torch.Generator().manual_seed(derived_seed("filter", base_seed, seeds[0]))
    state = dvrl.initial_state(b)
    errors = [position_error(model, readout(dvrl.summarize(state)), states[:, 0])]
    out = {"seconds": 0.0, "first_seconds": 0.0, "timed_steps": max(steps - 1, 1), "steps": steps,
           "input_hashes": [tensor_hash(states[i], actions[i], obs[i]) for i in range(b)],
           "belief_hashes": [""] * b, "filter": f"{method} ({display_path(Path(checkpoint))})", "failed": None}
    for t in range(steps):
        t0 = time.perf_counter()
        state, _, summary = dvrl.step(state, actions[:, t], obs[:, t], None, g)
        estimate = readout(summary)
        if t == 0 and steps > 1:
            out["first_seconds"] = time.perf_counter() - t0
        else:
            out["seconds"] += time.perf_counter() - t0
        errors.append(position_error(model, estimate, states[:, t + 1]))
    out["errors"] = torch.stack(errors, dim=1)
    return out


def _chunk_task(domain: str, method: str, seeds: list[int], n: int, steps: int, base_seed: int,
                filter_set: tuple = ()) -> dict:
    """One worker process's share: regenerate its seeds' trajectories (identical to the main process's:
    same per-seed generators; the hashes are checked) and filter them. Module-level for spawn."""
    model, _ = build_domain(domain)
    traj = generate_trajectories(model, steps, seeds, base_seed)
    out = filter_trajectories(domain, method, traj, seeds, n, base_seed, filter_set)
    out["errors"] = out["errors"].tolist()
    return out


def _worker_init(threads: int) -> None:
    torch.set_num_threads(threads)


def split_seeds(seeds: list[int], workers: int) -> list[list[int]]:
    """``workers`` contiguous chunks (fewer if there are fewer seeds), sizes differing by at most 1."""
    k = max(1, min(workers, len(seeds)))
    q, r = divmod(len(seeds), k)
    chunks, start = [], 0
    for i in range(k):
        size = q + (1 if i < r else 0)
        chunks.append(seeds[start:start + size])
        start += size
    return chunks


def mean_se(values) -> tuple[float, float]:
    v = [float(a) for a in values if not math.isnan(float(a))]
    if not v:
        return float("nan"), float("nan")
    m = sum(v) / len(v)
    if len(v) < 2:
        return m, 0.0
    return m, math.sqrt(sum((a - m) ** 2 for a in v) / (len(v) - 1) / len(v))


def _row(domain: str, method: str, n: int, parts: list[dict], seeds: list[int]) -> dict:
    failed = [p["failed"] for p in parts if p.get("failed")]
    if failed:  # a diverged belief: no error figures, the earliest failure is reported
        first = min(failed, key=lambda f: f["step"])
        nan = (float("nan"), float("nan"))
        return {"domain": domain, "method": method, "filter": parts[0]["filter"], "particles": n, "seeds": seeds,
                "steps": parts[0]["steps"], "failed": first, "summary": {"final_error": nan, "mean_error": nan},
                "input_hashes": [h for p in parts for h in p["input_hashes"]],
                "initial_belief_hashes": [h for p in parts for h in p["belief_hashes"]]}
    errors = torch.tensor([e for p in parts for e in p["errors"]], dtype=torch.float64)  # [B, T+1]
    b = errors.shape[0]
    steps = parts[0]["steps"]
    seconds = sum(p["seconds"] for p in parts)
    timed = parts[0]["timed_steps"]
    first = sum(p["first_seconds"] for p in parts)
    final = errors[:, -1]
    avg = errors[:, 1:].mean(1) if steps > 0 else errors[:, 0]
    se_t = errors.std(0, unbiased=True) / math.sqrt(b) if b > 1 else torch.zeros(errors.shape[1])
    if not torch.isfinite(errors).all() or (errors < 0).any():
        raise NonFiniteBeliefError(f"method '{method}' on domain '{domain}': the position error is NaN, Inf "
                                   "or negative")
    return {
        "domain": domain, "method": method, "filter": parts[0]["filter"], "particles": n, "seeds": seeds,
        "steps": steps, "failed": None,
        "per_seed": {"final_error": final.tolist(), "mean_error": avg.tolist()},
        "summary": {"final_error": mean_se(final.tolist()), "mean_error": mean_se(avg.tolist())},
        "error_over_time": {"mean": errors.mean(0).tolist(), "se": se_t.tolist()},
        "filter_seconds": seconds + first,
        "first_step_seconds": first,
        "seconds_per_step": seconds / timed,
        "seconds_per_step_per_env": seconds / timed / b,
        "input_hashes": [h for p in parts for h in p["input_hashes"]],
        "initial_belief_hashes": [h for p in parts for h in p["belief_hashes"]],
    }


class _Runner:
    """Runs (domain, method, N) jobs over seed chunks, inline (``workers = 1``) or in a spawn pool."""

    def __init__(self, workers: int, seeds: list[int], base_seed: int, trajs: dict, filter_set: tuple,
                 threads: int | None = None, learned: dict | None = None) -> None:
        self.learned = learned or {}  # (domain, method) -> checkpoint: run inline, on all seeds
        self.chunks = split_seeds(seeds, workers)
        self.filter_set = filter_set
        self.trajs = trajs
        self.seeds = seeds
        self.base_seed = base_seed
        self.pool = None
        self.worker_threads = None
        if len(self.chunks) > 1:
            import multiprocessing as mp

            threads = threads or max(1, (os.cpu_count() or 1) // len(self.chunks))
            self.worker_threads = threads
            self.pool = ProcessPoolExecutor(len(self.chunks), mp_context=mp.get_context("spawn"),
                                            initializer=_worker_init, initargs=(threads,))

    def run(self, jobs: list[tuple[str, str, int, int]], on_row=None) -> list[dict]:
        """``jobs``: (domain, method, N, steps). Rows in job order; ``on_row`` is called as each completes."""
        rows = []
        inline = self.pool is None
        futures = [None if inline or (d, m) in self.learned else
                   [self.pool.submit(_chunk_task, d, m, c, n, s, self.base_seed, self.filter_set) for c in self.chunks]
                   for d, m, n, s in jobs]
        for (domain, method, n, _), fs in zip(jobs, futures):
            if fs is not None:
                parts = [f.result() for f in fs]
            else:
                if (domain, method) in self.learned:
                    part = learned_trajectories(domain, method, self.trajs[domain], self.seeds,
                                                self.learned[(domain, method)], self.base_seed)
                else:
                    part = filter_trajectories(domain, method, self.trajs[domain], self.seeds, n, self.base_seed,
                                               self.filter_set)
                part["errors"] = part["errors"].tolist()
                parts = [part]
            rows.append(_row(domain, method, n, parts, self.seeds))
            if on_row is not None:
                on_row(rows[-1])
        return rows

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)


def time_per_step(domain: str, method: str, traj: dict, seeds: list[int], n: int, steps: int,
                  base_seed: int = 0, filter_set: tuple = ()) -> float:
    """Seconds per batched update of ``method`` at ``n`` particles: one warm-up update, then the mean
    of ``steps`` timed updates on the shared trajectories of ``seeds``."""
    model, _ = build_domain(domain)
    filt = build_method(domain, method, filter_set)
    belief, _ = initial_beliefs(filt, model, seeds, n, base_seed)
    g = torch.Generator().manual_seed(derived_seed("filter", base_seed, seeds[0]))
    total_steps = min(traj["actions"].shape[1], steps + 1)
    seconds = 0.0
    for t in range(total_steps):
        t0 = time.perf_counter()
        belief = filt.update(model, belief, traj["actions"][:, t], traj["observations"][:, t], g)
        if t > 0 or total_steps == 1:
            seconds += time.perf_counter() - t0
        _check_finite(belief, method, domain, t + 1, seeds)
    return seconds / max(total_steps - 1, 1)


def run_domains(domains=DEFAULT_DOMAINS, methods=DEFAULT_METHODS, seeds: int = 30, n: int = 100,
                steps: int | None = None, workers: int = 1, equal_time: bool = True,
                max_particles: int = 2000, particle_grid=PARTICLE_GRID, reference: str = "escort",
                calibration_steps: int = 3, base_seed: int = 0, filter_set=(), threads: int | None = None,
                progress=None, plot_dir=None, runs_dir=None) -> dict:
    """Protocol (a) for every method on every domain; per-seed values and mean ± s.e.

    ``steps``: the horizon (default: each domain's ``env.max_steps``). ``filter_set``: (key, value)
    pairs set on every method's filter config that has the key (e.g. ``("num_steps", "10")``).
    ``threads``: torch threads in this process and in each worker (default: torch's default here,
    ``cpu_count // workers`` in workers); restored on return. Small batched updates are often fastest
    on one thread, and much slower with several threads on a busy machine. ``progress(kind, payload)`` is
    called with ``("row", row)`` after each (domain, method) and ``("calibration", dict)`` after each
    equal-time measurement. With ``plot_dir``, writes ``error_over_time_<domain>.png``.
    Learned-belief methods (``dvrl``) are trained first in ``runs_dir/<domain>/<method>`` (required
    for them; see :func:`train_learned_beliefs`); they have no particle count, so they sit out the
    equal-time table.
    """
    domains, methods = list(domains), list(methods)
    filter_set = tuple(tuple(kv) for kv in filter_set)
    check_names(domains, methods, filter_set)
    check_at_least_one(seeds=seeds, particles=n, steps=steps, workers=workers, threads=threads)
    learned = [m for m in methods if m in learned_methods()]
    if learned and runs_dir is None:
        raise ValueError(f"--output: the learned beliefs {', '.join(learned)} need a folder to train in")
    previous_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        checkpoints = train_learned_beliefs(domains, learned, Path(runs_dir)) if learned else {}
        return _run_domains(domains, methods, seeds, n, steps, workers, equal_time, max_particles, particle_grid,
                            reference, calibration_steps, base_seed, filter_set, threads, progress, plot_dir,
                            checkpoints)
    finally:
        torch.set_num_threads(previous_threads)


def _run_domains(domains, methods, seeds, n, steps, workers, equal_time, max_particles, particle_grid, reference,
                 calibration_steps, base_seed, filter_set, threads, progress, plot_dir, checkpoints) -> dict:
    seed_list = list(range(seeds))
    horizon = {d: (steps if steps is not None else build_domain(d)[1]) for d in domains}
    t_start = time.perf_counter()

    domain_info, trajs = {}, {}
    for d in domains:
        model, max_steps = build_domain(d)
        traj = generate_trajectories(model, horizon[d], seed_list, base_seed)
        trajs[d] = traj
        info = {"steps": horizon[d], "env_max_steps": max_steps, "state_dim": model.state_dim,
                "obs_dim": model.obs_dim, "n_actions": model.n_actions,
                "position_error": position_error_label(model), "trajectory_hashes": traj["hashes"]}
        if hasattr(model, "distance_to_goal"):
            dist = model.distance_to_goal(traj["states"][:, -1]).tolist()
            info["shared_final_distance_to_goal"] = mean_se(dist)
        domain_info[d] = info

    def on_row(row):
        if progress is not None:
            progress("row", row)

    runner = _Runner(workers, seed_list, base_seed, trajs, filter_set, threads, checkpoints)
    filters = [m for m in methods if not any((d, m) in checkpoints for d in domains)]
    try:
        rows = runner.run([(d, m, n, horizon[d]) for d in domains for m in methods], on_row)
        equal = None
        if equal_time and filters:
            equal = _equal_time(domains, filters, rows, trajs, seed_list, n, horizon, runner, max_particles,
                                particle_grid, reference, calibration_steps, base_seed, progress)
    finally:
        runner.close()
    for row in rows:
        if row["input_hashes"] != domain_info[row["domain"]]["trajectory_hashes"]:
            raise RuntimeError(f"method '{row['method']}' on '{row['domain']}' saw a different trajectory")

    result = {
        "protocol": "a: shared trajectories",
        "behaviour_policy": BEHAVIOUR_POLICY,
        "seeds": seeds, "particles": n, "workers": workers, "base_seed": base_seed,
        "methods": methods, "domains": domains, "domain_info": domain_info,
        "filter_set": {m: applied_filter_set(m, filter_set) for m in filters},
        "learned": {f"{d}/{m}": display_path(Path(c)) for (d, m), c in checkpoints.items()},
        "torch_threads": torch.get_num_threads(),
        "worker_threads": (runner.worker_threads if workers > 1 else None), "seconds": time.perf_counter() - t_start,
        "rows": rows, "equal_time": equal,
    }
    if plot_dir is not None:
        for d in domains:
            plot_error_over_time(result, d, Path(plot_dir) / f"error_over_time_{d}.png")
    return result


def _calibrate(domains, methods, trajs, seed_list, n, runner, grid, ref, calibration_steps, base_seed,
               progress, failed: dict) -> dict:
    """Per domain: the reference's seconds per step at ``n`` (the budget), each other method's seconds
    per step on the grid (stopping at the first ``N'`` over the budget), and the ``N'`` chosen: the
    largest within the budget, or the smallest of the grid (listed in ``over_budget``) if none is.
    ``failed``: domain -> methods whose equal-N run failed; they are not timed."""
    out = {}
    for d in domains:
        budget = time_per_step(d, ref, trajs[d], seed_list, n, calibration_steps, base_seed, runner.filter_set)
        calib, chosen = {}, {}
        for m in methods:
            if m == ref or m in failed.get(d, ()):  # a failed method keeps N (its failed row is reused)
                calib[m], chosen[m] = {str(n): (budget if m == ref else float("nan"))}, n
                continue
            times = {}
            for k in grid:
                times[str(k)] = time_per_step(d, m, trajs[d], seed_list, k, calibration_steps, base_seed,
                                              runner.filter_set)
                if times[str(k)] > budget:
                    break  # time grows with N: larger N' cannot fit either
            fits = [int(k) for k, t in times.items() if t <= budget]
            calib[m], chosen[m] = times, (max(fits) if fits else grid[0])
            if progress is not None:
                progress("calibration", {"domain": d, "method": m, "times": times, "budget": budget,
                                         "chosen": chosen[m]})
        out[d] = {"budget_seconds_per_step": budget, "calibration": calib, "chosen": chosen,
                  "over_budget": [m for m in methods if calib[m][str(chosen[m])] > budget]}
        if failed.get(d) and ref in failed[d]:
            raise NonFiniteBeliefError(f"the equal-time reference '{ref}' failed on '{d}'; pass --no-equal-time")
    return out


def _equal_time(domains, methods, rows, trajs, seed_list, n, horizon, runner, max_particles, particle_grid,
                reference, calibration_steps, base_seed, progress) -> dict:
    ref = reference if reference in methods else methods[0]
    grid = sorted({int(k) for k in particle_grid if k <= max_particles} | {n})
    out = {"reference": ref, "reference_particles": n, "grid": grid, "calibration_steps": calibration_steps,
           "domains": {}, "rows": []}
    jobs = []
    threads_here = torch.get_num_threads()
    if runner.worker_threads:  # time under the workers' thread count, as the runs they are compared with
        torch.set_num_threads(runner.worker_threads)
    try:
        failed = {d: {r["method"] for r in rows if r["domain"] == d and r["failed"]} for d in domains}
        choices = _calibrate(domains, methods, trajs, seed_list, n, runner, grid, ref, calibration_steps, base_seed,
                             progress, failed)
    finally:
        torch.set_num_threads(threads_here)
    for d in domains:
        out["domains"][d] = choices[d]
        jobs += [(d, m, choices[d]["chosen"][m], horizon[d]) for m in methods if choices[d]["chosen"][m] != n]

    def on_row(row):
        if progress is not None:
            progress("row", row)

    rerun = {(r["domain"], r["method"]): r for r in runner.run(jobs, on_row)}
    for d in domains:
        for m in methods:
            if (d, m) in rerun:
                row = dict(rerun[(d, m)], reused_equal_n=False)
            else:  # N' equals the base N: the equal-N run is that row
                row = dict(next(r for r in rows if r["domain"] == d and r["method"] == m), reused_equal_n=True)
            row["calibrated_seconds_per_step"] = out["domains"][d]["calibration"][m][str(row["particles"])]
            out["rows"].append(row)
    return out


# ---------------------------------------------------------------------------------------- reporting
def plot_error_over_time(result: dict, domain: str, path: Path) -> Path:
    """Mean position error against the step, one line per method, shaded ± s.e."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for row in (r for r in result["rows"] if r["domain"] == domain and not r["failed"]):
        m = torch.tensor(row["error_over_time"]["mean"])
        se = torch.tensor(row["error_over_time"]["se"])
        t = torch.arange(m.shape[0])
        ax.plot(t.numpy(), m.numpy(), label=row["method"], lw=1.2)
        ax.fill_between(t.numpy(), (m - se).numpy(), (m + se).numpy(), alpha=0.2)
    ax.set_xlabel("step (0: prior)")
    ax.set_ylabel("position error ‖E_b[pos] − pos_true‖₂")
    ax.set_title(f"{domain}: protocol (a), N = {result['particles']}, {result['seeds']} seeds (mean ± s.e.)",
                 fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _fmt(pair, digits: int = 3) -> str:
    m, se = pair
    return "—" if m is None or math.isnan(m) else f"{m:.{digits}f} ± {se:.{digits}f}"


def _table(result: dict, rows: list[dict], cell) -> list[str]:
    """One row per method, one column per domain; a failed run's cell says at which step it failed."""
    domains = result["domains"]
    lines = ["| method | " + " | ".join(domains) + " |", "| --- | " + " | ".join("---" for _ in domains) + " |"]
    by = {(r["domain"], r["method"]): r for r in rows}

    def show(r):
        return f"failed at step {r['failed']['step']}" if r["failed"] else cell(r)

    learned = {key.split("/", 1)[1] for key in result.get("learned", {})}
    for m in result["methods"]:
        label = f"{m.upper()} (learned belief, readout)" if m in learned else m
        if not any((d, m) in by for d in domains):
            continue  # e.g. a learned belief in the equal-time table
        lines.append(f"| {label} | " + " | ".join(show(by[(d, m)]) if (d, m) in by else "—" for d in domains) + " |")
    return lines


def domains_markdown(result: dict) -> str:
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
        *([("Filter settings changed from the configs: " + "; ".join(
            f"{m}: " + ", ".join(f"{k}={v}" for k, v in kv.items()) for m, kv in result["filter_set"].items() if kv)
            + "."), ""] if any(result.get("filter_set", {}).values()) else []),
        *([("Learned-belief rows (DVRL) were trained closed-loop with protocol (b)'s budget (checkpoints: "
            + ", ".join(f"{k}: `{v}`" for k, v in result["learned"].items()) + "); they read the same "
            "action/observation sequences, and their position error is that of a readout head from the belief "
            "summary to the state, fitted to the training trajectories' true states. They have no particle "
            "count and are not in the equal-time table."), ""] if result.get("learned") else []),
        "## Final position error (after the last step)",
        "",
        *_table(result, result["rows"], lambda r: _fmt(r["summary"]["final_error"])),
        "",
        "## Time-averaged position error (steps 1..T)",
        "",
        *_table(result, result["rows"], lambda r: _fmt(r["summary"]["mean_error"])),
        "",
        "## Wall-clock per filter update",
        "",
        f"Milliseconds per step for the whole batch of {result['seeds']} beliefs / per belief "
        f"(`--workers {result['workers']}`" + (
            f": the sum over the worker processes, each with {result['worker_threads']} torch threads"
            if result.get("worker_threads") else f", torch threads: {result['torch_threads']}") + "), "
        "over steps 2..T; the first update is a warm-up (it compiles, for `compile=true`) and its "
        "seconds are in brackets.",
        "",
        *_table(result, result["rows"],
                lambda r: f"{1e3 * r['seconds_per_step']:.1f} / {1e3 * r['seconds_per_step_per_env']:.2f} "
                          f"({r.get('first_step_seconds', float('nan')):.1f} s)"),
        "",
    ]
    eq = result.get("equal_time")
    if eq:
        lines += [
            "## Equal wall-clock per step",
            "",
            f"Each method gets the largest N' in {eq['grid']} whose measured time per batched update (one "
            f"warm-up, then the mean of {eq['calibration_steps']} updates on the same trajectories) is not "
            f"above {eq['reference']}'s at N = {eq['reference_particles']}; {eq['reference']} keeps N = "
            f"{eq['reference_particles']}. Cells: final error mean ± s.e. (N', ms per step in the timing "
            "measurement / in the run itself). A row at N' = N reuses the equal-N run. With `--workers` > 1 the "
            "runs' own times are sums over processes running side by side; the choice of N' uses the timing "
            "measurement, one process at a time.",
            "",
            *_table(result, eq["rows"], lambda r: f"{_fmt(r['summary']['final_error'])} "
                                                  f"(N'={r['particles']}, {1e3 * r['calibrated_seconds_per_step']:.1f}"
                                                  f" / {1e3 * r['seconds_per_step']:.1f} ms)"),
            "",
            "Budgets (ms per step of the reference): " + ", ".join(
                f"{d} {1e3 * v['budget_seconds_per_step']:.1f}" for d, v in eq["domains"].items()) + ".",
        ]
        over = [f"{m} on {d}" for d, v in eq["domains"].items() for m in v["over_budget"]]
        if over:
            lines.append("Even the smallest N' is over the budget for: " + ", ".join(over) + ".")
        lines.append("")
    failures = [r for r in result["rows"] + (eq["rows"] if eq else []) if r["failed"]]
    if failures:
        lines += ["## Failed runs", "",
                  "A failed run's belief diverged on at least one seed; the run stops there and has no error figures.",
                  ""]
        seen = set()
        for r in failures:
            if (r["domain"], r["method"], r["particles"]) not in seen:
                seen.add((r["domain"], r["method"], r["particles"]))
                lines.append(f"- {r['method']} on {r['domain']} (N = {r['particles']}): step {r['failed']['step']}: "
                             f"{r['failed']['message']}")
        lines.append("")
    lines += [
        "## Task outcome",
        "",
        "Under protocol (a) the actions come from the behaviour policy, not from the belief, so the true "
        "trajectory, and with it the final distance to goal, success and return, is the same for every "
        "method; only the error metrics above differ between methods. The closed-loop task outcome "
        "(each filter driving its own trained policy, or POMCPOW) is protocol (b), reported separately.",
    ]
    shared = [f"{d} {_fmt(info[d]['shared_final_distance_to_goal'])}" for d in result["domains"]
              if "shared_final_distance_to_goal" in info[d]]
    if shared:
        lines.append("Shared trajectories' final true distance to goal (the same for all methods): "
                     + ", ".join(shared) + ".")
    return "\n".join(lines) + "\n"
