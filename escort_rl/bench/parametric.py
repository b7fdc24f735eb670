"""The DVRL-style parametric row of the synthetic benchmark.

DVRL's belief draws its particles from a proposal network, a diagonal Gaussian
``q(z) = N(μ(h), diag σ(h)²)`` (:class:`escort_rl.modules.dvrl_networks.GaussianHead`), and weights
them by the model. On a static target ``p̃`` (unnormalised) that family is fitted by the
importance-weighted ELBO with ``K`` particles (Burda et al. 2016), the bound DVRL's ELBO reduces to on
one step:

    L_K(q) = E_{z_1..K ~ q} [ log (1/K) Σ_k p̃(z_k) / q(z_k) ]  <=  log ∫ p̃,

maximised by Adam on the reparameterised samples ``z = μ + σ ε``, with the doubly reparameterised
gradient (DReG, Tucker et al. 2019): the surrogate ``Σ_k sg(w̄_k²) · log w_k`` with ``log q``'s
parameters held fixed has the gradient of ``L_K`` with respect to the proposal, without the score
term whose signal-to-noise ratio falls as ``K`` grows (Rainforth et al. 2018); with the plain
gradient, a broad start did not move in 400 steps. The row's ``N`` particles are then
``N`` samples of the fitted ``q``. The network's input ``h`` is a learned vector (there is nothing to
condition on), and the fit starts from the benchmark's initial cloud (``μ`` at its mean, ``σ`` at its
standard deviation), as the particle methods do. Each seed is an independent fit with its own
generator.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.distributions import Independent, Normal

from escort_rl.modules.dvrl_networks import GaussianHead


class ParametricProposal(nn.Module):
    """DVRL's proposal family with a learned input: ``q = GaussianHead(h)``, event shape ``[d]``."""

    def __init__(self, dim: int, hidden: int = 64, init_mean: float = 0.0, init_std: float = 1.0) -> None:
        super().__init__()
        self.h = nn.Parameter(torch.zeros(hidden))
        self.head = GaussianHead(hidden, dim, hidden)
        with torch.no_grad():  # start at the initial cloud: the output layers give a constant
            for layer in (self.head.mean, self.head.raw_std):
                layer.weight.mul_(0.01)
            self.head.mean.bias.fill_(init_mean)
            self.head.raw_std.bias.fill_(math.log(math.expm1(init_std - self.head.min_std)))

    def forward(self):
        return self.head(self.h)


def iw_elbo(log_target, q, k: int, generator: torch.Generator) -> Tensor:
    """One reparameterised estimate of ``L_K`` (see the module docstring); ``log_target(z [K, d]) -> [K]``."""
    eps = torch.randn(k, q.mean.shape[-1], generator=generator)
    z = q.mean + q.stddev * eps
    log_w = log_target(z) - q.log_prob(z)
    return torch.logsumexp(log_w, dim=0) - math.log(k)


def dreg_surrogate(log_target, q, k: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """``(surrogate, L_K estimate)``: the surrogate's gradient with respect to ``q``'s parameters is the
    DReG estimate of ``∇ L_K``: ``Σ_k sg(w̄_k²) ∂ log w_k / ∂z_k · ∂z_k/∂φ`` with ``w̄ = softmax(log w)``."""
    eps = torch.randn(k, q.mean.shape[-1], generator=generator)
    z = q.mean + q.stddev * eps
    q_fixed = Independent(Normal(q.mean.detach(), q.stddev.detach()), 1)
    log_w = log_target(z) - q_fixed.log_prob(z)
    w_bar = torch.softmax(log_w.detach(), dim=0)
    return (w_bar**2 * log_w).sum(), torch.logsumexp(log_w.detach(), dim=0) - math.log(k)


def fit_parametric(log_target, dim: int, seeds: list[int], n: int, k: int = 100, num_steps: int = 500,
                   lr: float = 0.01, hidden: int = 64, init_mean: float = 0.0, init_std: float = 1.0) -> Tensor:
    """Fit :class:`ParametricProposal` by ``num_steps`` Adam steps on ``L_K`` for each seed, then draw
    ``n`` samples. ``log_target(z [K, d]) -> [K]`` (unnormalised). Returns ``[S, n, d]`` float32."""
    if k < 1 or n < 1 or num_steps < 0 or lr <= 0:
        raise ValueError(f"fit_parametric: need k >= 1, n >= 1, num_steps >= 0, lr > 0; got k={k}, n={n}, "
                         f"num_steps={num_steps}, lr={lr}")
    out = []
    for seed in seeds:
        g = torch.Generator().manual_seed(1_000_003 + seed)
        torch.manual_seed(seed)  # the network's initial weights
        q_net = ParametricProposal(dim, hidden, init_mean, init_std)
        optimizer = torch.optim.Adam(q_net.parameters(), lr=lr)
        for _ in range(num_steps):
            surrogate, bound = dreg_surrogate(log_target, q_net(), k, g)
            loss = -surrogate
            if not torch.isfinite(bound):
                raise FloatingPointError(f"fit_parametric: the IW-ELBO is not finite (seed {seed}); lower lr")
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        with torch.no_grad():
            q = q_net()
            out.append((q.mean + q.stddev * torch.randn(n, dim, generator=g)).to(torch.float32))
    return torch.stack(out)
