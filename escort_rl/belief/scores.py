"""The scores ESCORT's particle evolution follows: ``∇ log`` of the likelihood, of the smoothed
prior and of their sum, each with the health flags that name a model's NaN or inf.

A score term maps particles ``x`` ``[*B, N, d]`` to ``(score [*B, N, d], flags bool [*B, N, C])``
(:data:`ScoreTerm`); its ``C`` channels come with ``(lead, fix)`` message pairs (:data:`Channels`,
see :mod:`escort_rl.belief.checks`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from escort_rl.belief.checks import is_finite, log_density_channels, log_density_flags, value_channels, value_flags
from escort_rl.belief.prior import SmoothedPrior

MAX_SCORE = 1e6  # finite scores are clamped to ±MAX_SCORE; AdaGrad normalises the step anyway

ScoreTerm = Callable[[Tensor], tuple[Tensor, Tensor]]
"""A score with its health flags: ``x`` ``[*B, N, d]`` -> ``(score [*B, N, d], flags bool [*B, N, C])``,
where flag ``c`` marks the particles at which the score's source gave a NaN or an inf (see
:mod:`escort_rl.belief.checks`); it comes with ``C`` ``(lead, fix)`` message pairs."""

Channels = tuple[tuple[str, str], ...]


def autograd_score(log_density: Callable[[Tensor], Tensor], x: Tensor,
                   with_value: bool = False) -> Tensor | tuple[Tensor, Tensor]:
    """``∇_x Σ log_density(x)`` by autograd, whatever the caller's grad mode. ``x`` ``[*B, N, d]`` ->
    ``[*B, N, d]``; with ``with_value``, also the log-density ``[*B, N]`` (detached).

    Where the log-density is not finite the gradient is 0: ``−inf`` is a zero density, flat, and NaN
    or ``+inf`` is an error the caller detects from the value (:func:`~escort_rl.belief.checks.log_density_flags`).
    Such values are replaced by ``−1e30`` before the sum, so they do not turn the other particles'
    gradients into NaN.
    """

    def total(z: Tensor) -> tuple[Tensor, Tensor]:
        lp = log_density(z)
        return torch.where(is_finite(lp), lp, torch.full_like(lp, -1e30)).sum(), lp

    if torch.compiler.is_compiling():  # dynamo traces torch.func.grad, not torch.autograd.grad
        grad, lp = torch.func.grad(total, has_aux=True)(x.detach())
    else:
        with torch.enable_grad():  # eager: torch.autograd.grad has less per-call overhead
            xg = x.detach().requires_grad_(True)
            value, lp = total(xg)
            # a log-density that does not depend on x (a flat likelihood) has no graph: its gradient is 0
            grad = (torch.autograd.grad(value, xg, allow_unused=True)[0] if value.requires_grad else None)
            grad = torch.zeros_like(xg) if grad is None else grad
    lp = lp.detach()
    # 0·∞ in the backward pass of an impossible particle gives NaN: its gradient is 0 by definition
    grad = torch.where(is_finite(lp).unsqueeze(-1), grad, torch.zeros_like(grad))
    return (grad, lp) if with_value else grad


def clamp_non_finite(t: Tensor, bound: float = MAX_SCORE) -> Tensor:
    """NaN → 0 and ±inf → ±bound (finite values are left as they are). Only for the SVGD velocity,
    whose kernel can overflow for particles far apart; the scores that feed it are checked first."""
    return torch.nan_to_num(t, nan=0.0, posinf=bound, neginf=-bound)


def log_density_score(log_density: Callable[[Tensor], Tensor], name: str, fix: str) -> tuple[ScoreTerm, Channels]:
    """The :data:`ScoreTerm` of ``log_density`` (``[*B, N, d] -> [*B, N]``) by :func:`autograd_score`,
    flagging a NaN or +inf value and a non-finite gradient at a finite value; with their messages."""

    def score(x: Tensor) -> tuple[Tensor, Tensor]:
        grad, lp = autograd_score(log_density, x, with_value=True)
        return grad, log_density_flags(lp, grad)

    return score, log_density_channels(name, fix)


def likelihood_score(model, obs: Tensor, action: Tensor) -> tuple[ScoreTerm, Channels]:
    """``x ↦ ∇_x log O(obs | x, action)`` for particles ``x`` ``[*B, N, d]`` (``obs`` ``[*B, 1, obs_dim]``,
    ``action`` ``[*B, N]``) -> ``[*B, N, d]``, as a :data:`ScoreTerm` with its messages.

    Uses the model's closed-form ``observation_score`` when it has one (no autograd graph is recorded
    and replayed: cheaper per iteration, eager or compiled), flagging NaN and ±inf; otherwise
    :func:`autograd_score` through ``observation_log_prob`` (a model without a closed form works
    unchanged), flagging a NaN or +inf log-likelihood and a non-finite gradient. A ``-inf``
    log-likelihood (zero likelihood) is allowed and has a zero score.
    """
    own = getattr(model, "observation_score", None)
    where = "wherever the particles move (it may be 0 where the likelihood is flat)"
    if callable(own):

        def closed_form(x: Tensor) -> tuple[Tensor, Tensor]:
            s = own(obs, x, action)
            return s, value_flags(s)

        return closed_form, value_channels("model.observation_score",
                                           f"the model's observation_score must be finite {where}")
    fix = f"the model's observation_log_prob must be finite or -inf, with a finite gradient, {where}"
    return log_density_score(lambda z: model.observation_log_prob(obs, z, action), "model.observation_log_prob", fix)


def smoothed_prior_score(prior: SmoothedPrior) -> tuple[ScoreTerm, Channels]:
    """The :data:`ScoreTerm` of the smoothed prior (:meth:`SmoothedPrior.score`), flagging a NaN or inf
    score (its means and covariance are checked when it is built, so this is an overflow)."""

    def score(x: Tensor) -> tuple[Tensor, Tensor]:
        s = prior.score(x)
        return s, ~is_finite(s).all(-1, keepdim=True)

    return score, (("the smoothed prior's score was NaN or inf",
                    "the particles overflowed; check the scale of the model's transition_mean and "
                    "transition_scale_tril"),)


def target_score(likelihood: tuple[ScoreTerm, Channels],
                 prior: tuple[ScoreTerm, Channels]) -> tuple[Callable[[Tensor], tuple[Tensor, Tensor]], Channels]:
    """The score of ESCORT's target ``log p(x) = log-likelihood(x) + log p̂(x)`` from the two
    :data:`ScoreTerm` s: ``x`` ``[*B, N, d]`` -> ``(score [*B, N, d], counts [*B, C])``, the score clamped
    to ``±MAX_SCORE`` and ``counts`` the particles of each belief flagged by each of the ``C`` channels
    (the likelihood's, then the prior's; returned with the function). What :meth:`ESCORTFilter.evolve`
    takes as ``score_fn``."""
    likelihood_fn, lik_channels = likelihood
    prior_fn, prior_channels = prior

    def score(x: Tensor) -> tuple[Tensor, Tensor]:
        s_lik, f_lik = likelihood_fn(x)
        s_prior, f_prior = prior_fn(x)
        counts = torch.cat([f_lik, f_prior], dim=-1).sum(-2)  # [*B, C]
        return (s_lik + s_prior).clamp(-MAX_SCORE, MAX_SCORE), counts

    return score, lik_channels + prior_channels


def gaussian_fit_log_prob(x: Tensor) -> Tensor:
    """``log N(x_i; x̄, Σ̂)`` of each particle under the Gaussian with the particles' own mean and
    covariance (a ridge of ``1e-6 · tr(Σ̂)/d`` keeps it factorable; with ``N ≤ d`` particles, where
    ``Σ̂`` is singular, its diagonal): ``[*B, N, d] -> [*B, N]``; NaN for a belief whose covariance is
    not finite or cannot be factored (never an exception: :meth:`ESCORTFilter.fit` names bad particles)."""
    d = x.shape[-1]
    mean = x.mean(-2, keepdim=True)
    c = x - mean
    cov = c.transpose(-1, -2) @ c / max(x.shape[-2] - 1, 1)
    if x.shape[-2] <= d:
        cov = torch.diag_embed(torch.diagonal(cov, dim1=-2, dim2=-1))
    ridge = 1e-6 * torch.diagonal(cov, dim1=-2, dim2=-1).mean(-1).clamp_min(1e-12)
    cov = cov + ridge[..., None, None] * torch.eye(d, dtype=x.dtype, device=x.device)
    bad = ~is_finite(cov).all(-1).all(-1)  # non-finite particles: the caller's guard names them
    cov = torch.where(bad[..., None, None], torch.eye(d, dtype=x.dtype, device=x.device), cov)
    tril, info = torch.linalg.cholesky_ex(cov)
    bad = bad | (info != 0)
    tril = torch.where(bad[..., None, None], torch.eye(d, dtype=x.dtype, device=x.device), tril)
    z = torch.linalg.solve_triangular(tril, c.transpose(-1, -2), upper=False)  # [*B, d, N]
    half_log_det = torch.log(torch.diagonal(tril, dim1=-2, dim2=-1)).sum(-1, keepdim=True)
    out = -0.5 * (z * z).sum(-2) - half_log_det - 0.5 * d * math.log(2 * math.pi)
    # a belief whose moments cannot be factored gets no Gaussian: NaN, which its weights treat as impossible
    return torch.where(bad.unsqueeze(-1), torch.full_like(out, float("nan")), out)
