"""A GRU actor-critic on frames: the model-free baseline of Flickering Atari (DVRL's "RNN" agent).

    o_t ──encoder──▶     φ(o_t) ─┐
    a_{t-1} ──one-hot, Linear──▶ φ(a) ─┴─▶ GRUCell(h_{t-1}) ──▶ h_t ──┬──▶ actor head ──▶ logits ──▶ action
                                                                      └──▶ critic head ──▶ state_value

:class:`FrameGRUPolicy` runs it on a tensordict with the same keys as
:class:`~escort_rl.modules.dvrl_torchrl.DVRLPolicy` (``*B`` the env batch, ``H`` the width):

- read: ``"observation"`` ``[*B, C, S, S]`` (``S`` = 84 on Atari, 10 on MinAtar), ``"is_init"``
  ``[*B, 1]`` (where the hidden state restarts from zeros), ``"gru_h"`` ``[*B, H]`` and
  ``"gru_prev_action"`` ``[*B]`` int64;
- written: ``"logits"`` ``[*B, A]``, ``"action"`` ``[*B]``, ``"action_log_prob"`` ``[*B]``,
  ``"state_value"`` ``[*B, 1]``, and ``("next", "gru_h")``, ``("next", "gru_prev_action")``.

The hidden state is passed along with its graph, so a trainer that steps the policy with gradients
backpropagates through time over its window (and cuts the graph by detaching the carried state).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor, nn
from torchrl.data import Unbounded
from torchrl.envs.transforms import TensorDictPrimer

from escort_rl.modules.dvrl_networks import ATARI_SIZE, frame_networks, mlp
from escort_rl.modules.dvrl_torchrl import sample_action


class FrameGRU(nn.Module):
    """The networks: ``step(h [B, H], action_prev [B], observation [B, C, S, S], reset [B])`` ->
    ``(h' [B, H], logits [B, A], value [B])``; rows with ``reset`` start from ``h = 0`` and no action.
    The frame encoder is :func:`~escort_rl.modules.dvrl_networks.frame_networks`'s for ``S = frame_size``
    (84: Atari, 10: MinAtar)."""

    def __init__(self, channels: int, n_actions: int, hidden: int = 256, frame_size: int = ATARI_SIZE) -> None:
        super().__init__()
        for name, value in (("channels", channels), ("n_actions", n_actions), ("hidden", hidden)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name}: expected a positive int, got {value!r}")
        self.n_actions, self.hidden = n_actions, hidden
        self.encoder = frame_networks((channels, frame_size, frame_size))[0](channels, hidden)
        self.action_encoder = mlp([n_actions, hidden])
        self.cell = nn.GRUCell(2 * hidden, hidden)
        self.actor_head = nn.Linear(hidden, n_actions)
        self.critic_head = nn.Linear(hidden, 1)

    def step(self, h: Tensor, action_prev: Tensor, observation: Tensor, reset: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        keep = (~reset.reshape(-1, 1)).to(h.dtype)
        one_hot = nn.functional.one_hot(action_prev.long().clamp(0, self.n_actions - 1), self.n_actions).to(h.dtype)
        x = torch.cat([self.encoder(observation), self.action_encoder(one_hot * keep)], dim=-1)
        h = self.cell(x, h * keep)
        return h, self.actor_head(h), self.critic_head(h).squeeze(-1)


class FrameGRUPolicy(TensorDictModuleBase):
    """:class:`FrameGRU` as a TorchRL policy (keys in the module docstring); samples the action, or
    takes the most probable one under ``set_interaction_type("mode")``."""

    def __init__(self, net: FrameGRU, observation_key: str = "observation", is_init_key: str = "is_init",
                 state_prefix: str = "gru") -> None:
        super().__init__()
        self.net = net
        self.observation_key, self.is_init_key = observation_key, is_init_key
        self.h_key, self.prev_key = f"{state_prefix}_h", f"{state_prefix}_prev_action"
        self.in_keys = [observation_key, self.h_key, self.prev_key, is_init_key]
        self.out_keys = ["logits", "action", "action_log_prob", "state_value", ("next", self.h_key),
                         ("next", self.prev_key)]

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """The env-side primer of the recurrent state: ``gru_h`` zeros ``[H]``, ``gru_prev_action`` 0."""
        specs = {self.h_key: Unbounded(shape=(self.net.hidden,), dtype=torch.float32),
                 self.prev_key: Unbounded(shape=(), dtype=torch.int64)}
        return TensorDictPrimer(specs, default_value={self.h_key: 0.0, self.prev_key: 0}, expand_specs=True)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        for key in (self.observation_key, self.h_key, self.prev_key, self.is_init_key):
            if key not in tensordict.keys():
                raise KeyError(f"FrameGRUPolicy: '{key}' is missing from the tensordict; the env needs "
                               "InitTracker() and policy.make_tensordict_primer() among its transforms")
        batch = tensordict.batch_size
        n = batch.numel()
        obs = tensordict.get(self.observation_key)
        h, logits, value = self.net.step(tensordict.get(self.h_key).reshape(n, -1),
                                         tensordict.get(self.prev_key).reshape(n),
                                         obs.reshape(n, *obs.shape[len(batch):]),
                                         tensordict.get(self.is_init_key).reshape(n))
        action, log_prob = sample_action(logits)

        def out(x: Tensor) -> Tensor:
            return x.reshape(*batch, *x.shape[1:])

        tensordict.set("logits", out(logits))
        tensordict.set("action", out(action))
        tensordict.set("action_log_prob", out(log_prob))
        tensordict.set("state_value", out(value.unsqueeze(-1)))
        tensordict.set(("next", self.h_key), out(h))
        tensordict.set(("next", self.prev_key), out(action))
        return tensordict
