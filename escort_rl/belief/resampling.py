"""Resampling schemes and the effective sample size, batched over beliefs.

A resampling scheme turns ``N`` weighted particles into ``M`` equally weighted ones by drawing
ancestor indices. Every scheme here is *unbiased*: the number of offspring ``Nᵢ`` of particle ``i``
has ``E[Nᵢ] = M·wᵢ``, with ``w = softmax(log_weights)``. They differ in the variance of ``Nᵢ``, which is
noise the filter adds for nothing:

- :func:`multinomial`: ``M`` independent draws from ``w``. ``Var Nᵢ = M·wᵢ(1 − wᵢ)``, the largest;
  the textbook scheme, a baseline.
- :func:`residual`: ``⌊M·wᵢ⌋`` copies of each particle, then the ``R = M − Σ⌊M·wᵢ⌋`` left over drawn
  multinomially from the residual weights ``rᵢ ∝ M·wᵢ − ⌊M·wᵢ⌋``: ``Var Nᵢ = R·rᵢ(1 − rᵢ)``.
- :func:`stratified`: one uniform in each of the ``M`` strata ``[k/M, (k+1)/M)``, inverted through
  the cumulative weights.
- :func:`systematic`: the same strata with one uniform shared by all of them. ``Nᵢ`` is ``⌊M·wᵢ⌋``
  or ``⌈M·wᵢ⌉``, so ``Var Nᵢ = f(1 − f)`` with ``f`` the fractional part of ``M·wᵢ``: the least
  possible for each particle alone. The default of :class:`~escort_rl.belief.SIRFilter`.

Douc and Cappé (2005, *Comparison of resampling schemes for particle filtering*) show that residual
and stratified resampling never have a larger conditional variance than multinomial; systematic has
no such guarantee in general (its counts are dependent across particles) but is usually the best in
practice, and the cheapest. When to resample at all is the effective sample size's job:
:func:`effective_sample_size` (of :mod:`~escort_rl.belief.importance`) ``= 1 / Σ wᵢ²`` is ``N`` for
equal weights and 1 when one particle holds them all; a filter resamples when ``ESS / N`` falls below
its threshold.

Every function takes log-weights ``[*B, N]`` (not necessarily normalised; ``-inf`` is weight 0) and
returns int64 ancestor indices ``[*B, M]`` with ``M = num_samples`` (default ``N``), drawing its
uniforms from ``generator``. A row whose weights are not finite (all ``-inf``, or a NaN) is resampled
as if its weights were equal. :data:`SCHEMES` maps each scheme's name (``filter.resampling``) to its
function, and :func:`resample_indices` dispatches on it.

Examples:
    >>> g = torch.Generator().manual_seed(0)
    >>> log_w = torch.log(torch.tensor([0.5, 0.0, 0.5]))
    >>> systematic(log_w, g, num_samples=4)
    tensor([0, 0, 2, 2])
    >>> effective_sample_size(log_w)
    tensor(2.)
    >>> sorted(SCHEMES)
    ['multinomial', 'residual', 'stratified', 'systematic']
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from escort_rl.belief.importance import effective_sample_size, normalised_weights

__all__ = ["SCHEMES", "effective_sample_size", "multinomial", "resample_indices", "residual", "stratified",
           "systematic"]


def _weights(log_weights: Tensor) -> Tensor:
    """:func:`~escort_rl.belief.importance.normalised_weights` ``[*B, N]``, with a row that is not finite
    (a NaN) resampled as if its weights were equal."""
    w = normalised_weights(log_weights)
    return torch.where(torch.isfinite(w).all(-1, keepdim=True), w, torch.full_like(w, 1.0 / w.shape[-1]))


def _num_samples(log_weights: Tensor, num_samples: int | None) -> int:
    m = log_weights.shape[-1] if num_samples is None else int(num_samples)
    if m < 1:
        raise ValueError(f"num_samples: expected at least 1 index per belief, got {num_samples}")
    return m


def _invert_cdf(w: Tensor, positions: Tensor) -> Tensor:
    """The indices ``i`` with ``C_{i-1} ≤ p < C_i`` of ``positions`` ``[*B, M]`` in ``[0, 1)``, where ``C``
    is the cumulative sum of ``w`` ``[*B, N]`` rescaled to end exactly at 1 (a trailing zero weight is
    never drawn)."""
    n = w.shape[-1]
    cdf = torch.cumsum(w, dim=-1)
    cdf = cdf / cdf[..., -1:]
    one = torch.ones((), dtype=w.dtype, device=w.device)
    positions = positions.clamp_max(torch.nextafter(one, torch.zeros_like(one)))  # (u + M − 1)/M may round to 1
    return torch.searchsorted(cdf.contiguous(), positions.contiguous(), right=True).clamp_max(n - 1)


def _uniforms(log_weights: Tensor, m: int, generator: torch.Generator | None, dtype: torch.dtype) -> Tensor:
    return torch.rand((*log_weights.shape[:-1], m), generator=generator, device=log_weights.device, dtype=dtype)


def multinomial(log_weights: Tensor, generator: torch.Generator | None = None,
                num_samples: int | None = None) -> Tensor:
    """Multinomial resampling: ``M`` independent draws from ``w``, as sorted uniforms inverted through
    the cumulative weights (the indices come out non-decreasing).

    Examples:
        >>> g = torch.Generator().manual_seed(0)
        >>> multinomial(torch.log(torch.tensor([0.0, 1.0])), g, num_samples=3)
        tensor([1, 1, 1])
    """
    m = _num_samples(log_weights, num_samples)
    w = _weights(log_weights)
    return _invert_cdf(w, _uniforms(log_weights, m, generator, w.dtype).sort(-1).values)


def stratified(log_weights: Tensor, generator: torch.Generator | None = None,
               num_samples: int | None = None) -> Tensor:
    """Stratified resampling: position ``k`` is ``(uₖ + k)/M`` with ``uₖ ~ U[0, 1)`` independent.

    Examples:
        >>> g = torch.Generator().manual_seed(0)
        >>> stratified(torch.log(torch.tensor([0.25, 0.25, 0.5])), g)
        tensor([0, 2, 2])
    """
    m = _num_samples(log_weights, num_samples)
    w = _weights(log_weights)
    k = torch.arange(m, device=w.device, dtype=w.dtype)
    return _invert_cdf(w, (_uniforms(log_weights, m, generator, w.dtype) + k) / m)


def systematic(log_weights: Tensor, generator: torch.Generator | None = None,
               num_samples: int | None = None) -> Tensor:
    """Systematic resampling: position ``k`` is ``(u + k)/M`` with one ``u ~ U[0, 1)`` per belief.

    Examples:
        >>> g = torch.Generator().manual_seed(0)
        >>> systematic(torch.log(torch.tensor([0.5, 0.0, 0.5])), g, num_samples=4)
        tensor([0, 0, 2, 2])
    """
    m = _num_samples(log_weights, num_samples)
    w = _weights(log_weights)
    k = torch.arange(m, device=w.device, dtype=w.dtype)
    return _invert_cdf(w, (_uniforms(log_weights, 1, generator, w.dtype) + k) / m)


def residual(log_weights: Tensor, generator: torch.Generator | None = None,
             num_samples: int | None = None) -> Tensor:
    """Residual resampling: ``⌊M·wᵢ⌋`` copies of particle ``i``, then the ``R`` left over drawn by
    multinomially from the residual weights ``M·wᵢ − ⌊M·wᵢ⌋``. Batched: every belief draws ``M``
    independent residual candidates and keeps its first ``R``.

    Examples:
        >>> g = torch.Generator().manual_seed(0)
        >>> residual(torch.log(torch.tensor([0.5, 0.25, 0.25])), g, num_samples=4)
        tensor([0, 0, 1, 2])
    """
    m = _num_samples(log_weights, num_samples)
    w = _weights(log_weights.double())
    scaled = m * w
    # M·w of float32 log-weights is off by a few ulps: 0.9999999 must still give its one copy
    slack = 4 * m * torch.finfo(log_weights.dtype).eps if log_weights.is_floating_point() else 0.0
    copies = torch.floor(scaled + slack)  # [*B, N]
    left = m - copies.sum(-1, keepdim=True)  # [*B, 1]: R
    remainder = (scaled - copies).clamp_min(0)
    remainder = torch.where(remainder.sum(-1, keepdim=True) > 0, remainder, torch.ones_like(remainder))
    drawn = _invert_cdf(remainder, _uniforms(log_weights, m, generator, w.dtype))  # [*B, M], independent
    keep = torch.arange(m, device=w.device) < left  # [*B, M]: the first R of the draws
    counts = copies.scatter_add(-1, drawn, keep.to(copies.dtype))  # [*B, N]: offspring per particle
    ends = counts.cumsum(-1)
    slots = torch.arange(m, device=w.device, dtype=ends.dtype).expand(*ends.shape[:-1], m)
    return torch.searchsorted(ends.contiguous(), slots.contiguous(), right=True).clamp_max(w.shape[-1] - 1)


SCHEMES: dict[str, Callable[..., Tensor]] = {
    "multinomial": multinomial,
    "residual": residual,
    "stratified": stratified,
    "systematic": systematic,
}
"""Each scheme's function by its name (``filter.resampling``)."""


def resample_indices(log_weights: Tensor, scheme: str = "systematic", generator: torch.Generator | None = None,
                     num_samples: int | None = None) -> Tensor:
    """Ancestor indices ``[*B, M]`` of ``log_weights`` ``[*B, N]`` by the scheme named ``scheme``."""
    try:
        fn = SCHEMES[scheme]
    except KeyError:
        raise ValueError(f"resampling: unknown scheme {scheme!r}; expected one of {sorted(SCHEMES)}") from None
    return fn(log_weights, generator, num_samples)
