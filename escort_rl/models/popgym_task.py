"""What POPGym's CartPole and Pendulum models share beyond their dynamics: their parameters and
building one of POPGym's tasks by name."""

from __future__ import annotations

from dataclasses import dataclass

from escort_rl.config.params import param


@dataclass(frozen=True)
class POPGymParams:
    """The parameters of a POPGym control model (each model's module docstring says why).

    Attributes:
        max_episode_length: POPGym's episode length ``L``: the reward is scaled by ``1/L``, and the
            env truncates after ``L`` steps (each task's is in the model's ``TASKS``).
        obs_noise: POPGym's ``noise_sigma``, the std of the clipped observation noise (0 on the
            stateless tasks; 0.1, 0.2, 0.3 on the noisy ones).
        obs_noise_floor: the smallest observation std the density uses (filter side).
        process_noise: the filter-side process noise, in units of the model's ``TYPICAL_STEP`` per
            coordinate (0: POPGym's deterministic step, and no transition density).
    """

    max_episode_length: int = param(200, ge=1)
    obs_noise: float = param(0.0, ge=0)
    obs_noise_floor: float = param(0.01, ge=0)
    process_noise: float = param(0.05, ge=0)


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

