"""PPO on particle beliefs: TorchRL's ``ClipPPOLoss`` with ``GAE``, minibatch epochs from a
``ReplayBuffer``, on a TorchRL collector.

Read top to bottom: :class:`PPO` builds a DeepSets actor and a DeepSets critic (a ``ValueOperator``)
reading the belief transform's keys, the loss and the optimiser. One iteration
(:meth:`PPO.iteration`) reseeds and resets the envs, then runs ``env.max_steps / rollout_steps``
PPO updates, each on a fresh batch of ``num_envs × rollout_steps`` frames:

1. scale the rewards by ``reward_scale`` (the critic fits returns of order one);
2. compute GAE advantages and value targets with the critic (no gradient);
3. ``epochs`` passes over the batch in ``minibatches`` shuffled minibatches, each one Adam step on
   ``loss_objective + loss_critic + loss_entropy`` with the gradient norm clipped.

Episodes run on across the batches of an iteration (finished envs reset on their own); the reset at
each iteration start makes every iteration reproducible from its seed alone, so resume is exact.

Action repeat (``trainer.action_repeat = k``, default 1): the policy decides every ``k`` env steps
(:class:`~escort_rl.transforms.ActionRepeat`; the belief is still updated at every step). Its
frames are decisions: ``rollout_steps`` counts decisions per env, ``gamma`` discounts per decision,
and an iteration runs ``⌈env.max_steps / k⌉`` decisions per env. The ``frames`` it reports are env
steps. On Light-Dark one push moves the position by about 0.1 over some 20 steps, so with ``k = 4``
a decision's effect on the return is four times larger and the horizon in decisions four times
shorter, and each update trains on a quarter as many frames per env step.

The iteration and the update are :class:`PPOBase`'s, shared with recurrent PPO
(:class:`escort_rl.trainers.recurrent_ppo.RecurrentPPO`); a variant gives its networks, its envs
and the hooks where the two differ (how a batch is laid out, how minibatches are drawn, the mode
the loss runs in).
"""

from __future__ import annotations

import time
from abc import abstractmethod

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import SamplerWithoutReplacement
from torchrl.modules import ValueOperator
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from escort_rl.config import ConfigError
from escort_rl.models.protocol import check_action_box, is_continuous
from escort_rl.trainers.algorithm import trainer_params
from escort_rl.trainers.builders import (
    belief_keys,
    build_critic,
    build_policy,
    env_factory,
    scripted_policy,
    teacher_gain,
)
from escort_rl.trainers.params import PPOParams
from escort_rl.trainers.scaffold import CollectorAlgorithm, episode_stats, make_collector


class ClipPPOLossKeepingDist(ClipPPOLoss):
    """TorchRL's ``ClipPPOLoss`` that keeps the policy's distribution from its last forward pass
    (``last_dist``), so that another term on the same minibatch (the kickstart's cross-entropy to a teacher)
    reads it instead of running the actor a second time."""

    last_dist = None

    def _log_weight(self, tensordict, adv_shape):
        out = super()._log_weight(tensordict, adv_shape)
        self.last_dist = out[1]
        return out


def clip_ppo_loss(policy, value, params: PPOParams) -> ClipPPOLoss:
    """TorchRL's ``ClipPPOLoss`` with ``params``' clip, coefficients and importance cap
    (``max_importance_ratio``), a smooth-L1 critic loss and normalised advantages, reading the
    log-probability the policy wrote (``action_log_prob``). The caller sets its value estimator."""
    p = params
    cap = p.max_importance_ratio
    loss = ClipPPOLossKeepingDist(policy, value, clip_epsilon=p.clip_epsilon, entropy_coeff=p.entropy_coef,
                       critic_coeff=p.critic_coef, loss_critic_type="smooth_l1",
                       normalize_advantage=True, max_importance_ratio=None if cap is None else float(cap))
    loss.set_keys(sample_log_prob="action_log_prob")
    return loss


def make_ppo_loss(policy, critic, cfg: DictConfig, critic_keys: list | None = None) -> ClipPPOLoss:
    """``ClipPPOLoss`` over ``policy`` (a ``ProbabilisticActor`` on ``cfg``'s belief keys, e.g. from
    :func:`~escort_rl.trainers.builders.build_policy`) and a critic reading ``critic_keys`` (default:
    the belief keys), with GAE as its value estimator; the settings are ``cfg.trainer``'s, read as
    :class:`~escort_rl.trainers.params.PPOParams`. The loss reads the log-probability the policy
    wrote (``action_log_prob``); a TanhNormal policy's entropy is estimated by sampling (a clipped
    Gaussian's is its Gaussian's, in closed form)."""
    p = trainer_params(PPOParams, cfg.trainer)
    value = ValueOperator(critic, in_keys=critic_keys or list(belief_keys(cfg)))
    loss = clip_ppo_loss(policy, value, p)
    loss.make_value_estimator(ValueEstimators.GAE, gamma=p.gamma, lmbda=p.gae_lambda)
    return loss


TEACHER_ACTION = "teacher_action"
"""The key of the kickstart teacher's action in a training batch."""


def kickstart_teacher(cfg: DictConfig, model, params: PPOParams):
    """The policy PPO kickstarts from (``trainer.teacher``), writing :data:`TEACHER_ACTION`, or ``None``: the
    env's scripted controller on the belief (at ``env.teacher_gain``, else ``env.scripted_gain``, with the
    options of ``env.teacher_options``, else ``env.scripted_options``) for
    ``scripted``, on the simulator's true state for ``state``, and for ``auto`` where the env group sets
    ``scripted_teacher``; ``None`` for ``none`` or a zero ``kickstart_coef``."""
    if params.teacher == "none" or params.kickstart_coef == 0:
        return None
    if params.teacher == "auto" and not OmegaConf.select(cfg, "env.scripted_teacher", default=False):
        return None
    teacher = scripted_policy(cfg, model, action_key=TEACHER_ACTION, gain_v=teacher_gain(cfg),
                              on_true_state=params.teacher == "state", role="teacher")
    if teacher is None:
        raise ConfigError(f"trainer.teacher: env '{cfg.env.name}' has no scripted controller to learn from; set "
                          "trainer.teacher=none")
    return teacher


class PPOBase(CollectorAlgorithm):
    """Clipped PPO's iteration and update on a TorchRL collector, shared by :class:`PPO` and
    recurrent PPO.

    A subclass builds its networks, then calls ``super().__init__(cfg, model, policy, loss,
    repeat, teacher)`` with ``policy`` (what the collector runs; it writes ``action`` and
    ``action_log_prob``), ``teacher`` (the kickstart teacher of :func:`kickstart_teacher`, or ``None``)
    and ``loss`` (a ``ClipPPOLoss`` with GAE as its value estimator). This sets
    the optimiser (Adam over ``loss.parameters()``), the batch sizes and the collectors. The hooks:

    - :meth:`make_env_factory` ``(cfg, num_envs, seed)``: a picklable zero-argument factory of the
      ``num_envs`` training envs (required);
    - :meth:`prepare` ``(batch) -> [E, T]``: a collected batch as env rows by time;
    - :meth:`estimate_advantages` ``(batch [E, T])``: write ``advantage`` and ``value_target``;
    - :meth:`fill` ``(batch [E, T]) -> source``: what an update's epochs draw from (required);
    - :meth:`minibatches` ``(source) -> iterable of tensordicts``: one epoch's minibatches (required);
    - :meth:`loss_terms` ``(minibatch) -> tensordict``: the loss's ``loss_objective``,
      ``loss_critic``, ``loss_entropy`` (and ``entropy``, ``clip_fraction`` where it gives them).

    Attributes: ``repeat`` (env steps per decision), ``rollout_steps`` (decisions per env and batch,
    never past one episode), ``batches`` (PPO updates per iteration), ``frames_per_batch``
    (``num_envs × rollout_steps``), ``epochs`` (this iteration's, see :meth:`epochs_for`)."""

    def __init__(self, cfg: DictConfig, model, policy, loss: ClipPPOLoss, repeat: int = 1, teacher=None) -> None:
        super().__init__(cfg, model, lambda c: make_collector(
            c, lambda n, s: self.make_env_factory(c, n, s), self.policy, self.frames_per_batch,
            reset_at_each_iter=False))
        p = self.params
        self.policy, self.loss, self.repeat = policy, loss, int(repeat)
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=p.lr)
        self.epochs = p.epochs
        decisions = -(-int(cfg.env.max_steps) // self.repeat)  # per env and episode
        self.rollout_steps = min(p.rollout_steps, decisions)  # never past one episode
        self.batches = -(-decisions // self.rollout_steps)  # PPO updates per iteration
        self.frames_per_batch = p.num_envs * self.rollout_steps
        self.teacher = teacher  # the kickstart teacher (kickstart_teacher), or None
        self.kickstart = 0.0  # this iteration's teacher weight

    def epochs_for(self, index: int) -> int:
        """The epochs of iteration ``index``'s updates: ``trainer.warm_start_epochs`` during the warm
        start when set, else ``trainer.epochs``. Where collection is cheap (SIR beliefs: a batch
        costs about what its update does) fresh batches beat more passes; where it is dear (ESCORT
        beliefs: about twenty times the update) more passes over each batch pay."""
        p = self.params
        return p.warm_start_epochs if p.warm_start_epochs is not None and p.in_warm_start(index) else p.epochs

    def set_lr(self, update: int) -> None:
        """Adam's rate for update ``update`` of the run (``trainer.lr_schedule``)."""
        lr = self.params.lr_at(update, int(self.params.iterations) * self.batches)
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def plan_note(self) -> str:
        if self.teacher is None:
            return ""
        p = self.params
        span = p.kickstart_span
        on = " on the true state" if p.teacher == "state" else ""
        rule = getattr(self.teacher.controller, "rule", None)  # a controller without a gain says what it does
        what = f" ({rule})" if rule else f" at gain {self.teacher.gain_v:g}"
        note = f"; kickstarted by the scripted controller{on}{what}, weight {p.kickstart_coef:g}"
        return note + (f" falling to 0 by iteration {span + 1}" if span < p.iterations else
                       " falling linearly over the run")

    # ------------------------------------------------------------------ the hooks
    @abstractmethod
    def make_env_factory(self, cfg: DictConfig, num_envs: int, seed: int | None):
        """A picklable zero-argument factory of ``num_envs`` training envs of ``cfg``, seeded ``seed``."""

    def prepare(self, batch):
        """A collected batch as ``[E, T]``."""
        return batch.reshape(-1, batch.shape[-1])

    def estimate_advantages(self, batch) -> None:
        """Write GAE's ``advantage`` and ``value_target`` into ``batch`` (no gradient)."""
        with torch.no_grad():
            self.loss.value_estimator(batch)

    @abstractmethod
    def fill(self, batch):
        """What the epochs draw minibatches from, given the batch ``[E, T]`` with its advantages."""

    @abstractmethod
    def minibatches(self, source):
        """One epoch's minibatches drawn from ``source`` (what :meth:`fill` returned)."""

    def loss_terms(self, minibatch):
        """The loss's terms on one minibatch."""
        return self.loss(minibatch)

    def total_loss(self, minibatch, out):
        """What one Adam step minimises: PPO's loss, plus the kickstart term ``λ_i · E[−log π_θ(a_teacher | b)]``
        while ``λ_i > 0`` (logged as ``loss_kickstart``, unweighted)."""
        total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
        if self.kickstart <= 0:
            return total
        teacher_action = minibatch[TEACHER_ACTION]
        dist = getattr(self.loss, "last_dist", None)  # the distribution of the loss's own forward on this minibatch
        if dist is None or tuple(dist.batch_shape)[: minibatch.batch_dims] != tuple(minibatch.batch_size):
            dist = self.policy.get_dist(minibatch)
        if is_continuous(self.model) and not getattr(dist, "edge_has_mass", False):
            # inside the box: a TanhNormal's density at its edge is 0
            low, high = (b.to(teacher_action) for b in check_action_box(self.model))
            margin = 1e-3 * (high - low)
            teacher_action = torch.minimum(torch.maximum(teacher_action, low + margin), high - margin)
        imitation = -dist.log_prob(teacher_action).mean()
        out["loss_kickstart"] = imitation.detach()
        return total + self.kickstart * imitation

    # ------------------------------------------------------------------ the shared update
    def update(self, batch) -> dict:
        """One PPO update on ``batch`` ``[E, T]`` (rewards already scaled): GAE, then ``epochs`` passes
        of one Adam step per minibatch. Returns every scalar the loss gives (its terms, ``entropy``,
        ``clip_fraction``, ``kl_approx``, ``ESS``, ``explained_variance``) and ``grad_norm``, averaged over the
        steps taken, and
        ``skipped_steps``: the fraction of minibatches whose gradient was non-finite and was not applied
        (a TanhNormal's log-probability of an action at the edge of its box can overflow). Raises
        ``FloatingPointError`` when no step of the update was finite."""
        self.estimate_advantages(batch)
        if self.kickstart > 0:  # the teacher's action on each frame's whole belief, before any subsampling
            with torch.no_grad():
                self.teacher(batch)
        source = self.fill(batch)
        sums: dict[str, float] = {}
        steps = skipped = 0
        for _ in range(self.epochs):
            for minibatch in self.minibatches(source):
                out = self.loss_terms(minibatch)
                total = self.total_loss(minibatch, out)
                self.optimizer.zero_grad(set_to_none=True)
                total.backward()
                grad_norm = torch.nn.utils.clip_grad_norm_(self.loss.parameters(), self.params.max_grad_norm)
                if not torch.isfinite(grad_norm):
                    skipped += 1  # clipping cannot rescale an inf: applying it would turn every weight to NaN
                    continue
                self.optimizer.step()
                # every scalar the loss returns: its terms, entropy, clip_fraction, kl_approx, ESS,
                # explained_variance (of the critic), ...
                for key, value in [*out.items(), ("grad_norm", grad_norm)]:
                    if isinstance(key, str) and value.numel() == 1:
                        sums[key] = sums.get(key, 0.0) + float(value.detach())
                steps += 1
        if steps == 0:
            raise FloatingPointError(
                f"PPO update: all {skipped} gradient steps were non-finite, so training has diverged; cap the "
                "importance ratio (trainer.max_importance_ratio=3), or lower trainer.lr or trainer.epochs")
        return {**{k: v / steps for k, v in sums.items()}, "skipped_steps": skipped / (steps + skipped)}

    def iteration(self, index: int, seed: int) -> dict:
        collector = self.collectors.for_iteration(index)
        self.epochs = self.epochs_for(index)
        self.kickstart = self.params.kickstart_weight(index) if self.teacher is not None else 0.0
        collector.set_seed(seed)
        collector.reset()
        stats, seen, collect_s, frames = {}, [], 0.0, 0
        for _ in range(self.batches):
            self.set_lr(index * self.batches + len(seen))
            t0 = time.perf_counter()
            batch = self.collectors.next()
            collect_s += time.perf_counter() - t0
            batch = self.prepare(batch)  # [E, T]
            seen.append(batch.select(("next", "reward"), ("next", "done"), ("next", "terminated"),
                                     ("next", "true_state"), strict=False).clone())  # no true_state in POPGym's env
            frames += int(batch["next", "repeats"].sum()) if self.repeat > 1 else batch.numel()
            batch["next", "reward"] = batch["next", "reward"] * self.params.reward_scale
            for key, value in self.update(batch).items():
                stats[key] = stats.get(key, 0.0) + value / self.batches
            if int(self.cfg.collector.workers) > 1:
                self.collectors.update_policy_weights()
        episodes = episode_stats(torch.cat(seen, dim=1), self.model)
        teacher = {"kickstart_weight": self.kickstart} if self.teacher is not None else {}
        return {"frames": frames, **episodes, **stats, "fps": frames / max(collect_s, 1e-9),
                "lr": self.optimizer.param_groups[0]["lr"], **teacher}


class PPO(PPOBase):
    """Clipped PPO with GAE on the belief particles (see the module docstring). Components:
    ``actor`` and ``critic`` (DeepSets networks) and ``optimizer``."""

    Params = PPOParams

    def __init__(self, cfg: DictConfig, model) -> None:
        params = trainer_params(self.Params, cfg.trainer)
        self.actor, policy = build_policy(cfg, model)  # the policy is what the collector runs
        self.critic, critic_keys = build_critic(cfg, model, params.critic_input)
        loss = make_ppo_loss(policy, self.critic, cfg, critic_keys)
        super().__init__(cfg, model, policy, loss, repeat=params.action_repeat,
                         teacher=kickstart_teacher(cfg, model, params))
        self.minibatch = max(1, self.frames_per_batch // self.params.minibatches)
        self.buffer = ReplayBuffer(storage=LazyTensorStorage(self.frames_per_batch),
                                   sampler=SamplerWithoutReplacement(), batch_size=self.minibatch)

    @property
    def components(self) -> dict:
        return {"actor": self.actor, "critic": self.critic, "optimizer": self.optimizer}

    def make_env_factory(self, cfg: DictConfig, num_envs: int, seed: int | None):
        """The belief envs (:func:`escort_rl.trainers.builders.make_env`) with ``trainer.action_repeat``."""
        return env_factory(cfg, num_envs, seed=seed, action_repeat=self.repeat)

    def fill(self, batch):
        """The batch's frames (:meth:`subsample_particles`) in the replay buffer."""
        self.buffer.empty()
        self.buffer.extend(self.subsample_particles(batch).reshape(-1))
        return self.buffer

    def minibatches(self, source):
        """One epoch's minibatches: ``minibatches`` shuffled draws of frames without replacement."""
        return (source.sample() for _ in range(self.params.minibatches))

    def subsample_particles(self, batch):
        """The batch the epochs train on: with ``trainer.update_particles = M`` below the belief's
        ``N``, each frame keeps M of its particles drawn without replacement (with their log-weights;
        pooling renormalises them), and ``action_log_prob`` is recomputed on that subset, so that the
        PPO ratio compares the new and the old policy on the same input. The policy still acts on all
        N particles; the update's cost, mostly the per-particle encoder, falls by ``N / M``."""
        m = self.params.update_particles
        if m is None:
            return batch
        particles_key, log_weights_key = belief_keys(self.cfg)
        x = batch[particles_key]  # [E, T, N, d]
        if int(m) >= x.shape[-2]:
            return batch
        keep = torch.rand(x.shape[:-1], device=x.device).argsort(-1)[..., : int(m)]  # [E, T, M]
        batch = batch.clone(False)
        batch[particles_key] = x.gather(-2, keep.unsqueeze(-1).expand(*keep.shape, x.shape[-1]))
        batch[log_weights_key] = batch[log_weights_key].gather(-1, keep)
        with torch.no_grad():
            batch["action_log_prob"] = self.policy.get_dist(batch).log_prob(batch["action"])
        return batch
