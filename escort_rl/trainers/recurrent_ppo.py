"""Recurrent PPO on raw observations: a GRU actor-critic (:mod:`escort_rl.modules.recurrent`) with
TorchRL's ``ClipPPOLoss`` and ``GAE`` in recurrent mode, on a TorchRL collector. The model-free
baseline to a belief: the GRU's hidden state is the agent's memory, and no filter runs.

Read top to bottom: :func:`make_recurrent_env` builds the env (``POMDPEnv`` with ``InitTracker`` and
the GRU's primer; no belief transform), :class:`RecurrentPPO` the actor-critic, the loss and the
optimiser. One iteration (:meth:`RecurrentPPO.iteration`) reseeds and resets the envs (the hidden
states go back to zero), then runs ``ceil(env.max_steps / rollout_steps)`` PPO updates, each on a
fresh batch ``[E, T]`` of ``num_envs × rollout_steps`` frames, in time order:

1. scale the rewards by ``reward_scale``;
2. compute GAE advantages and value targets (no gradient) with the value network in recurrent mode
   over the whole batch: each row runs the GRU along time from the hidden state the collector
   stored at its first step, restarting from zero where an episode starts (``is_init``);
3. ``epochs`` passes, each over the E rows split into ``minibatches`` random groups of whole rows
   (time is never shuffled: the GRU needs the sequence), one Adam step per group on
   ``loss_objective + loss_critic + loss_entropy`` in recurrent mode, gradient norm clipped.

The hidden state the collector carries from one batch to the next is the one the policy had when it
acted; the loss restarts each row from it (truncated backpropagation through time at the batch
boundary). Episodes run on across the batches of an iteration; the reset at each iteration start
makes every iteration reproducible from its seed alone, so resume is exact.
"""

from __future__ import annotations

from functools import partial

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from escort_rl.config import ConfigError
from escort_rl.modules import policy_outputs
from escort_rl.modules.recurrent import make_recurrent_actor_critic, make_recurrent_primer
from escort_rl.trainers.algorithm import trainer_params
from escort_rl.trainers.builders import build_model, build_pomdp_env, continuous_head, input_scaling
from escort_rl.trainers.params import RecurrentPPOParams
from escort_rl.trainers.ppo import PPOBase, clip_ppo_loss


# ------------------------------------------------------------------------------------ building
def observation_scaling(cfg: DictConfig, model) -> tuple[list[float], list[float]]:
    """The standardisation ``(o − loc) / scale`` of the observation, from the env group's per-state
    ``input_loc`` / ``input_scale`` (:func:`escort_rl.trainers.builders.input_scaling`):

    - a model whose observation is its position (``len(model.position_dims) == obs_dim``, e.g.
      Light-Dark 10D: a noisy 5-D position) takes the entries of ``position_dims``;
    - a model without ``position_dims`` whose observation is no longer than its state takes the first
      ``obs_dim`` entries;
    - any other observation (Kidnapped Robot's landmark readings, Multi-Target Tracking's agent
      position and detections) is not a slice of the state: it is left as is (loc 0, scale 1).

    Returns two lists of ``obs_dim`` floats."""
    d, m = int(model.state_dim), int(model.obs_dim)
    loc, scale = input_scaling(cfg, d)
    loc = [float(loc)] * d if not isinstance(loc, (list, tuple)) else [float(x) for x in loc]
    scale = [float(scale)] * d if not isinstance(scale, (list, tuple)) else [float(x) for x in scale]
    dims = getattr(model, "position_dims", None)
    if dims is not None and len(dims) == m:
        idx = [int(i) for i in dims]
    elif dims is None and m <= d:
        idx = list(range(m))
    else:
        return [0.0] * m, [1.0] * m
    return [loc[i] for i in idx], [scale[i] for i in idx]


def recurrent_hidden(cfg: DictConfig) -> int:
    """``trainer.hidden``: the width of the GRU and of its encoder and heads."""
    return recurrent_params(cfg).hidden


def recurrent_params(cfg: DictConfig) -> RecurrentPPOParams:
    """``cfg.trainer`` as :class:`~escort_rl.trainers.params.RecurrentPPOParams` (checked; a key the config
    lacks takes its default)."""
    return trainer_params(RecurrentPPOParams, cfg.trainer)


def build_recurrent_actor_critic(cfg: DictConfig, model):
    """``(policy, value, primer)`` of :func:`escort_rl.modules.recurrent.make_recurrent_actor_critic`
    for ``model`` with ``trainer.hidden`` and :func:`observation_scaling`."""
    loc, scale = observation_scaling(cfg, model)
    n_outputs, box = policy_outputs(model)
    policy, value, primer = make_recurrent_actor_critic(model.obs_dim, n_outputs, hidden=recurrent_hidden(cfg),
                                                        obs_loc=loc, obs_scale=scale, action_box=box,
                                                        **continuous_head(cfg))
    return policy.to(cfg.device), value.to(cfg.device), primer


def make_recurrent_env(cfg: DictConfig, num_envs: int, seed: int | None = None) -> TransformedEnv:
    """``TransformedEnv(POMDPEnv(model, (num_envs,)), Compose(InitTracker(), primer))``: the raw
    observations, ``is_init`` and the GRU's hidden state ``recurrent_state`` ``[num_envs, 1, H]``
    (zeros at every reset of an env, partial resets included). No belief transform. Building it
    draws nothing from torch's generator.

    Module-level, so ``functools.partial(make_recurrent_env, cfg, n, seed)`` is picklable (spawned
    collector and ``ParallelEnv`` workers build it), like :func:`escort_rl.trainers.builders.make_env`."""
    model = build_model(cfg.env, cfg.device)
    base = build_pomdp_env(cfg, num_envs, seed, model)
    return TransformedEnv(base, Compose(InitTracker(), make_recurrent_primer(recurrent_hidden(cfg))))


def recurrent_env_factory(cfg: DictConfig, num_envs: int, seed: int | None = None):
    """A picklable zero-argument factory for :func:`make_recurrent_env` (the config made plain)."""
    plain = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    return partial(make_recurrent_env, plain, num_envs, seed)


def make_recurrent_ppo_loss(policy, value, cfg: DictConfig) -> ClipPPOLoss:
    """``ClipPPOLoss`` over the recurrent policy and value network, with GAE as its value estimator
    (``ClipPPOLoss`` finds the parameters the two share and counts them once). Call the loss and its
    value estimator under ``set_recurrent_mode(True)`` on batches ``[E, T]``."""
    p = recurrent_params(cfg)
    loss = clip_ppo_loss(policy, value, p)
    loss.make_value_estimator(ValueEstimators.GAE, gamma=p.gamma, lmbda=p.gae_lambda, deactivate_vmap=True)
    return loss


def validate_recurrent_ppo_config(cfg: DictConfig) -> None:
    t = recurrent_params(cfg)
    if t.warm_start_filter or t.warm_start_iterations > 0:
        raise ConfigError("trainer.warm_start_filter: trainer=recurrent_ppo runs on raw observations (no belief "
                          f"filter to warm start), got {t.warm_start_filter}; set it to null and "
                          "trainer.warm_start_iterations=0")
    if t.action_repeat != 1:
        raise ConfigError("trainer.action_repeat: trainer=recurrent_ppo decides at every step (its GRU reads every "
                          f"observation), got {t.action_repeat}; set it to 1")
    if t.update_particles is not None:
        raise ConfigError("trainer.update_particles: trainer=recurrent_ppo reads raw observations, no particles, "
                          f"got {t.update_particles}; set it to null")
    if t.teacher != "none":
        raise ConfigError("trainer.teacher: trainer=recurrent_ppo has no belief for a scripted teacher to act on, "
                          f"got {t.teacher}; set it to none")
    per_worker = int(t.num_envs) // int(cfg.collector.workers)
    if int(t.minibatches) > int(t.num_envs):
        raise ConfigError(f"trainer.minibatches: minibatches are whole env rows, so at most trainer.num_envs "
                          f"({t.num_envs}), got {t.minibatches}")
    if per_worker < 1:
        raise ConfigError(f"collector.workers: at most trainer.num_envs ({t.num_envs}), got {cfg.collector.workers}")


# ------------------------------------------------------------------------------------ training
class RecurrentPPO(PPOBase):
    """Clipped PPO with GAE and a GRU actor-critic on the raw observations (see the module
    docstring): :class:`~escort_rl.trainers.ppo.PPOBase`'s update and iteration, with whole env rows
    as minibatches and the loss in recurrent mode. Components: ``actor`` (the policy), ``critic``
    (the value network; it shares the encoder and the GRU with the policy) and ``optimizer``."""

    Params = RecurrentPPOParams
    belief_label = "none (GRU on raw observations)"
    model_free = True

    @classmethod
    def trained_policy(cls, cfg: DictConfig, checkpoint):
        """The GRU policy on raw observations, in its env; no state estimate (NaN)."""
        model = build_model(cfg.env, cfg.device)
        return (load_recurrent_policy(cfg, checkpoint), make_recurrent_env,
                lambda rollout: no_state_estimate(rollout, model))

    def __init__(self, cfg: DictConfig, model) -> None:
        validate_recurrent_ppo_config(cfg)
        policy, self.value, _ = build_recurrent_actor_critic(cfg, model)
        super().__init__(cfg, model, policy, make_recurrent_ppo_loss(policy, self.value, cfg), repeat=1)

    @property
    def components(self) -> dict:
        return {"actor": self.policy, "critic": self.value, "optimizer": self.optimizer}

    def make_env_factory(self, cfg: DictConfig, num_envs: int, seed: int | None):
        """The raw-observation envs of :func:`make_recurrent_env`."""
        return recurrent_env_factory(cfg, num_envs, seed=seed)

    def prepare(self, batch: TensorDictBase) -> TensorDictBase:
        batch = batch.reshape(-1, batch.shape[-1])  # [E, T]; a MultiSyncCollector's is [K, E/K, T]
        batch.names = [None, "time"]
        return batch

    def estimate_advantages(self, batch: TensorDictBase) -> None:
        with torch.no_grad(), set_recurrent_mode(True):
            self.loss.value_estimator(batch)

    def fill(self, batch: TensorDictBase) -> TensorDictBase:
        return batch

    def minibatches(self, batch: TensorDictBase):
        """One epoch's minibatches: the E rows in ``minibatches`` random groups (time is never shuffled)."""
        return (batch[rows] for rows in torch.randperm(batch.shape[0]).tensor_split(self.params.minibatches))

    def loss_terms(self, minibatch: TensorDictBase):
        with set_recurrent_mode(True):
            return self.loss(minibatch)


# ------------------------------------------------------------------------------------ evaluation
def load_recurrent_policy(cfg: DictConfig, checkpoint):
    """The trained recurrent policy of a checkpoint (eval mode), to run in :func:`make_recurrent_env`."""
    from escort_rl.trainers.checkpointing import load_checkpoint

    policy, value, _ = build_recurrent_actor_critic(cfg, build_model(cfg.env, cfg.device))
    load_checkpoint(checkpoint, actor=policy, critic=value)
    policy.eval()
    return policy


def no_state_estimate(rollout: TensorDictBase, model) -> torch.Tensor:
    """``[E, T, state_dim]`` of NaN: a recurrent policy has no belief, so no position error."""
    return torch.full((*rollout.batch_size, model.state_dim), float("nan"))
