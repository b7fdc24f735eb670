"""TorchRL transforms."""

from escort_rl.transforms.action_repeat import ActionRepeat, action_repeat_of
from escort_rl.transforms.belief_transform import BeliefTransform

__all__ = ["ActionRepeat", "BeliefTransform", "action_repeat_of"]
