"""A task known only by its spaces: what an agent observes and how it acts, with no dynamics."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass(frozen=True)
class TaskSpaces:
    """What a model-free agent needs of a task whose dynamics no model here knows (POPGym's memory
    games, say): the observation's width and the actions. It stands where a trainer would read a
    model's spaces (``trainer=recurrent_ppo``); it has no transition, likelihood or state, so no
    filter, belief policy or DVRL can run on it.

    Attributes:
        obs_dim: the width of the flat float observation.
        n_actions: the number of discrete actions (``None`` for real ones).
        action_dim, action_low, action_high: real actions, ``[action_dim]`` bounds (``None`` for
            discrete ones).
        state_dim: 0: there is no state to read.

    Example:
        >>> from escort_rl.models.protocol import is_continuous
        >>> spaces = TaskSpaces(obs_dim=4, n_actions=4)
        >>> is_continuous(spaces), spaces.state_dim
        (False, 0)
    """

    obs_dim: int
    n_actions: int | None = None
    action_dim: int | None = None
    action_low: Tensor | None = None
    action_high: Tensor | None = None
    state_dim: int = 0

    def __post_init__(self) -> None:
        if (self.n_actions is None) == (self.action_dim is None):
            raise ValueError("TaskSpaces: give n_actions (discrete) or action_dim with its bounds (real), "
                             f"not both or neither; got n_actions={self.n_actions}, action_dim={self.action_dim}")
