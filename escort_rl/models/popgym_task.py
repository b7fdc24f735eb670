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
        key = str(name).removeprefix("popgym-").removesuffix("-v0")
        if key not in cls.TASKS:
            raise ValueError(f"name: unknown POPGym {cls.SYSTEM} task '{name}'; choose one of {sorted(cls.TASKS)}")
        return cls(**{**cls.TASKS[key], **kwargs})
