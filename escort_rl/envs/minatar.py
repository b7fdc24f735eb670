"""Flickering MinAtar: MinAtar's ``10×10×C`` games, each frame blanked with probability 0.5.

MinAtar (Young & Tian 2019, the ``minatar`` package) reimplements five Atari games on a ``10×10``
grid with one binary channel per kind of object: Breakout (4 channels), Space Invaders (6), Asterix
(4), Freeway (7) and Seaquest (10). It keeps what makes Atari a control problem and costs a small
fraction of it, so the flickering POMDP of the paper's Table 4 becomes one that agents learn on a
CPU. One wrapper per concern, as for Atari:

- :class:`MinAtarFrames`: the game with MinAtar's own settings (sticky actions with probability 0.1,
  difficulty ramping on), its minimal action set, and the state as ``[C, 10, 10]`` ``float32`` in
  ``{0, 1}`` (channels first, as TorchRL's convolutions take it). A game is one episode (MinAtar has
  no lives); ``info["game_over"]`` is set at its end, as the Atari envs set it, and a game that
  reaches ``max_steps`` is truncated.
- :class:`~escort_rl.envs.atari.Flicker`: the same flicker as Flickering Atari, each observation all
  zeros with probability ``p_blank`` from the wrapper's own generator.

The ids ``escort_rl/FlickeringMinAtar{Breakout,SpaceInvaders,Asterix,Freeway,Seaquest}-v0`` are
registered by :func:`register_minatar_envs` (the package does it on import; ``minatar`` is imported
only when an env is made).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from escort_rl.config import ConfigError
from escort_rl.config.errors import MissingExtra
from escort_rl.envs.atari import P_BLANK, Flicker

# short name -> (minatar's game module, gymnasium id)
GAMES = {
    "breakout": ("breakout", "escort_rl/FlickeringMinAtarBreakout-v0"),
    "spaceinvaders": ("space_invaders", "escort_rl/FlickeringMinAtarSpaceInvaders-v0"),
    "asterix": ("asterix", "escort_rl/FlickeringMinAtarAsterix-v0"),
    "freeway": ("freeway", "escort_rl/FlickeringMinAtarFreeway-v0"),
    "seaquest": ("seaquest", "escort_rl/FlickeringMinAtarSeaquest-v0"),
}
GRID_SIZE = 10
MAX_STEPS = 10_000
MISSING_MINATAR = "Flickering MinAtar needs the minatar package: install with pip install escort-rl[minatar]"


def check_game(game: str) -> str:
    """The short name of ``game`` (case, ``-``/``_`` and a ``minatar`` prefix ignored:
    ``"SpaceInvaders"``, ``"space_invaders"``, ``"minatar-breakout"``); an unknown game raises
    ``ConfigError`` naming the choices."""
    key = str(game).lower().replace("_", "").replace("-", "")
    key = key.removeprefix("minatar")
    if key not in GAMES:
        raise ConfigError(f"game: unknown MinAtar game '{game}'; choose one of {sorted(GAMES)}")
    return key


def _import_minatar():
    try:
        import minatar
    except ImportError:
        raise MissingExtra(MISSING_MINATAR) from None
    return minatar


class MinAtarFrames(gym.Env):
    """One MinAtar game as a gymnasium env (see the module docstring).

    Observation: ``Box(0, 1, [C, 10, 10], float32)``; action: ``Discrete`` over the game's minimal
    action set (3 to 6 actions).

    Args:
        game: a key of :data:`GAMES`.
        sticky_action_prob: the probability that the previous action repeats (MinAtar's 0.1).
        difficulty_ramping: MinAtar's speed-up of a game as it goes on (on, as MinAtar's default).
        max_steps: steps after which a game is truncated (10 000).
    """

    metadata = {"render_modes": []}

    def __init__(self, game: str = "breakout", sticky_action_prob: float = 0.1, difficulty_ramping: bool = True,
                 max_steps: int = MAX_STEPS) -> None:
        self.game = check_game(game)
        if isinstance(sticky_action_prob, bool) or not 0.0 <= float(sticky_action_prob) <= 1.0:
            raise ValueError(f"sticky_action_prob: expected a probability in [0, 1], got {sticky_action_prob!r}")
        if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
            raise ValueError(f"max_steps: expected an int >= 1, got {max_steps!r}")
        minatar = _import_minatar()
        self.minatar_env = minatar.Environment(GAMES[self.game][0], sticky_action_prob=float(sticky_action_prob),
                                               difficulty_ramping=bool(difficulty_ramping))
        self.actions = list(self.minatar_env.minimal_action_set())
        height, width, channels = self.minatar_env.state_shape()
        self.action_space = gym.spaces.Discrete(len(self.actions))
        self.observation_space = gym.spaces.Box(0.0, 1.0, (channels, height, width), np.float32)
        self.max_steps = max_steps
        self._steps = 0

    def _frame(self) -> np.ndarray:
        """MinAtar's ``[10, 10, C]`` bool state as ``[C, 10, 10]`` float32."""
        return np.ascontiguousarray(self.minatar_env.state().transpose(2, 0, 1), dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:  # MinAtar draws from one RandomState, shared by the game and the sticky actions
            self.minatar_env.seed(int(self.np_random.integers(0, 2**31 - 1)))
        self.minatar_env.reset()
        self._steps = 0
        return self._frame(), {"game_over": np.False_}

    def step(self, action):
        if not self.action_space.contains(action):
            raise ValueError(f"action: expected an int in [0, {self.action_space.n}), got {action!r}")
        reward, terminated = self.minatar_env.act(self.actions[int(action)])
        self._steps += 1
        truncated = not terminated and self._steps >= self.max_steps
        info = {"game_over": np.bool_(terminated or truncated)}  # numpy: TorchRL reads it
        return self._frame(), float(reward), bool(terminated), truncated, info


def make_flickering_minatar(game: str = "breakout", p_blank: float = P_BLANK, **kwargs) -> Flicker:
    """The entry point of the registered ids: :class:`~escort_rl.envs.atari.Flicker` over
    :class:`MinAtarFrames` (``kwargs`` go to :class:`MinAtarFrames`)."""
    return Flicker(MinAtarFrames(game, **kwargs), p_blank=p_blank)


def register_minatar_envs() -> None:
    """Register ``escort_rl/FlickeringMinAtar<Game>-v0`` for the five games (idempotent; imports nothing
    from ``minatar``)."""
    for game, (_, env_id) in GAMES.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="escort_rl.envs.minatar:make_flickering_minatar",
                         kwargs={"game": game})
