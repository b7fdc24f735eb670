"""DVRLPolicy: the DVRL belief model as a TorchRL policy with its recurrent state in the tensordict.

The particles travel like TorchRL's recurrent modules' hidden states (``LSTMModule``): the policy
reads them at the root, writes the updated ones under ``("next", key)``, and ``step_mdp`` carries them
to the next root. :meth:`DVRLPolicy.make_tensordict_primer` registers them in the env's specs, which
ParallelEnv and the collectors need, and fills fresh values on (partial) resets; ``InitTracker``'s
``"is_init"`` tells the policy which rows start an episode, as ``LSTMModule`` uses it.

Keys (``*B`` the env batch, ``K`` particles, prefix ``"dvrl"`` by default):

- read: ``"observation"`` ``[*B, *obs_shape]``, ``"is_init"`` ``[*B, 1]`` bool, and the state
  ``"dvrl_h"`` ``[*B, K, H]``, ``"dvrl_z"`` ``[*B, K, Z]``, ``"dvrl_log_w"`` ``[*B, K]``,
  ``"dvrl_prev_action"`` ``[*B]`` int64 (the action taken before this observation).
- written: ``"logits"`` ``[*B, n_actions]``, ``"action"`` ``[*B]`` int64, ``"action_log_prob"`` ``[*B]``,
  ``"state_value"`` ``[*B, 1]``, ``"dvrl_elbo"`` ``[*B]`` (this step's ELBO term), ``"dvrl_summary"``
  ``[*B, S]`` (the belief summary), with a readout also ``"state_estimate"`` ``[*B, state_dim]`` (the
  readout's estimate of the current state), and the four state keys under ``"next"``
  (``("next", "dvrl_prev_action")`` is the action just chosen).

**The state's lifecycle**, the same for this policy-side state and for the env-side belief of
:class:`~escort_rl.transforms.BeliefTransform` (its particles, log-weights and log-evidence):

1. *reset*: fresh state in the rows being reset (every row, or those ``"_reset"`` marks), written
   by the primer here and by the transform there; ``InitTracker`` marks the rows ``"is_init"``;
2. *step*: the module reads the state at the root and writes the updated state under ``"next"``;
3. ``step_mdp`` (a rollout, a collector) moves ``"next"`` to the root for the following step;
4. *partial reset*: only the rows reset get fresh state; the others carry theirs, and the policy
   steps on from the mixed batch.

Example:
    >>> import torch
    >>> from torchrl.envs import Compose, InitTracker, TransformedEnv
    >>> from torchrl.envs.utils import step_mdp
    >>> from escort_rl.envs import POMDPEnv
    >>> from escort_rl.models import LightDark10D
    >>> from escort_rl.modules import DVRL, DVRLPolicy
    >>> model = LightDark10D()
    >>> policy = DVRLPolicy(DVRL(model.obs_dim, model.n_actions, latent_dim=2, hidden=4, num_particles=3))
    >>> env = TransformedEnv(POMDPEnv(model, batch_size=(2,), seed=0, max_steps=5),
    ...                      Compose(InitTracker(), policy.make_tensordict_primer()))
    >>> td = env.reset()
    >>> td["is_init"].squeeze(-1).tolist(), float(td["dvrl_h"].abs().sum())
    ([True, True], 0.0)
    >>> with torch.no_grad():
    ...     td = step_mdp(env.step(policy(td)))
    >>> _ = td.set("_reset", torch.tensor([[True], [False]]))  # env 0 starts a new episode
    >>> td = env.reset(td)
    >>> td["is_init"].squeeze(-1).tolist(), float(td["dvrl_h"][0].abs().sum()), bool(td["dvrl_h"][1].abs().sum() > 0)
    ([True, False], 0.0, True)
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModuleBase
from tensordict.nn.probabilistic import interaction_type
from torch import nn
from torch.distributions import Categorical
from torchrl.data import Unbounded
from torchrl.envs.transforms import TensorDictPrimer

from escort_rl.modules.dvrl import DVRL, DVRLState

_GREEDY = (InteractionType.MODE, InteractionType.DETERMINISTIC, InteractionType.MEDIAN, InteractionType.MEAN)


def sample_action(logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(action [B], log π(action) [B])`` from ``logits [B, A]``: the most probable action under
    ``set_interaction_type("mode")`` (or ``"deterministic"``), a sample otherwise."""
    dist = Categorical(logits=logits)
    action = logits.argmax(-1) if interaction_type() in _GREEDY else dist.sample()
    return action, dist.log_prob(action)


class DVRLPolicy(TensorDictModuleBase):
    """Runs :meth:`DVRL.step` on a tensordict and samples the action from the actor head.

    Under ``set_interaction_type("mode")`` (or ``"deterministic"``) the action is the most probable
    one; otherwise (the default, and the collectors' ``"random"``) it is sampled.

    Args:
        dvrl: the :class:`~escort_rl.modules.dvrl.DVRL` model.
        observation_key, action_key, is_init_key: keys of the env and of ``InitTracker``.
        state_prefix: the state keys are ``f"{state_prefix}_h"``, ``_z``, ``_log_w``, ``_prev_action``.
        readout: an optional :class:`~escort_rl.modules.dvrl_networks.StateReadout`; with one, the
            policy also writes ``"state_estimate"``.
    """

    def __init__(self, dvrl: DVRL, observation_key: str = "observation", action_key: str = "action",
                 is_init_key: str = "is_init", state_prefix: str = "dvrl", readout: nn.Module | None = None) -> None:
        super().__init__()
        if not isinstance(dvrl, DVRL):
            raise TypeError(f"dvrl: expected a DVRL module, got {type(dvrl).__name__}")
        self.dvrl = dvrl
        self.readout = readout
        self.observation_key, self.action_key, self.is_init_key = observation_key, action_key, is_init_key
        self.state_keys = {name: f"{state_prefix}_{name}" for name in ("h", "z", "log_w", "prev_action")}
        self.elbo_key = f"{state_prefix}_elbo"
        self.summary_key = f"{state_prefix}_summary"
        self.in_keys = [observation_key, *self.state_keys.values(), is_init_key]
        self.out_keys = ["logits", action_key, "action_log_prob", "state_value", self.elbo_key, self.summary_key,
                         *(["state_estimate"] if readout is not None else []),
                         *(("next", key) for key in self.state_keys.values())]

    # ------------------------------------------------------------------------------ specs
    def make_tensordict_primer(self) -> TensorDictPrimer:
        """A ``TensorDictPrimer`` with ``Unbounded`` specs of the state (without the env batch dims,
        which the primer expands), filled on reset with fresh particles: zeros and ``log_w = -log K``."""
        m = self.dvrl
        k = m.num_particles
        keys = self.state_keys
        specs = {
            keys["h"]: Unbounded(shape=(k, m.hidden), dtype=torch.float32),
            keys["z"]: Unbounded(shape=(k, m.latent_dim), dtype=torch.float32),
            keys["log_w"]: Unbounded(shape=(k,), dtype=torch.float32),
            keys["prev_action"]: Unbounded(shape=(), dtype=torch.int64),
        }
        defaults = {keys["h"]: 0.0, keys["z"]: 0.0, keys["log_w"]: -math.log(k), keys["prev_action"]: 0}
        return TensorDictPrimer(specs, default_value=defaults, expand_specs=True)

    # ------------------------------------------------------------------------------ forward
    def read_state(self, tensordict: TensorDictBase) -> tuple[DVRLState, torch.Tensor, torch.Tensor]:
        """``(state, prev_action [N], is_init [N])`` with the env batch flattened to ``N``."""
        for key in (self.observation_key, *self.state_keys.values()):
            if key not in tensordict.keys():
                hint = ("append policy.make_tensordict_primer() to the env's transforms"
                        if key != self.observation_key else "the env must write it")
                raise KeyError(f"DVRLPolicy: '{key}' is missing from the tensordict; {hint}")
        if self.is_init_key not in tensordict.keys():
            raise KeyError(
                f"DVRLPolicy: '{self.is_init_key}' is missing from the tensordict; append "
                "torchrl.envs.InitTracker() to the env's transforms (it marks the first step of an episode)"
            )
        n = tensordict.batch_size.numel()
        m = self.dvrl
        state = DVRLState(
            tensordict.get(self.state_keys["h"]).reshape(n, m.num_particles, m.hidden),
            tensordict.get(self.state_keys["z"]).reshape(n, m.num_particles, m.latent_dim),
            tensordict.get(self.state_keys["log_w"]).reshape(n, m.num_particles),
        )
        prev_action = tensordict.get(self.state_keys["prev_action"]).reshape(n)
        is_init = tensordict.get(self.is_init_key).reshape(n)
        return state, prev_action, is_init

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.batch_size
        n = batch.numel()
        state, prev_action, is_init = self.read_state(tensordict)
        observation = tensordict.get(self.observation_key)
        observation = observation.reshape(n, *observation.shape[len(batch):])
        new_state, elbo, summary = self.dvrl.step(state, prev_action, observation, is_init)
        logits, value = self.dvrl.heads(summary)
        action, log_prob = sample_action(logits)

        def out(x: torch.Tensor) -> torch.Tensor:
            return x.reshape(*batch, *x.shape[1:])

        tensordict.set("logits", out(logits))
        tensordict.set(self.action_key, out(action))
        tensordict.set("action_log_prob", out(log_prob))
        tensordict.set("state_value", out(value.unsqueeze(-1)))
        tensordict.set(self.elbo_key, out(elbo))
        tensordict.set(self.summary_key, out(summary))
        if self.readout is not None:
            tensordict.set("state_estimate", out(self.readout(summary.detach())))
        for name, value_ in (("h", new_state.h), ("z", new_state.z), ("log_w", new_state.log_w),
                             ("prev_action", action)):
            tensordict.set(("next", self.state_keys[name]), out(value_))
        return tensordict

    # ------------------------------------------------------------------------------ training
    def replay(self, batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Re-run the belief along collected trajectories ``[E, T]``, with gradients, from the state
        stored at ``t = 0`` (for a loss; the particles are sampled afresh).

        Returns ``(logits [E, T, n_actions], value [E, T], elbo [E, T])``.
        """
        if batch.batch_dims != 2:
            raise ValueError(f"batch: expected a [E, T] tensordict, got batch_size {tuple(batch.batch_size)}")
        state, _, _ = self.read_state(batch[:, 0])
        e, t = batch.batch_size
        observations = batch.get(self.observation_key)
        actions_prev = batch.get(self.state_keys["prev_action"])
        reset = batch.get(self.is_init_key).reshape(e, t)
        _, elbo, summaries = self.dvrl.unroll(state, actions_prev, observations, reset)
        logits, value = self.dvrl.heads(summaries)
        return logits, value, elbo


def make_dvrl_primer(policy: DVRLPolicy) -> TensorDictPrimer:
    """The env-side primer of ``policy``'s recurrent state (see :meth:`DVRLPolicy.make_tensordict_primer`)."""
    return policy.make_tensordict_primer()
