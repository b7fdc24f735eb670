"""A linear-Gaussian POMDP. Its exact posterior is the Kalman filter, so it calibrates the filters.

    s' = F s + u_a + w,   w ~ N(0, Q)
    o  = H s' + v,        v ~ N(0, R)
    s_0 ~ N(m_0, P_0)

Actions select a control offset ``u_a`` from a fixed table ``[n_actions, d]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from escort_rl.config.params import HasParams, build_params, param
from escort_rl.models.gaussian import GaussianNoise


@dataclass(frozen=True)
class LinearGaussianParams:
    """:class:`LinearGaussian`'s scalar family: the sizes and the scales its matrices default to, so
    that a config can build the model by dimension and observation sharpness
    (``env=linear_gaussian env.model.state_dim=100 env.model.obs_std=0.1``).

    Attributes:
        state_dim: ``d``, the state dimension.
        obs_dim: ``m``, the observation dimension; ``None``: every coordinate is observed (``m = d``).
        n_actions: the number of actions; ``None``: one per row of the control table (``2d`` by default).
        transition_scale: ``F = transition_scale·I`` unless a transition matrix is given.
        process_std: ``Q = process_std²·I`` unless a process covariance is given (default sqrt(0.1)).
        obs_std: ``R = obs_std²·I`` unless an observation covariance is given.
        prior_std: ``P_0 = prior_std²·I`` unless a prior covariance is given.
    """

    state_dim: int = param(4, ge=1)
    obs_dim: Optional[int] = param(None, ge=1)
    n_actions: Optional[int] = param(None, ge=1)
    transition_scale: float = param(0.95)
    process_std: float = param(0.1 ** 0.5, gt=0)
    obs_std: float = param(0.5, gt=0)
    prior_std: float = param(1.0, gt=0)


class LinearGaussian(HasParams):
    """Linear-Gaussian model with dense matrices (float32 on ``device``).

    Takes :class:`LinearGaussianParams` (or its fields as keyword arguments), ``device``, and any of
    the matrices, which replace the scalar family's defaults (tensors or nested lists, so they are
    arguments, not config values):

    - ``transition_matrix``: ``F`` ``[d, d]``; default ``transition_scale·I``;
    - ``process_cov``: ``Q`` ``[d, d]``; default ``process_std²·I``;
    - ``observation_matrix``: ``H`` ``[m, d]``; default the first ``m`` coordinates;
    - ``observation_cov``: ``R`` ``[m, m]``; default ``obs_std²·I``;
    - ``controls``: ``u`` ``[n_actions, d]``; default ``±0.5`` along each axis;
    - ``prior_mean``, ``prior_cov``: ``m_0`` ``[d]`` and ``P_0`` ``[d, d]``; default ``0`` and ``prior_std²·I``.
    """

    Params = LinearGaussianParams

    def __init__(
        self,
        params: LinearGaussianParams | None = None,
        *,
        device: torch.device | str | None = None,
        transition_matrix: Tensor | None = None,
        process_cov: Tensor | None = None,
        observation_matrix: Tensor | None = None,
        observation_cov: Tensor | None = None,
        controls: Tensor | None = None,
        prior_mean: Tensor | None = None,
        prior_cov: Tensor | None = None,
        **kwargs,
    ) -> None:
        self.params = p = build_params(LinearGaussianParams, params, kwargs, owner=type(self).__name__)
        d = p.state_dim
        m = p.obs_dim if p.obs_dim is not None else d
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        f32 = dict(dtype=torch.float32, device=self.device)
        eye = torch.eye(d, **f32)
        self.F = (torch.as_tensor(transition_matrix, **f32) if transition_matrix is not None
                  else p.transition_scale * eye)
        self.Q = torch.as_tensor(process_cov, **f32) if process_cov is not None else p.process_std**2 * eye
        self.H = (torch.as_tensor(observation_matrix, **f32) if observation_matrix is not None
                  else torch.eye(m, d, **f32))
        self.R = (torch.as_tensor(observation_cov, **f32) if observation_cov is not None
                  else p.obs_std**2 * torch.eye(m, **f32))
        if controls is None:
            eye = torch.eye(d, **f32)
            controls = torch.cat([0.5 * eye, -0.5 * eye], dim=0)
        self.controls = torch.as_tensor(controls, **f32)
        self.m0 = torch.as_tensor(prior_mean, **f32) if prior_mean is not None else torch.zeros(d, **f32)
        self.P0 = torch.as_tensor(prior_cov, **f32) if prior_cov is not None else p.prior_std**2 * eye
        self.state_dim, self.obs_dim = d, m
        self.n_actions = p.n_actions if p.n_actions is not None else self.controls.shape[0]
        self._factorise(f32)

    def _factorise(self, f32: dict) -> None:
        """The Cholesky factors of ``Q``, ``R`` and ``P_0`` (raising unless each is symmetric positive
        definite), the noises, and the matrices the methods use."""
        for name, mat in (("process_cov", self.Q), ("observation_cov", self.R), ("prior_cov", self.P0)):
            try:
                torch.linalg.cholesky(mat)
            except RuntimeError as err:
                raise ValueError(f"LinearGaussian.{name}: must be symmetric positive definite") from err
        self._q_tril = torch.linalg.cholesky(self.Q)
        self._r_tril = torch.linalg.cholesky(self.R)
        self._p0_tril = torch.linalg.cholesky(self.P0)
        self._process = GaussianNoise(self._q_tril)
        self._obs_noise = GaussianNoise(self._r_tril)
        self._H_t = self.H.T.contiguous()
        self._F_t = self.F.T.contiguous()
        # R⁻¹H [m, d], the matrix of the observation score (solved in float64)
        self._score_matrix = torch.cholesky_solve(self.H.double(), self._r_tril.double()).to(**f32)

    def _noise(self, shape, tril: Tensor, generator) -> Tensor:
        eps = torch.randn(*shape, tril.shape[0], generator=generator, device=self.device)
        return eps @ tril.T

    def initial_state(self, shape, generator=None) -> Tensor:
        return self.m0 + self._noise(tuple(shape), self._p0_tril, generator)

    def initial_belief(self, shape, n, generator=None) -> Tensor:
        return self.initial_state((*shape, n), generator)

    def transition_mean(self, s: Tensor, a: Tensor) -> Tensor:
        return s @ self._F_t + self.controls[a.long()]

    def transition_scale_tril(self) -> Tensor:
        return self._q_tril

    def transition(self, s, a, generator=None) -> Tensor:
        mean = self.transition_mean(s, a)
        return mean + self._noise(mean.shape[:-1], self._q_tril, generator)

    def transition_log_prob(self, s_next, s, a) -> Tensor:
        return self._process.log_prob(s_next - self.transition_mean(s, a))

    def observe(self, s_next, a, generator=None) -> Tensor:
        mean = s_next @ self._H_t
        return mean + self._noise(mean.shape[:-1], self._r_tril, generator)

    def observation_log_prob(self, o, s_next, a) -> Tensor:
        return self._obs_noise.log_prob(o - s_next @ self._H_t)

    def observation_score(self, o, s_next, a) -> Tensor:
        """``∇_{s'} log N(o; H s', R) = Hᵀ R⁻¹ (o − H s')``, written for row vectors as
        ``(o − s' Hᵀ) R⁻¹ H``. ``o`` ``[*S, m]``, ``s_next`` ``[*S, d]`` (broadcast) -> ``[*S, d]``."""
        return (o - s_next @ self._H_t) @ self._score_matrix

    def reward(self, s, a, s_next) -> Tensor:
        return -torch.linalg.vector_norm(s_next, dim=-1)

    def is_terminal(self, s) -> Tensor:
        return torch.zeros(s.shape[:-1], dtype=torch.bool, device=s.device)

    def kalman_step(self, mean: Tensor, cov: Tensor, a: Tensor, o: Tensor) -> tuple[Tensor, Tensor]:
        """The exact posterior after one (action, observation) step, in float64.

        ``mean`` ``[*B, d]``, ``cov`` ``[*B, d, d]``, ``a`` ``[*B]``, ``o`` ``[*B, m]``.
        Predict: ``m⁻ = F m + u_a``, ``P⁻ = F P Fᵀ + Q``. Update: ``K = P⁻Hᵀ(H P⁻ Hᵀ + R)⁻¹``,
        ``m = m⁻ + K(o - H m⁻)``, ``P = (I - K H) P⁻``.
        """
        F, Q, H, R = (t.double() for t in (self.F, self.Q, self.H, self.R))
        mean, cov, o = mean.double(), cov.double(), o.double()
        m_pred = mean @ F.T + self.controls.double()[a.long()]
        p_pred = F @ cov @ F.T + Q
        s = H @ p_pred @ H.T + R
        gain = torch.linalg.solve(s, H @ p_pred).transpose(-1, -2)  # P⁻Hᵀ S⁻¹ (S symmetric)
        innov = o - m_pred @ H.T
        m_post = m_pred + (gain @ innov.unsqueeze(-1)).squeeze(-1)
        p_post = p_pred - gain @ H @ p_pred
        return m_post, (p_post + p_post.transpose(-1, -2)) / 2
