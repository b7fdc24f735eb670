"""The stochastic ensemble Kalman filter (Evensen 1994; Burgers, van Leeuwen & Evensen 1998), batched
over beliefs ``[*B, N, d]``, on the model protocol alone.

One update, for ensemble members ``x_i`` (the belief's particles), action ``a`` and observation ``o``:

1. Forecast: ``x̃_i = transition(x_i, a)``; with ``inflation = ρ``, ``x̃_i ← x̄ + ρ (x̃_i − x̄)``.
2. Perturbed observations: ``y_i ~ O(· | x̃_i, a)`` drawn by ``model.observe``, so the filter needs
   neither an observation matrix nor the noise covariance: ``y_i − ȳ`` carries both ``H (x̃_i − x̄)``
   and the observation noise.
3. Gain from the ensemble's covariances (``N − 1`` normalised)::

       C_xy = (1/(N−1)) Σ_i (x̃_i − x̄)(y_i − ȳ)ᵀ   [d, m],    C_yy = (1/(N−1)) Σ_i (y_i − ȳ)(y_i − ȳ)ᵀ   [m, m],
       K = C_xy C_yy⁻¹,

   each tapered elementwise by the Gaspari–Cohn function of the distance between coordinates when
   ``localisation_radius`` is set (Houtekamer & Mitchell 2001).
4. Analysis: ``x_i = x̃_i + K (o − y_i)``.

For a linear-Gaussian model (``o = H s + v``) the analysis ensemble's mean and covariance converge to
the Kalman filter's as ``N → ∞``; for other models the EnKF is the Gaussian (linear-update)
approximation: it cannot hold two modes. No resampling and no weights: members are equally weighted.

Examples:
    >>> import torch
    >>> from escort_rl.models import LinearGaussian
    >>> model = LinearGaussian()
    >>> f = EnKFFilter()
    >>> b = f.init(model, (2,), 100, torch.Generator().manual_seed(0))
    >>> a = torch.zeros(2, dtype=torch.long)
    >>> f.update(model, b, a, torch.zeros(2, model.obs_dim)).particles.shape
    torch.Size([2, 100, 4])
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from escort_rl.belief.base import BeliefFilter, check_output_shape
from escort_rl.belief.checks import OFF
from escort_rl.belief.importance import effective_sample_size
from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.config.params import HasParams, build_params, param


def gaspari_cohn(r: Tensor) -> Tensor:
    """The Gaspari–Cohn (1999) compactly supported correlation function of ``r = distance / c``
    (eq. 4.10): 1 at 0, 0 from ``r = 2`` on, smooth (C²) and positive definite in 3-D. Elementwise."""
    r = r.abs()
    inner = ((((-0.25 * r + 0.5) * r + 0.625) * r - 5.0 / 3.0) * r * r) + 1.0
    outer = (((((r / 12.0 - 0.5) * r + 0.625) * r + 5.0 / 3.0) * r - 5.0) * r + 4.0 - 2.0 / (3.0 * r.clamp_min(1e-12)))
    return torch.where(r <= 1.0, inner, torch.where(r < 2.0, outer, torch.zeros_like(r)))


def coordinates(model, kind: str, size: int, state_dim: int) -> Tensor:
    """Where each state (``kind="state"``) or observation (``"observation"``) coordinate lies, for
    localisation: ``model.state_coordinates`` / ``model.observation_coordinates`` (``[size]`` or
    ``[size, k]``) when the model defines them, else the index (state ``i``; observation ``j`` spread
    over the state's index range, ``j · d / m``). Returns ``[size, k]`` float32."""
    own = getattr(model, f"{kind}_coordinates", None)
    if own is not None:
        where = f"model.{kind}_coordinates"
        try:
            c = torch.as_tensor(own, dtype=torch.float32)
        except (TypeError, ValueError, RuntimeError):
            raise ValueError(f"{where}: expected a list or tensor of positions, [{size}] or [{size}, k], got "
                             f"{type(own).__name__} {own!r:.60}") from None
        c = c.unsqueeze(-1) if c.ndim == 1 else c
        if c.ndim != 2 or c.shape[0] != size:
            raise ValueError(f"{where}: expected {size} rows ([{size}] or [{size}, k]: where each {kind} coordinate "
                             f"lies), got shape {tuple(c.shape)}")
        if not bool(torch.isfinite(c).all()):
            raise ValueError(f"{where}: expected finite positions, got NaN or inf (the taper would cut every "
                             "correlation of that coordinate); give each coordinate a finite position")
        return c
    index = torch.arange(size, dtype=torch.float32)
    return (index if kind == "state" else index * state_dim / max(size, 1)).unsqueeze(-1)


MIN_MEMBERS = "EnKFFilter needs at least 2 particles (its gain is the ensemble's covariance)"


@dataclass(frozen=True)
class EnKFParams:
    """:class:`EnKFFilter`'s parameters.

    Attributes:
        inflation: multiplicative covariance inflation ``ρ ≥ 1`` of the forecast anomalies (1: off).
            Small ensembles underestimate their spread; ``ρ`` slightly above 1 counters it.
        localisation_radius: the Gaspari–Cohn half-width ``c`` of the taper applied to ``C_xy`` and
            ``C_yy``, in the units of the model's coordinates (:func:`coordinates`); correlations
            beyond ``2c`` are cut. ``None``: off.
        ridge: added to the diagonal of ``C_yy``, times its mean diagonal, so that ``C_yy`` stays
            invertible when ``N ≤ m``.
    """

    inflation: float = param(1.0, ge=1)
    localisation_radius: Optional[float] = param(None, gt=0)
    ridge: float = param(1e-6, ge=0)


class EnKFFilter(HasParams, BeliefFilter):
    """The stochastic ensemble Kalman filter with perturbed observations (see the module docstring).

    Takes :class:`EnKFParams` (or its fields as keyword arguments: ``EnKFFilter(inflation=1.05)``).

    Attribute ``check_finite`` (default True; see :class:`BeliefFilter`): raise a ``ValueError``
    naming the culprit when the input belief, what ``model.transition`` or ``model.observe`` returns,
    or the result holds a NaN or an inf. One host synchronisation per update.
    """

    Params = EnKFParams

    def __init__(self, params: EnKFParams | None = None, **kwargs) -> None:
        self.params = build_params(EnKFParams, params, kwargs, owner=type(self).__name__)

    def __repr__(self) -> str:
        extra = "" if self.check_finite else ", check_finite=False"
        return (f"EnKFFilter(inflation={self.inflation}, localisation_radius={self.localisation_radius}, "
                f"ridge={self.ridge}{extra})")

    def tapers(self, model, d: int, m: int, like: Tensor) -> tuple[Tensor, Tensor] | None:
        """The Gaspari–Cohn tapers ``[d, m]`` of ``C_xy`` and ``[m, m]`` of ``C_yy``, or ``None``."""
        if self.localisation_radius is None:
            return None
        xs, ys = coordinates(model, "state", d, d), coordinates(model, "observation", m, d)
        if xs.shape[1] != ys.shape[1]:
            raise ValueError(f"model.state_coordinates, model.observation_coordinates: expected positions in the same "
                             f"space, got {xs.shape[1]} and {ys.shape[1]} columns; give both [size, k] with one k")
        c = self.localisation_radius
        taper_xy = gaspari_cohn(torch.cdist(xs, ys) / c)
        taper_yy = gaspari_cohn(torch.cdist(ys, ys) / c)
        return taper_xy.to(like), taper_yy.to(like)

    def init(self, model, batch_shape, num_particles, generator=None, start_state=None) -> ParticleBelief:
        """As :meth:`BeliefFilter.init`, with at least 2 particles (the gain is the ensemble's covariance)."""
        if isinstance(num_particles, int) and num_particles == 1:
            raise ValueError(f"num_particles: {MIN_MEMBERS}, got 1; use num_particles >= 2")
        return super().init(model, batch_shape, num_particles, generator, start_state)

    def _update(self, model, belief, action, observation, generator, *, guard=None):
        guard = OFF if guard is None else guard
        x = belief.particles
        n, d = x.shape[-2], x.shape[-1]
        if n < 2:
            raise ValueError(f"belief.particles: {MIN_MEMBERS}, got {n} per belief; build it with num_particles >= 2")
        x_pred, a = self._predict(model, belief, action, generator, guard)
        w = belief.weights().unsqueeze(-1)  # [*B, N, 1]; equal for an EnKF's own beliefs
        mean = (w * x_pred).sum(-2, keepdim=True)
        if self.inflation != 1.0:
            x_pred = mean + self.inflation * (x_pred - mean)
        y = model.observe(x_pred, a, generator)
        check_output_shape("model.observe", y, (*x.shape[:-1], observation.shape[-1]),
                           "one observation per particle, [*B, N, obs_dim]", dtype=x.dtype)
        guard.model_values("model.observe", y)
        m = y.shape[-1]
        dx = x_pred - mean
        dy = y - (w * y).sum(-2, keepdim=True)
        scale = n / max(n - 1, 1)  # weighted covariances with the N − 1 normalisation at equal weights
        c_xy = scale * (w * dx).transpose(-1, -2) @ dy  # [*B, d, m]
        c_yy = scale * (w * dy).transpose(-1, -2) @ dy  # [*B, m, m]
        tapers = self.tapers(model, d, m, c_xy)
        if tapers is not None:
            c_xy, c_yy = c_xy * tapers[0], c_yy * tapers[1]
        eye = torch.eye(m, dtype=c_yy.dtype, device=c_yy.device)
        jitter = self.ridge * torch.diagonal(c_yy, dim1=-2, dim2=-1).mean(-1).clamp_min(1e-12)
        c_yy = c_yy + jitter[..., None, None] * eye
        innovations = observation.unsqueeze(-2) - y  # [*B, N, m]
        # K (o − y_i) = C_xy C_yy⁻¹ (o − y_i), for every member at once: solve C_yy Z = (o − y)ᵀ
        try:
            z = torch.linalg.solve(c_yy, innovations.transpose(-1, -2))  # [*B, m, N]
        except torch.linalg.LinAlgError:
            raise ValueError(f"EnKFFilter.ridge: the ensemble's observation covariance is singular ({n} particles, "
                             f"obs_dim {m}, ridge={self.ridge}); set ridge > 0 (default 1e-6), or use more particles "
                             "than obs_dim with a model.observe that draws noise") from None
        x_post = x_pred + (c_xy @ z).transpose(-1, -2)
        # the ensemble's Gaussian predictive density N(o; ȳ, C_yy) of the observation
        increment = gaussian_log_density(observation - (w * y).sum(-2), c_yy)
        ess = effective_sample_size(belief.log_weights)  # the EnKF moves its members, it does not weigh them
        return ParticleBelief(x_post, belief.log_weights).diagnosed(increment, ess, previous=belief)


def gaussian_log_density(residual: Tensor, covariance: Tensor) -> Tensor:
    """``log N(r; 0, S)`` of residuals ``r`` ``[*B, m]`` under covariances ``S`` ``[*B, m, m]``:
    ``−½ (m log 2π + log det S + rᵀ S⁻¹ r)``, by the Cholesky factor of ``S``.

    Example:
        >>> round(float(gaussian_log_density(torch.zeros(1), torch.eye(1))), 4)  # −½ log 2π
        -0.9189
    """
    chol = torch.linalg.cholesky(covariance)
    z = torch.linalg.solve_triangular(chol, residual.unsqueeze(-1), upper=False).squeeze(-1)
    log_det = 2 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    return -0.5 * (residual.shape[-1] * math.log(2 * math.pi) + log_det + (z * z).sum(-1))
