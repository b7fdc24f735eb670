"""The cells of ``bench popgym``: one row's training run on one task and seed
(:class:`POPGymTrainCell`), and a uniform-random policy's episodes on one task
(:class:`POPGymRandomCell`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from escort_rl.bench.core.runner import Cell
from escort_rl.reporting.paths import safe_name


def task_overrides(task: str) -> tuple[str, ...]:
    """The env group and model keys of POPGym's ``task``: its system's env group
    (``env=popgym_cartpole`` or ``env=popgym_pendulum``), its noise and its episode length.

    Example:
        >>> task_overrides("NoisyPositionOnlyPendulumHard")
        ('env=popgym_pendulum', 'env.model.obs_noise=0.3', 'env.model.max_episode_length=200', 'env.max_steps=200')
    """
    from escort_rl.config.registry import name_of
    from escort_rl.models import popgym_model_class

    model = popgym_model_class(task)
    group, params = name_of("model", model), model.TASKS[task]
    return (f"env={group}", f"env.model.obs_noise={params['obs_noise']}",
            f"env.model.max_episode_length={params['max_episode_length']}",
            f"env.max_steps={params['max_episode_length']}")


def frames_per_iteration(cfg) -> int:
    """Env steps in one training iteration of ``cfg``: ``num_envs × env.max_steps`` for DVRL's A2C;
    for PPO and recurrent PPO, ``num_envs × rollout × ⌈max_steps / rollout⌉`` with ``rollout =
    min(rollout_steps, max_steps)`` (whole batches, the last one past the episode's end)."""
    steps, envs = int(cfg.env.max_steps), int(cfg.trainer.num_envs)
    rollout = cfg.trainer.get("rollout_steps", None)
    if rollout is None:
        return envs * steps
    rollout = min(int(rollout), steps)
    return envs * rollout * -(-steps // rollout)


@dataclass(frozen=True, kw_only=True)
class POPGymTrainCell(Cell):
    """One training run: ``overrides`` (the task's, then the row's) with ``seed`` into ``run_dir`` for
    as many iterations as reach ``frames`` env steps (a killed cell resumes from its last checkpoint).
    Returns each iteration's frames, mean episode return and seconds."""

    task: str
    label: str
    overrides: tuple[str, ...]
    seed: int
    frames: int
    run_dir: str

    def key(self) -> str:
        return f"trained/{self.task}/{safe_name(self.label)}/seed{self.seed}"

    def run_overrides(self) -> list[str]:
        """The overrides with the seed, the folder and the iterations that reach ``frames``
        (:func:`frames_per_iteration`)."""
        from escort_rl.config import compose

        per_iteration = frames_per_iteration(compose(list(self.overrides)))
        iterations = max(1, -(-int(self.frames) // per_iteration))
        return [*self.overrides, f"seed={self.seed}", f"output_dir={self.run_dir}", f"trainer.iterations={iterations}"]

    def run(self) -> dict:
        from escort_rl.trainers.checkpointing import load_checkpoint, resolve_checkpoint
        from escort_rl.trainers.resume import train_config
        from escort_rl.trainers.training import train

        overrides = self.run_overrides()
        if (Path(self.run_dir) / "checkpoints").is_dir():
            overrides.append(f"resume={self.run_dir}")
        cfg, saved = train_config(overrides)
        if saved is None or saved["trainer_state"]["iteration"] < int(cfg.trainer.iterations):
            train(cfg, resume_state=saved, progress=False)
        history = load_checkpoint(resolve_checkpoint(self.run_dir))["trainer_state"]["history"]
        return {"task": self.task, "label": self.label, "seed": self.seed,
                "frames": [int(r["frames"]) for r in history],
                "episode_return": [float(r.get("episode_return", float("nan"))) for r in history],
                "seconds": [float(r.get("seconds", float("nan"))) for r in history]}


@dataclass(frozen=True, kw_only=True)
class POPGymRandomCell(Cell):
    """A uniform-random policy on ``episodes`` episodes of ``task`` from env seed ``seed``: their returns."""

    task: str
    overrides: tuple[str, ...]
    episodes: int
    seed: int = 10000

    def key(self) -> str:
        return f"random/{self.task}/seed{self.seed}"

    def run(self) -> dict:
        from escort_rl.config import compose
        from escort_rl.trainers.builders import build_pomdp_env

        cfg = compose([*self.overrides, "filter=sir"])
        env = build_pomdp_env(cfg, int(self.episodes), seed=int(self.seed))
        rollout = env.rollout(int(cfg.env.max_steps), break_when_any_done=False)
        reward = rollout["next", "reward"].squeeze(-1)
        done = rollout["next", "done"].squeeze(-1)
        alive = (done.long().cumsum(1) - done.long()) == 0  # the steps of each env's first episode
        return {"task": self.task, "episode_return": (reward * alive).sum(1).double().tolist()}
