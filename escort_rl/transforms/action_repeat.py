"""ActionRepeat: each action held for ``repeat`` env steps, for batched and stateful-belief envs.

TorchRL's ``FrameSkipTransform`` steps the parent again with the *same* input tensordict and keeps
stepping envs that are already done. Both are wrong here: :class:`~escort_rl.transforms.BeliefTransform`
reads the prior belief from the input tensordict (so every inner step must see the belief the step
before it wrote), and in a batch of envs one that finishes mid-repeat must keep its final step. This
transform does both.

For one decision with action ``a`` it runs up to ``repeat`` steps of its parent env. Step ``j + 1``
reads what step ``j`` wrote (observation, belief, every key but reward and done flags) with the
same action. For each env it returns the output of the step where the env finished, or of the last
step, with

    reward = Σ_j r_j  (over the steps up to and including the one where the env finished),
    "repeats" = the number of those steps  (``[*B, 1]``, int64: what a frame counter adds).

Envs that are done early go on stepping with the others (the batch steps as one), but their
outputs are discarded; the collector resets them as usual.

Example:
    >>> from torchrl.envs import TransformedEnv, Compose
    >>> from escort_rl.models import LightDark10D
    >>> from escort_rl.envs import POMDPEnv
    >>> from escort_rl.belief import SIRFilter
    >>> from escort_rl.transforms import BeliefTransform, ActionRepeat
    >>> model = LightDark10D()
    >>> env = TransformedEnv(POMDPEnv(model, batch_size=(8,), seed=0, max_steps=500),
    ...                      Compose(BeliefTransform(model, SIRFilter(), 100), ActionRepeat(4)))
    >>> import torch
    >>> _ = torch.manual_seed(0)       # the rollout's random actions
    >>> td = env.rollout(10)           # 10 decisions, 40 env steps, 40 belief updates per env
    >>> td["next", "repeats"].shape
    torch.Size([8, 10, 1])
    >>> td["next", "repeats"].sum(1).squeeze(-1).tolist()  # 40 each (fewer where an episode ended)
    [40, 40, 40, 40, 40, 40, 40, 40]
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform


class ActionRepeat(Transform):
    """Hold each action for ``repeat`` steps of the parent env; rewards summed, done envs frozen.

    Args:
        repeat: env steps per decision (``>= 1``; 1 passes steps through and writes ``repeats = 1``).
        repeats_key: where the number of env steps the decision took is written, ``[*B, 1]`` int64.

    Shapes: unchanged except ``("next", repeats_key)`` ``[*B, 1]``.
    """

    def __init__(self, repeat: int, repeats_key: str = "repeats") -> None:
        if isinstance(repeat, bool) or not isinstance(repeat, int) or repeat < 1:
            raise ValueError(f"ActionRepeat.repeat: must be an integer >= 1, got {repeat!r}")
        super().__init__()
        self.repeat = repeat
        self.repeats_key = repeats_key

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec[self.repeats_key] = Unbounded(
            shape=(*observation_spec.shape, 1), dtype=torch.int64, device=observation_spec.device)
        return observation_spec

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        tensordict_reset.set(self.repeats_key, torch.zeros((*tensordict_reset.batch_size, 1), dtype=torch.int64,
                                                           device=tensordict_reset.device))
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        done = next_tensordict.get("done")  # [*B, 1]
        count = torch.ones(done.shape, dtype=torch.int64, device=done.device)
        if self.repeat > 1 and not bool(done.all()):
            parent = self.parent
            reward_key, done_keys = parent.reward_key, parent.done_keys
            reward = next_tensordict.get(reward_key)
            out = next_tensordict
            for _ in range(self.repeat - 1):
                carried = out.exclude(reward_key, *done_keys, self.repeats_key)
                new = parent._step(tensordict.clone(False).update(carried))
                live = ~done  # [*B, 1]: envs still running before this step
                reward = reward + torch.where(live, new.get(reward_key), torch.zeros_like(reward))
                count = count + live.long()
                out = new.where(live.squeeze(-1), out)  # envs done earlier keep their last step
                done = out.get("done")
                if bool(done.all()):
                    break
            next_tensordict = out.set(reward_key, reward)
        return next_tensordict.set(self.repeats_key, count)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError("ActionRepeat is an environment transform: append it to a TransformedEnv")


def action_repeat_of(env) -> int:
    """The env steps per decision of ``env``: the ``repeat`` of its :class:`ActionRepeat` (1 without one)."""
    transform = getattr(env, "transform", None)
    stack = [transform] if transform is not None else []
    while stack:
        t = stack.pop()
        if isinstance(t, ActionRepeat):
            return t.repeat
        stack.extend(getattr(t, "transforms", []))
    return 1
