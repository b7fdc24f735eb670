"""The trainers' parameters (``trainer.*``): one frozen dataclass per algorithm, with its ranges.

Each trainer class names its dataclass as ``Params`` (``PPO.Params is PPOParams``); Hydra's schema of
``configs/trainer/<name>.yaml`` is made from it, so the yaml holds only what differs from these
defaults. They live in this light module, apart from the trainers' code, so that composing a config
does not import TorchRL. An iteration is ``num_envs`` episodes of ``env.max_steps`` steps.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from escort_rl.config.files import check_filter_name
from escort_rl.config.params import MAX_LR, param


@dataclass(frozen=True)
class TrainerParams:
    """The parameters every trainer reads.

    Attributes:
        iterations: training iterations.
        num_envs: environments collected in parallel.
        lr: the optimiser's learning rate.
        gamma: the discount per decision.
        entropy_coef: the entropy bonus's weight.
        max_grad_norm: gradients are clipped to this norm.
        checkpoint_every: iterations between checkpoints (and one at the end).
        keep_checkpoints: the newest checkpoints kept.
    """

    iterations: int = param(20, ge=1)
    num_envs: int = param(16, ge=1)
    lr: float = param(1e-3, gt=0, lt=MAX_LR)
    gamma: float = param(0.99, gt=0, le=1)
    entropy_coef: float = param(0.01, ge=0)
    max_grad_norm: float = param(0.5, gt=0)
    checkpoint_every: int = param(5, ge=1)
    keep_checkpoints: int = param(3, ge=1)


@dataclass(frozen=True)
class BeliefTrainerParams(TrainerParams):
    """The parameters of the trainers that collect on a belief filter's beliefs.

    Attributes:
        reward_scale: rewards are multiplied by this before the losses (the critic fits returns of
            order one to ten instead of hundreds).
        exploring_starts: the training envs start from the env group's ``exploring_starts`` (a start
            box that covers the goal), the evaluation from the env's own start distribution.
        warm_start_filter: the first ``warm_start_iterations`` iterations collect on this filter's
            beliefs (a ``configs/filter/`` name), the rest on the run's filter; ``None``: every
            iteration on the run's filter. Policies over particles move between filters, and an SIR
            update costs about a hundredth of an ESCORT one.
        warm_start_iterations: see ``warm_start_filter``.
    """

    reward_scale: float = param(0.1, gt=0)
    exploring_starts: bool = param(False)
    warm_start_filter: Optional[str] = param(None, check=check_filter_name)
    warm_start_iterations: int = param(0, ge=0)

    def in_warm_start(self, index: int) -> bool:
        """Whether iteration ``index`` (0-based) collects on ``warm_start_filter``'s beliefs.

        Examples:
            >>> p = BeliefTrainerParams(warm_start_filter="sir_rough", warm_start_iterations=2)
            >>> [p.in_warm_start(i) for i in range(3)]
            [True, True, False]
        """
        return bool(self.warm_start_filter) and index < self.warm_start_iterations

    def filter_at(self, index: int, run_filter: str) -> str:
        """The filter (a ``configs/filter/`` name) whose beliefs iteration ``index`` collects on: the
        warm-start filter during the warm start, ``run_filter`` (the run's ``filter.name``) after it."""
        return str(self.warm_start_filter) if self.in_warm_start(index) else str(run_filter)


@dataclass(frozen=True)
class ReinforceParams(BeliefTrainerParams):
    """REINFORCE (:class:`escort_rl.trainers.reinforce.Reinforce`).

    Attributes:
        baseline: ``time`` (the mean return-to-go per time step) or ``learned`` (a DeepSets critic);
            checked before training only, so that a config naming another baseline still composes.
        minibatch_size: samples per backward pass (gradients are accumulated over a batch).
    """

    lr: float = param(3e-3, gt=0, lt=MAX_LR)
    max_grad_norm: float = param(1.0, gt=0)
    reward_scale: float = param(0.01, gt=0)
    baseline: str = param("time", choices=["time", "learned"], stage="train")
    minibatch_size: int = param(4000, ge=1)


@dataclass(frozen=True)
class PPOParams(BeliefTrainerParams):
    """PPO (:class:`escort_rl.trainers.ppo.PPO`): TorchRL's ``ClipPPOLoss`` with GAE, minibatch
    epochs from a replay buffer. An iteration runs ``env.max_steps`` steps in every env (episodes
    reset on their own inside it), as ``env.max_steps / rollout_steps`` PPO updates on batches of
    ``num_envs × rollout_steps`` frames. The defaults are the default job's: 4 iterations on SIR
    beliefs (the warm start), then 4 on the run's filter (256,000 frames, half on each).

    Attributes:
        rollout_steps: steps per env in one PPO batch (64 × 125 = 8000 frames).
        gae_lambda: GAE's λ.
        clip_epsilon: PPO's clip ε.
        epochs: passes over each batch on the run's filter (ESCORT: collection is dear).
        warm_start_epochs: the passes during the warm start; ``None`` (the default): ``epochs``. Over
            5 seeds of the default job, 8 passes in the warm start instead of 4 raised greedy success
            on ESCORT beliefs from 0.898 ± 0.014 to 0.926 ± 0.007 at no measured cost in minutes.
        minibatches: minibatches per batch (1000-frame minibatches: 32 Adam steps per batch).
        critic_coef: the value loss's weight.
        critic_input: ``belief``: the critic is a DeepSets network on the particles, like the policy;
            ``state``: an MLP on the simulator's true state (asymmetric actor-critic: only training
            reads it, the policy acts on beliefs).
        action_repeat: env steps per decision (:class:`escort_rl.transforms.ActionRepeat`; the belief
            is updated at every step); ``rollout_steps`` counts decisions and ``gamma`` discounts per
            decision.
        update_particles: particles per frame in the update (``None``: all): the epochs train on a
            random subset of M of each frame's N particles, with the old log-probabilities recomputed
            on it; the policy acts on all N. 25 of 100 halved a 64-env iteration on SIR beliefs and
            learned as fast per frame as all 100 did.
        max_importance_ratio: a cap ``c`` on the ratio ``π_θ(a|b) / π_old(a|b)`` that weighs the
            surrogate (``ClipPPOLoss``'s own ``max_importance_ratio``); ``None``: no cap. PPO's clip
            bounds the ratio only where the advantage is positive; where it is negative the surrogate
            grows with the ratio unbounded, and a TanhNormal that has learned bang-bang control gives
            ratios of 1e18 (an action near the box's edge drawn from a wide policy, later narrowed).
            The cap bounds that term at ``c·A``, as dual-clip PPO does (Ye et al. 2020, ``c = 3``).
        lr_schedule: ``constant``: Adam's rate is ``lr`` throughout; ``linear``: it falls linearly
            from ``lr`` at the first update to ``lr / updates`` at the last, over all ``iterations``
            (PPO's annealing, as in Stable-Baselines3 and CleanRL). It is a function of the update's
            index, so a resumed run continues on the same schedule.
        teacher: the policy PPO kickstarts from (Schmitt et al. 2018): ``scripted``: the env's scripted
            controller on the same belief (at ``env.teacher_gain``, else ``env.scripted_gain``; an error
            where the env has none); ``state``: the same controller on the simulator's true state
            (``true_state``; a privileged teacher: only training reads it, as the state critic does, and the
            policy learns what the full-information rule would do from the belief alone);
            ``auto``: that controller where the env group marks it a teacher (``env.scripted_teacher``),
            else none; ``none``: no teacher. Each Adam step then also minimises
            ``λ_i · E[−log π_θ(a_teacher | b)]``, the policy's cross-entropy to the teacher's action.
        kickstart_coef: the teacher term's first weight ``λ₀``.
        kickstart_iterations: ``λ_i = λ₀ · (1 − i / K)`` at iteration ``i`` (0-based), 0 from ``K`` on;
            ``None``: ``K`` is the run's ``iterations``. The learner starts from the hand rule's actions
            and PPO's own objective takes over as the weight falls. On Light-Dark 10D the default job's
            training episodes reached the goal 88% of the time in its first iteration (the job without a
            teacher: 0.95 first at iterations 9 to 14 of 5 seeds).
    """

    iterations: int = param(8, ge=1)
    num_envs: int = param(64, ge=1)
    entropy_coef: float = param(0.001, ge=0)  # 0.01 kept the policy near 1.9 nats; both learn alike
    exploring_starts: bool = param(True)
    warm_start_filter: Optional[str] = param("sir_rough", check=check_filter_name)
    warm_start_iterations: int = param(4, ge=0)
    rollout_steps: int = param(125, ge=1)
    gae_lambda: float = param(0.95, ge=0, le=1)
    clip_epsilon: float = param(0.2, gt=0)
    epochs: int = param(8, ge=1)
    warm_start_epochs: Optional[int] = param(None, ge=1)
    minibatches: int = param(8, ge=1)
    critic_coef: float = param(0.5, ge=0)
    critic_input: str = param("state", choices=["belief", "state"])
    action_repeat: int = param(1, ge=1)
    update_particles: Optional[int] = param(25, ge=1)
    max_importance_ratio: Optional[float] = param(None, gt=1)
    lr_schedule: str = param("constant", choices=["constant", "linear"])
    teacher: str = param("auto", choices=["auto", "scripted", "state", "none"])
    kickstart_coef: float = param(1.0, ge=0)
    kickstart_iterations: Optional[int] = param(None, ge=1)

    @property
    def kickstart_span(self) -> int:
        """``K``: the iterations over which the teacher's weight falls to 0 (``kickstart_iterations``, else all)."""
        return int(self.kickstart_iterations or self.iterations)

    def kickstart_weight(self, index: int) -> float:
        """The teacher term's weight at iteration ``index`` (0-based), where the run has a teacher.

        Examples:
            >>> p = PPOParams(kickstart_coef=1.0, kickstart_iterations=4)
            >>> [p.kickstart_weight(i) for i in range(5)]
            [1.0, 0.75, 0.5, 0.25, 0.0]
            >>> PPOParams(iterations=2).kickstart_weight(1)
            0.5
        """
        return float(self.kickstart_coef) * max(0.0, 1.0 - index / self.kickstart_span)

    def lr_at(self, update: int, updates: int) -> float:
        """Adam's rate at update ``update`` (0-based) of ``updates`` in the whole run.

        Examples:
            >>> p = PPOParams(lr=1e-3, lr_schedule="linear")
            >>> [round(p.lr_at(u, 4), 6) for u in range(4)]
            [0.001, 0.00075, 0.0005, 0.00025]
            >>> PPOParams(lr=1e-3).lr_at(3, 4)
            0.001
        """
        if self.lr_schedule == "constant":
            return float(self.lr)
        return float(self.lr) * (1.0 - min(max(update, 0), updates - 1) / max(updates, 1))


@dataclass(frozen=True)
class RecurrentPPOParams(PPOParams):
    """Recurrent PPO (:class:`escort_rl.trainers.recurrent_ppo.RecurrentPPO`): a GRU on the raw
    observations, no belief.

    Attributes:
        hidden: width of the observation encoder, the GRU's hidden state and the heads.
    """

    iterations: int = param(60, ge=1)
    entropy_coef: float = param(0.01, ge=0)
    exploring_starts: bool = param(False)
    warm_start_filter: Optional[str] = param(None, check=check_filter_name)
    warm_start_iterations: int = param(0, ge=0)
    epochs: int = param(3, ge=1)
    warm_start_epochs: Optional[int] = param(None, ge=1)
    minibatches: int = param(4, ge=1)  # groups of num_envs / minibatches whole rows
    critic_input: str = param("belief", choices=["belief", "state"])
    update_particles: Optional[int] = param(None, ge=1)
    teacher: str = param("none", choices=["auto", "scripted", "state", "none"])
    hidden: int = param(64, ge=1)


@dataclass(frozen=True)
class DVRLA2CParams(TrainerParams):
    """DVRL by A2C (:class:`escort_rl.trainers.dvrl_a2c.DVRLA2C`); the module's sizes are the
    ``dvrl`` group's. Values marked (original) are DVRL's.

    Attributes:
        lr: Adam's rate (ours; the original used RMSprop at 2e-4 with 16 Atari envs).
        readout_lr: the state readout's Adam (ours: a probe for the position error).
    """

    lr: float = param(5e-4, gt=0, lt=MAX_LR)
    readout_lr: float = param(1e-3, gt=0, lt=MAX_LR)
