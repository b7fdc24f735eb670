"""``escort-rl bench enkf-kalman``: is the EnKF's belief the Kalman posterior, up to its sampling error?

On ``S`` independent episodes of the linear-Gaussian family (``env=linear_gaussian``, its config's
parameters, uniform random actions), the EnKF with ``N`` members and the Kalman filter run side by
side (:func:`~escort_rl.bench.calibration.kalman_episode`). Per episode, the differences are averaged
over the ``T`` steps:

    δ_s = (1/T) Σ_t (m̂_t − m_t),    Δ_s = (1/T) Σ_t (Ĉ_t − P_t),

with ``m̂, Ĉ`` the ensemble's mean and covariance, ``m, P`` Kalman's. The episodes are independent, so
per coordinate ``i`` (and per covariance entry ``ij``, ``i ≤ j``) the bias has the z-score

    z_i = mean_s δ_si / (std_s δ_si / √S),

which is N(0, 1) where the EnKF is unbiased. The table reports ``max |z|``, the share of ``|z| > 3``
(0.27 % for an unbiased filter) and ``mean z²`` (1 ± √(2/D) for an unbiased one); and the size of the
error against what ``N`` exact posterior draws would give, ``E[(m̂_i − m_i)²] / (P_ii / N)`` (1 for
an i.i.d. sample of the posterior; the stochastic EnKF adds the noise of its perturbed observations).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from escort_rl.bench.core import options
from escort_rl.reporting.paths import write_results


def enkf_against_kalman(dim: int = 50, particles: int = 1000, episodes: int = 20, steps: int = 20,
                        obs_std: float | None = None, seed: int = 0, **enkf) -> dict:
    """The z-scores of the EnKF's mean and covariance against Kalman's (see the module docstring);
    ``enkf``: :class:`~escort_rl.belief.EnKFFilter`'s arguments (``inflation``, ``localisation_radius``)."""
    from escort_rl.belief import EnKFFilter
    from escort_rl.bench.calibration import kalman_episode
    from escort_rl.bench.frontier.cells import frontier_model

    args = (f"model.state_dim={int(dim)}",) + ((f"model.obs_std={float(obs_std)}",) if obs_std is not None else ())
    model = frontier_model("env:linear_gaussian", args)
    g = torch.Generator().manual_seed(int(seed))
    d_mean = torch.zeros(episodes, dim, dtype=torch.float64)
    d_cov = torch.zeros(episodes, dim, dim, dtype=torch.float64)
    sq_mean = torch.zeros(episodes, dim, dtype=torch.float64)  # (m̂ − m)² / (P_ii / N), time-averaged
    trace_p = 0.0  # tr(P), averaged over episodes and steps
    for belief, mean, cov in kalman_episode(EnKFFilter(**enkf), model, particles, steps, episodes, g):
        m_hat, c_hat = belief.mean().double(), belief.covariance().double()
        if not (torch.isfinite(m_hat).all() and torch.isfinite(c_hat).all()):
            raise FloatingPointError("EnKF belief: non-finite mean or covariance")
        d_mean += (m_hat - mean) / steps
        d_cov += (c_hat - cov) / steps
        sq_mean += (m_hat - mean) ** 2 / (torch.diagonal(cov, dim1=-2, dim2=-1) / particles) / steps
        trace_p += float(torch.diagonal(cov, dim1=-2, dim2=-1).sum(-1).mean()) / steps
    iu = torch.triu_indices(dim, dim)
    out = {"dim": dim, "particles": particles, "episodes": episodes, "steps": steps, "seed": seed,
           "model_args": list(args), "enkf": dict(enkf)}
    for name, x in (("mean", d_mean), ("covariance", d_cov[:, iu[0], iu[1]])):
        z = x.mean(0) / (x.std(0) / math.sqrt(episodes)).clamp_min(1e-300)
        out[name] = {"max_abs_z": float(z.abs().max()), "share_above_3": float((z.abs() > 3).double().mean()),
                     "mean_z2": float((z**2).mean()), "entries": int(z.numel())}
    out["mean"]["error_over_iid_floor"] = float(sq_mean.mean())
    out["covariance"]["trace_ratio"] = float(torch.diagonal(d_cov, dim1=-2, dim2=-1).sum(-1).mean() / trace_p) + 1.0
    return out


def kalman_markdown(r: dict) -> str:
    n_entries = r["mean"]["entries"]
    flags = "".join(f" --{k.replace('_', '-')} {v:g}" for k, v in r.get("enkf", {}).items())
    lines = [f"# EnKF against the Kalman posterior (D = {r['dim']}, N = {r['particles']})", "",
             f"`escort-rl bench enkf-kalman --dim {r['dim']} --particles {r['particles']} --episodes {r['episodes']} "
             f"--steps {r['steps']}{flags}`; model "
             f"`env=linear_gaussian {' '.join('env.' + a for a in r['model_args'])}`. "
             f"Bias z-scores per coordinate (mean) and per entry i ≤ j (covariance) over {r['episodes']} independent "
             f"episodes, each time-averaged over {r['steps']} steps.", "",
             "| quantity | entries | max abs z | share of abs z > 3 (unbiased: 0.0027) | mean z² (unbiased: 1 ± "
             f"{math.sqrt(2 / n_entries):.2f}) |", "| --- | --- | --- | --- | --- |"]
    for name in ("mean", "covariance"):
        q = r[name]
        lines.append(f"| {name} | {q['entries']} | {q['max_abs_z']:.2f} | {q['share_above_3']:.4f} | "
                     f"{q['mean_z2']:.2f} |")
    lines += ["", f"Mean error against N exact posterior draws: E[(m̂ − m)²] / (P_ii / N) = "
              f"{r['mean']['error_over_iid_floor']:.2f} (1 for an i.i.d. posterior sample). Total variance "
              f"tr(Ĉ)/tr(P) = {r['covariance']['trace_ratio']:.3f}."]
    return "\n".join(lines) + "\n"


QUICK = dict(dim=5, particles=50, episodes=4, steps=5)
"""``--quick``: D = 5, N = 50, 4 episodes of 5 steps."""


def register(subparsers) -> None:
    p = subparsers.add_parser("enkf-kalman", help="the EnKF's bias against the Kalman posterior (z-scores)",
                              description="Run the EnKF and the Kalman filter on independent linear-Gaussian "
                              "episodes and report the z-scores of the ensemble mean's and covariance's bias.")
    for flag, full, what in (("dim", 50, "state dimension"), ("particles", 1000, "ensemble size N"),
                             ("episodes", 20, "independent episodes"), ("steps", 20, "updates per episode")):
        p.add_argument(f"--{flag}", type=int, default=None, help=f"{what} (default: {full}; --quick: {QUICK[flag]})")
    p.add_argument("--obs-std", type=float, default=None, help="observation noise std (default: the config's)")
    p.add_argument("--seed", type=int, default=0, help="the first episode's seed")
    p.add_argument("--inflation", type=float, default=None, help="EnKF covariance inflation (default: off)")
    p.add_argument("--localisation-radius", type=float, default=None, help="EnKF Gaspari-Cohn radius, in "
                   "state-index units for this family (default: off)")
    options.add_quick_option(p, f"D = {QUICK['dim']}, N = {QUICK['particles']}, {QUICK['episodes']} episodes of "
                     f"{QUICK['steps']} steps")
    options.add_threads_option(p)
    options.add_output_option(p, "outputs/bench/enkf_kalman", "enkf_kalman.md and enkf_kalman.json")
    p.set_defaults(handler=main)


def main(args) -> None:
    full = dict(dim=50, particles=1000, episodes=20, steps=20)
    kw = {k: getattr(args, k) if getattr(args, k) is not None else (QUICK if args.quick else full)[k] for k in full}
    for flag in ("dim", "particles", "steps"):
        if kw[flag] < 1:
            raise ValueError(f"--{flag}: must be >= 1, got {kw[flag]}")
    if kw["episodes"] < 2:
        raise ValueError(f"--episodes: needs at least 2 for a standard error, got {kw['episodes']}")
    if kw["particles"] < 2:
        raise ValueError(f"--particles: the EnKF needs at least 2 members, got {kw['particles']}")
    options.set_threads(args)
    enkf = {k: getattr(args, k) for k in ("inflation", "localisation_radius") if getattr(args, k) is not None}
    result = enkf_against_kalman(kw["dim"], kw["particles"], kw["episodes"], kw["steps"], args.obs_std, args.seed,
                                 **enkf)
    write_results(Path(args.output), "enkf_kalman", result, kalman_markdown(result))
