"""A recurrent actor-critic on raw observations: TorchRL's ``GRUModule`` under a categorical policy
and a value head, the model-free alternative to a belief (the GRU's hidden state is the agent's
memory of the observation history).

Read top to bottom: :func:`make_recurrent_actor_critic` builds, from shared modules,

    observation ──standardise──▶ encoder (Linear, tanh) ──▶ GRU ──┬──▶ policy head ──▶ logits ──▶ action
                                                                  └──▶ value head ──▶ state_value

and returns the policy (a ``ProbabilisticActor``), the value network and the ``TensorDictPrimer``
that makes an env carry the GRU's hidden state. The env must also have ``InitTracker`` (it writes
``is_init``, which tells the GRU where a new episode starts).

Keys and shapes (``B`` = the batch of envs, ``T`` = time, ``H`` = ``hidden``):

- reads ``observation_key`` ``[*B, obs_dim]``, ``"is_init"`` ``[*B, 1]`` (bool) and the hidden state
  ``"recurrent_state"`` ``[*B, 1, H]`` (one GRU layer; zeros at reset, from the primer);
- writes ``"rnn_input"`` ``[*B, H]``, ``"rnn_output"`` ``[*B, H]``, the next hidden state
  ``("next", "recurrent_state")`` ``[*B, 1, H]`` (the env's ``step_mdp`` moves it to the root for
  the next step), ``"logits"`` ``[*B, n_actions]``, ``"action"`` ``[*B]`` int64 and
  ``"action_log_prob"`` ``[*B]``; the value network writes ``"state_value"`` ``[*B, 1]``.

Two modes, TorchRL's convention (:class:`torchrl.modules.set_recurrent_mode`):

- sequential (the default, what collectors and ``env.rollout`` run): one step per call, any batch
  shape; where ``is_init`` is true the hidden state is zeroed before the step;
- recurrent (``with set_recurrent_mode(True):``, what the loss runs): a batch ``[E, T]`` whose last
  dimension is time; each row is split at its ``is_init`` steps, and every piece starts from the
  hidden state stored at its first step, so the outputs equal stepping the policy along the row.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torch.distributions import Categorical
from torchrl.envs import TensorDictPrimer
from torchrl.modules import GRUModule, ProbabilisticActor, ValueOperator

from escort_rl.modules.action_heads import DEFAULT_DISTRIBUTION, DEFAULT_MIN_SCALE, gaussian_in_box, normal_params

RECURRENT_KEY = "recurrent_state"


class Standardise(nn.Module):
    """``(x − loc) / scale`` per dimension (``loc``, ``scale``: scalars or ``[dim]``, stored as
    buffers so checkpoints carry them). ``[*B, dim]`` -> ``[*B, dim]``."""

    def __init__(self, dim: int, loc: float | list[float] = 0.0, scale: float | list[float] = 1.0) -> None:
        super().__init__()
        self.register_buffer("loc", torch.as_tensor(loc, dtype=torch.float32).expand(dim).clone())
        self.register_buffer("scale", torch.as_tensor(scale, dtype=torch.float32).expand(dim).clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.loc) / self.scale


def _gru(hidden: int, device=None) -> GRUModule:
    """The GRU of width ``hidden``: ``"rnn_input"`` and ``"recurrent_state"`` -> ``"rnn_output"`` and
    ``("next", "recurrent_state")``."""
    return GRUModule(input_size=hidden, hidden_size=hidden, in_keys=["rnn_input", RECURRENT_KEY],
                     out_keys=["rnn_output", ("next", RECURRENT_KEY)], device=device)


def make_recurrent_primer(hidden: int = 64) -> TensorDictPrimer:
    """The primer of :func:`make_recurrent_actor_critic` with width ``hidden`` (``recurrent_state``
    ``[*B, 1, hidden]``, zeros at reset), without building the networks: the GRU it comes from is on
    the meta device, so building an env draws nothing from torch's generator (a run stays
    reproducible whenever its collector is built)."""
    return _gru(hidden, device="meta").make_tensordict_primer()


def _head(hidden: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, out))


def make_recurrent_actor_critic(obs_dim: int, n_actions: int, hidden: int = 64,
                                obs_loc: float | list[float] = 0.0, obs_scale: float | list[float] = 1.0,
                                observation_key: str = "observation",
                                action_box: tuple[torch.Tensor, torch.Tensor] | None = None,
                                min_scale: float = DEFAULT_MIN_SCALE, distribution: str = DEFAULT_DISTRIBUTION,
                                ) -> tuple[ProbabilisticActor, TensorDictSequential, TensorDictPrimer]:
    """``(policy, value, primer)``: a GRU actor-critic on the standardised observation (see the
    module docstring for the keys, shapes and modes).

    The policy and the value network share the encoder and the GRU (one set of parameters: an
    optimiser over ``policy`` and ``value`` trains them with both losses). ``primer`` is
    ``gru.make_tensordict_primer()`` (the same as :func:`make_recurrent_primer`): append it, after
    ``InitTracker()``, to the env the policy runs in (see
    :func:`escort_rl.trainers.recurrent_ppo.make_recurrent_env`).

    Args:
        obs_dim: the observation's size.
        n_actions: the number of discrete actions; with ``action_box``, ``2·A`` (a Gaussian's loc and
            scale, put in the box as :func:`escort_rl.modules.action_heads.gaussian_in_box` does).
        hidden: the width of the encoder, of the GRU's hidden state and of the heads.
        obs_loc, obs_scale: the observation is standardised as ``(o − loc) / scale`` (scalars or
            ``[obs_dim]``).
        observation_key: the key the policy reads.
        action_box: ``(low, high)`` tensors ``[A]`` for continuous actions (``None``: discrete).
        min_scale, distribution: the continuous head's scale floor and law (``actor.min_scale``,
            ``actor.distribution``; see :mod:`escort_rl.modules.action_heads`).
    """
    encoder = TensorDictModule(
        nn.Sequential(Standardise(obs_dim, obs_loc, obs_scale), nn.Linear(obs_dim, hidden), nn.Tanh()),
        in_keys=[observation_key], out_keys=["rnn_input"])
    gru = _gru(hidden)
    if action_box is None:
        logits = TensorDictModule(_head(hidden, n_actions), in_keys=["rnn_output"], out_keys=["logits"])
        policy = ProbabilisticActor(TensorDictSequential(encoder, gru, logits), in_keys=["logits"], out_keys=["action"],
                                    distribution_class=Categorical, return_log_prob=True,
                                    log_prob_key="action_log_prob")
    else:
        params = TensorDictSequential(
            TensorDictModule(_head(hidden, n_actions), in_keys=["rnn_output"], out_keys=["normal_params"]),
            normal_params(min_scale))
        policy = gaussian_in_box(TensorDictSequential(encoder, gru, params), action_box, n_actions,
                                 distribution=distribution)
    value = TensorDictSequential(encoder, gru, ValueOperator(_head(hidden, 1), in_keys=["rnn_output"]))
    return policy, value, gru.make_tensordict_primer()
