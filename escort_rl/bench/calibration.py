"""Calibration against the exact posterior: filters on a linear-Gaussian model versus the Kalman
filter over one episode."""

from __future__ import annotations

import torch
from torch import Tensor

from escort_rl.bench.core import options
from escort_rl.models import LinearGaussian


def kalman_episode(filt, model, n: int, steps: int, batch: int, generator: torch.Generator):
    """Run ``filt`` and the Kalman filter (``model.kalman_step``) on the same seeded episode of a
    linear-Gaussian ``model`` (uniform random actions), yielding after each step the belief and the
    exact posterior's mean ``[batch, d]`` and covariance ``[batch, d, d]`` (float64)."""
    d = model.state_dim
    belief = filt.init(model, (batch,), n, generator)
    s = model.initial_state((batch,), generator)
    mean = model.m0.expand(batch, d).double()
    cov = model.P0.expand(batch, d, d).double()
    for _ in range(steps):
        a = torch.randint(0, model.n_actions, (batch,), generator=generator)
        s = model.transition(s, a, generator)
        o = model.observe(s, a, generator)
        belief = filt.update(model, belief, a, o, generator)
        mean, cov = model.kalman_step(mean, cov, a, o)
        yield belief, mean, cov


def kalman_errors(belief, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    """Per belief: the Mahalanobis distance of the belief mean from the Kalman mean in the Kalman
    covariance, ``sqrt((m − m_K)ᵀ P_K⁻¹ (m − m_K))``, and the total-variance ratio ``tr(Σ)/tr(P_K)``
    (``[B]`` each, float64)."""
    diff = (belief.mean().double() - mean).unsqueeze(-1)
    maha = torch.sqrt((diff.transpose(-1, -2) @ torch.linalg.solve(cov, diff)).squeeze((-1, -2)))
    ratio = (torch.diagonal(belief.covariance().double(), dim1=-2, dim2=-1).sum(-1)
             / torch.diagonal(cov, dim1=-2, dim2=-1).sum(-1))
    return maha, ratio


def kalman_calibration(filt, steps: int = 12, n: int = 300, batch: int = 4, state_dim: int = 4,
                       seed: int = 0) -> tuple[float, float]:
    """Run ``filt`` and the Kalman filter on the same seeded episodes of ``LinearGaussian(state_dim)``.

    Returns, averaged over the steps and the ``batch`` episodes: the Mahalanobis distance of the
    belief mean from the Kalman mean and the ratio of total variances (:func:`kalman_errors`).
    Raises if particles turn non-finite.
    """
    model = LinearGaussian(state_dim=state_dim)
    maha, ratio = [], []
    for belief, mean, cov in kalman_episode(filt, model, n, steps, batch, torch.Generator().manual_seed(seed)):
        if not torch.isfinite(belief.particles).all():
            raise FloatingPointError("belief.particles: non-finite values during calibration")
        m, r = kalman_errors(belief, mean, cov)
        maha.append(m.mean())
        ratio.append(r.mean())
    return float(torch.stack(maha).mean()), float(torch.stack(ratio).mean())


def ar1_correlation(d: int, rho: float) -> torch.Tensor:
    """``C_ij = ρ^|i−j|``, ``[d, d]`` (float64)."""
    i = torch.arange(d, dtype=torch.float64)
    return rho ** (i[:, None] - i[None, :]).abs()


def fixed_point_check(filt, d: int = 5, n: int = 300, batch: int = 8, rho: float = 0.6, num_steps: int = 1000,
                      seed: int = 0) -> tuple[float, float, float]:
    """Fit ``filt`` (:meth:`ESCORTFilter.fit`) to the Gaussian ``N(0, C)``, ``C = ar1_correlation(d, ρ)``,
    from ``N(0, 4 I)`` for ``num_steps`` iterations: where the evolution comes to rest, against the exact
    target. Returns, over ``batch`` fits: the total-variance ratio ``tr(Σ̂)/tr(C)``, the correlation error
    ``‖corr(x) − C‖_F`` and the error of the mean ``‖x̄‖``."""
    cov = ar1_correlation(d, rho).to(torch.float32)
    precision = torch.linalg.inv(cov)
    g = torch.Generator().manual_seed(seed)
    x0 = 2.0 * torch.randn(batch, n, d, generator=g)
    x = filt.fit(lambda z: -0.5 * torch.einsum("...i,ij,...j->...", z, precision, z), x0, num_steps=num_steps,
                 generator=g, proposal_log_prob=lambda z: -0.125 * (z * z).sum(-1))
    centred = x - x.mean(-2, keepdim=True)
    c = centred.transpose(-1, -2) @ centred / n
    ratio = torch.diagonal(c, dim1=-2, dim2=-1).sum(-1) / cov.trace()
    std = torch.diagonal(c, dim1=-2, dim2=-1).sqrt()
    corr_err = torch.linalg.matrix_norm(c / std[..., :, None] / std[..., None, :] - cov)
    return float(ratio.mean()), float(corr_err.mean()), float(x.mean(-2).norm(dim=-1).mean())


def register(subparsers) -> None:
    """Add ``bench calibration`` to the ``bench`` subparsers."""
    cal = subparsers.add_parser("calibration", help="SVGD/ESCORT variants against the Kalman filter",
                                description="Linear-Gaussian model (d=4), N=300, 12 steps, 4 episodes: mean "
                                "Mahalanobis error and variance ratio against the exact Kalman posterior.")
    cal.add_argument("--particles", type=int, default=None, metavar="N",
                     help=f"particles of every filter (default: 300; --quick: {QUICK['particles']})")
    cal.add_argument("--steps", type=int, default=None,
                     help=f"steps of each episode (default: 12; --quick: {QUICK['steps']})")
    options.add_quick_option(cal, f"N={QUICK['particles']}, {QUICK['steps']} steps (--fixed-point: K = 10)")
    options.add_threads_option(cal)
    options.add_output_option(cal, None, "calibration.md (--fixed-point: fixed_point.md), the table also printed "
                      "(default: print only)")
    cal.add_argument("--fixed-point", action="store_true",
                     help="instead: where the correlation term's two forms bring a static fit to rest "
                     "(N(0, AR(1) 0.6) in 5D, N = 300, 8 fits, K = 100 and 1000, lambda_corr 0, 0.1, 0.3, 1)")
    cal.set_defaults(handler=main)


QUICK = dict(particles=50, steps=3)
"""``--quick``: a smoke run."""


def fixed_point_table(iterations=(100, 1000), emit=print) -> None:
    """:func:`fixed_point_check` for both forms of the correlation term over λ and K, a line at a
    time to ``emit``."""
    from escort_rl.belief import ESCORTFilter

    emit("| corr_form | lambda_corr | K | variance ratio | correlation error | error of the mean |")
    emit("| --- | --- | --- | --- | --- | --- |")
    for form in ("velocity", "position"):
        for lam in (0.0, 0.1, 0.3, 1.0) if form == "velocity" else (0.1, 0.3, 1.0):
            for k in iterations:
                r, c, m = fixed_point_check(ESCORTFilter(lambda_corr=lam, corr_form=form), num_steps=k)
                emit(f"| {form} | {lam} | {k} | {r:.3f} | {c:.3f} | {m:.3f} |")


def main(args) -> None:
    from escort_rl.belief import ESCORTFilter, SIRFilter, SVGDFilter

    # the default training job's filter exactly as configs/filter/escort_train.yaml sets it (eager:
    # compiling changes nothing but the speed)
    from escort_rl.config import compose
    from escort_rl.trainers.builders import build_filter

    options.set_threads(args)
    lines = []

    def emit(line: str) -> None:
        lines.append(line)
        print(line, flush=True)

    if args.fixed_point:
        fixed_point_table((10,) if args.quick else (100, 1000), emit)
        _write_table(args.output, "fixed_point.md", lines)
        return
    pick = QUICK if args.quick else dict(particles=300, steps=12)
    particles = args.particles if args.particles is not None else pick["particles"]
    steps = args.steps if args.steps is not None else pick["steps"]
    train_filter = build_filter(compose(["filter=escort_train", "filter.compile=false"]).filter)
    variants = [("sir", SIRFilter()), ("svgd", SVGDFilter()), ("escort", ESCORTFilter()),
                ("escort lambda_corr=0.3", ESCORTFilter(lambda_corr=0.3)),
                ("escort lambda_corr=1", ESCORTFilter(lambda_corr=1.0)),
                ("escort corr_form=position lambda_corr=0.3", ESCORTFilter(corr_form="position", lambda_corr=0.3)),
                ("escort corr_form=position", ESCORTFilter(corr_form="position")),
                ("escort temp_schedule=constant", ESCORTFilter(temp_schedule="constant")),
                ("escort jitter=0", ESCORTFilter(jitter=0.0)),
                ("svgd repulsion=enhanced", SVGDFilter(repulsion="enhanced")),
                ("escort num_steps=15 step_size=0.15", ESCORTFilter(num_steps=15, step_size=0.15)),
                ("escort num_steps=10", ESCORTFilter(num_steps=10)),
                ("escort prior=shrunk", ESCORTFilter(prior="shrunk")),
                ("escort num_steps=15 step_size=0.15 prior=shrunk", ESCORTFilter(num_steps=15, step_size=0.15,
                                                                                 prior="shrunk")),
                ("escort anneal_cycles=4", ESCORTFilter(anneal_cycles=4)),
                ("svgd anneal_cycles=4", SVGDFilter(anneal_cycles=4)),
                ("escort bandwidth_start=4", ESCORTFilter(bandwidth_start=4.0)),
                ("escort jitter_at=start", ESCORTFilter(jitter_at="start")),
                ("escort prior=shrunk jitter_at=start", ESCORTFilter(prior="shrunk", jitter_at="start")),
                ("filter=escort_train", train_filter)]
    emit("| filter | mean Mahalanobis error | variance ratio |")
    emit("| --- | --- | --- |")
    for name, filt in variants:
        m, r = kalman_calibration(filt, steps=steps, n=particles)
        emit(f"| {name} | {m:.3f} | {r:.3f} |")
    _write_table(args.output, "calibration.md", lines)


def _write_table(output: str | None, name: str, lines: list[str]) -> None:
    """The printed table as ``<output>/<name>`` (nothing without ``--output``)."""
    if output is not None:
        from pathlib import Path

        path = Path(output) / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines) + "\n")
        print(f"results: {path.resolve()}")
