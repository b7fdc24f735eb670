"""The one map from a POPGym control task to the model of its system."""

from __future__ import annotations

from escort_rl.models.popgym_cartpole import POPGymCartPole
from escort_rl.models.popgym_pendulum import POPGymPendulum
from escort_rl.models.popgym_task import POPGymTask, task_key

POPGYM_MODELS: tuple[type[POPGymTask], ...] = (POPGymCartPole, POPGymPendulum)
"""The models of POPGym's control systems; each one's ``TASKS`` names its tasks."""


def popgym_model_class(name: str) -> type[POPGymTask]:
    """The model class whose ``TASKS`` hold POPGym's task ``name`` (or its gymnasium id): the one map
    from a task to its system.

    Example:
        >>> popgym_model_class("NoisyPositionOnlyCartPoleEasy").__name__
        'POPGymCartPole'
    """
    key = task_key(name)
    for model in POPGYM_MODELS:
        if key in model.TASKS:
            return model
    tasks = [task for model in POPGYM_MODELS for task in sorted(model.TASKS)]
    raise ValueError(f"name: unknown POPGym control task '{name}'; choose one of {', '.join(tasks)}")
