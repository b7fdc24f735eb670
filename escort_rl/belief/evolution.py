"""One iteration of ESCORT's particle evolution (:func:`evolution_step`, the part ``torch.compile``
fuses), the moments the adaptive stop watches, and the jitter."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from escort_rl.belief.kernels import svgd_direction
from escort_rl.belief.projections import TemporalReference, correlation_force
from escort_rl.belief.scores import clamp_non_finite
from escort_rl.belief.timing import NO_TIMER, PartTimer


def evolution_step(x: Tensor, hist: Tensor, score_fn: Callable[[Tensor], tuple[Tensor, Tensor | None]],
                   bandwidth: Tensor, scalars: Tensor, *, repulsion: float = 1.0, proj: Tensor | None = None,
                   lambda_corr: float = 0.0, corr_form: str = "velocity", temporal: TemporalReference | None = None,
                   temp_clip: float = 10.0, timer: PartTimer | None = None,
                   active: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor | None]:
    """One ESCORT iteration: ``x ← x + ε v / (sqrt(G) + 1e-6)``, ``G ← α G + (1 − α) v²``, with the
    velocity ``v = φ_SVGD + F_corr + F_temp``.

    ``x``, ``hist`` (``G``) ``[*B, N, d]``; ``bandwidth`` ``[*B]``; ``scalars`` ``[3]`` or ``[5]`` holds
    ``(ε, α, λ_temp)`` of this iteration and, when given, the annealing factor ``γ`` that multiplies
    the score in ``φ_SVGD`` and the bandwidth's multiplier (:meth:`ESCORTFilter.schedule`); ``proj``
    ``[*B, d, d]`` is ``Σ_k w_k A_k A_kᵀ`` (``None``
    turns ``F_corr`` off); ``temporal`` is the sorted reference of ``F_temp`` (``None`` turns it off).
    ``score_fn(x)`` gives the score ``[*B, N, d]`` and the counts ``[*B, C]`` of particles at which
    its sources gave NaN or inf (or ``None``): they are passed on, never read here (no host sync).
    ``active`` ``[*B]`` (1 or 0; ``None``: all 1) scales each belief's step: the adaptive stop freezes
    the beliefs that have converged.
    Pure apart from ``timer``, so ``torch.compile`` fuses it whole. Returns the new ``(x, hist)`` and
    the counts.

    The velocity's NaN → 0 and ±inf → ±``MAX_SCORE`` (:func:`~escort_rl.belief.scores.clamp_non_finite`)
    guards against the kernel
    overflowing for particles far apart; a non-finite score shows in the counts, not hidden by it.
    """
    timer = timer or NO_TIMER
    eps, alpha, lam_temp = scalars[0], scalars[1], scalars[2]
    with timer("score"):
        score, bad = score_fn(x)
    with timer("kernel"):
        if scalars.shape[0] > 3:  # annealing and the bandwidth schedule (1 and 1 when off)
            phi = svgd_direction(x, scalars[3] * score, bandwidth * scalars[4], repulsion)
        else:
            phi = svgd_direction(x, score, bandwidth, repulsion)
    velocity = phi
    if proj is not None:
        with timer("correlation"):
            velocity = velocity + correlation_force(phi, None, None, lambda_corr, corr_form, x, proj=proj)
    if temporal is not None:
        with timer("temporal"):
            velocity = velocity + temporal.force(x, lam_temp, temp_clip)
    with timer("step"):
        velocity = clamp_non_finite(velocity)
        hist = alpha * hist + (1.0 - alpha) * velocity * velocity
        move = eps * velocity / (hist.sqrt() + 1e-6)
        if active is not None:
            move = active[..., None, None] * move
        x = x + move
    return x, hist, bad


def belief_moments(x: Tensor) -> tuple[Tensor, Tensor]:
    """The mean ``[*B, d]`` and per-coordinate standard deviation ``[*B, d]`` of equally weighted
    particles ``x`` ``[*B, N, d]``."""
    mean = x.mean(-2)
    return mean, (x - mean.unsqueeze(-2)).pow(2).mean(-2).sqrt()


def moment_change(before: tuple[Tensor, Tensor], after: tuple[Tensor, Tensor], eps: float = 1e-12) -> Tensor:
    """How far a belief moved, relative to its spread: ``max(‖μ' − μ‖, ‖σ' − σ‖) / ‖σ‖`` per belief,
    for the moments ``(μ, σ)`` of :func:`belief_moments` (``[*B, d]`` each) -> ``[*B]``."""
    (m0, s0), (m1, s1) = before, after
    scale = torch.linalg.vector_norm(s0, dim=-1).clamp_min(eps)
    return torch.maximum(torch.linalg.vector_norm(m1 - m0, dim=-1), torch.linalg.vector_norm(s1 - s0, dim=-1)) / scale


def jittered(x: Tensor, std: float, generator: torch.Generator | None) -> Tensor:
    """``x + std · ε``, ``ε ~ N(0, I)`` of ``x``'s shape, device and dtype."""
    return x + std * torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
