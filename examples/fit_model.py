"""Fit a model's unknown noise from logged data: gradient ascent on a particle filter's log-evidence.

A linear-Gaussian tracker (2-D state, two sensors) whose sensor noise scales are unknown. From 50
logged trajectories (actions and observations, no states) we maximise the SIR filter's estimate of
``log p(o_1:T | σ)`` over ``σ``: ``SIRFilter(differentiable=True)`` resamples with stop-gradient
weights, so ``belief.log_evidence.sum().backward()`` gives an estimate of its gradient. On this model
the Kalman filter gives the exact log-evidence, so its maximum-likelihood estimate is the yardstick.

    python examples/fit_model.py             # about ten seconds on two cores
    python examples/fit_model.py --particles 1000 --steps 300
"""

from __future__ import annotations

import argparse
import math

import torch

from escort_rl.belief import SIRFilter
from escort_rl.models import LinearGaussian

TRUE_STD = (0.3, 0.8)
"""The two sensors' noise std that generated the logged data."""


class Tracker(LinearGaussian):
    """The tracker with sensor noise std ``exp(log_std)`` (a tensor that may need a gradient)."""

    def __init__(self, log_std: torch.Tensor) -> None:
        super().__init__(state_dim=2, obs_dim=2, obs_std=1.0)
        self.log_std = log_std
        self.R = torch.diag((2 * log_std.detach()).exp())  # what observe() and Kalman use

    def observe(self, s_next, a, generator=None):
        mean = s_next @ self.H.T
        return mean + torch.randn(mean.shape, generator=generator) * self.log_std.detach().exp()

    def observation_log_prob(self, o, s_next, a):
        return torch.distributions.Normal(s_next @ self.H.T, self.log_std.exp()).log_prob(o).sum(-1)


def logged_data(trajectories: int, steps: int, seed: int = 0):
    """Actions ``[E, T]`` and observations ``[E, T, 2]`` of the true tracker under random actions."""
    model, g = Tracker(torch.tensor(TRUE_STD).log()), torch.Generator().manual_seed(seed)
    s = model.initial_state((trajectories,), g)
    actions, observations = [], []
    for _ in range(steps):
        a = torch.randint(0, model.n_actions, (trajectories,), generator=g)
        s = model.transition(s, a, g)
        actions.append(a)
        observations.append(model.observe(s, a, g))
    return torch.stack(actions, 1), torch.stack(observations, 1)


def sir_log_evidence(log_std, actions, observations, particles: int, generator) -> torch.Tensor:
    """The differentiable SIR estimate of ``Σ_e log p(o^e_1:T)``."""
    model, filt = Tracker(log_std), SIRFilter(differentiable=True)
    belief = filt.init(model, (actions.shape[0],), particles, generator)
    for t in range(actions.shape[1]):
        belief = filt.update(model, belief, actions[:, t], observations[:, t], generator)
    return belief.log_evidence.sum()


def kalman_log_evidence(log_std, actions, observations) -> torch.Tensor:
    """The exact ``Σ_e log p(o^e_1:T)`` (float64), differentiable in ``log_std``."""
    model = Tracker(log_std.detach().float())
    F, Q, H = model.F.double(), model.Q.double(), model.H.double()
    R = torch.diag((2 * log_std).exp())
    e, d = actions.shape[0], model.state_dim
    mean, cov = model.m0.double().expand(e, d), model.P0.double().expand(e, d, d)
    total = log_std.new_zeros(())
    for t in range(actions.shape[1]):
        mean = mean @ F.T + model.controls.double()[actions[:, t]]
        cov = F @ cov @ F.T + Q
        s = H @ cov @ H.T + R
        innovation = observations[:, t].double() - mean @ H.T
        density = torch.distributions.MultivariateNormal(torch.zeros_like(innovation), s)
        total = total + density.log_prob(innovation).sum()
        gain = torch.linalg.solve(s, H @ cov).transpose(-1, -2)
        mean = mean + (gain @ innovation.unsqueeze(-1)).squeeze(-1)
        cov = cov - gain @ H @ cov
    return total


def fit(objective, start: torch.Tensor, steps: int, lr: float) -> torch.Tensor:
    """Adam on ``-objective(log_std) / E`` from ``start``; returns the fitted ``log_std``."""
    log_std = start.clone().requires_grad_(True)
    optimizer = torch.optim.Adam([log_std], lr=lr)
    for _ in range(steps):
        optimizer.zero_grad()
        (-objective(log_std)).backward()
        optimizer.step()
    return log_std.detach()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", type=int, default=50)
    parser.add_argument("--length", type=int, default=20, help="steps per trajectory")
    parser.add_argument("--particles", type=int, default=300)
    parser.add_argument("--steps", type=int, default=150, help="gradient steps")
    args = parser.parse_args()
    torch.manual_seed(0)
    actions, observations = logged_data(args.trajectories, args.length)
    start = torch.tensor([0.0, 0.0])  # σ = (1, 1)
    generator = torch.Generator().manual_seed(1)
    scale = 1.0 / (args.trajectories * args.length)  # per observation: a step size that does not depend on E or T
    sir = fit(lambda p: scale * sir_log_evidence(p, actions, observations, args.particles, generator),
              start, args.steps, lr=0.05)
    kalman = fit(lambda p: scale * kalman_log_evidence(p, actions, observations), start.double(), args.steps,
                 lr=0.05)
    sir_std, kalman_std = sir.exp(), kalman.exp()
    error = ((sir_std.double() - kalman_std) / kalman_std).abs().max().item()
    print(f"true noise std:       {', '.join(f'{s:.3f}' for s in TRUE_STD)}")
    print(f"Kalman's MLE:         {', '.join(f'{s:.3f}' for s in kalman_std.tolist())}")
    print(f"SIR log-evidence fit: {', '.join(f'{s:.3f}' for s in sir_std.tolist())}")
    print(f"largest relative difference from Kalman's MLE: {100 * error:.1f}%")
    if not math.isfinite(error) or error > 0.10:
        raise SystemExit(f"the fit is {100 * error:.1f}% from Kalman's MLE (more than 10%)")


if __name__ == "__main__":
    main()
