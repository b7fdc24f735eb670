"""A2C on Flickering Atari for the three agents of the paper's Table 4, on the training scaffold.

Agents (``cfg.agent``): ``dvrl`` (DVRL with its convolutional encoder and decoder), ``escort_latent``
(:class:`~escort_rl.modules.ESCORTLatent`: ESCORT over DVRL's learned latent) and ``gru`` (a GRU
actor-critic on frames). The two belief agents share the VRNN sizes (``cfg.vrnn``), so they differ
only in how the belief is updated.

Read top to bottom: build the env (``num_envs`` flickering games with ``InitTracker`` and the agent's
state primer), the policy and RMSprop; then each iteration runs ``updates_per_iteration`` A2C
updates, each on a window of ``rollout_steps`` steps taken with gradients (the belief updates,
actions, values and ELBO terms of a window are one graph, cut after the update), with the loss of
:func:`escort_rl.trainers.dvrl_a2c.a2c_loss` on clipped rewards. Games are not restarted between
iterations (an Atari game lasts thousands of steps); a session's first iteration seeds and resets
them. A resumed run therefore restores the networks, the optimiser and the finished games' returns,
and starts new games: it is statistically, not bitwise, the same as an uninterrupted run.

The run config (``cfg``) holds ``seed``, ``device``, ``output_dir``, ``logger``, ``game``, ``agent``
and the sections of ``configs/bench/atari.yaml`` (``trainer`` with ``iterations`` added, ``vrnn``,
``escort``, ``gru``); :func:`escort_rl.bench.atari.cell_config` builds it.
"""

from __future__ import annotations

import functools
import math
import time

import torch
from omegaconf import DictConfig
from torchrl.envs import Compose, InitTracker, ParallelEnv, SerialEnv, TransformedEnv

from escort_rl.belief import ESCORTFilter
from escort_rl.config import ConfigError
from escort_rl.envs.flickering import flickering_game, game_spaces, make_flickering_torchrl_env
from escort_rl.modules import DVRL, DVRLPolicy, ESCORTLatent, FrameGRU, FrameGRUPolicy
from escort_rl.trainers.algorithm import Algorithm
from escort_rl.trainers.dvrl_a2c import a2c_loss

AGENTS = ("dvrl", "escort_latent", "gru")


def check_agent(agent: str) -> str:
    if agent not in AGENTS:
        raise ConfigError(f"agent: unknown '{agent}'; choose one of {list(AGENTS)}")
    return agent


def agent_lr(cfg: DictConfig) -> float:
    """RMSprop's rate for ``cfg.agent``: ``trainer.belief_lr`` for the belief agents (DVRL, ESCORT-latent)
    when set, else ``trainer.lr``."""
    belief_lr = cfg.trainer.belief_lr
    return float(belief_lr) if belief_lr is not None and cfg.agent != "gru" else float(cfg.trainer.lr)


def build_atari_policy(cfg: DictConfig, obs_shape: tuple[int, ...], n_actions: int) -> DVRLPolicy | FrameGRUPolicy:
    """The policy of ``cfg.agent`` for a game with frames of ``obs_shape`` (``(C, S, S)``) and
    ``n_actions`` actions."""
    agent = check_agent(cfg.agent)
    if agent == "gru":
        return FrameGRUPolicy(FrameGRU(obs_shape[0], n_actions, hidden=int(cfg.gru.hidden), frame_size=obs_shape[1]))
    vrnn = {k: cfg.vrnn[k] for k in ("num_particles", "latent_dim", "hidden", "encoding_dim", "summary")}
    vrnn["emission_min_std"] = float(cfg.vrnn.emission_min_std)
    if agent == "dvrl":
        return DVRLPolicy(DVRL(obs_shape, n_actions, resample=True, **vrnn))
    latent = ("likelihood", "elbo")
    escort = ESCORTFilter(**{k: v for k, v in cfg.escort.items() if k not in latent})
    return DVRLPolicy(ESCORTLatent(obs_shape, n_actions, escort=escort, **{k: cfg.escort[k] for k in latent}, **vrnn))


def make_atari_env(game: str, num_envs: int, primer, parallel: bool = False, seed: int | None = None,
                   device: str = "cpu", vectorized: bool = False) -> TransformedEnv:
    """``num_envs`` flickering games (a ``SerialEnv``, a ``ParallelEnv`` of spawned workers, or with
    ``vectorized`` the Atari games on ALE's C++ vector env,
    :class:`~escort_rl.envs.atari_vector.FlickeringAtariVectorEnv`: the same frames, faster) with
    ``InitTracker`` and the agent's state ``primer``, their tensors on ``device``."""
    if vectorized and parallel:
        raise ValueError("vectorized: ALE's vector env runs the games on its own threads; pass parallel=False "
                         "with it")
    factory = functools.partial(make_flickering_torchrl_env, flickering_game(game).name, device=device)
    if vectorized:
        from escort_rl.envs.atari_vector import make_atari_vector_env

        batched = make_atari_vector_env(game, num_envs, device=device)
    else:
        batched = (ParallelEnv(num_envs, factory, mp_start_method="spawn") if parallel
                   else SerialEnv(num_envs, factory))
    env = TransformedEnv(batched, Compose(InitTracker(), primer))
    if seed is not None:
        env.set_seed(int(seed))
    return env


class GameLog:
    """The returns of finished games and the frame at which each ended; a checkpoint component
    (``state_dict`` of plain lists)."""

    def __init__(self) -> None:
        self.returns: list[float] = []
        self.frames: list[int] = []

    def state_dict(self) -> dict:
        return {"returns": list(self.returns), "frames": list(self.frames)}

    def load_state_dict(self, state: dict) -> None:
        self.returns, self.frames = [float(r) for r in state["returns"]], [int(f) for f in state["frames"]]


class AtariA2C(Algorithm):
    """A2C on flickering Atari for ``cfg.agent`` (see the module docstring); an algorithm of
    :func:`escort_rl.trainers.scaffold.run_training` without a POMDP model, stepping its envs
    itself. Components: ``actor``, ``optimizer`` and ``games`` (:class:`GameLog`)."""

    def __init__(self, cfg: DictConfig) -> None:
        super().__init__(cfg)
        t = cfg.trainer
        self.agent = check_agent(cfg.agent)
        self.policy = build_atari_policy(cfg, *game_spaces(cfg.game)).to(cfg.device)
        self.optimizer = torch.optim.RMSprop(self.policy.parameters(), lr=agent_lr(cfg), alpha=float(t.rmsprop_alpha),
                                             eps=float(t.rmsprop_eps))
        self.games = GameLog()
        vectorized = bool(t.vectorized_envs)
        if vectorized and t.parallel_envs:
            raise ConfigError("trainer.vectorized_envs: ALE's vector env runs the games on its own threads; set "
                              "trainer.parallel_envs=false with it")
        self.env = make_atari_env(cfg.game, int(t.num_envs), self.policy.make_tensordict_primer(),
                                  parallel=bool(t.parallel_envs), device=cfg.device, vectorized=vectorized)
        self.td = None  # the envs' current tensordict, carried across iterations
        self.running = torch.zeros(int(t.num_envs))  # the unclipped return of each env's current game
        self.frames = 0  # frames of this session (for the game log, offset by the resumed frames)

    @property
    def components(self) -> dict:
        return {"actor": self.policy, "optimizer": self.optimizer, "games": self.games}

    @classmethod
    def belief_of(cls, cfg: DictConfig, params, index: int) -> str:
        """The agent's own state (``cfg.agent``): no particle filter runs here."""
        return f"{cfg.agent} (learned)"

    def iteration(self, index: int, seed: int) -> dict:
        t = self.cfg.trainer
        if self.td is None:  # a session's first iteration: new games, seeded
            self.env.set_seed(seed)
            self.td = self.env.reset()
            self.frames = index * int(t.num_envs) * int(t.rollout_steps) * int(t.updates_per_iteration)
        elbo_key = None if self.agent == "gru" else self.policy.elbo_key
        sums = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0, "elbo": 0.0, "grad_norm": 0.0}
        finished: list[float] = []
        t0 = time.perf_counter()
        frames = 0
        for _ in range(int(t.updates_per_iteration)):
            steps = []
            for _ in range(int(t.rollout_steps)):
                td = self.policy(self.td)
                td, self.td = self.env.step_and_maybe_reset(td)
                steps.append(td)
            window = torch.stack(steps, dim=1)  # [B, T]
            frames += window.numel()
            finished += self.score_games(window)
            if t.reward_clip:
                window.set(("next", "reward"), window["next", "reward"].sign())
            with torch.no_grad():
                bootstrap = self.policy(self.td.clone())["state_value"].squeeze(-1)
            loss, terms = a2c_loss(window, bootstrap, float(t.gamma), float(t.entropy_coef),
                                   float(t.value_loss_coef), float(t.encoding_loss_coef), elbo_key=elbo_key,
                                   normalize_advantage=bool(t.normalize_advantage))
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            grad_norm = torch.nn.utils.clip_grad_norm_(self.policy.parameters(), float(t.max_grad_norm))
            self.optimizer.step()
            self.td = self.td.detach()  # truncate backpropagation through time
            for key, value in {**terms, "grad_norm": float(grad_norm)}.items():
                sums[key] += value
        seconds = time.perf_counter() - t0
        updates = int(t.updates_per_iteration)
        record = {"frames": frames, "episode_return": sum(finished) / len(finished) if finished else float("nan"),
                  "games": len(finished), **{k: v / updates for k, v in sums.items()},
                  "fps": frames / max(seconds, 1e-9)}
        if not all(math.isfinite(record[k]) for k in ("policy_loss", "value_loss", "elbo")):
            raise FloatingPointError(f"Atari A2C ({self.agent}): a non-finite loss ({record}); lower trainer.lr or "
                                     "trainer.encoding_loss_coef")
        return record

    def score_games(self, window) -> list[float]:
        """Add the window's unclipped rewards to each env's game and log the games that ended
        (``("next", "game_over")``); returns their returns."""
        reward = window["next", "reward"].squeeze(-1).detach().cpu()
        over = window["next", "game_over"].reshape(reward.shape).cpu()
        ended = []
        for step in range(reward.shape[1]):
            self.frames += reward.shape[0]
            self.running += reward[:, step]
            for env in over[:, step].nonzero().flatten().tolist():
                ended.append(float(self.running[env]))
                self.games.returns.append(float(self.running[env]))
                self.games.frames.append(self.frames)
                self.running[env] = 0.0
        return ended

    def close(self) -> None:
        if self.env is not None and not self.env.is_closed:
            self.env.close()
