"""A trained policy, loaded for a user's own TorchRL loop."""

from __future__ import annotations

from pathlib import Path

from escort_rl.trainers.checkpointing import load_checkpoint, resolve_checkpoint
from escort_rl.trainers.resume import run_config


def load_policy(run: str | Path):
    """The trained policy of a run: a TorchRL ``ProbabilisticActor`` (a ``TensorDictModule``).

    ``run`` is a run directory, its ``checkpoints/`` folder or one checkpoint; a run directory gives
    its newest intact checkpoint (a damaged one is detected, not loaded). The policy of a belief
    trainer (PPO, REINFORCE) reads the belief keys of the run's config (``keys.particles``,
    ``keys.log_weights``: ``[*B, N, d]`` and ``[*B, N]``) and writes ``"action"``; recurrent PPO's
    and DVRL's read the observation and their own state. It samples its action by default; under
    ``torchrl.envs.utils.set_exploration_type(ExplorationType.DETERMINISTIC)`` it takes the most
    probable one, as the evaluation does.

    Example (after ``make run``; ``env`` the run's belief env)::

        policy = escort_rl.load_policy("outputs/lightdark10d/escort_train-ppo-seed0")
        td = policy(env.reset())  # td["action"]: [B]
    """
    from escort_rl.trainers.evaluate import trained_policy

    checkpoint = resolve_checkpoint(run)
    cfg = run_config(load_checkpoint(checkpoint))
    return trained_policy(cfg, checkpoint)[0]
