"""POPGym's tasks as TorchRL envs, and the known models of its control tasks.

POPGym (Morad et al., ICLR 2023, the ``popgym`` package, installed by ``pip install
'escort-rl[popgym]'``) has twelve control tasks, each in three difficulties:

- ``PositionOnlyCartPole{Easy,Medium,Hard}`` (the paper's Stateless CartPole): CartPole without its
  velocities; episodes of 200, 400, 600 steps; 2 discrete actions.
- ``NoisyPositionOnlyCartPole{Easy,Medium,Hard}``: the same, with observation noise σ = 0.1, 0.2, 0.3
  clipped to the observation box; episodes of 200 steps.
- ``PositionOnlyPendulum{Easy,Medium,Hard}``: Pendulum without its angular velocity; episodes of 200,
  150, 100 steps; a continuous torque in ``[−2, 2]``.
- ``NoisyPositionOnlyPendulum{Easy,Medium,Hard}``: the same, with noise σ = 0.1, 0.2, 0.3 clipped to
  ``[−1, 1]``; episodes of 200 steps.

POPGym scales the rewards so that an episode's return lies in ``[−1, 1]``, and truncates an episode
itself at its length. ``import popgym`` registers the gymnasium ids ``popgym-<name>-v0`` (:data:`
POPGYM_CONTROL`); :func:`make_popgym_env` imports it when it builds an env (in every worker process
too), so importing this module needs no ``popgym``.

:func:`popgym_model` gives a task's known torch model
(:class:`~escort_rl.models.POPGymCartPole`, :class:`~escort_rl.models.POPGymPendulum`), which
reproduces the env step for step and adds the densities a filter needs. POPGym's other tasks (the
memory games: Repeat Previous, Battleship, Concentration...) have no model here; they run through
:func:`make_popgym_env` with one-hot observations, and the GRU trains on them (``env=popgym``).
"""

from __future__ import annotations

import functools
import numbers

import gymnasium as gym
import numpy as np

from escort_rl.config.errors import MissingExtra

POPGYM_CONTROL = {
    f"{noisy}PositionOnly{system}{level}": f"popgym-{noisy}PositionOnly{system}{level}-v0"
    for noisy in ("", "Noisy") for system in ("CartPole", "Pendulum") for level in ("Easy", "Medium", "Hard")
}
"""POPGym's twelve control tasks: name -> gymnasium id (registered by ``import popgym``)."""
MISSING_POPGYM = "POPGym's tasks need the popgym package: install it with pip install 'escort-rl[popgym]'"


def import_popgym():
    """``popgym``, imported (which registers its gymnasium ids); ``ImportError`` naming the extra
    when it is not installed."""
    try:
        import popgym
    except ImportError:
        raise MissingExtra(MISSING_POPGYM) from None
    return popgym


def popgym_task(name: str) -> str:
    """The task name of ``name`` (a key of :data:`POPGYM_CONTROL`, or its gymnasium id
    ``popgym-<name>-v0``); an unknown one raises ``ValueError`` listing the twelve.

    Example:
        >>> popgym_task("popgym-NoisyPositionOnlyPendulumHard-v0")
        'NoisyPositionOnlyPendulumHard'
    """
    from escort_rl.models.popgym_task import task_key

    key = task_key(name)
    if key not in POPGYM_CONTROL:
        raise ValueError(f"name: unknown POPGym control task '{name}'; choose one of {sorted(POPGYM_CONTROL)}")
    return key


def popgym_tasks() -> dict[str, str]:
    """Every POPGym task (the memory games as well as the control tasks): name -> gymnasium id, read
    from gymnasium's registry after ``import popgym`` (which needs the ``popgym`` extra).

    Example:
        >>> popgym_tasks()["RepeatPreviousEasy"]  # doctest: +SKIP
        'popgym-RepeatPreviousEasy-v0'
    """

    import_popgym()
    return {env_id.removeprefix("popgym-").removesuffix("-v0"): env_id
            for env_id in gym.registry if env_id.startswith("popgym-")}


def popgym_any_task(name: str) -> str:
    """The task name of ``name`` (any of :func:`popgym_tasks`, or its gymnasium id); an unknown one
    raises ``ValueError`` listing them."""
    from escort_rl.models.popgym_task import task_key

    key, tasks = task_key(name), popgym_tasks()
    if key not in tasks:
        raise ValueError(f"name: unknown POPGym task '{name}'; choose one of {', '.join(sorted(tasks))}")
    return key


def make_gym_popgym_env(name: str):
    """POPGym's task ``name`` as a gymnasium env with a flat float observation and one discrete (or
    real) action: a discrete, multi-discrete or tuple observation becomes its one-hot encoding in
    float32 (gymnasium's ``FlattenObservation`` and ``DtypeObservation``), a multi-discrete action
    one discrete action over their product (POPGym's ``DiscreteAction``). The control tasks are left
    as they are."""

    key = popgym_any_task(name)
    from popgym.wrappers import DiscreteAction

    env = gym.make(popgym_tasks()[key])
    if isinstance(env.action_space, gym.spaces.MultiDiscrete):
        env = DiscreteAction(env.unwrapped)  # POPGym's wrappers take its own env, not gymnasium's
    if not isinstance(env.observation_space, gym.spaces.Box):
        env = gym.wrappers.DtypeObservation(gym.wrappers.FlattenObservation(env), np.float32)
    return CheckedAction(env)


class CheckedAction(gym.Wrapper):
    """A POPGym env that refuses an action outside its action space with one line naming ``action``,
    where POPGym would clip a torque silently, step a NaN into NaN observations or fail an ``assert``."""

    def step(self, action):
        space, value, fix = self.action_space, np.asarray(action), None
        if isinstance(space, gym.spaces.Discrete):
            if not (value.shape == () and np.issubdtype(value.dtype, np.integer) and space.contains(int(value))):
                fix = f"pass an integer index in [{space.start}, {space.start + space.n})"
        elif isinstance(space, gym.spaces.Box):
            if not (np.issubdtype(value.dtype, np.number) and space.contains(value.astype(space.dtype))):
                fix = "pass finite values inside the box (squash or clip the policy's output)"
        if fix is not None:
            raise ValueError(f"action: expected an element of {space}, got {value.tolist()!r}; {fix}")
        return self.env.step(action)


def popgym_episode_length(name: str) -> int | None:
    """The longest episode of POPGym's task ``name`` (its ``max_episode_length``, or the fixed
    ``episode_length`` of Concentration), or ``None`` where POPGym states none (HigherLower: a deck)."""
    env = make_gym_popgym_env(name).unwrapped
    length = getattr(env, "max_episode_length", None) or getattr(env, "episode_length", None)
    return None if length is None else int(length)


def popgym_task_spaces(name: str, device: str = "cpu"):
    """The :class:`~escort_rl.models.TaskSpaces` of POPGym's task ``name`` as
    :func:`make_single_popgym_env` presents it: the observation's width and the actions."""
    import torch

    from escort_rl.models import TaskSpaces

    env = make_gym_popgym_env(name)
    obs_dim = int(gym.spaces.flatdim(env.observation_space))
    action = env.action_space
    if isinstance(action, gym.spaces.Discrete):
        return TaskSpaces(obs_dim=obs_dim, n_actions=int(action.n))
    low, high = (torch.as_tensor(bound, dtype=torch.float32, device=device).reshape(-1)
                 for bound in (action.low, action.high))
    return TaskSpaces(obs_dim=obs_dim, action_dim=int(low.numel()), action_low=low, action_high=high)


def make_single_popgym_env(name: str, device: str = "cpu", seed: int | None = None):
    """One POPGym task (any of :func:`popgym_tasks`) as a TorchRL ``GymWrapper``: ``"observation"`` a flat
    float32 vector (``[2]`` on the control tasks; one-hot codes on the memory games, see
    :func:`make_gym_popgym_env`), ``"action"`` an int64 scalar (``Categorical``) or, on Pendulum, ``[1]``
    float32 in ``Bounded(−2, 2)``. Module level, so ``functools.partial`` of it travels to
    ``ParallelEnv`` workers."""
    from torchrl.envs import GymWrapper

    env = GymWrapper(make_gym_popgym_env(name), device=device, categorical_action_encoding=True)
    if seed is not None:
        env.set_seed(int(seed))
    return env


def make_popgym_env(name: str, num_envs: int = 1, parallel: bool = False, seed: int | None = None,
                    device: str = "cpu"):
    """POPGym's task ``name`` as a TorchRL env (:func:`make_single_popgym_env`).

    Args:
        name: any task of :func:`popgym_tasks` (or its gymnasium id); an unknown one raises
            ``ValueError`` listing them.
        num_envs: ``1``: a ``GymWrapper`` (batch size ``()``); more: a ``SerialEnv`` of that many, batch size
            ``(num_envs,)``.
        parallel: a ``ParallelEnv`` (spawned worker processes) instead of a ``SerialEnv``.
        seed: seeds the env (a batched env seeds its workers ``seed``, ``seed + 1``, ...).
        device: where the env's tensors live.
    """
    from torchrl.envs import ParallelEnv, SerialEnv

    key = popgym_any_task(name)
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs: expected a positive int, got {num_envs!r}")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, numbers.Integral)):
        raise ValueError(f"seed: expected an int or None, got {seed!r}")
    import_popgym()  # here too, for the message before any worker starts
    if num_envs == 1 and not parallel:
        return make_single_popgym_env(key, device=device, seed=seed)
    factory = functools.partial(make_single_popgym_env, key, device=device)
    env = (ParallelEnv(num_envs, factory, mp_start_method="spawn", device=device) if parallel
           else SerialEnv(num_envs, factory, device=device))
    if seed is not None:
        env.set_seed(int(seed))
    return env


def popgym_model(name: str, **kwargs):
    """The known torch model of POPGym's task ``name``: :class:`~escort_rl.models.POPGymCartPole` or
    :class:`~escort_rl.models.POPGymPendulum` with the task's episode length and noise; ``kwargs``
    (``process_noise``, ``obs_noise_floor``, ``device``) on top. Needs no ``popgym``.

    Example:
        >>> m = popgym_model("NoisyPositionOnlyCartPoleMedium")
        >>> type(m).__name__, m.obs_noise, m.max_episode_length
        ('POPGymCartPole', 0.2, 200)
    """
    from escort_rl.models import popgym_model_class

    key = popgym_task(name)
    return popgym_model_class(key).from_name(key, **kwargs)
