"""POMCPOWPolicy: a TorchRL policy module that plans one POMCPOW decision per belief in a batch."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from escort_rl.models.protocol import check_model
from escort_rl.planners.pomcpow import POMCPOW, Decision


class POMCPOWPolicy(TensorDictModuleBase):
    """Reads a particle belief from the tensordict, plans with :class:`POMCPOW`, writes the action.

    Keys (``*B`` is the tensordict's batch shape, ``N`` particles of dimension ``d``):

    - reads ``particles_key`` ``[*B, N, d]`` and ``log_weights_key`` ``[*B, N]`` (the keys
      :class:`escort_rl.transforms.BeliefTransform` writes);
    - writes ``action_key``: int64 ``[*B]``, one decision per belief (a Python loop over the batch).

    So it drops into ``env.rollout(T, policy)`` and into collectors of the envs built by
    :func:`escort_rl.trainers.builders.make_env`.

    Args:
        model: the model the planner simulates (the env's model, or an approximation of it).
        planner: a :class:`POMCPOW`.
        seed: seeds the planner's generator (``None``: a random seed).
        particles_key, log_weights_key, action_key: the tensordict keys.

    ``last_decisions`` holds the :class:`Decision` of each belief of the latest call (flattened batch
    order), for inspection; ``decisions`` and ``planning_seconds`` count all decisions since the
    policy was built (or :meth:`reset_counters`), for timing.
    """

    def __init__(self, model, planner: POMCPOW, seed: int | None = None, particles_key: str = "particles",
                 log_weights_key: str = "particle_log_weights", action_key: str = "action") -> None:
        check_model(model)
        if not isinstance(planner, POMCPOW):
            raise TypeError(f"planner: expected a POMCPOW, got {type(planner).__name__}")
        super().__init__()
        self.in_keys = [particles_key, log_weights_key]
        self.out_keys = [action_key]
        self.model, self.planner, self.seed = model, planner, seed
        self.particles_key, self.log_weights_key, self.action_key = particles_key, log_weights_key, action_key
        self._generator: torch.Generator | None = None
        self.last_decisions: list[Decision] = []
        self.decisions, self.planning_seconds = 0, 0.0

    def reset_counters(self) -> None:
        """Zero ``decisions`` and ``planning_seconds``."""
        self.decisions, self.planning_seconds = 0, 0.0

    def _generator_on(self, device: torch.device) -> torch.Generator:
        """The planner's generator, (re)created on ``device`` with ``seed`` when first needed there."""
        if self._generator is None or self._generator.device != device:
            self._generator = torch.Generator(device=device)
            if self.seed is None:
                self._generator.seed()
            else:
                self._generator.manual_seed(int(self.seed))
        return self._generator

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        particles = tensordict.get(self.particles_key, None)
        if particles is None:
            raise KeyError(f"POMCPOWPolicy.particles_key: '{self.particles_key}' is not in the tensordict; "
                           "add a BeliefTransform to the env")
        log_weights = tensordict.get(self.log_weights_key, None)
        if particles.dim() < 2 or particles.shape[-1] != self.model.state_dim:
            raise ValueError(f"{self.particles_key}: expected shape [*B, N, {self.model.state_dim}], "
                             f"got {tuple(particles.shape)}")
        batch, (n, d) = particles.shape[:-2], particles.shape[-2:]
        if log_weights is not None and log_weights.shape != (*batch, n):
            raise ValueError(f"{self.log_weights_key}: expected shape {(*batch, n)}, got {tuple(log_weights.shape)}")
        flat_particles = particles.reshape(-1, n, d)
        flat_log_weights = None if log_weights is None else log_weights.reshape(-1, n)
        generator = self._generator_on(particles.device)
        self.last_decisions = [
            self.planner.plan(self.model, flat_particles[i],
                              None if flat_log_weights is None else flat_log_weights[i], generator)
            for i in range(flat_particles.shape[0])
        ]
        self.decisions += len(self.last_decisions)
        self.planning_seconds += sum(dec.seconds for dec in self.last_decisions)
        actions = torch.tensor([dec.action for dec in self.last_decisions], dtype=torch.int64, device=particles.device)
        tensordict.set(self.action_key, actions.reshape(batch))
        return tensordict
