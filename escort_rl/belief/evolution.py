"""One iteration of ESCORT's particle evolution (:func:`evolution_step`, the part ``torch.compile``
fuses), the numbers it takes each iteration (:class:`IterationScalars`), the adaptive stop
(:class:`AdaptiveStop`) and the jitter."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from escort_rl.belief.kernels import svgd_direction
from escort_rl.belief.projections import TemporalReference, correlation_force
from escort_rl.belief.scores import clamp_non_finite
from escort_rl.belief.timing import NO_TIMER, PartTimer


class IterationScalars(NamedTuple):
    """The numbers of iteration ``k`` (:meth:`ESCORTFilter.iteration_scalars
    <escort_rl.belief.escort.ESCORTFilter.iteration_scalars>`). They travel as one tensor
    ``values`` ``[5]``, an input of a compiled step, so that it is compiled once and not once per
    iteration; ``scheduled`` (a Python bool) says whether the annealing or the bandwidth schedule is
    on, so that without them the step does not multiply by 1."""

    values: Tensor
    scheduled: bool

    @property
    def step_size(self) -> Tensor:
        """``ε_k = ε / (1 + step_decay · k)``."""
        return self.values[0]

    @property
    def adagrad_alpha(self) -> Tensor:
        """``α``, 0 at ``k = 0`` (the history starts at ``v²``)."""
        return self.values[1]

    @property
    def lambda_temp(self) -> Tensor:
        """``λ_temp,k`` (annealed, or constant)."""
        return self.values[2]

    @property
    def score_scale(self) -> Tensor:
        """``γ_k``, the annealing factor of the score in ``φ_SVGD`` (1 when off)."""
        return self.values[3]

    @property
    def bandwidth_scale(self) -> Tensor:
        """``b_k``, the bandwidth schedule's multiplier (1 when off)."""
        return self.values[4]


def evolution_step(x: Tensor, hist: Tensor, score_fn: Callable[[Tensor], tuple[Tensor, Tensor | None]],
                   bandwidth: Tensor, scalars: IterationScalars, *, repulsion: float = 1.0, proj: Tensor | None = None,
                   lambda_corr: float = 0.0, corr_form: str = "velocity", temporal: TemporalReference | None = None,
                   temp_clip: float = 10.0, timer: PartTimer | None = None,
                   active: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor | None]:
    """One ESCORT iteration: ``x ← x + ε v / (sqrt(G) + 1e-6)``, ``G ← α G + (1 − α) v²``, with the
    velocity ``v = φ_SVGD + F_corr + F_temp``.

    ``x``, ``hist`` (``G``) ``[*B, N, d]``; ``bandwidth`` ``[*B]``; ``scalars`` are this iteration's
    ``ε``, ``α``, ``λ_temp`` and schedule (:class:`IterationScalars`); ``proj``
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
    with timer("score"):
        score, bad = score_fn(x)
    with timer("kernel"):
        if scalars.scheduled:
            score, bandwidth = scalars.score_scale * score, bandwidth * scalars.bandwidth_scale
        phi = svgd_direction(x, score, bandwidth, repulsion)
    velocity = phi
    if proj is not None:
        with timer("correlation"):
            velocity = velocity + correlation_force(phi, None, None, lambda_corr, corr_form, x, proj=proj)
    if temporal is not None:
        with timer("temporal"):
            velocity = velocity + temporal.force(x, scalars.lambda_temp, temp_clip)
    with timer("step"):
        velocity = clamp_non_finite(velocity)
        alpha = scalars.adagrad_alpha
        hist = alpha * hist + (1.0 - alpha) * velocity * velocity
        move = scalars.step_size * velocity / (hist.sqrt() + 1e-6)
        if active is not None:
            move = active[..., None, None] * move
        x = x + move
    return x, hist, bad


class AdaptiveStop:
    """The adaptive stop of ``stop_tolerance`` (:class:`~escort_rl.belief.escort.SVGDParams`) over an
    evolution from particles ``x`` ``[*B, N, d]``: every ``window`` iterations, each belief whose
    mean and spread moved by less than ``tolerance`` times its spread over the window
    (:func:`moment_change`) stops moving. ``tolerance = 0``: off, every belief runs every iteration.

    ``active`` ``[*B]`` (1 while a belief moves; ``None`` when off) scales each belief's step.
    """

    def __init__(self, x: Tensor, tolerance: float, window: int) -> None:
        self.on = tolerance > 0
        self.tolerance, self.window = tolerance, window
        full = dict(dtype=x.dtype, device=x.device)
        self.active = torch.ones(x.shape[:-2], **full) if self.on else None
        self.used = torch.zeros(x.shape[:-2], **full) if self.on else None  # iterations run, per belief
        self.anchor = belief_moments(x) if self.on else None  # the moments at the window's start

    def after(self, k: int, k_total: int, x: Tensor) -> bool:
        """Count iteration ``k`` of ``k_total``, which gave ``x``; at the end of a window, freeze the
        beliefs that have converged. True when every belief has stopped (then the loop ends): one host
        synchronisation per window."""
        if not self.on:
            return False
        self.used = self.used + self.active
        if (k + 1) % self.window or k + 1 >= k_total:
            return False
        moments = belief_moments(x)
        self.active = self.active * (moment_change(self.anchor, moments) >= self.tolerance)
        self.anchor = moments
        return not bool(self.active.any())

    def iterations(self, k_total: int) -> Tensor | int:
        """The iterations each belief ran: ``[*B]``, or ``k_total`` when the stop is off."""
        return self.used if self.on else k_total


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
