"""Light-Dark 10D with continuous actions: a force vector instead of one pushed dimension.

The paper's Light-Dark 10D (:class:`~escort_rl.models.LightDark10D`) pushes one velocity coordinate
per step with force ``±f``. Here the action is the force itself, ``a ∈ [−f, f]^{n_pos}``
(``action_dim = n_pos``), added to every velocity coordinate at once:

    x' = x + Δt·v + η_x
    v' = v + a − γ·v + η_v

Everything else (the light field, the observation law with its dark swaps, the reward, the goal and
the process noise) is the discrete model's, with the same :class:`LightDark10DParams`. The discrete
model's actions are the box's axis-aligned vertices ``±f·e_i``, so this model can do whatever it can,
and more: it can push every coordinate in one step.

Example:
    >>> import torch
    >>> m = LightDark10DContinuous()
    >>> m.action_dim, m.action_high.tolist()
    (5, [0.10000000149011612, 0.10000000149011612, 0.10000000149011612, 0.10000000149011612, 0.10000000149011612])
    >>> m.transition_mean(torch.zeros(10), torch.full((5,), 0.1))[5:].tolist()  # the force lands in v'
    [0.10000000149011612, 0.10000000149011612, 0.10000000149011612, 0.10000000149011612, 0.10000000149011612]
"""

from __future__ import annotations

import torch
from torch import Tensor

from escort_rl.models.light_dark import LightDark10D, LightDark10DParams


class LightDark10DContinuous(LightDark10D):
    """Light-Dark 10D whose action is a force vector ``a [*S, n_pos]`` in ``[−force, force]^{n_pos}``.

    Takes :class:`LightDark10DParams` (or its fields as keyword arguments) and ``device``, as
    :class:`LightDark10D` does. ``n_actions`` is ``None``; ``action_dim = n_pos``, and ``action_low``,
    ``action_high`` are ``[n_pos]`` tensors ``∓force``.
    """

    n_actions = None  # continuous actions: action_dim, action_low, action_high instead
    action_dim = 5

    def __init__(self, params: LightDark10DParams | None = None, *, device: torch.device | str | None = None,
                 **kwargs) -> None:
        super().__init__(params, device=device, **kwargs)
        self.n_actions = None  # the parent sets 2·n_pos for n_pos > 5

    def _set_actions(self, force: float) -> None:
        """The action box ``[−force, force]^{n_pos}``."""
        if not force > 0:
            raise ValueError(f"LightDark10DContinuous.force: the action box is [-force, force], so force must be "
                             f"> 0, got {force}")
        self.action_dim = self.n_pos
        self.action_high = torch.full((self.n_pos,), float(force), device=self.device)
        self.action_low = -self.action_high

    def transition_mean(self, s: Tensor, a: Tensor) -> Tensor:
        """Noise-free dynamics: ``x + Δt·v``, ``(1 − γ)·v + a``. ``s``: ``[*S, 2·n_pos]``, ``a``:
        ``[*S, n_pos]`` (broadcast) -> ``[*S, 2·n_pos]``."""
        pos, vel = s[..., : self.n_pos], s[..., self.n_pos :]
        new_vel = (1.0 - self.damping) * vel + a.to(s.dtype)
        return torch.cat([(pos + self.dt * vel).expand(new_vel.shape), new_vel], dim=-1)
