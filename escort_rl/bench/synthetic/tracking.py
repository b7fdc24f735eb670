"""The tracking protocol of the synthetic benchmark: a latent state moving through a GMM-shaped
likelihood, and each filter's error against the true state over the trajectory.

The model (:class:`GMMTracking`), on the model protocol, for a mixture ``η ~ Σ_k w_k N(μ_k, Σ_k)``
of the benchmark's targets, centred to mean 0:

    s_0 ~ N(0, σ_0² I),     s_{t+1} = s_t + N(0, q² I),     o_t = s_t + η_t.

The likelihood of ``s`` given ``o`` is the mixture placed at ``o − μ_k``: every observation is
explained by as many hypotheses as the mixture has modes, each with the mode's correlations, so the
posterior is multi-modal and correlated where the prior does not settle it.

Each filter runs ``T`` updates from its prior belief; the error of one run is the paper's

    RMSE = sqrt( (1/T) Σ_t ‖s_t − ŝ_t‖² ),    ŝ_t the belief mean after observing o_t,

in the units of the state (no ``1/√d``). ``track`` runs a batch of seeds at once.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from escort_rl.bench.targets import GaussianMixture

PRIOR_STD = 4.0
PROCESS_STD = 0.5
STEPS = 10


class GMMTracking:
    """A random walk observed through additive Gaussian-mixture noise (see the module docstring).

    ``noise``: the mixture ``η`` is drawn from (centred to mean 0 here); ``prior_std`` ``σ_0``,
    ``process_std`` ``q``. Never terminal. With ``control = 0`` (default) one action
    (``n_actions = 1``) and reward 0. With ``control = c > 0`` a regulation task: ``2d + 1`` actions,
    action 0 does nothing and actions ``2i + 1`` / ``2i + 2`` push coordinate ``i`` by ``+c`` / ``−c``
    (``s_{t+1} = s_t + u_a + N(0, q² I)``), and the reward is ``−‖s_{t+1}‖``: keep the state at the
    origin while the observations say only up to which mode of the noise where it is.

    Example:
        >>> from escort_rl.bench.targets import load_target
        >>> m = GMMTracking(load_target("gmm2d"))
        >>> s = m.initial_state((3,), torch.Generator().manual_seed(0))
        >>> m.observation_log_prob(m.observe(s, None), s, None).shape
        torch.Size([3])
    """

    def __init__(self, noise: GaussianMixture, prior_std: float = PRIOR_STD, process_std: float = PROCESS_STD,
                 control: float = 0.0):
        for name, value in (("prior_std", prior_std), ("process_std", process_std)):
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and 0 < value < math.inf):
                raise ValueError(f"{name}: expected a positive finite number, got {value!r}")
        if not (isinstance(control, (int, float)) and not isinstance(control, bool) and 0 <= control < math.inf):
            raise ValueError(f"control: expected a finite number >= 0 (0: no actions), got {control!r}")
        mean = noise.mean()
        self.noise = GaussianMixture(noise.weights, noise.means - mean, noise.covariances,
                                     name=f"{noise.name or 'mixture'} (centred)")
        self.state_dim = self.obs_dim = d = noise.dim
        self.prior_std, self.process_std, self.control = float(prior_std), float(process_std), float(control)
        self.n_actions = 2 * d + 1 if control > 0 else 1
        offsets = torch.zeros(self.n_actions, d)
        if control > 0:
            offsets[1 + 2 * torch.arange(d), torch.arange(d)] = float(control)
            offsets[2 + 2 * torch.arange(d), torch.arange(d)] = -float(control)
        self.controls = offsets  # [n_actions, d]: u_a

    def _randn(self, shape, like: Tensor | None, generator) -> Tensor:
        dtype = like.dtype if like is not None else torch.float32
        device = like.device if like is not None else None
        return torch.randn(*shape, generator=generator, dtype=dtype, device=device)

    def initial_state(self, shape, generator=None) -> Tensor:
        return self.prior_std * self._randn((*shape, self.state_dim), None, generator)

    def initial_belief(self, shape, n, generator=None) -> Tensor:
        return self.prior_std * self._randn((*shape, n, self.state_dim), None, generator)

    def _offset(self, s: Tensor, a) -> Tensor:
        if self.control == 0 or a is None:
            return torch.zeros((), dtype=s.dtype, device=s.device)
        return self.controls.to(s.dtype).to(s.device)[torch.as_tensor(a).long()]

    def transition(self, s: Tensor, a, generator=None) -> Tensor:
        return s + self._offset(s, a) + self.process_std * self._randn(s.shape, s, generator)

    def transition_mean(self, s: Tensor, a) -> Tensor:
        return s + self._offset(s, a)

    def transition_scale_tril(self) -> Tensor:
        return self.process_std * torch.eye(self.state_dim)

    def transition_log_prob(self, s_next: Tensor, s: Tensor, a) -> Tensor:
        z = (s_next - self.transition_mean(s, a)) / self.process_std
        return -0.5 * (z * z).sum(-1) - self.state_dim * (math.log(self.process_std) + 0.5 * math.log(2 * math.pi))

    def observe(self, s_next: Tensor, a, generator=None) -> Tensor:
        flat = s_next.reshape(-1, self.state_dim)
        eta = self.noise.sample(flat.shape[0], generator).to(s_next.dtype).to(s_next.device)
        return s_next + eta.reshape(s_next.shape)

    def observation_log_prob(self, o: Tensor, s_next: Tensor, a) -> Tensor:
        return self.noise.log_prob(o - s_next)

    def observation_score(self, o: Tensor, s_next: Tensor, a) -> Tensor:
        """``∇_s log p_η(o − s) = −∇log p_η(o − s)`` (the mixture's closed-form score)."""
        return -self.noise.score(o - s_next)

    def reward(self, s: Tensor, a, s_next: Tensor) -> Tensor:
        if self.control == 0:
            return torch.zeros(s.shape[:-1], dtype=s.dtype, device=s.device)
        return -torch.linalg.vector_norm(s_next, dim=-1)

    def is_terminal(self, s: Tensor) -> Tensor:
        return torch.zeros(s.shape[:-1], dtype=torch.bool, device=s.device)

    # -- the exact posterior: a Gaussian sum -----------------------------------------------------
    max_components: int = 256
    """Components the exact posterior keeps after each update (the heaviest; see
    :meth:`exact_posterior_step`)."""

    def exact_posterior_init(self, batch: int) -> tuple[Tensor, Tensor, Tensor]:
        """The prior as a one-component mixture: ``log_w`` ``[B, 1]``, ``means`` ``[B, 1, d]``,
        ``covs`` ``[B, 1, d, d]`` (float64)."""
        d = self.state_dim
        eye = torch.eye(d, dtype=torch.float64)
        return (torch.zeros(batch, 1, dtype=torch.float64), torch.zeros(batch, 1, d, dtype=torch.float64),
                (self.prior_std**2 * eye).expand(batch, 1, d, d).clone())

    def exact_posterior_step(self, log_w: Tensor, means: Tensor, covs: Tensor, a, o: Tensor
                             ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """One exact Bayes update of a Gaussian-sum posterior (Alspach & Sorenson 1972).

        Predict each component ``j``: ``m_j ← m_j + u_a``, ``C_j ← C_j + q² I``. Each noise mode ``k`` (weight ``π_k``,
        mean ``μ_k``, covariance ``Σ_k``) turns it into a Kalman update with ``H = I``, ``R = Σ_k``
        and the observation ``o − μ_k``:

            S = C_j + Σ_k,   K = C_j S⁻¹,   m' = m_j + K (o − μ_k − m_j),   C' = C_j − K C_j,
            log w' = log w_j + log π_k + log N(o − μ_k; m_j, S).

        The ``J·K`` components are cut to the :attr:`max_components` heaviest and renormalised.
        Returns the new ``(log_w, means, covs)`` and ``dropped`` ``[B]``: the posterior mass cut away
        (0 while nothing is cut; the reference is exact up to it). ``o`` ``[B, d]``."""
        b, j, d = means.shape
        noise = self.noise
        pi = torch.log(noise.weights.double())  # [K]
        mu, sig = noise.means.double(), noise.covariances.double()  # [K, d], [K, d, d]
        k = pi.shape[0]
        c = covs + self.process_std**2 * torch.eye(d, dtype=torch.float64)  # [B, J, d, d]
        means = means + self._offset(means, a).double().reshape(b, 1, d) if self.control > 0 and a is not None \
            else means
        s = c.unsqueeze(2) + sig  # [B, J, K, d, d]
        lower = torch.linalg.cholesky(s)
        innov = (o.double()[:, None, None, :] - mu - means.unsqueeze(2))  # [B, J, K, d]
        z = torch.linalg.solve_triangular(lower, innov.unsqueeze(-1), upper=False).squeeze(-1)
        half_log_det = torch.log(torch.diagonal(lower, dim1=-2, dim2=-1)).sum(-1)
        log_lik = -0.5 * (z * z).sum(-1) - half_log_det - 0.5 * d * math.log(2 * math.pi)  # [B, J, K]
        cj = c.unsqueeze(2).expand(b, j, k, d, d)
        gain_t = torch.cholesky_solve(cj, lower)  # S⁻¹ C_j = Kᵀ (C_j and S symmetric)
        gain = gain_t.transpose(-1, -2)
        new_means = means.unsqueeze(2) + (gain @ innov.unsqueeze(-1)).squeeze(-1)
        new_covs = cj - gain @ cj
        new_covs = 0.5 * (new_covs + new_covs.transpose(-1, -2))
        new_log_w = (log_w.unsqueeze(2) + pi + log_lik).reshape(b, j * k)
        new_log_w = new_log_w - torch.logsumexp(new_log_w, -1, keepdim=True)
        keep = min(self.max_components, j * k)
        top, idx = new_log_w.topk(keep, dim=-1)
        dropped = (1.0 - top.exp().sum(-1)).clamp_min(0.0)
        top = top - torch.logsumexp(top, -1, keepdim=True)
        gather = lambda x: x.reshape(b, j * k, *x.shape[3:]).gather(  # noqa: E731
            1, idx.reshape(b, keep, *([1] * (x.dim() - 3))).expand(b, keep, *x.shape[3:]))
        return top, gather(new_means), gather(new_covs), dropped


def gmm_tracking(dim: int = 5, correlation: str = "block", noise_scale: float = 1.0, prior_std: float = PRIOR_STD,
                 process_std: float = PROCESS_STD, target_seed: int = 0, max_components: int = 256,
                 control: float = 0.0) -> GMMTracking:
    """The tracking model of the synthetic benchmark's scalability mixture in ``dim`` dimensions
    (:func:`~escort_rl.bench.targets.scalability_target`: 5 modes, correlation structure
    ``correlation``), each mode's covariance scaled by ``noise_scale²`` (below 1: sharper modes, an
    observation that tells the hypotheses apart more sharply). A multi-modal family by dimension with
    an exact (Gaussian-sum) posterior, for the frontier:
    ``bench frontier --model escort_rl.bench.synthetic.tracking:gmm_tracking --model-arg dim=20``.
    ``control > 0`` makes it a regulation task (:class:`GMMTracking`)."""
    from escort_rl.bench.targets import scalability_target

    if not (isinstance(noise_scale, (int, float)) and not isinstance(noise_scale, bool) and 0 < noise_scale < math.inf):
        raise ValueError(f"noise_scale: expected a positive finite number, got {noise_scale!r}")
    if isinstance(max_components, bool) or not isinstance(max_components, int) or max_components < 1:
        raise ValueError(f"max_components: expected an integer >= 1, got {max_components!r}")
    mix = scalability_target(int(dim), correlation, int(target_seed))
    if noise_scale != 1.0:
        mix = GaussianMixture(mix.weights, mix.means, mix.covariances * float(noise_scale) ** 2,
                              name=f"{mix.name} x{noise_scale:g}")
    model = GMMTracking(mix, prior_std=prior_std, process_std=process_std, control=control)
    model.max_components = max_components
    return model


def simulate(model: GMMTracking, seeds: list[int], steps: int = STEPS) -> tuple[Tensor, Tensor]:
    """The true states and observations of each seed: ``[S, T, d]`` each (float32). Seed ``s`` draws
    its trajectory from ``torch.Generator().manual_seed(s)`` alone, whatever the other seeds."""
    states, observations = [], []
    for seed in seeds:
        g = torch.Generator().manual_seed(int(seed))
        s = model.initial_state((), g)
        traj, obs = [], []
        for _ in range(steps):
            s = model.transition(s, None, g)
            traj.append(s)
            obs.append(model.observe(s, None, g))
        states.append(torch.stack(traj))
        observations.append(torch.stack(obs))
    return torch.stack(states), torch.stack(observations)


def track(filt, model: GMMTracking, seeds: list[int], n: int, steps: int = STEPS) -> dict:
    """Run ``filt`` (any belief filter) on every seed's trajectory at once, with ``n`` particles.

    Returns per-seed lists ``rmse`` (the module's RMSE) and ``final_error`` (``‖s_T − ŝ_T‖``), and
    ``importance``: the filter's :meth:`~escort_rl.belief.base.BeliefFilter.importance_diagnostics`
    over the run (the ESS of every importance-weighted step; empty for a filter that forms none).
    """
    states, observations = simulate(model, seeds, steps)
    batch = (len(seeds),)
    g = torch.Generator().manual_seed(int(seeds[0]) + 7_919)
    belief = filt.init(model, batch, n, generator=g)
    action = torch.zeros(batch, dtype=torch.long)
    sq_errors = []
    for t in range(steps):
        belief = filt.update(model, belief, action, observations[:, t], generator=g)
        sq_errors.append((belief.mean() - states[:, t]).pow(2).sum(-1))
    sq = torch.stack(sq_errors, dim=1)  # [S, T]
    return {"rmse": sq.mean(-1).sqrt().tolist(), "final_error": sq[:, -1].sqrt().tolist(),
            "importance": filt.importance_diagnostics()}
