"""The flickering games, Atari's and MinAtar's, behind one name each, as TorchRL envs.

``game`` names are the short names of :data:`escort_rl.envs.atari.GAMES` (``pong``, ``icehockey``,
``mspacman``, ``asteroids``: ``84×84`` frames) and of :data:`escort_rl.envs.minatar.GAMES`
(``breakout``, ``spaceinvaders``, ``asterix``, ``freeway``, ``seaquest``: ``10×10×C`` grids).
:func:`make_flickering_torchrl_env` builds either as a TorchRL ``GymEnv`` that also writes
``"game_over"``; it is module level, so ``functools.partial`` of it travels to ``ParallelEnv`` workers.
"""

from __future__ import annotations

from typing import NamedTuple

from escort_rl.config import ConfigError
from escort_rl.envs import atari, minatar


class FlickeringGame(NamedTuple):
    """A flickering game: its ``tier`` (``"atari"`` or ``"minatar"``), short ``name`` and gymnasium id."""

    tier: str
    name: str
    env_id: str


TIERS = {"atari": atari.GAMES, "minatar": minatar.GAMES}
"""tier -> its games (short name -> (the emulator's name, gymnasium id))."""


def game_names() -> list[str]:
    """Every game's short name, Atari's first."""
    return [name for games in TIERS.values() for name in games]


def flickering_game(game: str) -> FlickeringGame:
    """The game named ``game`` (case and ``-``/``_`` ignored); an unknown name raises ``ConfigError``
    naming the choices."""
    key = str(game).lower().replace("_", "").replace("-", "").removeprefix("minatar")
    for tier, games in TIERS.items():
        if key in games:
            return FlickeringGame(tier, key, games[key][1])
    raise ConfigError(f"game: unknown '{game}'; choose one of {game_names()}")


def make_flickering_torchrl_env(game: str = "pong", seed: int | None = None, device: str = "cpu", **kwargs):
    """A TorchRL ``GymEnv`` of the flickering ``game``, writing ``"observation"`` (``[1, 84, 84]`` on
    Atari, ``[C, 10, 10]`` on MinAtar) and ``"game_over"`` (a bool scalar per env) from the env's info.
    ``kwargs`` go to the game's entry point (:func:`~escort_rl.envs.atari.make_flickering_atari` or
    :func:`~escort_rl.envs.minatar.make_flickering_minatar`)."""
    import torch
    from torchrl.data import Categorical
    from torchrl.envs.libs.gym import GymEnv, default_info_dict_reader

    from escort_rl.envs.registration import register_gymnasium_envs

    register_gymnasium_envs()
    env = GymEnv(flickering_game(game).env_id, device=device, categorical_action_encoding=True, **kwargs)
    env.set_info_dict_reader(default_info_dict_reader(
        ["game_over"], spec={"game_over": Categorical(2, shape=(), dtype=torch.bool)}))
    if seed is not None:
        env.set_seed(int(seed))
    return env


def game_spaces(game: str) -> tuple[tuple[int, ...], int]:
    """``(observation shape, number of actions)`` of ``game``, read from one env, closed at once."""
    import gymnasium as gym

    from escort_rl.envs.registration import register_gymnasium_envs

    register_gymnasium_envs()
    env = gym.make(flickering_game(game).env_id)
    try:
        return tuple(int(s) for s in env.observation_space.shape), int(env.action_space.n)
    finally:
        env.close()
