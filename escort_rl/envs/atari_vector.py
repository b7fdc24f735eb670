"""Flickering Atari on ALE's C++ vector env: ``num_envs`` games stepped in parallel by ALE's threads,
with the frames, lives, resets and blanks of :class:`~escort_rl.envs.atari.Flicker` over
:class:`~escort_rl.envs.atari.DVRLAtari`.

How it is built, and why:

- One ``ale_py.vector_env.AtariVectorEnv`` of one game per env. ALE's vector env steps every one of
  its games at each ``send``, while DVRL's resets take a different number of steps per game (up to
  30 no-op steps, then FIRE and action 2, each of 4 frames) that the other games must not take. With
  one vector env per game, a batched step sends every game its action, then receives from every
  game, so ALE's threads still run the games in parallel, and a reset steps only its own games.
- ALE does the frame skip (the maximum of the last two frames, as DVRLAtari) and the grayscale, at the
  full ``210×160`` (its resize off), with everything else it offers off: its no-op and FIRE resets
  (they differ from baselines': single frames, FIRE before the no-ops), its episodic life (its reset
  starts a new game), reward clipping and frame stacking. The rest is done here as DVRLAtari does it:
  the no-op count, FIRE then action 2 at every reset, a lost life ending the episode but not the game
  (the next reset takes one no-op step), ``game_over`` at the end of the game.
- The resize is DVRLAtari's own, :func:`~escort_rl.envs.atari.resize_screens` (the box average of
  :func:`~escort_rl.envs.atari.area_resize_matrix` by integer sums, exact in ``float32``, one rounding
  division) over the whole batch, so the frames are DVRLAtari's bit for bit. Not BLAS matrix
  products: OpenBLAS's threads spin between calls, and on a busy machine they starved ALE's threads
  (a step of 2 games took 24 ms instead of 0.8).
  Not ALE's resize (OpenCV's ``INTER_AREA``): the same box average, but in ``uint8``, every pixel
  rounded to a multiple of 1/255.
- Seeds: a reset with seed ``s`` draws the ALE seed and the no-op count from ``default_rng(s)`` (gym's
  ``np_random``, as DVRLAtari) and the blanks from ``default_rng([s, FLICKER_STREAM])`` (as
  Flicker); :meth:`FlickeringAtariVectorEnv.set_seed` gives env ``k`` the seed TorchRL's ``SerialEnv``
  gives its ``k``-th env. The same seed thus gives the same games, frames and blanks as
  ``SerialEnv(n, make_atari_torchrl_env)``, but for what follows.

What does not hold exactly:

- ALE's vector env takes seeds in ``[0, 2**31)``; DVRLAtari's ALE gets a 32-bit seed. For the seeds
  whose ALE seed is ``2**31`` or more (about half) the vector env's ALE gets it less ``2**31``, so
  sticky actions, the only use ALE makes of its seed, draw another stream. With
  ``repeat_action_probability=0`` the games are DVRLAtari's for every seed.
- At the step that ends a game (game over or truncation) ALE's vector env stops the frame skip
  without reading the screen, so that step's observation is a stale frame (the previous maximum, or
  its maximum with the third frame) where DVRLAtari shows the last screen. An agent never acts on it:
  the next observation is the new game's first.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from escort_rl.config import ConfigError
from escort_rl.config.errors import MissingExtra
from escort_rl.envs.atari import (
    FLICKER_STREAM,
    FRAME_SIZE,
    GAMES,
    MISSING_ALE,
    P_BLANK,
    area_taps,
    check_game,
    resize_screens,
)

SCREEN = (210, 160)  # ALE's Atari screen, [height, width]
ALE_SEED_LIMIT = 2**31  # ALE's vector env takes seeds in [0, 2**31)


def _import_vector_env():
    try:
        from ale_py.vector_env import AtariVectorEnv
    except ImportError:
        raise MissingExtra(MISSING_ALE) from None
    return AtariVectorEnv


def check_vector_game(game: str) -> str:
    """The short name of the Atari ``game`` (:func:`~escort_rl.envs.atari.check_game`); any other name
    raises ``ConfigError`` saying that only Atari games have a vectorised env."""
    try:
        return check_game(game)
    except ConfigError:
        raise ConfigError(f"game: '{game}' has no vectorised env (ALE's vector env runs Atari games only); choose "
                          f"one of {sorted(GAMES)}") from None


def check_settings(num_envs: int, frame_skip: int, noop_max: int, max_frames: int, repeat_action_probability: float,
                   p_blank: float) -> None:
    """Raise ``ValueError`` naming the first bad argument (the checks of DVRLAtari and Flicker, and
    ``num_envs >= 1``)."""
    for name, value, low in (("num_envs", num_envs, 1), ("frame_skip", frame_skip, 1), ("noop_max", noop_max, 0),
                             ("max_frames", max_frames, 1)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name}: expected an int >= {low}, got {value!r}")
    for name, value in (("repeat_action_probability", repeat_action_probability), ("p_blank", p_blank)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
            raise ValueError(f"{name}: expected a probability in [0, 1], got {value!r}")


def dvrl_ale_seed(reset_seed: int) -> int:
    """The ALE seed (32 bits) of a DVRLAtari whose ``ale_py`` env is reset with ``reset_seed``
    (``AtariEnv.seed_game``: the second word of ``SeedSequence(reset_seed)``)."""
    return int(np.random.SeedSequence(int(reset_seed)).generate_state(2)[1])


def vector_ale_seed(ale_seed: int) -> int:
    """The seed ALE's vector env can take for ``ale_seed``: itself below ``2**31``, else less ``2**31``
    (a different sticky-action stream; see the module docstring)."""
    return int(ale_seed) % ALE_SEED_LIMIT


def serial_env_seeds(seed: int, num_envs: int, static_seed: bool = False) -> tuple[list[int], int]:
    """The seed of each of ``num_envs`` envs and the next seed, as ``SerialEnv.set_seed`` hands them
    out: env 0 gets ``seed``, env ``k + 1`` gets ``seed_generator`` of env ``k``'s (the same seed for
    all with ``static_seed``)."""
    from torchrl._utils import seed_generator

    seeds = [int(seed)]
    for _ in range(num_envs - 1):
        seeds.append(seeds[-1] if static_seed else seed_generator(seeds[-1]))
    return seeds, seeds[-1] if static_seed else seed_generator(seeds[-1])


class DVRLAtariVector:
    """``num_envs`` games of ``game`` with DVRLAtari's preprocessing and Flicker's blanks, batched, in
    numpy (see the module docstring). The arguments are DVRLAtari's and Flicker's.

    - :meth:`reset` ``(mask [N] bool | None, seeds: N ints or Nones | None)`` -> observations
      ``[N, 1, 84, 84]`` ``float32``: new episodes in the envs of ``mask`` (all by default), seeded
      where ``seeds`` gives a seed; the other envs keep theirs.
    - :meth:`step` ``(actions [N] ints)`` -> ``(observation [N, 1, 84, 84], reward [N] float32,
      terminated [N], truncated [N], game_over [N])``, as DVRLAtari's ``step`` for each env.
    - ``blank [N]``, ``lives [N]``: whether each env's last observation was blanked, and its lives.
    """

    def __init__(self, game: str = "pong", num_envs: int = 1, frame_skip: int = 4, noop_max: int = 30,
                 repeat_action_probability: float = 0.25, episodic_life: bool = True, max_frames: int = 108_000,
                 p_blank: float = P_BLANK) -> None:
        self.game = check_vector_game(game)
        check_settings(num_envs, frame_skip, noop_max, max_frames, repeat_action_probability, p_blank)
        vector_env = _import_vector_env()
        self.num_envs, self.noop_max, self.episodic_life = int(num_envs), int(noop_max), bool(episodic_life)
        self.p_blank = float(p_blank)
        self._envs = [vector_env(GAMES[self.game][0], 1, frameskip=int(frame_skip), grayscale=True,
                                 img_height=SCREEN[0], img_width=SCREEN[1], stack_num=1, maxpool=True, noop_max=0,
                                 use_fire_reset=False, episodic_life=False, life_loss_info=False,
                                 reward_clipping=False, max_num_frames_per_episode=int(max_frames),
                                 repeat_action_probability=float(repeat_action_probability), num_threads=1)
                      for _ in range(self.num_envs)]
        action_set = list(self._envs[0].ale.get_action_set())
        self.n_actions = len(action_set)
        fire = [i for i, a in enumerate(action_set) if a.name == "FIRE"]
        self._fire = fire[0] if fire else None
        self._rows, self._cols = area_taps(SCREEN[0], FRAME_SIZE), area_taps(SCREEN[1], FRAME_SIZE)
        n = self.num_envs
        self._np_random: list[np.random.Generator | None] = [None] * n  # DVRLAtari's np_random, per env
        self._flicker: list[np.random.Generator | None] = [None] * n  # Flicker's generator, per env
        self._seeded = np.zeros(n, dtype=bool)  # whether the env's ALE has had a seed
        self._screens = np.zeros((n, *SCREEN), dtype=np.uint8)
        self.observation = np.zeros((n, 1, FRAME_SIZE, FRAME_SIZE), dtype=np.float32)
        self.lives = np.zeros(n, dtype=np.int64)
        self.blank = np.zeros(n, dtype=bool)
        self.game_over = np.ones(n, dtype=bool)  # no game yet: the first reset starts one

    # ------------------------------------------------------------------------------- ALE calls
    def _new_game(self, env: int, ale_seed: int | None) -> None:
        """ALE's reset of ``env`` (a new game; its ALE reseeded first when ``ale_seed`` is given)."""
        screens, info = self._envs[env].reset(seed=None if ale_seed is None else np.array([ale_seed]))
        self._screens[env], self.lives[env] = screens[0, 0], info["lives"][0]

    def _exchange(self, envs: list[int], actions: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One frame-skipped step of each env of ``envs`` with its action, run in parallel by ALE's
        threads; updates their screens and lives. Returns ``(reward [k] float32, game over [k],
        truncated [k])``."""
        for env, action in zip(envs, actions):
            self._envs[env].send(np.array([action], dtype=np.int64))
        reward = np.zeros(len(envs), dtype=np.float32)
        over, truncated = np.zeros(len(envs), dtype=bool), np.zeros(len(envs), dtype=bool)
        for k, env in enumerate(envs):
            screens, rewards, overs, truncations, info = self._envs[env].recv()  # each of one env
            self._screens[env], self.lives[env] = screens[0, 0], info["lives"][0]
            reward[k], over[k], truncated[k] = rewards[0], overs[0], truncations[0]
        return reward, over, truncated

    # ------------------------------------------------------------------------------- resets
    def _start_episode(self, env: int, seed: int | None) -> list[int]:
        """Begin DVRLAtari's reset of ``env`` (seeding its generators when ``seed`` is given; a new
        game when its game is over or it is seeded) and return the actions it still takes."""
        if seed is not None:
            self._np_random[env] = np.random.default_rng(int(seed))
            self._flicker[env] = np.random.default_rng([int(seed), FLICKER_STREAM])
        if self._flicker[env] is None:
            self._flicker[env] = np.random.default_rng()
        if self._np_random[env] is None:
            self._np_random[env] = np.random.default_rng()
        if self.game_over[env] or seed is not None:
            ale_seed = None
            if seed is not None:
                ale_seed = vector_ale_seed(dvrl_ale_seed(self._np_random[env].integers(0, 2**31 - 1)))
            elif not self._seeded[env]:  # ALE would seed it from the clock, the same for every env
                ale_seed = int(np.random.default_rng().integers(ALE_SEED_LIMIT))
            self._new_game(env, ale_seed)
            self._seeded[env] = True
            noops = int(self._np_random[env].integers(1, self.noop_max + 1)) if self.noop_max else 0
            program = [0] * noops
        else:  # a life was lost: the game goes on after one no-op step (baselines' EpisodicLifeEnv)
            program = [0]
        return program + ([self._fire, 2] if self._fire is not None else [])

    def _run_programs(self, programs: dict[int, list[int]]) -> None:
        """Step each env through its list of actions, the envs in parallel; a game that ends on the
        way is restarted (ALE's reset), as in DVRLAtari's reset."""
        longest = max((len(p) for p in programs.values()), default=0)
        for step in range(longest):
            envs = [env for env, program in programs.items() if step < len(program)]
            _, over, truncated = self._exchange(envs, [programs[env][step] for env in envs])
            for env in np.asarray(envs)[over | truncated]:
                self._new_game(int(env), None)

    def reset(self, mask: np.ndarray | None = None, seeds=None) -> np.ndarray:
        """New episodes in the envs of ``mask`` (``[N]`` bool; all when ``None``), each seeded with
        ``seeds[env]`` where ``seeds`` (``N`` ints or ``None``) gives one. Returns every env's current
        observation ``[N, 1, 84, 84]``."""
        envs = np.arange(self.num_envs) if mask is None else np.flatnonzero(np.asarray(mask, dtype=bool))
        if seeds is not None and len(seeds) != self.num_envs:
            raise ValueError(f"seeds: expected {self.num_envs} seeds (or None), got {len(seeds)}")
        programs = {int(env): self._start_episode(int(env), None if seeds is None else seeds[env]) for env in envs}
        self._run_programs(programs)
        self.game_over[envs] = False
        self._observe(envs)
        return self.observation

    # ------------------------------------------------------------------------------- steps
    def _check_actions(self, actions) -> np.ndarray:
        actions = np.asarray(actions)
        if (actions.shape != (self.num_envs,) or not np.issubdtype(actions.dtype, np.integer)
                or (actions < 0).any() or (actions >= self.n_actions).any()):
            raise ValueError(f"action: expected {self.num_envs} ints in [0, {self.n_actions}), got {actions!r}")
        if self.game_over.any():
            raise RuntimeError(f"step: the games of envs {np.flatnonzero(self.game_over).tolist()} are over (or "
                               "never started); reset them first")
        return actions.astype(np.int64)

    def step(self, actions) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One step of every env (see the class docstring); a lost life terminates the env's episode
        (``episodic_life``), the end of its game sets ``game_over``."""
        actions = self._check_actions(actions)
        lives_before = self.lives.copy()
        reward, over, truncated = self._exchange(list(range(self.num_envs)), actions.tolist())
        life_lost = self.episodic_life & (self.lives > 0) & (self.lives < lives_before)
        self.game_over = over | truncated
        self._observe(np.arange(self.num_envs))
        return self.observation, reward, over | life_lost, truncated & ~over, self.game_over.copy()

    def _observe(self, envs: np.ndarray) -> None:
        """Set the observations of ``envs`` from their screens, each blanked with probability
        ``p_blank`` from its own flicker generator."""
        if len(envs) == 0:
            return
        frames = resize_screens(self._screens[envs], self._rows, self._cols)
        blank = np.array([self._flicker[env].random() < self.p_blank for env in envs])
        frames[blank] = 0.0
        self.observation[envs], self.blank[envs] = frames, blank

    def close(self) -> None:
        self._envs = []  # ALE's vector envs stop their threads when freed


class FlickeringAtariVectorEnv(EnvBase):
    """A TorchRL env of ``num_envs`` flickering games (batch size ``[N]``) on :class:`DVRLAtariVector`,
    with the keys and specs of a ``SerialEnv`` of :func:`~escort_rl.envs.atari.make_atari_torchrl_env`:
    ``observation [N, 1, 84, 84]`` (``Bounded`` in ``[0, 1]``), ``game_over [N]``, ``action [N]``
    (``Categorical``), ``reward [N, 1]``, ``done``/``terminated``/``truncated [N, 1]``. ``kwargs`` go to
    :class:`DVRLAtariVector`. ``set_seed(s)`` seeds and resets env ``k`` as ``SerialEnv`` seeds its
    ``k``-th env."""

    def __init__(self, game: str = "pong", num_envs: int = 1, device: str = "cpu", **kwargs) -> None:
        games = DVRLAtariVector(game, num_envs, **kwargs)
        super().__init__(device=device, batch_size=torch.Size([games.num_envs]))
        self.games = games
        n = games.num_envs
        flag = dict(n=2, shape=(n, 1), dtype=torch.bool, device=self.device)
        self.observation_spec = Composite(
            observation=Bounded(0.0, 1.0, (n, 1, FRAME_SIZE, FRAME_SIZE), dtype=torch.float32, device=self.device),
            game_over=Categorical(2, shape=(n,), dtype=torch.bool, device=self.device), shape=(n,))
        self.action_spec = Categorical(games.n_actions, shape=(n,), dtype=torch.int64, device=self.device)
        self.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(done=Categorical(**flag), terminated=Categorical(**flag),
                                   truncated=Categorical(**flag), shape=(n,))
        self.is_closed = False

    def _output(self, observation: np.ndarray, game_over: np.ndarray, terminated: np.ndarray,
                truncated: np.ndarray, reward: np.ndarray | None = None) -> TensorDict:
        n = self.games.num_envs
        out = {"observation": torch.from_numpy(observation.copy()), "game_over": torch.from_numpy(game_over),
               "terminated": torch.from_numpy(terminated).reshape(n, 1),
               "truncated": torch.from_numpy(truncated).reshape(n, 1),
               "done": torch.from_numpy(terminated | truncated).reshape(n, 1)}
        if reward is not None:
            out["reward"] = torch.from_numpy(reward).reshape(n, 1)
        return TensorDict(out, batch_size=self.batch_size).to(self.device)

    def _reset(self, tensordict: TensorDict | None = None, **kwargs) -> TensorDict:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict["_reset"].reshape(self.games.num_envs, -1).any(-1).cpu().numpy()
        observation = self.games.reset(mask)
        false = np.zeros(self.games.num_envs, dtype=bool)
        return self._output(observation, false, false, false)

    def _step(self, tensordict: TensorDict) -> TensorDict:
        observation, reward, terminated, truncated, game_over = self.games.step(tensordict["action"].cpu().numpy())
        return self._output(observation, game_over, terminated, truncated, reward)

    def set_seed(self, seed: int | None = None, static_seed: bool = False) -> int | None:
        """Seed and reset every env, env ``k`` with the seed ``SerialEnv.set_seed(seed)`` gives its
        ``k``-th env (``None``: unseeded resets); returns the next seed, as ``SerialEnv`` does."""
        if seed is None:
            self.games.reset()
            return None
        seeds, next_seed = serial_env_seeds(int(seed), self.games.num_envs, static_seed)
        self.games.reset(seeds=seeds)
        return next_seed

    def _set_seed(self, seed: int | None) -> None:
        self.set_seed(seed)

    def close(self, *, raise_if_closed: bool = True) -> None:
        self.games.close()
        super().close(raise_if_closed=raise_if_closed)


def make_atari_vector_env(game: str = "pong", num_envs: int = 1, seed: int | None = None, device: str = "cpu",
                          **kwargs) -> FlickeringAtariVectorEnv:
    """``num_envs`` flickering games of ``game`` on ALE's vector env (:class:`FlickeringAtariVectorEnv`),
    seeded with ``seed`` when given (env ``k`` as a ``SerialEnv``'s ``k``-th env). ``kwargs`` go to
    :class:`DVRLAtariVector` (``frame_skip``, ``noop_max``, ``repeat_action_probability``,
    ``episodic_life``, ``max_frames``, ``p_blank``)."""
    env = FlickeringAtariVectorEnv(game, num_envs, device=device, **kwargs)
    if seed is not None:
        env.set_seed(int(seed))
    return env
