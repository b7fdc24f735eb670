"""Every setting of one ``bench popgym`` run in a frozen :class:`POPGymSpec`, with ``quick()``
(``--quick``); the field defaults are the full run, and this module is the only place that states a
default."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

DEFAULT_OUTPUT = "outputs/bench/popgym"
"""``bench popgym``'s ``--output``."""

TASKS = tuple(f"NoisyPositionOnly{system}{level}" for system in ("CartPole", "Pendulum")
              for level in ("Easy", "Medium", "Hard"))
"""The tasks: POPGym's Noisy Stateless CartPole and Pendulum at its three difficulties."""

COMMON = ("trainer.num_envs=16",)
"""Under every row: 16 envs."""

CONTINUOUS = ("trainer.max_importance_ratio=3",)
"""Under every row on a task with continuous actions (Pendulum; every such row is PPO): the ratio that
weighs PPO's surrogate is capped at 3, as dual-clip PPO does. Without it a TanhNormal that learns
bang-bang torques meets ratios of 1e18 and non-finite gradients (one EnKF seed on Pendulum Hard
diverged). CartPole's categorical policies never came near it, and run without."""

BELIEF_PPO = ("trainer=ppo", "trainer.exploring_starts=false", "trainer.warm_start_filter=null",
              "trainer.warm_start_iterations=0", "trainer.critic_input=belief", "trainer.rollout_steps=50")
"""PPO on beliefs from the task's own start distribution, no warm start, and a critic that reads the
belief (no true state), as the GRU's and DVRL's read only what they act on. Batches of 50 steps
divide every task's episode (100 to 600 steps), so an iteration is ``num_envs × max_steps`` frames
for every row, as DVRL's is: equal frames."""

ROWS = (
    ("PPO on SIR beliefs", (*BELIEF_PPO, "filter=sir")),
    ("PPO on EnKF beliefs", (*BELIEF_PPO, "filter=enkf")),
    ("PPO on ESCORT beliefs", (*BELIEF_PPO, "filter=escort_train")),
    ("GRU (recurrent PPO)", ("trainer=recurrent_ppo", "trainer.rollout_steps=50")),
    ("DVRL", ("trainer=dvrl_a2c",)),
)
"""The trained rows: a label and its overrides. DVRL takes discrete actions: it runs on CartPole only."""

_QUICK = dict(seeds=1, frames=800, tasks=("NoisyPositionOnlyCartPoleEasy", "NoisyPositionOnlyPendulumEasy"),
              overrides=("trainer.num_envs=4", "env.max_steps=20", "env.model.max_episode_length=20",
                         "num_particles=16", "actor.hidden=8"))
"""What ``bench popgym --quick`` changes: one seed of 800 frames on the two Easy tasks, 20-step episodes."""


@dataclass(frozen=True)
class POPGymSpec:
    """The POPGym comparison: each row trained on each task for ``frames`` env steps per seed
    (``seeds`` training seeds), reported as POPGym's MMER beside a uniform-random policy's.

    ``overrides`` go under every row's own (after :data:`COMMON`); ``threads``: torch threads per cell.
    ``popgym_env``: the agents act in POPGym's own env (``env.popgym_task``, TorchRL's ``GymEnv``)
    instead of the verified model's simulator (DVRL, whose readout reads the true state, then sits out).

    Examples:
        >>> POPGymSpec().seeds, POPGymSpec.quick().frames
        (3, 800)
    """

    tasks: tuple[str, ...] = TASKS
    rows: tuple[tuple[str, tuple[str, ...]], ...] = ROWS
    seeds: int = 3
    frames: int = 200_000
    random_episodes: int = 100
    popgym_env: bool = False
    overrides: tuple[str, ...] = ()
    threads: int = 1
    output: Path = Path(DEFAULT_OUTPUT)

    def __post_init__(self) -> None:
        from escort_rl.envs.popgym import POPGYM_CONTROL

        for task in self.tasks:
            if task not in POPGYM_CONTROL:
                raise ValueError(f"--tasks: unknown task '{task}'; choose from {', '.join(sorted(POPGYM_CONTROL))}")
        for name, value, low in (("--seeds", self.seeds, 1), ("--frames", self.frames, 1),
                                 ("--threads", self.threads, 1)):
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"{name}: must be >= {low}, got {value}")

    @classmethod
    def quick(cls) -> POPGymSpec:
        return cls(**{**_QUICK, "tasks": tuple(_QUICK["tasks"]), "overrides": tuple(_QUICK["overrides"])})

    def replace(self, **changes) -> POPGymSpec:
        return dataclasses.replace(self, **changes)
