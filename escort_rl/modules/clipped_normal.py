"""ClippedNormal: a Gaussian policy whose action is clipped into a box, with the clip's mass on the edge.

A continuous-action policy must act inside the box ``[low, high]``. A TanhNormal squashes a Gaussian
into it; this distribution clips one instead, as CleanRL's PPO does with an environment wrapper, but with
the clip inside the distribution, so that the log-probability PPO weighs is the one of the action the
environment received. In the box's unit coordinates (``c = (low + high)/2``, ``h = (high − low)/2``),

    u ~ N(c + h·loc, (h·scale)²),    a = clamp(u, low, high),

independently in each of the ``A`` dimensions. The law of ``a`` is a censored Gaussian: a density inside
the box and an atom on each face,

    log p(a_j) = log N(a_j; μ_j, σ_j²)      for low_j < a_j < high_j,
    log p(a_j) = log Φ((low_j − μ_j)/σ_j)   for a_j = low_j,
    log p(a_j) = log Φ((μ_j − high_j)/σ_j)  for a_j = high_j,

with ``μ = c + h·loc``, ``σ = h·scale``, and ``log p(a) = Σ_j log p(a_j)``. These are densities with
respect to one measure (Lebesgue inside, a point mass on each face), the same for every ``loc`` and
``scale``, so the ratio ``p_θ(a) / p_θ_old(a)`` PPO clips is exact.

Why it exists: a TanhNormal learning bang-bang control (a controller that pushes at full force, then
brakes) moves its mean deep into the squashing's flat part, where a small change of the mean is a large
change of the log-density of an action near the edge; PPO's epochs then move the policy far each update.
Here an action on the edge has a log-probability that tends to 0, flat in the mean, as the mean moves
past the edge, so learning to act on the edge costs nothing in stability.

``entropy()`` is the entropy of the Gaussian before the clip, ``Σ_j log(σ_j √(2πe))`` (the censored law
has an atom, so no differential entropy); PPO's entropy bonus uses it as a regulariser on the scale, as
CleanRL does with its Gaussian.

Example:
    >>> import torch
    >>> low, high = torch.full((2,), -0.1), torch.full((2,), 0.1)
    >>> d = ClippedNormal(torch.tensor([0.0, 5.0]), torch.tensor([1.0, 1.0]), low, high)
    >>> d.sample((4,)).shape, bool((d.sample((100,)).abs() <= 0.1).all())
    (torch.Size([4, 2]), True)
    >>> round(float(d.log_prob(torch.tensor([0.0, 0.1]))), 4)  # N(0; 0, 0.1²) in dim 1, Φ(4) on the edge in dim 2
    1.3836
    >>> d.deterministic_sample.tolist()  # the clipped mean
    [0.0, 0.10000000149011612]
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.distributions import Distribution, Normal, constraints


class ClippedNormal(Distribution):
    """``a = clamp(u, low, high)`` with ``u ~ N(c + h·loc, (h·scale)²)`` per dimension (see the module).

    Args:
        loc: ``[*B, A]``, the mean in the box's unit coordinates (0: the box's centre, ±1: its faces);
            any real value (past ±1 the action sits on the face most of the time).
        scale: ``[*B, A]`` (or broadcastable), positive, in the same units.
        low, high: ``[A]`` finite bounds with ``low < high``.

    ``batch_shape`` is ``B`` and ``event_shape`` is ``[A]``: ``log_prob`` sums over the ``A`` dimensions.
    """

    arg_constraints = {"loc": constraints.real, "scale": constraints.positive}
    has_rsample = True
    edge_has_mass = True  # an action on the box's face has a finite log-probability (see the module)

    def __init__(self, loc: Tensor, scale: Tensor, low: Tensor, high: Tensor, validate_args: bool | None = False):
        low, high = (torch.as_tensor(b, dtype=loc.dtype, device=loc.device) for b in (low, high))
        scale = torch.as_tensor(scale, dtype=loc.dtype, device=loc.device)
        self.loc, self.scale = torch.broadcast_tensors(loc, scale)
        self.low, self.high = low, high
        centre, half = (high + low) / 2, (high - low) / 2
        self.gaussian = Normal(centre + half * self.loc, half * self.scale, validate_args=False)
        super().__init__(self.loc.shape[:-1], self.loc.shape[-1:], validate_args=validate_args)

    @property
    def support(self):
        return constraints.independent(constraints.interval(self.low, self.high), 1)

    def _clip(self, u: Tensor) -> Tensor:
        return torch.minimum(torch.maximum(u, self.low), self.high)

    def sample(self, sample_shape: torch.Size = torch.Size()) -> Tensor:
        with torch.no_grad():
            return self._clip(self.gaussian.sample(sample_shape))

    def rsample(self, sample_shape: torch.Size = torch.Size()) -> Tensor:
        """A reparametrised sample: its gradient is the Gaussian's inside the box and 0 on a face."""
        return self._clip(self.gaussian.rsample(sample_shape))

    def log_prob(self, value: Tensor) -> Tensor:
        """``Σ_j log p(a_j)``: the Gaussian's log-density inside the box, the log of the clipped tail's mass
        on a face (``torch.special.log_ndtr``, accurate far in the tail). ``value [*S, *B, A]`` -> ``[*S, *B]``."""
        mu, sigma = self.gaussian.loc, self.gaussian.scale
        inside = self.gaussian.log_prob(value)
        below = torch.special.log_ndtr((self.low - mu) / sigma)
        above = torch.special.log_ndtr((mu - self.high) / sigma)
        per_dim = torch.where(value <= self.low, below, torch.where(value >= self.high, above, inside))
        return per_dim.sum(-1)

    def entropy(self) -> Tensor:
        """The Gaussian's entropy before the clip, ``Σ_j log(σ_j √(2πe))``, ``[*B]``."""
        return (torch.log(self.gaussian.scale) + 0.5 * math.log(2 * math.pi * math.e)).sum(-1)

    @property
    def mean(self) -> Tensor:
        """The clipped Gaussian mean ``clamp(μ, low, high)`` (the action a deterministic policy takes; the
        censored law's own mean lies closer to the centre)."""
        return self._clip(self.gaussian.loc)

    @property
    def mode(self) -> Tensor:
        return self.mean

    @property
    def deterministic_sample(self) -> Tensor:
        return self.mean
