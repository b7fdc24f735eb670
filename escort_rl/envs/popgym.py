"""POPGym's control tasks as TorchRL envs, and their known models.

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
reproduces the env step for step and adds the densities a filter needs.
"""

from __future__ import annotations

import functools

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
        raise ImportError(MISSING_POPGYM) from None
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


def make_single_popgym_env(name: str, device: str = "cpu", seed: int | None = None):
    """One POPGym task as a TorchRL ``GymEnv``: ``"observation"`` ``[2]`` float32, ``"action"`` an int64
    scalar (``Categorical(2)``) on CartPole and ``[1]`` float32 in ``Bounded(−2, 2)`` on Pendulum.
    Module level, so ``functools.partial`` of it travels to ``ParallelEnv`` workers."""
    from torchrl.envs import GymEnv

    env_id = POPGYM_CONTROL[popgym_task(name)]
    import_popgym()
    env = GymEnv(env_id, device=device, categorical_action_encoding=True)
    if seed is not None:
        env.set_seed(int(seed))
    return env


def make_popgym_env(name: str, num_envs: int = 1, parallel: bool = False, seed: int | None = None,
                    device: str = "cpu"):
    """POPGym's control task ``name`` as a TorchRL env.

    Args:
        name: a task of :data:`POPGYM_CONTROL` (or its gymnasium id); an unknown one raises
            ``ValueError`` listing them.
        num_envs: ``1``: a ``GymEnv`` (batch size ``()``); more: a ``SerialEnv`` of that many, batch size
            ``(num_envs,)``.
        parallel: a ``ParallelEnv`` (spawned worker processes) instead of a ``SerialEnv``.
        seed: seeds the env (a batched env seeds its workers ``seed``, ``seed + 1``, ...).
        device: where the env's tensors live.
    """
    from torchrl.envs import ParallelEnv, SerialEnv

    key = popgym_task(name)
    if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs: expected a positive int, got {num_envs!r}")
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
