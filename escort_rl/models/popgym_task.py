"""What POPGym's CartPole and Pendulum models share beyond their dynamics: building one of POPGym's
tasks by name."""

from __future__ import annotations


class POPGymTask:
    """A model of one POPGym system whose tasks differ only in parameters: ``TASKS`` maps each task
    name to its keyword arguments (episode length, noise), ``SYSTEM`` names the system in messages."""

    TASKS: dict[str, dict] = {}
    SYSTEM = ""

    @classmethod
    def from_name(cls, name: str, **kwargs):
        """The model of POPGym's task ``name`` (a key of ``TASKS``, or its gymnasium id
        ``popgym-<name>-v0``); ``kwargs`` (``process_noise``, ``obs_noise_floor``, ``device``) on top."""
        key = task_key(name)
        if key not in cls.TASKS:
            raise ValueError(f"name: unknown POPGym {cls.SYSTEM} task '{name}'; choose one of {sorted(cls.TASKS)}")
        return cls(**{**cls.TASKS[key], **kwargs})


def task_key(name: str) -> str:
    """POPGym's task name without its gymnasium id's ``popgym-`` and ``-v0``.

    Example:
        >>> task_key("popgym-NoisyPositionOnlyPendulumHard-v0")
        'NoisyPositionOnlyPendulumHard'
    """
    return str(name).removeprefix("popgym-").removesuffix("-v0")


def popgym_model_class(name: str) -> type[POPGymTask]:
    """The model class whose ``TASKS`` hold POPGym's task ``name`` (or its gymnasium id): the one map
    from a task to its system.

    Example:
        >>> popgym_model_class("NoisyPositionOnlyCartPoleEasy").__name__
        'POPGymCartPole'
    """
    from escort_rl.models.popgym_cartpole import POPGymCartPole
    from escort_rl.models.popgym_pendulum import POPGymPendulum

    key = task_key(name)
    for model in (POPGymCartPole, POPGymPendulum):
        if key in model.TASKS:
            return model
    tasks = sorted(POPGymCartPole.TASKS) + sorted(POPGymPendulum.TASKS)
    raise ValueError(f"name: unknown POPGym control task '{name}'; choose one of {', '.join(tasks)}")
