"""Flickering Atari: single 84×84 grayscale frames, blanked with probability 0.5.

The preprocessing is DVRL's (Igl et al. 2018), which used OpenAI baselines' ``make_atari`` and
``wrap_deepmind`` on ``<Game>NoFrameskip-v0``. Here it is written against ``ale_py`` directly (no
OpenCV), one wrapper per concern:

- :class:`DVRLAtari`: the ALE game with sticky actions (``repeat_action_probability=0.25``, the
  ``-v0`` games), up to 30 no-op actions at the start of a game, FIRE at every reset in games that
  have it, frame skip 4 with the maximum over the last two frames, episodic lives (losing a life
  ends the agent's episode; the next reset continues the game unless it is over), and an area
  resize of ALE's grayscale screen to ``[1, 84, 84]`` ``float32`` in ``[0, 1]``. Rewards are the
  game's own (unclipped); ``info["game_over"]`` marks the end of the game, so that a user can score
  whole games while the agent's episodes are lives.
- :class:`Flicker`: each observation (reset or step) is all zeros with probability ``p_blank``,
  drawn from the wrapper's own generator, seeded from the ``reset(seed=...)`` seed;
  ``info["blank"]`` says whether it was.

The ids ``escort_rl/Flickering<Game>-v0`` are registered with :func:`register_atari_envs` (the
package does it on import; ``ale_py`` is imported only when an env is made). For TorchRL,
:func:`make_atari_torchrl_env` builds a ``GymEnv`` that also writes ``"game_over"`` into the
tensordict; it is a module-level function, so ``functools.partial`` of it travels to ``ParallelEnv``
workers.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from escort_rl.config import ConfigError
from escort_rl.config.errors import MissingExtra

# short name -> (ALE game id, gymnasium id)
GAMES = {
    "pong": ("pong", "escort_rl/FlickeringPong-v0"),
    "icehockey": ("ice_hockey", "escort_rl/FlickeringIceHockey-v0"),
    "mspacman": ("ms_pacman", "escort_rl/FlickeringMsPacman-v0"),
    "asteroids": ("asteroids", "escort_rl/FlickeringAsteroids-v0"),
}
FRAME_SIZE = 84
P_BLANK = 0.5
FLICKER_STREAM = 0x5EED_F11C  # separates the flicker's generator from the game's seed
MISSING_ALE = "Flickering Atari needs the ale-py package: install with pip install escort-rl[atari]"


def check_game(game: str) -> str:
    """The short name of ``game`` (case and ``-``/``_`` ignored: ``"MsPacman"``, ``"ms_pacman"``);
    an unknown game raises ``ConfigError`` naming the choices."""
    key = str(game).lower().replace("_", "").replace("-", "")
    if key not in GAMES:
        raise ConfigError(f"game: unknown '{game}'; choose one of {sorted(GAMES)}")
    return key


def _import_ale():
    try:
        import ale_py
    except ImportError:
        raise MissingExtra(MISSING_ALE) from None
    return ale_py


def area_resize_matrix(source: int, target: int) -> np.ndarray:
    """``[target, source]`` weights of an area (box) resize along one axis: output pixel ``i`` is the
    mean of the source interval ``[i·s/t, (i+1)·s/t)``, partial pixels weighted by their overlap (what
    OpenCV's ``INTER_AREA`` computes, which baselines' ``WarpFrame`` used). Rows sum to 1."""
    edges = np.arange(target + 1) * source / target
    lo, hi = edges[:-1, None], edges[1:, None]
    pixels = np.arange(source)[None, :]
    overlap = np.clip(np.minimum(hi, pixels + 1) - np.maximum(lo, pixels), 0.0, None)
    return (overlap / overlap.sum(1, keepdims=True)).astype(np.float32)


def area_taps(source: int, target: int) -> tuple[np.ndarray, np.ndarray]:
    """The weights of :func:`~escort_rl.envs.atari.area_resize_matrix` ``(source, target)`` as integer
    taps: ``(index [target, k], weight [target, k])``, ``weight / source`` the matrix's nonzero entries,
    ``k`` the most source pixels one output pixel overlaps (spare taps weigh 0). An entry is an
    overlap over the box width ``source / target``, and overlaps are multiples of ``1 / target`` (the
    box edges are), so ``entry · source`` (the overlap in ``1/target`` of a pixel) is an integer and a
    row's weights sum to ``source``. The weights are ``float32`` holding integers."""
    exact = np.rint(area_resize_matrix(source, target).astype(np.float64) * source)
    k = int((exact > 0).sum(1).max())
    index = np.argsort(exact == 0, axis=1, kind="stable")[:, :k]  # each row's nonzero columns first
    return index, np.take_along_axis(exact, index, 1).astype(np.float32)


def resize_screens(screens: np.ndarray, rows: tuple[np.ndarray, np.ndarray],
                   cols: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """``[B, H, W]`` ``uint8`` screens -> ``[B, 1, S, S]`` ``float32`` in ``[0, 1]``: DVRLAtari's area
    resize, exactly. ``rows`` and ``cols`` are :func:`area_taps` ``(H, S)`` and ``(W, S)``; every sum
    of weighted pixels is an integer below ``2**24`` (at most ``H·W·255``), so exact in ``float32``, and
    the one division by ``H·W·255`` rounds the box average once."""
    (row_index, row_weight), (col_index, col_weight) = rows, cols
    _, h, w = screens.shape
    if h * w * 255 >= 2**24:
        raise ValueError(f"screens: {h}×{w} is too large for exact float32 sums (at most 2**24 / 255 pixels)")
    x = row_weight[None, :, 0, None] * screens[:, row_index[:, 0], :]  # [B, S, W]
    for t in range(1, row_index.shape[1]):
        x += row_weight[None, :, t, None] * screens[:, row_index[:, t], :]
    y = col_weight[None, None, :, 0] * x[:, :, col_index[:, 0]]  # [B, S, S]
    for t in range(1, col_index.shape[1]):
        y += col_weight[None, None, :, t] * x[:, :, col_index[:, t]]
    return (y / np.float32(h * w * 255))[:, None]


class DVRLAtari(gym.Env):
    """One ALE game with DVRL's preprocessing (see the module docstring).

    Observation: ``Box(0, 1, [1, 84, 84], float32)``; action: the game's minimal ``Discrete`` set.

    Args:
        game: a key of :data:`GAMES` (``"pong"``, ``"icehockey"``, ``"mspacman"``, ``"asteroids"``).
        frame_skip: emulator frames per action (4); the frame is the maximum of the last two.
        noop_max: at the start of a game, a uniform number in ``[1, noop_max]`` of no-op actions
            (30; 0 turns it off).
        repeat_action_probability: sticky actions (0.25, as the ``-v0`` games).
        episodic_life: losing a life terminates the agent's episode (True, as DVRL).
        max_frames: emulator frames after which a game is truncated (108 000: 30 minutes of play).
    """

    metadata = {"render_modes": []}

    def __init__(self, game: str = "pong", frame_skip: int = 4, noop_max: int = 30,
                 repeat_action_probability: float = 0.25, episodic_life: bool = True,
                 max_frames: int = 108_000) -> None:
        self.game = check_game(game)
        for name, value, low in (("frame_skip", frame_skip, 1), ("noop_max", noop_max, 0),
                                 ("max_frames", max_frames, 1)):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"{name}: expected an int >= {low}, got {value!r}")
        if not 0.0 <= float(repeat_action_probability) <= 1.0:
            raise ValueError("repeat_action_probability: expected a number in [0, 1], got "
                             f"{repeat_action_probability!r}")
        ale_py = _import_ale()
        self.ale_env = ale_py.env.AtariEnv(GAMES[self.game][0], obs_type="grayscale", frameskip=1,
                                           repeat_action_probability=float(repeat_action_probability),
                                           full_action_space=False, max_num_frames_per_episode=max_frames)
        self.frame_skip, self.noop_max, self.episodic_life = frame_skip, noop_max, bool(episodic_life)
        self.action_space = self.ale_env.action_space
        self.observation_space = gym.spaces.Box(0.0, 1.0, (1, FRAME_SIZE, FRAME_SIZE), np.float32)
        meanings = self.ale_env.get_action_meanings()
        self._fire = meanings.index("FIRE") if "FIRE" in meanings else None
        height, width = self.ale_env.observation_space.shape
        self._rows, self._cols = area_taps(height, FRAME_SIZE), area_taps(width, FRAME_SIZE)
        self._lives, self._game_over = 0, True

    def _frame(self, screen: np.ndarray) -> np.ndarray:
        """``[210, 160]`` uint8 -> ``[1, 84, 84]`` float32 in ``[0, 1]`` (:func:`resize_screens`: exact
        integer sums, no BLAS call, whose threads would contend with the emulator's and the agent's)."""
        return resize_screens(screen[None], self._rows, self._cols)[0]

    def _emulate(self, action: int) -> tuple[np.ndarray, float, bool, bool]:
        """``frame_skip`` emulator frames of ``action``: (max of the last two screens, summed reward,
        game over, truncated)."""
        total, last = 0.0, []
        terminated = truncated = False
        for i in range(self.frame_skip):
            screen, reward, terminated, truncated, _ = self.ale_env.step(action)
            total += float(reward)
            if i >= self.frame_skip - 2:
                last.append(screen)
            if terminated or truncated:
                last.append(screen)
                break
        return np.maximum(last[-2], last[-1]) if len(last) > 1 else last[-1], total, terminated, truncated

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if self._game_over or seed is not None:
            screen, _ = self.ale_env.reset(seed=None if seed is None else int(self.np_random.integers(0, 2**31 - 1)))
            for _ in range(int(self.np_random.integers(1, self.noop_max + 1)) if self.noop_max else 0):
                screen, _, over, trunc = self._emulate(0)
                if over or trunc:
                    screen, _ = self.ale_env.reset()
        else:  # a life was lost: the game goes on (baselines' EpisodicLifeEnv takes one no-op step)
            screen, _, over, trunc = self._emulate(0)
            if over or trunc:
                screen, _ = self.ale_env.reset()
        if self._fire is not None:  # baselines' FireResetEnv: FIRE, then action 2, at every reset
            for action in (self._fire, 2):
                screen, _, over, trunc = self._emulate(action)
                if over or trunc:
                    screen, _ = self.ale_env.reset()
        self._lives, self._game_over = self.ale_env.ale.lives(), False
        return self._frame(screen), {"game_over": np.False_, "lives": self._lives}

    def step(self, action):
        if not self.action_space.contains(action):
            raise ValueError(f"action: expected an int in [0, {self.action_space.n}), got {action!r}")
        screen, reward, over, truncated = self._emulate(int(action))
        lives = self.ale_env.ale.lives()
        life_lost = self.episodic_life and 0 < lives < self._lives
        self._lives, self._game_over = lives, over or truncated
        info = {"game_over": np.bool_(self._game_over), "lives": lives}  # numpy: TorchRL reads it
        return self._frame(screen), reward, over or life_lost, truncated and not over, info

    def close(self) -> None:
        self.ale_env.close()


class Flicker(gym.ObservationWrapper):
    """Shows an all-zero observation with probability ``p_blank`` at every reset and step.

    The draws come from the wrapper's own ``numpy`` generator, seeded at ``reset(seed=s)`` from
    ``(s, a fixed stream id)``: the same seed gives the same blanks, different seeds independent
    ones, and the game's randomness is untouched. ``info["blank"]`` says whether the frame was blanked.
    """

    def __init__(self, env: gym.Env, p_blank: float = P_BLANK) -> None:
        super().__init__(env)
        if isinstance(p_blank, bool) or not isinstance(p_blank, (int, float)) or not 0.0 <= p_blank <= 1.0:
            raise ValueError(f"p_blank: expected a probability in [0, 1], got {p_blank!r}")
        self.p_blank = float(p_blank)
        self._rng: np.random.Generator | None = None
        self._blank = False

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(None if seed is None else [int(seed), FLICKER_STREAM])
        obs, info = super().reset(seed=seed, options=options)
        return obs, {**info, "blank": self._blank}

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        return obs, reward, terminated, truncated, {**info, "blank": self._blank}

    def observation(self, observation):
        self._blank = bool(self._rng.random() < self.p_blank)
        return np.zeros_like(observation) if self._blank else observation


def make_flickering_atari(game: str = "pong", p_blank: float = P_BLANK, **kwargs) -> Flicker:
    """The entry point of the registered ids: :class:`Flicker` over :class:`DVRLAtari` (``kwargs``
    go to :class:`DVRLAtari`)."""
    return Flicker(DVRLAtari(game, **kwargs), p_blank=p_blank)


def register_atari_envs() -> None:
    """Register ``escort_rl/Flickering{Pong,IceHockey,MsPacman,Asteroids}-v0`` (idempotent; imports
    nothing from ``ale_py``)."""
    for game, (_, env_id) in GAMES.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="escort_rl.envs.atari:make_flickering_atari",
                         kwargs={"game": game})


def make_atari_torchrl_env(game: str = "pong", seed: int | None = None, device: str = "cpu", **kwargs):
    """A TorchRL ``GymEnv`` of the flickering game, writing ``"observation"`` ``[1, 84, 84]`` and
    ``"game_over"`` (a bool scalar per env) from the env's info. ``kwargs`` go to :func:`make_flickering_atari`.
    Module level: ``functools.partial(make_atari_torchrl_env, "pong")`` is a ``ParallelEnv`` factory."""
    import torch
    from torchrl.data import Categorical
    from torchrl.envs.libs.gym import GymEnv, default_info_dict_reader

    register_atari_envs()
    env_id = GAMES[check_game(game)][1]
    env = GymEnv(env_id, device=device, categorical_action_encoding=True, **kwargs)
    env.set_info_dict_reader(default_info_dict_reader(
        ["game_over"], spec={"game_over": Categorical(2, shape=(), dtype=torch.bool)}))
    if seed is not None:
        env.set_seed(int(seed))
    return env
