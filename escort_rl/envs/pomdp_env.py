"""POMDPEnv: a batched TorchRL environment over any POMDP model."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from escort_rl.models.protocol import (
    action_in_range,
    action_shape,
    check_model,
    describe_action_range,
    is_continuous,
    null_action,
)


class POMDPEnv(EnvBase):
    """Runs a POMDP model on a batch of environments.

    The true state is held by the env (a stateful env, like a simulator). It is not an observation:
    only with ``expose_state=True`` (what training and evaluation use, for the asymmetric critic, the
    metrics and a prior placed around the start) is it written under ``"true_state"``, a key no policy
    module of this package reads; an env composed without it cannot leak the hidden state to a
    generic actor that reads every observation.

    Keys (``B`` = ``batch_size``):
        - ``"observation"``: ``[*B, obs_dim]``. At reset it is an observation of the start state
          (``model.observe(s_0, a=0)``); after a step, of the next state.
        - ``"true_state"``: ``[*B, d]``, the hidden state, with ``expose_state=True`` only.
        - ``"step_count"``: ``[*B, 1]`` int64, steps since the last reset.
        - ``"action"``: ``[*B]`` int64 in ``[0, n_actions)`` (a ``Categorical`` spec); for a model with
          continuous actions, ``[*B, action_dim]`` float32 in ``[action_low, action_high]`` (``Bounded``).
        - ``"reward"``: ``[*B, 1]``; ``"done"``, ``"terminated"``, ``"truncated"``: ``[*B, 1]`` bool.

    ``terminated`` is ``model.is_terminal(s')``; ``truncated`` is set after ``max_steps`` steps.
    Partial resets (a ``"_reset"`` mask ``[*B, 1]``) reset only the selected rows.

    Args:
        model: any object following :class:`escort_rl.models.POMDPModel`.
        batch_size: the batch of environments, e.g. ``(32,)``.
        device: where tensors live; defaults to CPU.
        seed: seeds the env's generator (also via :meth:`set_seed`).
        max_steps: episode length before truncation (``None``: never truncate).
        expose_state: write the hidden state under ``"true_state"`` (default False).
    """

    def __init__(self, model, batch_size=(1,), device=None, seed: int | None = None,
                 max_steps: int | None = None, expose_state: bool = False) -> None:
        check_model(model, densities=False)  # the env simulates; the filters' densities are not its concern
        given = batch_size
        try:
            batch_size = tuple(batch_size) if not isinstance(batch_size, int) else (batch_size,)
        except TypeError:  # e.g. a float
            batch_size = (given,)
        if not all(isinstance(b, int) and not isinstance(b, bool) and b >= 1 for b in batch_size):
            raise ValueError(f"POMDPEnv.batch_size: every size must be a positive int, got {given!r}")
        batch_size = torch.Size(batch_size)
        if max_steps is not None and (not isinstance(max_steps, int) or isinstance(max_steps, bool) or max_steps < 1):
            raise ValueError(f"POMDPEnv.max_steps: must be a positive int or None, got {max_steps!r}")
        if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool)):
            raise ValueError(f"POMDPEnv.seed: must be an int or None, got {seed!r}")
        device = check_device(device)
        super().__init__(device=device, batch_size=batch_size)
        if not isinstance(expose_state, bool):
            raise ValueError(f"POMDPEnv.expose_state: must be True or False, got {expose_state!r}")
        self.model = model
        self.max_steps = max_steps
        self.expose_state = expose_state
        self.generator = torch.Generator(device=self.device)
        if seed is not None:
            self.generator.manual_seed(seed)
        else:
            self.generator.seed()
        b = tuple(batch_size)
        state = ({"true_state": Unbounded(shape=(*b, model.state_dim), dtype=torch.float32, device=self.device)}
                 if expose_state else {})
        self.observation_spec = Composite(
            observation=Unbounded(shape=(*b, model.obs_dim), dtype=torch.float32, device=self.device),
            **state,
            step_count=Bounded(low=0, high=torch.iinfo(torch.int64).max, shape=(*b, 1),
                               dtype=torch.int64, device=self.device),
            shape=batch_size,
            device=self.device,
        )
        if is_continuous(model):
            self.action_spec = Bounded(low=model.action_low.to(self.device).expand(*b, model.action_dim),
                                       high=model.action_high.to(self.device).expand(*b, model.action_dim),
                                       shape=(*b, model.action_dim), dtype=torch.float32, device=self.device)
        else:
            self.action_spec = Categorical(model.n_actions, shape=b, dtype=torch.int64, device=self.device)
        self.reward_spec = Unbounded(shape=(*b, 1), dtype=torch.float32, device=self.device)
        flag = Categorical(2, shape=(*b, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone(),
                                   shape=batch_size, device=self.device)
        self._state = model.initial_state(b, self.generator).to(self.device)
        self._obs = torch.zeros(*b, model.obs_dim, device=self.device)
        self._steps = torch.zeros(*b, 1, dtype=torch.int64, device=self.device)

    @property
    def state(self) -> torch.Tensor:
        """The hidden states ``[*B, d]`` (a copy)."""
        return self._state.clone()

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(int(seed))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        if reset is None:
            rows = torch.ones(self.batch_size, dtype=torch.bool, device=self.device)
        else:
            rows = reset.reshape(self.batch_size)
        n = int(rows.sum())
        if n:
            s0 = self.model.initial_state((n,), self.generator).to(self.device)
            a0 = null_action(self.model, (n,), self.device)
            self._state[rows] = s0
            self._obs[rows] = self.model.observe(s0, a0, self.generator).to(self.device)
            self._steps[rows] = 0
        done = torch.zeros(*self.batch_size, 1, dtype=torch.bool, device=self.device)
        out = TensorDict(
            {
                "observation": self._obs.clone(),
                "step_count": self._steps.clone(),
                "done": done,
                "terminated": done.clone(),
                "truncated": done.clone(),
            },
            batch_size=self.batch_size,
            device=self.device,
        )
        if self.expose_state:
            out.set("true_state", self._state.clone())
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = check_action(tensordict.get("action"), self.batch_size, self.model)
        s = self._state
        s_next = self.model.transition(s, action, self.generator)
        obs = self.model.observe(s_next, action, self.generator)
        reward = self.model.reward(s, action, s_next).unsqueeze(-1)
        terminated = self.model.is_terminal(s_next).unsqueeze(-1)
        self._steps = self._steps + 1
        if self.max_steps is not None:
            truncated = (self._steps >= self.max_steps) & ~terminated
        else:
            truncated = torch.zeros_like(terminated)
        self._state, self._obs = s_next, obs
        out = TensorDict(
            {
                "observation": obs.clone(),
                "step_count": self._steps.clone(),
                "reward": reward.to(torch.float32),
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
            },
            batch_size=self.batch_size,
            device=self.device,
        )
        if self.expose_state:
            out.set("true_state", s_next.clone())
        return out


def check_device(device) -> torch.device:
    """``device`` (``None``: CPU) as a ``torch.device``; ``ValueError`` naming ``POMDPEnv.device`` when
    it is not a device or is a CUDA device this machine does not have."""
    try:
        dev = torch.device("cpu" if device is None else device)
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(f"POMDPEnv.device: not a device: {device!r}; use 'cpu', 'cuda' or 'cuda:N'") from None
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0 or (dev.index is not None and dev.index >= count):
            raise ValueError(f"POMDPEnv.device: {str(dev)!r} but this machine has {count} CUDA device(s); "
                             "use device='cpu'")
    return dev


def check_action(action, batch_size: torch.Size, model) -> torch.Tensor:
    """Validate an action batch for ``model``: integer indices of shape ``batch_size`` in
    ``[0, n_actions)``, or, for a model with continuous actions, finite floats of shape
    ``[*batch_size, action_dim]`` in ``[action_low, action_high]``.

    Raises ``ValueError`` naming the ``action`` field. Returns the action as int64 (as float32, real).
    """
    continuous = is_continuous(model)
    shape = torch.Size((*batch_size, *action_shape(model)))
    if not isinstance(action, torch.Tensor):
        raise ValueError(f"action: expected a tensor of shape {tuple(shape)}, got {type(action).__name__}")
    floating = action.dtype.is_floating_point
    if continuous and not floating:
        raise ValueError(f"action: expected real actions (float32) of shape {tuple(shape)} for a model with "
                         f"continuous actions, got dtype {action.dtype}")
    if not continuous and (floating or action.dtype == torch.bool or action.is_complex()):
        raise ValueError(
            f"action: expected integer action indices (int64) of shape {tuple(shape)}, "
            f"got dtype {action.dtype}"
        )
    if action.shape != shape:
        what = (f"one vector of model.action_dim = {model.action_dim} per env" if continuous
                else "one index per env; one-hot actions are not accepted")
        raise ValueError(f"action: expected shape {tuple(shape)} ({what}), got {tuple(action.shape)}")
    if action.numel() and not bool(action_in_range(model, action).all()):
        raise ValueError(f"action: {describe_action_range(model, action)}")
    return action.to(torch.float32) if continuous else action.long()
