"""DVRL: Deep Variational Reinforcement Learning (Igl et al. 2018), the belief model and its step.

Each env keeps ``K`` weighted particles ``(h_k, z_k, w_k)`` of a variational RNN. One step, given
the previous action ``a_{t-1}`` and the new observation ``o_t``, follows the original order:

1. encode ``φ(o_t)`` and ``φ(a_{t-1})``;
2. resample the particles by their weights (systematic resampling; switchable);
3. sample ``z_t^k ~ q(z | h_{t-1}^k, a_{t-1}, o_t)`` (diagonal Gaussian, reparameterised);
4. weight it: ``Δ_t^k = log p(z_t^k | h_{t-1}^k, a_{t-1}) + log p(o_t | h_{t-1}^k, z_t^k, a_{t-1})
   - log q(z_t^k | h_{t-1}^k, a_{t-1}, o_t)``;
5. update ``h_t^k = GRUCell([φ(z_t^k), φ(o_t), φ(a_{t-1})], h_{t-1}^k)``.

The ELBO term of a step is the log of the weighted mean of the new weights,

    ELBO_t = log Σ_k w̄_{t-1}^k exp(Δ_t^k),    w̄_{t-1} = softmax(log w_{t-1}) (after resampling: 1/K),

so that ``exp(Σ_t ELBO_t)`` is the particle filter's unbiased estimate of ``p(o_{1:T} | a)``, and
``E[Σ_t ELBO_t] <= log p(o_{1:T} | a)`` (Jensen), with or without resampling. The carried log-weights
are the normalised ``log w_t^k = log w̄_{t-1}^k + Δ_t^k - ELBO_t``. As in the original, gradients flow
through the particles a resampling step picks, not through which ones it picks (the ELBO's gradient
ignores the discrete ancestor choice).

A belief summary (a GRU over the particles, or a DeepSets pooling) feeds an actor head (logits) and
a critic head (value). The TorchRL wrapper is :class:`escort_rl.modules.dvrl_torchrl.DVRLPolicy`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import torch
from torch import Tensor, nn

from escort_rl.belief.resampling import systematic
from escort_rl.config import ConfigError
from escort_rl.modules.dvrl_networks import (
    SUMMARIES,
    GaussianEmission,
    GaussianHead,
    GRURecurrence,
    ImageEmission,
    VectorEncoder,
    frame_networks,
    mlp,
)


class DVRLState(NamedTuple):
    """The particles of ``B`` envs: ``h [B, K, H]``, ``z [B, K, Z]``, normalised ``log_w [B, K]``."""

    h: Tensor
    z: Tensor
    log_w: Tensor

    def detach(self) -> DVRLState:
        """Cut the graph (truncated backpropagation through time)."""
        return DVRLState(self.h.detach(), self.z.detach(), self.log_w.detach())


# ------------------------------------------------------------------------------------ resampling
def resample(state: DVRLState, indices: Tensor) -> DVRLState:
    """Take the ancestors ``indices [B, K]`` of every particle; the weights become uniform ``-log K``."""
    k = state.log_w.shape[-1]

    def take(x: Tensor) -> Tensor:
        return torch.gather(x, 1, indices.unsqueeze(-1).expand(-1, -1, x.shape[-1]))

    return DVRLState(take(state.h), take(state.z), torch.full_like(state.log_w, -math.log(k)))


# ---------------------------------------------------------------------------------------- model
class DVRL(nn.Module):
    """The DVRL belief model with actor and critic heads.

    Args:
        obs_shape: ``obs_dim`` (an int) for vector observations, or frames: ``(C, 84, 84)`` (Atari) or
            ``(C, 10, 10)`` (MinAtar).
        n_actions: number of discrete actions.
        latent_dim: ``Z``, the size of ``z`` (the paper's ``d_belief``).
        hidden: ``H``, the size of ``h`` (the paper's ``d_h``), and the width of the heads.
        num_particles: ``K``.
        encoding_dim: the size of ``φ(o)``, ``φ(a)`` and ``φ(z)`` (default ``hidden``).
        summary: ``"gru"`` (the original) or ``"deepsets"``.
        summary_dim: the size of the belief summary (default ``hidden``).
        resample: systematic resampling at every step (the original) or none.
        emission_min_std: a floor on the frame emission's learned standard deviation (0: none; see
            :class:`~escort_rl.modules.dvrl_networks.ImageEmission`).
        observation_encoder, prior, proposal, emission, recurrence: replacements for the default
            networks, with the call signatures of :mod:`escort_rl.modules.dvrl_networks`:
            ``observation_encoder(o [B, *obs_shape]) -> [B, encoding_dim]``;
            ``prior(h, a_enc) -> Normal`` and ``proposal(h, a_enc, o_enc) -> Normal`` over ``z``
            (``Independent`` diagonal Gaussians with event shape ``[Z]``);
            ``emission(h, z, a_enc) -> Distribution`` with ``log_prob(o [B, K, *obs_shape]) -> [B, K]``;
            ``recurrence(h, z, o_enc, a_enc) -> h'``. All particle inputs are ``[B, K, ·]``.
    """

    def __init__(
        self,
        obs_shape: int | Sequence[int],
        n_actions: int,
        latent_dim: int,
        hidden: int = 64,
        num_particles: int = 100,
        encoding_dim: int | None = None,
        summary: str = "gru",
        summary_dim: int | None = None,
        resample: bool = True,
        emission_min_std: float = 0.0,
        *,
        observation_encoder: nn.Module | None = None,
        prior: nn.Module | None = None,
        proposal: nn.Module | None = None,
        emission: nn.Module | None = None,
        recurrence: nn.Module | None = None,
    ) -> None:
        super().__init__()
        self.obs_shape = _check_obs_shape(obs_shape)
        for name, value in (("n_actions", n_actions), ("latent_dim", latent_dim), ("hidden", hidden),
                            ("num_particles", num_particles)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name}: expected a positive int, got {value!r}")
        if summary not in SUMMARIES:
            raise ValueError(f"summary: expected one of {sorted(SUMMARIES)}, got {summary!r}")
        if not isinstance(resample, bool):
            raise ValueError(f"resample: expected a bool, got {resample!r}")
        e = hidden if encoding_dim is None else encoding_dim
        s = hidden if summary_dim is None else summary_dim
        self.n_actions, self.latent_dim, self.hidden = n_actions, latent_dim, hidden
        self.num_particles, self.encoding_dim, self.summary_dim = num_particles, e, s
        self.resample = resample
        self.emission_min_std = float(emission_min_std)

        self.latent_encoder = mlp([latent_dim, e])  # φ(z), shared by emission, recurrence, summary
        self.action_encoder = mlp([n_actions, e])  # φ(a) of a one-hot action (zeros: no action)
        is_image = len(self.obs_shape) == 3
        if observation_encoder is None:
            observation_encoder = (frame_networks(self.obs_shape)[0](self.obs_shape[0], e) if is_image
                                   else VectorEncoder(self.obs_shape[0], e))
        self.observation_encoder = observation_encoder
        self.prior = prior if prior is not None else GaussianHead(hidden + e, latent_dim, hidden)
        self.proposal = proposal if proposal is not None else GaussianHead(hidden + 2 * e, latent_dim, hidden)
        if emission is None:
            emission = (ImageEmission(self.latent_encoder, hidden + 2 * e, self.obs_shape[0], self.obs_shape[1],
                                      min_std=float(emission_min_std))
                        if is_image
                        else GaussianEmission(self.latent_encoder, hidden + 2 * e, self.obs_shape[0], hidden))
        self.emission = emission
        self.recurrence = recurrence if recurrence is not None else GRURecurrence(self.latent_encoder, 3 * e, hidden)
        self.summarizer = SUMMARIES[summary](hidden + e, s)
        self.actor_head = nn.Linear(s, n_actions)
        self.critic_head = nn.Linear(s, 1)

    @classmethod
    def from_config(cls, cfg: Mapping, obs_shape: int | Sequence[int], n_actions: int) -> DVRL:
        """Build from a ``configs/dvrl/<domain>.yaml`` mapping (the Hydra group ``dvrl``): its ``module``
        section holds the constructor's keyword arguments; ``obs_dim`` and ``n_actions``, when listed,
        must match the env's. Raises :class:`escort_rl.config.ConfigError` naming the bad key."""
        cfg = dict(cfg)
        if n_actions is None:
            raise ConfigError("dvrl.n_actions: DVRL takes discrete actions and this env's are continuous; train a "
                              "belief policy on it instead (trainer=ppo)")
        for key, actual in (("obs_dim", _check_obs_shape(obs_shape)[0]), ("n_actions", n_actions)):
            if cfg.get(key) is not None and int(cfg[key]) != actual:
                raise ConfigError(f"dvrl.{key}: the config says {cfg[key]} but the env has {actual}")
        module = dict(cfg.get("module") or {})
        allowed = {"num_particles", "latent_dim", "hidden", "encoding_dim", "summary", "summary_dim", "resample"}
        unknown = sorted(set(module) - allowed)
        if unknown:
            raise ConfigError(f"dvrl.module.{unknown[0]}: unknown key; expected some of {sorted(allowed)}")
        if "latent_dim" not in module:
            raise ConfigError("dvrl.module.latent_dim: missing (the paper's d_belief)")
        try:
            return cls(obs_shape, n_actions, **module)
        except ValueError as err:
            raise ConfigError(f"dvrl.module.{err}") from None

    # ------------------------------------------------------------------------------ state
    def initial_state(self, batch_size: int, device: torch.device | str | None = None) -> DVRLState:
        """Fresh particles: ``h = 0``, ``z = 0``, uniform ``log_w = -log K``."""
        k = self.num_particles
        return DVRLState(
            torch.zeros(batch_size, k, self.hidden, device=device),
            torch.zeros(batch_size, k, self.latent_dim, device=device),
            torch.full((batch_size, k), -math.log(k), device=device),
        )

    def reset_rows(self, state: DVRLState, reset_mask: Tensor) -> DVRLState:
        """Re-initialise the rows where ``reset_mask [B]`` is True; other rows are returned as they are."""
        fresh = self.initial_state(state.h.shape[0], state.h.device)
        m = reset_mask.reshape(-1, 1)
        return DVRLState(
            torch.where(m.unsqueeze(-1), fresh.h, state.h),
            torch.where(m.unsqueeze(-1), fresh.z, state.z),
            torch.where(m, fresh.log_w, state.log_w),
        )

    def encode_action(self, action: Tensor, no_action: Tensor) -> Tensor:
        """``φ(one_hot(a))`` ``[B, E]``; rows where ``no_action [B]`` is True (first steps) encode a zero
        one-hot vector, whatever their ``action`` holds."""
        one_hot = nn.functional.one_hot(action.long().clamp(0, self.n_actions - 1), self.n_actions)
        one_hot = one_hot.to(torch.float32) * (~no_action).to(torch.float32).unsqueeze(-1)
        return self.action_encoder(one_hot)

    # ------------------------------------------------------------------------------ step
    def step(
        self,
        state: DVRLState | tuple[Tensor, Tensor, Tensor],
        action_prev: Tensor,
        observation: Tensor,
        reset_mask: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> tuple[DVRLState, Tensor, Tensor]:
        """One belief update; pure in its tensor inputs (randomness from ``generator``).

        Args:
            state: ``h [B, K, H]``, ``z [B, K, Z]``, ``log_w [B, K]``.
            action_prev: ``a_{t-1}`` int64 ``[B]`` (ignored on rows being reset).
            observation: ``o_t`` ``[B, *obs_shape]``.
            reset_mask: bool ``[B]``: these rows start an episode: their particles are re-initialised
                (``h = z = 0``, uniform weights), ``a_{t-1}`` is "none", and their ELBO term is that of
                the first step. ``None``: no row is reset.
            generator: the source of the resampling offsets and of the proposal noise.

        Returns:
            ``(new_state, elbo [B], summary [B, summary_dim])``, with ``elbo`` the ``ELBO_t`` of the
            module docstring.
        """
        state, action_prev, reset_mask = self.prepare_step(state, action_prev, observation, reset_mask)
        b, k = state.log_w.shape
        obs_enc = self.observation_encoder(observation)  # [B, E]
        action_enc = self.encode_action(action_prev, reset_mask)  # [B, E]
        if self.resample:
            state = resample(state, systematic(state.log_w.detach(), generator))
        log_w_prev = torch.log_softmax(state.log_w, dim=-1)

        obs_k = obs_enc.unsqueeze(1).expand(b, k, -1)
        action_k = action_enc.unsqueeze(1).expand(b, k, -1)
        z, increment = self.importance_step(state.h, obs_k, action_k, observation, generator)
        joint = log_w_prev + increment
        elbo = torch.logsumexp(joint, dim=-1)  # ELBO_t, [B]
        # normalised weights; a row whose every weight is zero (ELBO = -inf) restarts uniform, not NaN
        uniform = torch.full_like(joint, -math.log(k))
        log_w = torch.where(torch.isfinite(elbo).unsqueeze(-1), joint - elbo.unsqueeze(-1), uniform)
        h = self.recurrence(state.h, z, obs_k, action_k)
        new_state = DVRLState(h, z, log_w)
        return new_state, elbo, self.summarize(new_state)

    def prepare_step(self, state: DVRLState | tuple[Tensor, Tensor, Tensor], action_prev: Tensor,
                     observation: Tensor, reset_mask: Tensor | None) -> tuple[DVRLState, Tensor, Tensor]:
        """Check the inputs of :meth:`step` and re-initialise the rows being reset. Returns
        ``(state, action_prev [B], reset_mask [B] bool)``."""
        state = DVRLState(*state)
        b, _ = self._check_step_inputs(state, action_prev, observation)
        if reset_mask is None:
            reset_mask = torch.zeros(b, dtype=torch.bool, device=observation.device)
        reset_mask = reset_mask.reshape(b).bool()
        state = self.reset_rows(state, reset_mask)
        action_prev = action_prev.reshape(b)
        out_of_range = ~reset_mask & ((action_prev < 0) | (action_prev >= self.n_actions))
        if out_of_range.any():
            raise ValueError(f"action_prev: values must lie in [0, {self.n_actions}) on rows not being reset, "
                             f"got {action_prev[out_of_range].tolist()}")
        return state, action_prev, reset_mask

    def importance_step(self, h: Tensor, obs_k: Tensor, action_k: Tensor, observation: Tensor,
                        generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """Steps 3 and 4 of the module docstring: ``z ~ q(z | h, a, o)`` (reparameterised) and its
        log-weight increment ``Δ = log p(z | h, a) + log p(o | h, z, a) − log q(z | h, a, o)``.

        ``h [B, K, H]``, ``obs_k`` and ``action_k`` ``[B, K, E]`` (the encodings expanded over the
        particles), ``observation [B, *obs_shape]``. Returns ``(z [B, K, Z], Δ [B, K])``.
        """
        b, k = h.shape[:2]
        q = self.proposal(h, action_k, obs_k)
        eps = torch.randn(b, k, self.latent_dim, generator=generator, device=observation.device)
        z = q.mean + q.stddev * eps  # reparameterised sample of q
        log_q = _check_log_prob(q.log_prob(z), "proposal", b, k)
        log_prior = _check_log_prob(self.prior(h, action_k).log_prob(z), "prior", b, k)
        log_lik = _check_log_prob(self.observation_log_prob(h, z, action_k, observation, obs_k), "emission", b, k)
        return z, log_prior + log_lik - log_q

    def observation_log_prob(self, h: Tensor, z: Tensor, action_k: Tensor, observation: Tensor,
                             obs_k: Tensor) -> Tensor:
        """``log p(o | h, z, a)`` ``[B, K]`` of the emission, at every particle: ``observation
        [B, *obs_shape]``, its encoding ``obs_k [B, K, E]`` (unused here; a subclass may read it)."""
        b, k = h.shape[:2]
        obs_rep = observation.unsqueeze(1).expand(b, k, *observation.shape[1:])
        return self.emission(h, z, action_k).log_prob(obs_rep)

    def summarize(self, state: DVRLState) -> Tensor:
        """The belief summary ``[B, summary_dim]`` of the particles ``(h, φ(z), w)``."""
        return self.summarizer(state.h, self.latent_encoder(state.z), state.log_w)

    def heads(self, summary: Tensor) -> tuple[Tensor, Tensor]:
        """``(logits [B, n_actions], value [B])`` from the summary ``[B, summary_dim]``."""
        return self.actor_head(summary), self.critic_head(summary).squeeze(-1)

    def unroll(
        self,
        state: DVRLState | tuple[Tensor, Tensor, Tensor],
        actions_prev: Tensor,
        observations: Tensor,
        reset_mask: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> tuple[DVRLState, Tensor, Tensor]:
        """:meth:`step` along a sequence (for truncated backpropagation through time).

        Args: ``actions_prev [B, T]``, ``observations [B, T, *obs_shape]``, ``reset_mask [B, T]``.
        Returns: ``(final_state, elbo [B, T], summaries [B, T, summary_dim])``.
        """
        steps = observations.shape[1]
        elbos, summaries = [], []
        for t in range(steps):
            reset_t = None if reset_mask is None else reset_mask[:, t]
            state, elbo, summary = self.step(state, actions_prev[:, t], observations[:, t], reset_t, generator)
            elbos.append(elbo)
            summaries.append(summary)
        return DVRLState(*state), torch.stack(elbos, 1), torch.stack(summaries, 1)

    # ------------------------------------------------------------------------------ checks
    def _check_step_inputs(self, state: DVRLState, action_prev: Tensor, observation: Tensor) -> tuple[int, int]:
        if tuple(observation.shape[1:]) != self.obs_shape:
            raise ValueError(
                f"observation: expected shape [B, {', '.join(map(str, self.obs_shape))}], "
                f"got {tuple(observation.shape)}"
            )
        if not torch.isfinite(observation).all():
            raise ValueError("observation: contains NaN or Inf")
        b, k = observation.shape[0], self.num_particles
        expected = {"h": (b, k, self.hidden), "z": (b, k, self.latent_dim), "log_w": (b, k)}
        for name, shape in expected.items():
            got = tuple(getattr(state, name).shape)
            if got != shape:
                raise ValueError(f"state.{name}: expected shape {shape} (B, K, ...), got {got}")
        if action_prev.numel() != b or action_prev.dtype.is_floating_point:
            raise ValueError(
                f"action_prev: expected int64 indices of shape ({b},), got {action_prev.dtype} "
                f"{tuple(action_prev.shape)}"
            )
        return b, k


def _check_obs_shape(obs_shape: int | Sequence[int]) -> tuple[int, ...]:
    shape = (int(obs_shape),) if isinstance(obs_shape, int) else tuple(int(s) for s in obs_shape)
    if len(shape) == 1 and shape[0] >= 1:
        return shape
    if len(shape) == 3 and shape[0] >= 1:
        frame_networks(shape)  # raises for a frame size without networks
        return shape
    raise ValueError(f"obs_shape: expected obs_dim (an int) or frames (C, S, S), got {obs_shape!r}")


def _check_log_prob(value: Tensor, name: str, b: int, k: int) -> Tensor:
    if tuple(value.shape) != (b, k):
        raise ValueError(
            f"{name}: log_prob must have shape ({b}, {k}) (one value per particle; use an Independent "
            f"distribution), got {tuple(value.shape)}"
        )
    return value
