"""TorchRL transforms."""

from escort_rl.transforms.belief_transform import BeliefTransform

__all__ = ["BeliefTransform"]
