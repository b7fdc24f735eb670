"""Value networks for asymmetric actor-critic training: a critic that reads the simulator's true
state, while the policy reads only the belief (Pinto et al. 2018, "Asymmetric Actor Critic")."""

from __future__ import annotations

import torch
from torch import Tensor, nn


class StateValueNet(nn.Module):
    """``V(s) = MLP((s − loc) / scale)``: a value network on the true state ``[*B, d] -> [*B, 1]``.

    Only training reads it (the simulator knows the state); the policy it trains acts on beliefs.

    Example:
        >>> v = StateValueNet(10, hidden=8)
        >>> v(torch.zeros(4, 10)).shape
        torch.Size([4, 1])
    """

    def __init__(self, state_dim: int, hidden: int = 64, loc: float | list[float] = 0.0,
                 scale: float | list[float] = 1.0) -> None:
        super().__init__()
        self.register_buffer("loc", torch.as_tensor(loc, dtype=torch.float32).expand(state_dim).clone())
        self.register_buffer("scale", torch.as_tensor(scale, dtype=torch.float32).expand(state_dim).clone())
        self.net = nn.Sequential(nn.Linear(state_dim, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                                 nn.Linear(hidden, 1))

    def forward(self, state: Tensor) -> Tensor:
        return self.net((state - self.loc) / self.scale)
