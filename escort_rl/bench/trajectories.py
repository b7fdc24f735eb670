"""Protocol (a)'s building blocks: seeded shared trajectories, seeded priors, and one method
filtering them.

For each domain and seed one trajectory is drawn with a seeded generator: the true start state from
``model.initial_state``, actions from a fixed behaviour policy (uniform random actions, seeded per
seed, or the model's own ``behaviour_action`` where it has one), states from ``model.transition`` and
observations from ``model.observe``. Episodes are not cut
at terminal states: every trajectory has the same horizon. Every method then filters the *same*
action/observation sequence from the *same* prior particles: seed ``s``'s prior is drawn by
``filt.init`` with a generator of its own, and the per-seed priors are stacked into one batch
``[B, N, d]``; the only Python loop in the filtering is over time steps.

Every stream is derived from ``(kind, base_seed, seed)``
(:func:`~escort_rl.belief.seeding.derived_seed`), so a seed's trajectory and prior do not depend on
which other seeds share its batch (the hashes prove it). The
filter's own noise (SIR's resampling offsets, ESCORT's propagation and jitter) comes from one
generator per batch, seeded by the batch's first seed.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch

from escort_rl.belief.seeding import derived_seed, initial_beliefs, tensor_hash
from escort_rl.bench.methods import build_domain, build_method
from escort_rl.models import position_dims, position_error
from escort_rl.models.protocol import random_action
from escort_rl.reporting.paths import display_path

BEHAVIOUR_POLICY = ("uniform random actions: a_t ~ U{0, ..., n_actions - 1}, drawn from the seed's "
                    "trajectory generator (the same actions for every method)")


class NonFiniteBeliefError(ValueError):
    """A filter produced NaN or Inf particles or weights; the message names the method and domain."""


def belief_failures() -> tuple[type[Exception], ...]:
    """The errors that mean a filter's belief diverged on a trajectory: the run records a failed row
    (with the step and the message) and goes on with the other methods."""
    from escort_rl.belief import NonFiniteError
    from escort_rl.belief.prior import PriorCovarianceError

    return NonFiniteBeliefError, PriorCovarianceError, NonFiniteError


def position_error_label(model) -> str:
    if callable(getattr(model, "position_error", None)):
        return f"{type(model).__name__}.position_error (see its docstring)"
    dims = list(position_dims(model))
    return f"‖E_b[s[{dims}]] − s_true[{dims}]‖₂"


def behaviour_policy(model) -> str:
    """What the shared trajectories' actions are on ``model``: its ``behaviour_description`` where it has its
    own ``behaviour_action``, else :data:`BEHAVIOUR_POLICY`."""
    if callable(getattr(model, "behaviour_action", None)):
        return str(getattr(model, "behaviour_description", "the model's own behaviour_action"))
    return BEHAVIOUR_POLICY


def generate_trajectory(model, steps: int, seed: int, base_seed: int = 0) -> dict:
    """One seeded trajectory under the behaviour policy (:func:`behaviour_policy`: uniform random actions, or
    the model's ``behaviour_action(s, generator)``).

    Returns ``states`` ``[T+1, d]`` (index 0 is the start), ``actions`` ``[T]`` (int64) and
    ``observations`` ``[T, obs_dim]`` (``observations[t]`` is seen after ``actions[t]``).
    """
    g = torch.Generator().manual_seed(derived_seed("trajectory", base_seed, seed))
    s = model.initial_state((), g)
    states, actions, observations = [s], [], []
    own = getattr(model, "behaviour_action", None)
    for _ in range(steps):
        a = own(s, g) if callable(own) else random_action(model, (), g)
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


def check_finite(belief, method: str, domain: str, step: int, seeds: list[int]) -> None:
    x, lw = belief.particles, belief.log_weights
    bad = ~torch.isfinite(x).all(-1).all(-1) | torch.isnan(lw).any(-1) | torch.isposinf(lw).any(-1)
    if bad.any():
        which = [seeds[i] for i in bad.nonzero().flatten().tolist()]
        raise NonFiniteBeliefError(f"method '{method}' on domain '{domain}': the belief became non-finite "
                                   f"(NaN/Inf particles or weights) at step {step}, seeds {which[:8]}")


def filter_trajectories(domain: str, method: str, traj: dict, seeds: list[int], n: int, base_seed: int = 0,
                        filter_set: tuple = (), references: tuple = ()) -> dict:
    """Run ``method`` on the shared trajectories ``traj`` of ``seeds`` (one batch), from the seeds'
    priors. Returns per-seed errors ``errors`` ``[B, T+1]`` (index 0: the prior), the filter seconds,
    and the per-seed hashes of the inputs it was fed and of its priors.

    ``references``: :class:`~escort_rl.metrics.reference.Reference` posteriors of the same seeds; the
    belief is compared with each at every step (untimed), and ``accuracy`` holds, per reference, the
    series ``{"<part>/<metric>": [B, T+1]}`` of :meth:`Reference.compare`."""
    model, _ = build_domain(domain)
    filt = build_method(domain, method, filter_set)
    states, actions, obs = traj["states"], traj["actions"], traj["observations"]
    steps = actions.shape[1]
    belief, belief_hashes = initial_beliefs(filt, model, seeds, n, base_seed)
    g = torch.Generator().manual_seed(derived_seed("filter", base_seed, seeds[0]))
    errors = [position_error(model, belief.mean(), states[:, 0])]
    accuracy = [[ref.compare(belief.particles, belief.log_weights, 0)] for ref in references]
    input_hashes = [tensor_hash(states[i], actions[i], obs[i]) for i in range(len(seeds))]
    out = {"seconds": 0.0, "first_seconds": 0.0, "timed_steps": max(steps - 1, 1), "steps": steps,
           "input_hashes": input_hashes, "belief_hashes": belief_hashes, "filter": repr(filt), "failed": None}
    for t in range(steps):
        t0 = time.perf_counter()
        try:
            belief = filt.update(model, belief, actions[:, t], obs[:, t], g)
            check_finite(belief, method, domain, t + 1, seeds)
        except belief_failures() as e:
            out["failed"] = {"step": t + 1, "message": str(e)}
            break
        # the first update is a warm-up (and, with compile=True, compiles): timed on its own
        if t == 0 and steps > 1:
            out["first_seconds"] = time.perf_counter() - t0
        else:
            out["seconds"] += time.perf_counter() - t0
        errors.append(position_error(model, belief.mean().detach(), states[:, t + 1]))
        for series, ref in zip(accuracy, references):
            series.append(ref.compare(belief.particles.detach(), belief.log_weights.detach(), t + 1))
    out["errors"] = torch.stack(errors, dim=1).detach()
    out["accuracy"] = [{k: torch.stack([s[k] for s in series], 1) for k in series[0]} for series in accuracy]
    # particle-evolution iterations per update (K, or fewer with the adaptive stop); NaN for SIR
    out["iterations"] = filt.mean_iterations() if hasattr(filt, "mean_iterations") else float("nan")
    out["importance"] = filt.importance_diagnostics()  # the ESS of every importance-weighted step
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
        check_finite(belief, method, domain, t + 1, seeds)
    return seconds / max(total_steps - 1, 1)
