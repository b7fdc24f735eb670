"""A continuous policy's head: a Gaussian put in the action box, under TorchRL's ``ProbabilisticActor``.

Every continuous-action policy of the package (the DeepSets policy on beliefs, the GRU on raw
observations) ends the same way: a network writes ``"normal_params"`` ``[*B, 2A]``,
``NormalParamExtractor`` splits it into ``"loc"`` and ``"scale"`` (``scale = max(biased_softplus(·),
min_scale)``), and a distribution puts the Gaussian in the box ``[low, high]``:

- ``tanh_normal`` (TorchRL's ``TanhNormal``): ``a = low + (high − low)·(tanh(u) + 1)/2``,
  ``u ~ N(loc, scale)``; its log-probability is the change of variables, and it has no closed-form
  entropy (``ClipPPOLoss`` estimates it by sampling).
- ``clipped_normal`` (:class:`~escort_rl.modules.clipped_normal.ClippedNormal`):
  ``a = clamp(c + h·u, low, high)`` (``c``, ``h`` the box's centre and half-width), with the clipped
  mass on the box's faces; its entropy is the Gaussian's.

The actor writes ``action_key`` (float ``[*B, A]``, inside the box) and ``"action_log_prob"`` ``[*B]``
(summed over the ``A`` dimensions).
"""

from __future__ import annotations

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from torch import Tensor
from torchrl.modules import ProbabilisticActor, TanhNormal

from escort_rl.modules.clipped_normal import ClippedNormal

DEFAULT_MIN_SCALE = 1e-4
"""The scale floor unless ``actor.min_scale`` says otherwise: TorchRL's ``NormalParamExtractor``'s own, which
every run saved before the key existed trained with."""

CONTINUOUS_DISTRIBUTIONS = {"tanh_normal": TanhNormal, "clipped_normal": ClippedNormal}
"""A continuous policy's law by its ``actor.distribution`` name."""

DEFAULT_DISTRIBUTION = "clipped_normal"
"""The law of a continuous policy unless ``actor.distribution`` says otherwise."""

SAVED_RUN_DISTRIBUTION = "tanh_normal"
"""The law of a run saved before ``actor.distribution`` existed: it loads with the TanhNormal it trained with."""


def check_action_box_pair(action_box, n_outputs: int) -> tuple[Tensor, Tensor]:
    """``action_box`` as float32 ``(low, high)`` ``[A]`` for a network of ``n_outputs = 2A`` outputs;
    ``ValueError`` naming ``action_box`` otherwise (not a pair, shapes that disagree, bounds not finite or
    not ``low < high``)."""
    if not isinstance(action_box, (tuple, list)) or len(action_box) != 2:
        raise ValueError(f"action_box: expected a pair (low, high) of tensors [A], got {type(action_box).__name__} "
                         f"of {len(action_box) if hasattr(action_box, '__len__') else 'no'} items")
    low, high = (torch.as_tensor(b, dtype=torch.float32) for b in action_box)
    if low.ndim != 1 or low.shape != high.shape or n_outputs != 2 * low.shape[0]:
        raise ValueError(f"action_box: expected (low, high) of shape [A] for an actor with n_actions = 2A, got shapes "
                         f"{tuple(low.shape)}, {tuple(high.shape)} and n_actions {n_outputs}")
    if not bool((torch.isfinite(low) & torch.isfinite(high) & (low < high)).all()):
        raise ValueError(f"action_box: expected finite bounds with low < high in every dimension (the policy "
                         f"puts its Gaussian in the box), got low {low.tolist()} and high {high.tolist()}")
    return low, high


def normal_params(min_scale: float = DEFAULT_MIN_SCALE) -> TensorDictModule:
    """``"normal_params"`` ``[*B, 2A]`` -> ``"loc"``, ``"scale"`` ``[*B, A]`` (TorchRL's ``NormalParamExtractor``,
    ``scale = max(biased_softplus(·), min_scale)``)."""
    return TensorDictModule(NormalParamExtractor(scale_lb=min_scale), in_keys=["normal_params"],
                            out_keys=["loc", "scale"])


def gaussian_in_box(module: TensorDictModule | TensorDictSequential, action_box, n_outputs: int, *,
                    action_key: str = "action", distribution: str = DEFAULT_DISTRIBUTION) -> ProbabilisticActor:
    """The ``ProbabilisticActor`` over ``module`` (writing ``"loc"`` and ``"scale"`` ``[*B, A]``, e.g. a network
    of ``n_outputs = 2A`` outputs followed by :func:`normal_params`) whose action is ``distribution``'s
    Gaussian in ``action_box`` (see the module).

    Example:
        >>> from tensordict import TensorDict
        >>> net = TensorDictModule(torch.nn.Linear(3, 4), in_keys=["obs"], out_keys=["normal_params"])
        >>> box = (-torch.ones(2), torch.ones(2))
        >>> policy = gaussian_in_box(TensorDictSequential(net, normal_params()), box, 4, distribution="clipped_normal")
        >>> policy(TensorDict({"obs": torch.randn(5, 3)}, [5]))["action"].shape
        torch.Size([5, 2])
    """
    if distribution not in CONTINUOUS_DISTRIBUTIONS:
        raise ValueError(f"distribution: expected one of {sorted(CONTINUOUS_DISTRIBUTIONS)}, got {distribution!r}")
    low, high = check_action_box_pair(action_box, n_outputs)
    return ProbabilisticActor(module, in_keys=["loc", "scale"], out_keys=[action_key],
                              distribution_class=CONTINUOUS_DISTRIBUTIONS[distribution],
                              distribution_kwargs={"low": low, "high": high}, return_log_prob=True,
                              log_prob_key="action_log_prob")
