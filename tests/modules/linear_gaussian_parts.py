"""A linear-Gaussian model as DVRL's parts, for tests with closed forms (imported by the tests of this
folder). ``h`` carries the previous ``z`` (``h_0 = 0``), so with ``H = Z = 1``:
``z_t ~ N(z_{t-1}, 1)``, ``o_t ~ N(z_t, σ²)``, ``q(z_t | h, o) = N(α h + β o + γ, s²)``."""

from __future__ import annotations

import torch
from torch import nn
from torch.distributions import Independent, Normal


class LinearPrior(nn.Module):
    def forward(self, h, action_enc):
        return Independent(Normal(h, torch.ones_like(h)), 1)


class LinearProposal(nn.Module):
    def __init__(self, h_coef: float, o_coef: float, bias: float, std: float) -> None:
        super().__init__()
        self.h_coef, self.o_coef, self.bias, self.std = h_coef, o_coef, bias, std

    def forward(self, h, action_enc, obs_enc):
        mean = self.h_coef * h + self.o_coef * obs_enc + self.bias
        return Independent(Normal(mean, torch.full_like(mean, self.std)), 1)


class LinearEmission(nn.Module):
    def __init__(self, sigma: float) -> None:
        super().__init__()
        self.sigma = sigma

    def forward(self, h, z, action_enc):
        return Independent(Normal(z, torch.full_like(z, self.sigma)), 1)


class CarryLatent(nn.Module):
    def forward(self, h, z, obs_enc, action_enc):
        return z
