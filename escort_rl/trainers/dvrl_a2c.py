"""DVRL trained as in Igl et al. (2018): A2C on its own belief, plus the ELBO, with truncated BPTT.

Read top to bottom: build the env (the POMDP env with ``InitTracker`` and DVRL's state primer, and no
belief transform: DVRL's belief is its own particles), the DVRL policy and the state readout; resume
if asked; then for each iteration reset ``num_envs`` envs (seeded per iteration) and run
``env.max_steps`` steps in windows of ``dvrl.loss.bptt_steps``. Each window:

1. steps the policy with gradients (the belief update, the action, the value and the ELBO term
   of every step are one graph), auto-resetting finished envs (``step_and_maybe_reset``);
2. bootstraps the window's returns with the value of the next belief (no gradient),
   ``R_t = c_r r_t + γ (1 − done_t) R_{t+1}``, with ``c_r`` = ``dvrl.loss.reward_scale`` (the value head
   fits ``c_r``-scaled returns: of order one instead of hundreds, which it could not reach from zero in
   a few hundred Adam steps);
3. takes one Adam step on

       L = −mean(log π(a_t) Â_t) + c_v · mean(Huber(V_t, R_t)) − c_H · mean(H[π_t])
           − c_enc · mean(ELBO_t),

   with ``Â = (R − V)`` standardised over the window, ``c_enc`` = ``dvrl.loss.encoding_loss_coef``;
4. fits the state readout to the true states on the detached summaries (a separate optimiser);
5. cuts the graph (the particles are detached) and goes on.

Collectors run their policy without gradients, and the belief must be differentiated along the very
particles that chose the actions (a replay would draw new ones), so this trainer steps the env itself,
as the original did. An iteration is ``num_envs × max_steps`` frames, like an iteration of the
REINFORCE trainer, so the same budget keys give the same frames. The value loss is a Huber loss (not
the original's squared error) because our domains' returns are in the hundreds, not clipped rewards.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import Compose, InitTracker, TransformedEnv

from escort_rl.config import ConfigError
from escort_rl.modules import DVRL, DVRLPolicy
from escort_rl.modules.dvrl_networks import StateReadout
from escort_rl.trainers.algorithm import Algorithm
from escort_rl.trainers.builders import build_model, build_pomdp_env, input_scaling
from escort_rl.trainers.checkpointing import load_checkpoint
from escort_rl.trainers.params import DVRLA2CParams
from escort_rl.trainers.resume import run_config
from escort_rl.trainers.scaffold import episode_stats
from escort_rl.trainers.validation import validate_train_config

EPISODE_KEYS = (("next", "reward"), ("next", "done"), ("next", "terminated"), ("next", "true_state"))


# ------------------------------------------------------------------------------------ building
def build_dvrl_policy(cfg: DictConfig, model) -> DVRLPolicy:
    """The :class:`DVRLPolicy` of ``cfg.dvrl`` (``configs/dvrl/<domain>.yaml``) for ``model``, with a
    :class:`StateReadout` to ``model.state_dim`` standardised by ``cfg.actor``'s input scaling."""
    dvrl = DVRL.from_config(OmegaConf.to_container(cfg.dvrl, resolve=True), model.obs_dim,
                            getattr(model, "n_actions", None))
    loc, scale = input_scaling(cfg, model.state_dim)
    readout = StateReadout(dvrl.summary_dim, model.state_dim, hidden=int(cfg.actor.hidden), loc=loc, scale=scale)
    return DVRLPolicy(dvrl, readout=readout).to(cfg.device)


def make_dvrl_env(cfg: DictConfig, num_envs: int, seed: int | None = None) -> TransformedEnv:
    """``POMDPEnv`` with ``InitTracker`` and the DVRL state primer (module level, picklable by
    ``functools.partial``, like :func:`escort_rl.trainers.builders.make_env`)."""
    model = build_model(cfg.env, cfg.device)
    base = build_pomdp_env(cfg, num_envs, seed, model)
    primer = build_dvrl_policy(cfg, model).make_tensordict_primer()
    return TransformedEnv(base, Compose(InitTracker(), primer))


def validate_dvrl_config(cfg: DictConfig) -> None:
    validate_train_config(cfg)  # types and ranges, from the schema (dvrl.loss.* included)
    if int(cfg.collector.workers) != 1:
        raise ConfigError(f"collector.workers: trainer=dvrl_a2c steps its envs in this process (it needs the "
                          f"gradients of the acting particles), got {cfg.collector.workers}; set collector.workers=1")
    if cfg.dvrl.name != cfg.env.name:
        raise ConfigError(f"dvrl: the config '{cfg.dvrl.name}' is for another env than '{cfg.env.name}'; "
                          f"pass dvrl={cfg.env.name}")


# ------------------------------------------------------------------------------------ the loss
def window_returns(reward: torch.Tensor, done: torch.Tensor, bootstrap: torch.Tensor, gamma: float) -> torch.Tensor:
    """n-step returns of a window: ``R_t = r_t + γ (1 − done_t) R_{t+1}``, ``R_T = bootstrap``.

    ``reward``, ``done``: ``[B, T]``; ``bootstrap``: ``[B]`` (the value after the window) -> ``[B, T]``.
    """
    out = torch.empty_like(reward)
    running = bootstrap
    for t in range(reward.shape[1] - 1, -1, -1):
        running = reward[:, t] + gamma * (~done[:, t]).to(reward.dtype) * running
        out[:, t] = running
    return out


def a2c_loss(window: TensorDictBase, bootstrap: torch.Tensor, gamma: float, entropy_coef: float,
             value_loss_coef: float, encoding_loss_coef: float, reward_scale: float = 1.0,
             elbo_key: str | None = "dvrl_elbo", normalize_advantage: bool = True) -> tuple[torch.Tensor, dict]:
    """The DVRL objective of one window ``[B, T]`` (see the module docstring).

    ``window`` holds ``logits [B, T, A]``, ``action [B, T]``, ``state_value [B, T, 1]``, ``elbo_key``
    ``[B, T]`` (with gradients) and ``("next", "reward" | "done") [B, T, 1]``; ``bootstrap [B]`` and the
    values are in units of ``reward_scale × reward``. ``elbo_key=None`` (an agent without a model, e.g.
    a GRU) drops the ELBO term: plain A2C. ``normalize_advantage``: the window's advantages standardised
    (ours; A2C and DVRL use them as they are). Returns the loss and its terms as floats.
    """
    reward = reward_scale * window["next", "reward"].squeeze(-1)
    done = window["next", "done"].squeeze(-1)
    value = window["state_value"].squeeze(-1)
    returns = window_returns(reward, done, bootstrap, gamma)
    advantage = (returns - value).detach()
    if normalize_advantage and advantage.numel() > 1:
        advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
    dist = torch.distributions.Categorical(logits=window["logits"])
    policy_loss = -(dist.log_prob(window["action"]) * advantage).mean()
    value_loss = torch.nn.functional.smooth_l1_loss(value, returns)
    entropy = dist.entropy().mean()
    elbo = window[elbo_key].mean() if elbo_key is not None else torch.zeros((), device=value.device)
    loss = policy_loss + value_loss_coef * value_loss - entropy_coef * entropy - encoding_loss_coef * elbo
    terms = {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy, "elbo": elbo}
    return loss, {k: float(v.detach()) for k, v in terms.items()}


# ------------------------------------------------------------------------------------ training
class DVRLA2C(Algorithm):
    """DVRL's A2C plus the ELBO with truncated BPTT, as an algorithm of the training scaffold
    (:func:`escort_rl.trainers.scaffold.run_training`; see the module docstring for one iteration).
    It steps its envs itself (no collector). Components: ``actor`` (the DVRL policy with its
    readout), ``optimizer`` and ``readout_optimizer``."""

    Params = DVRLA2CParams
    belief_label = "dvrl (learned belief)"
    watch = ("episode_return", "elbo")

    @classmethod
    def reads_true_state(cls, params) -> bool:
        """DVRL's readout (a probe of its belief) learns the true position."""
        return True

    @classmethod
    def trained_policy(cls, cfg: DictConfig, checkpoint):
        """The DVRL policy (its own belief) in the env with its state primer; the belief mean is its
        readout's estimate."""
        _, policy = load_dvrl_policy(checkpoint)
        return policy, make_dvrl_env, lambda rollout: next_state_estimates(policy, rollout)

    def __init__(self, cfg: DictConfig, model) -> None:
        validate_dvrl_config(cfg)
        super().__init__(cfg, model)
        t = cfg.trainer
        self.policy = build_dvrl_policy(cfg, model)
        self.optimizer = torch.optim.Adam(self.policy.dvrl.parameters(), lr=float(t.lr))
        self.readout_optimizer = torch.optim.Adam(self.policy.readout.parameters(), lr=float(t.readout_lr))
        # built here, not at the first iteration: building it draws from the global generator (the
        # primer's module), which must not shift the seeded iterations of a resumed run
        self.env = make_dvrl_env(cfg, int(t.num_envs), seed=int(cfg.seed))

    @property
    def components(self) -> dict:
        return {"actor": self.policy, "optimizer": self.optimizer, "readout_optimizer": self.readout_optimizer}

    def iteration(self, index: int, seed: int) -> dict:
        t, loss_cfg = self.cfg.trainer, self.cfg.dvrl.loss
        policy, env = self.policy, self.env
        horizon, bptt = int(self.cfg.env.max_steps), int(loss_cfg.bptt_steps)
        env.set_seed(seed)
        t0 = time.perf_counter()
        td = env.reset()
        sums = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "elbo": 0.0, "readout_loss": 0.0,
                "grad_norm": 0.0}
        episode_steps, windows = [], 0
        for start in range(0, horizon, bptt):
            steps = []
            for _ in range(min(bptt, horizon - start)):
                td = policy(td)
                td, td_root = env.step_and_maybe_reset(td)
                steps.append(td)
                td = td_root
            window = torch.stack(steps, dim=1)  # [B, T]
            with torch.no_grad():
                bootstrap = policy(td.clone())["state_value"].squeeze(-1)
            loss, terms = a2c_loss(window, bootstrap, float(t.gamma), float(t.entropy_coef),
                                   float(loss_cfg.value_loss_coef), float(loss_cfg.encoding_loss_coef),
                                   float(loss_cfg.reward_scale))
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            grad_norm = torch.nn.utils.clip_grad_norm_(policy.dvrl.parameters(), float(t.max_grad_norm))
            self.optimizer.step()

            readout_loss = policy.readout.loss(window["dvrl_summary"].detach(), window["true_state"])
            self.readout_optimizer.zero_grad(set_to_none=True)
            readout_loss.backward()
            self.readout_optimizer.step()

            for key, value in terms.items():
                sums[key] += value
            sums["readout_loss"] += float(readout_loss.detach())
            sums["grad_norm"] += float(grad_norm)
            windows += 1
            episode_steps.append(window.select(*EPISODE_KEYS).detach())
            td = td.detach()  # truncate backpropagation through time
        batch = torch.cat(episode_steps, dim=1)
        seconds = time.perf_counter() - t0
        record = {"frames": batch.numel(), **episode_stats(batch, self.model),
                  **{k: v / windows for k, v in sums.items()}, "fps": batch.numel() / max(seconds, 1e-9)}
        if not all(math.isfinite(record[k]) for k in ("policy_loss", "value_loss", "elbo")):
            raise FloatingPointError(f"DVRL training: a non-finite loss ({record}); "
                                     "lower trainer.lr or dvrl.loss.encoding_loss_coef")
        return record

    def close(self) -> None:
        if self.env is not None:
            self.env.close()


# ------------------------------------------------------------------------------------ evaluation
def load_dvrl_policy(checkpoint: str | Path) -> tuple[DictConfig, DVRLPolicy]:
    """The config and the trained :class:`DVRLPolicy` (with its readout) of a DVRL checkpoint."""
    from escort_rl.trainers.checkpointing import resolve_checkpoint

    path = resolve_checkpoint(checkpoint)
    cfg = run_config(load_checkpoint(path))
    policy = build_dvrl_policy(cfg, build_model(cfg.env, cfg.device))
    load_checkpoint(path, actor=policy)
    policy.eval()
    return cfg, policy


@torch.no_grad()
def next_state_estimates(policy: DVRLPolicy, rollout: TensorDict, chunk: int = 4096) -> torch.Tensor:
    """The readout's estimate of the state after each step of ``rollout`` ``[E, T]``: one belief
    update with ``("next", "observation")`` from the carried particles ``("next", "dvrl_*")``, the
    same update the policy makes at the next step. Returns ``[E, T, state_dim]``, comparable with
    ``("next", "true_state")`` like a filter's ``("next", "particles")``."""
    nxt = rollout["next"]
    e, t = rollout.batch_size
    flat = nxt.reshape(-1)
    out = []
    for start in range(0, flat.shape[0], chunk):
        part = flat[start:start + chunk].clone()
        part.set("is_init", torch.zeros(part.shape[0], 1, dtype=torch.bool))
        out.append(policy(part)["state_estimate"])
    return torch.cat(out).reshape(e, t, -1)
