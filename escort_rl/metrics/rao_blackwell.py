"""Rao-Blackwellised SMC: particles on the part of the state that needs them, the rest in closed form.

Where a model's state splits as ``s = (x, z)`` so that, given the path of ``x``, the posterior of ``z`` is
a Gaussian sum, a particle filter need only sample ``x`` (Doucet et al. 2000, "Rao-Blackwellised particle
filtering for dynamic Bayesian networks"). Each particle ``i`` carries its ``x_i`` and the exact posterior
of ``z`` given its path, ``Σ_j w_ij N(m_ij, diag v_i)``: the components share a diagonal covariance. The
posterior over the whole state is the mixture

    p(x, z | o_1:t) ≈ Σ_i W_i δ(x − x_i) Σ_j w_ij N(z; m_ij, diag v_i),

whose only Monte Carlo error is in the ``x_i``: the weights of ``z``'s modes, which a plain particle filter
must estimate from how many particles each mode kept, are computed exactly given the paths.

**The model's side** (the hidden goal's :class:`~escort_rl.models.hidden_goal.HiddenGoal` gives it):

- ``rao_blackwell_dims``: ``(x_dims, z_dims)``, the state's indices of each part;
- ``rao_blackwell_prior(batch, n, generator) -> (x, log_w, means, var)``: ``n`` draws of ``x``'s prior
  ``[B, n, dx]``, each with ``z``'s prior given it: normalised log weights ``[B, n, M]``, means
  ``[B, n, M, dz]`` and the shared diagonal variance ``[B, n, dz]``, float64;
- ``rao_blackwell_step(x, log_w, means, var, action, observation, generator) -> (x, log_w, means, var,
  log_increment)``: every particle moved by the model's proposal ``q(x' | x, o)``, its Gaussian sum updated
  exactly given ``x'``, and ``log_increment`` ``[B, n]`` the log of its incremental weight
  ``p(o | x', path) p(x' | x) / q(x' | x, o)``. ``action`` ``[B]``, ``observation`` ``[B, obs_dim]``.

Optionally, ``rao_blackwell_first_step(batch, n, action, observation, generator)``: the prior and the first
step in one, with the same returns as ``rao_blackwell_step``, its start drawn from its posterior given the first
reading (a fully adapted start). Prior draws weighted by a sharp first reading keep a share of their ESS that
falls geometrically with the dimension.

**The filter** (:class:`RaoBlackwellisedSMC`): ``log W += log_increment`` each step, then systematic
resampling of whole particles (``x`` with its Gaussian sum) when ESS/n < 0.5, as the bootstrap reference
does.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from escort_rl.belief.resampling import effective_sample_size, systematic
from escort_rl.metrics.moments import weighted_moments

MEMBERS = ("rao_blackwell_dims", "rao_blackwell_prior", "rao_blackwell_step")
"""What a model gives to be filtered by :class:`RaoBlackwellisedSMC` (the module docstring)."""


def has_rao_blackwell_form(model) -> bool:
    """Whether ``model`` gives every member of :data:`MEMBERS`."""
    return all(getattr(model, m, None) is not None for m in MEMBERS)


def _state_order(x_dims, z_dims) -> Tensor:
    """The columns of ``cat([x, z], -1)`` in the state's order: column ``k`` of the result is state dim ``k``.

    Example (x holds state dims 1 and 2, z dim 0: state dim 0 is column 2 of ``cat([x, z])``):
        >>> _state_order((1, 2), (0,)).tolist()
        [2, 0, 1]
    """
    return torch.argsort(torch.tensor([*x_dims, *z_dims]))


class ConditionalParticles(NamedTuple):
    """A Rao-Blackwellised belief of ``B`` beliefs of ``n`` particles, float64: ``x`` ``[B, n, dx]``,
    ``log_weights`` ``[B, n]`` (the particles'), and per particle ``z``'s Gaussian sum: ``mode_log_weights``
    ``[B, n, M]`` (normalised), ``mode_means`` ``[B, n, M, dz]``, ``variance`` ``[B, n, dz]``; ``at_prior``: the
    belief is :meth:`RaoBlackwellisedSMC.init`'s, not yet updated."""

    x: Tensor
    log_weights: Tensor
    mode_log_weights: Tensor
    mode_means: Tensor
    variance: Tensor
    at_prior: bool = False


class RaoBlackwellisedSMC:
    """The Rao-Blackwellised particle filter of a model that gives :data:`MEMBERS` (module docstring).

    Example:
        >>> from escort_rl.models import HiddenGoal
        >>> m, f = HiddenGoal(dim=2, modes=2), RaoBlackwellisedSMC()
        >>> g = torch.Generator().manual_seed(0)
        >>> b = f.init(m, 1, 100, g)
        >>> mean, cov = f.moments(m, b)
        >>> tuple(mean.shape), tuple(cov.shape), round(float(mean[0, 2:].abs().max()), 6)
        ((1, 4), (1, 4, 4), 0.0)
    """

    resample_threshold = 0.5

    def __init__(self) -> None:
        self.last_ess_fraction: Tensor | None = None
        """ESS/n of each belief's weights after the last update's reweighting, before it resampled."""

    @staticmethod
    def check(model) -> None:
        """Raise a ``ValueError`` naming every member of :data:`MEMBERS` that ``model`` lacks."""
        missing = [m for m in MEMBERS if getattr(model, m, None) is None]
        if missing:
            raise ValueError(f"--reference-filter rao_blackwell: {type(model).__name__} lacks {', '.join(missing)}; "
                             "a model whose state is (x, z) with z a Gaussian sum given x's path gives them "
                             "(escort_rl.belief.rao_blackwell), else use resample_move or sir")

    def init(self, model, batch: int, n: int, generator: torch.Generator | None = None) -> ConditionalParticles:
        """``n`` particles of the prior for each of ``batch`` beliefs, equally weighted."""
        self.check(model)
        x, log_w, means, var = model.rao_blackwell_prior(batch, n, generator)
        return ConditionalParticles(x, torch.full((batch, n), -math.log(n), dtype=torch.float64), log_w, means, var,
                                    at_prior=True)

    def update(self, model, b: ConditionalParticles, action: Tensor, observation: Tensor,
               generator: torch.Generator | None = None) -> ConditionalParticles:
        """One step: the model's proposal and exact conditional update, the weights, and systematic
        resampling of the beliefs whose ESS/n fell below :attr:`resample_threshold`. The first update after
        :meth:`init` is the model's ``rao_blackwell_first_step`` where it gives one (module docstring)."""
        first = getattr(model, "rao_blackwell_first_step", None) if b.at_prior else None
        if first is not None:
            bsz, n = b.log_weights.shape
            x, log_w, means, var, inc = first(bsz, n, action, observation, generator)
        else:
            x, log_w, means, var, inc = model.rao_blackwell_step(b.x, b.mode_log_weights, b.mode_means, b.variance,
                                                                 action, observation, generator)
        logw = b.log_weights + inc
        logw = logw - torch.logsumexp(logw, -1, keepdim=True)
        self.last_ess_fraction = effective_sample_size(logw) / logw.shape[-1]
        return self.resample(ConditionalParticles(x, logw, log_w, means, var),
                             self.last_ess_fraction < self.resample_threshold, generator)

    @staticmethod
    def resample(b: ConditionalParticles, where: Tensor, generator: torch.Generator | None = None
                 ) -> ConditionalParticles:
        """Systematic resampling of whole particles (each ``x_i`` with its Gaussian sum) in the beliefs
        ``where`` ``[B]`` (bool), to equal weights; the other beliefs unchanged."""
        if not bool(where.any()):
            return b
        n = b.log_weights.shape[-1]
        idx = torch.where(where[:, None], systematic(b.log_weights, generator), torch.arange(n))  # [B, n]

        def pick(t: Tensor) -> Tensor:
            return t.gather(1, idx.reshape(*idx.shape, *([1] * (t.dim() - 2))).expand(*idx.shape, *t.shape[2:]))

        logw = torch.where(where[:, None], torch.full_like(b.log_weights, -math.log(n)), b.log_weights)
        return ConditionalParticles(pick(b.x), logw, pick(b.mode_log_weights), pick(b.mode_means), pick(b.variance))

    @staticmethod
    def _components(model, b: ConditionalParticles) -> tuple[Tensor, Tensor, Tensor]:
        """The mixture's components ``(i, j)`` in state order: centres ``[B, n·M, d]``, probabilities
        ``[B, n·M]`` and the variance of each centre's ``z`` part ``[B, n·M, dz]``."""
        xd, zd = model.rao_blackwell_dims
        bsz, n, m, dz = b.mode_means.shape
        centres = torch.cat([b.x.unsqueeze(-2).expand(bsz, n, m, len(xd)), b.mode_means], -1)
        centres = centres[..., _state_order(xd, zd)]
        prob = torch.softmax(b.log_weights, -1).unsqueeze(-1) * torch.softmax(b.mode_log_weights, -1)
        var = b.variance.unsqueeze(-2).expand(bsz, n, m, dz)
        return centres.reshape(bsz, n * m, -1), prob.reshape(bsz, n * m), var.reshape(bsz, n * m, dz)

    def moments(self, model, b: ConditionalParticles) -> tuple[Tensor, Tensor]:
        """The mixture's exact mean ``[B, d]`` and covariance ``[B, d, d]`` given the particles:
        ``Σ π c`` and ``Σ π (c cᵀ + diag v) − m mᵀ`` over the components ``(i, j)``, ``π_ij = W_i w_ij``."""
        centres, prob, var = self._components(model, b)
        mean, cov = weighted_moments(centres, prob)
        zd = list(model.rao_blackwell_dims[1])
        cov[..., zd, zd] += (prob.unsqueeze(-1) * var).sum(-2)
        return mean, cov

    def draws(self, model, b: ConditionalParticles, m: int, generator: torch.Generator | None = None) -> Tensor:
        """``m`` equally weighted draws ``[B, m, d]`` of the mixture: a particle ``i`` by systematic resampling of
        ``W``, then a component ``j ~ w_i·`` and ``z ~ N(m_ij, diag v_i)``, each independently. (Systematic
        resampling over the components ``(i, j)`` at once would alias: consecutive components sit in different
        modes, and its evenly spaced draws would favour some modes over others.)"""
        xd, zd = model.rao_blackwell_dims
        i = systematic(b.log_weights, generator, m)  # [B, m]
        w = torch.softmax(b.mode_log_weights, -1).gather(1, i[..., None].expand(*i.shape, b.mode_log_weights.shape[-1]))
        j = torch.multinomial(w.reshape(-1, w.shape[-1]), 1, generator=generator).reshape(i.shape)  # [B, m]
        dz = b.mode_means.shape[-1]
        means = b.mode_means.gather(1, i[..., None, None].expand(*i.shape, *b.mode_means.shape[2:]))  # [B, m, M, dz]
        z = means.gather(2, j[..., None, None].expand(*j.shape, 1, dz)).squeeze(2)
        v = b.variance.gather(1, i[..., None].expand(*i.shape, dz))
        z = z + v.sqrt() * torch.randn(z.shape, generator=generator, dtype=z.dtype, device=z.device)
        x = b.x.gather(1, i[..., None].expand(*i.shape, b.x.shape[-1]))
        return torch.cat([x, z], -1)[..., _state_order(xd, zd)]
