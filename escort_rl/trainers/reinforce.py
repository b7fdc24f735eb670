"""REINFORCE with an entropy bonus on particle beliefs: TorchRL's ``ReinforceLoss`` with the
Monte-Carlo (``TD1``) value estimator, on a TorchRL collector.

Read top to bottom: :class:`Reinforce` builds a DeepSets actor and the baseline, a ``ValueOperator``:

- ``trainer.baseline=learned``: a DeepSets critic on the particles, trained by the loss's value term;
- ``trainer.baseline=time``: :class:`TimeBaseline`, one value per time step read from the env's
  ``step_count``, fitted in closed form to each batch's returns (the per-time mean return-to-go).

One iteration (:meth:`Reinforce.iteration`) collects ``num_envs`` full episodes, computes the
returns-to-go ``G_t`` (bootstrapped by the baseline where the time limit cuts an episode) and the
advantage ``G_t − b(s_t)``, standardises it over the batch, and takes one Adam step on
``loss_actor (+ loss_value) − entropy_coef · H[π]``, accumulating gradients over chunks of
``minibatch_size`` samples.
"""

from __future__ import annotations

import time

import torch
from omegaconf import DictConfig
from torch import Tensor, nn
from torchrl.modules import ValueOperator
from torchrl.objectives import ReinforceLoss, ValueEstimators

from escort_rl.config import ConfigError
from escort_rl.models.protocol import is_continuous
from escort_rl.modules import make_deepsets_policy
from escort_rl.trainers.builders import belief_keys, build_actor, build_critic, env_factory
from escort_rl.trainers.params import ReinforceParams
from escort_rl.trainers.scaffold import CollectorAlgorithm, episode_stats, make_collector


def standardised(x: Tensor) -> Tensor:
    """``(x − mean) / (std + 1e-8)`` over every element of ``x`` (same shape): how REINFORCE scales each
    batch's advantages.

    Example:
        >>> [round(v, 4) for v in standardised(torch.tensor([1.0, 3.0])).tolist()]
        [-0.7071, 0.7071]
    """
    return (x - x.mean()) / (x.std() + 1e-8)


class TimeBaseline(nn.Module):
    """A per-time baseline ``b(t)``: a table over the step count ``t ∈ [0, max_steps]``.

    ``forward(step_count [*B, 1]) -> [*B, 1]``. :meth:`fit_` sets each entry to the mean of the
    targets observed at that step (the least-squares fit), leaving unseen steps unchanged.

    Example:
        >>> b = TimeBaseline(3)
        >>> b.fit_(torch.tensor([[0], [0], [2]]), torch.tensor([[1.0], [3.0], [5.0]]))
        >>> b(torch.tensor([[0], [1], [2]])).squeeze(-1)
        tensor([2., 0., 5.])
    """

    def __init__(self, max_steps: int) -> None:
        super().__init__()
        self.register_buffer("table", torch.zeros(int(max_steps) + 1))

    def forward(self, step_count: Tensor) -> Tensor:
        index = step_count.long().clamp(0, self.table.numel() - 1)
        return self.table[index.squeeze(-1)].unsqueeze(-1)

    @torch.no_grad()
    def fit_(self, step_count: Tensor, target: Tensor) -> None:
        index = step_count.long().clamp(0, self.table.numel() - 1).flatten()
        sums = torch.zeros_like(self.table).index_add_(0, index, target.flatten().to(self.table.dtype))
        counts = torch.zeros_like(self.table).index_add_(0, index, torch.ones_like(sums[index]))
        self.table.copy_(torch.where(counts > 0, sums / counts.clamp_min(1), self.table))


class Reinforce(CollectorAlgorithm):
    """REINFORCE + entropy on ``ReinforceLoss`` (see the module docstring). Components: ``actor``,
    ``critic`` (the learned or the time baseline) and ``optimizer``."""

    Params = ReinforceParams

    def __init__(self, cfg: DictConfig, model) -> None:
        super().__init__(cfg, model, lambda c: make_collector(
            c, lambda n, s: env_factory(c, n, seed=s), self.policy, frames, reset_at_each_iter=True))
        t = self.params
        frames = t.num_envs * int(cfg.env.max_steps)  # num_envs full episodes
        if is_continuous(model):
            raise ConfigError("trainer: trainer=reinforce takes discrete actions and this env's are continuous; use "
                              "trainer=ppo (a Gaussian policy)")
        particles_key, log_weights_key = belief_keys(cfg)
        self.actor = build_actor(cfg, model.state_dim, model.n_actions, model)
        self.policy = make_deepsets_policy(self.actor, particles_key=particles_key, log_weights_key=log_weights_key)
        if t.baseline == "learned":
            self.critic, critic_keys = build_critic(cfg, model, "belief")
            value = ValueOperator(self.critic, in_keys=critic_keys)
        else:
            self.critic = TimeBaseline(int(cfg.env.max_steps))
            value = ValueOperator(self.critic, in_keys=["step_count"])
        self.loss = ReinforceLoss(self.policy, value, loss_critic_type="l2")
        self.loss.set_keys(sample_log_prob="action_log_prob")
        self.loss.make_value_estimator(ValueEstimators.TD1, gamma=t.gamma)
        self.trainable = list(self.actor.parameters()) + list(self.critic.parameters())
        self.optimizer = torch.optim.Adam(self.trainable, lr=t.lr)

    @property
    def components(self) -> dict:
        return {"actor": self.actor, "critic": self.critic, "optimizer": self.optimizer}

    def update(self, batch) -> dict:
        """One policy-gradient step on ``batch`` ``[E, T]`` of full episodes; returns scalar stats."""
        t = self.params
        keys = self.loss.tensor_keys
        with torch.no_grad():
            if isinstance(self.critic, TimeBaseline):  # fit b(t) to this batch's returns, then G − b(t)
                self.loss.value_estimator(batch)
                self.critic.fit_(batch["step_count"], batch[keys.value_target])
            self.loss.value_estimator(batch)
            batch[keys.advantage] = standardised(batch[keys.advantage])
        flat = batch.reshape(-1)
        m = flat.shape[0]
        self.optimizer.zero_grad(set_to_none=True)
        sums = {"loss_actor": 0.0, "loss_value": 0.0, "entropy": 0.0}
        for start in range(0, m, t.minibatch_size):
            mb = flat[start:start + t.minibatch_size]
            out = self.loss(mb)
            entropy = self.policy.get_dist(mb).entropy().mean()
            total = out["loss_actor"] - t.entropy_coef * entropy
            if t.baseline == "learned":
                total = total + out["loss_value"]
            (total * mb.shape[0] / m).backward()
            for key, value in (("loss_actor", out["loss_actor"]), ("loss_value", out["loss_value"]),
                               ("entropy", entropy)):
                sums[key] += float(value.detach()) * mb.shape[0] / m
        grad_norm = torch.nn.utils.clip_grad_norm_(self.trainable, t.max_grad_norm)
        self.optimizer.step()
        return {**sums, "grad_norm": float(grad_norm)}

    def iteration(self, index: int, seed: int) -> dict:
        collector = self.collectors.for_iteration(index)
        collector.set_seed(seed)
        t0 = time.perf_counter()
        batch = self.collectors.next()
        collect_s = time.perf_counter() - t0
        batch = batch.reshape(-1, batch.shape[-1])  # [E, T]
        episodes = episode_stats(batch, self.model)
        batch["next", "reward"] = batch["next", "reward"] * self.params.reward_scale
        stats = self.update(batch)
        if int(self.cfg.collector.workers) > 1:
            self.collectors.update_policy_weights()
        return {"frames": batch.numel(), **episodes, **stats, "fps": batch.numel() / max(collect_s, 1e-9)}
