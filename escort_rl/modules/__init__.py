"""Policy and belief modules."""

from escort_rl.modules.deepsets import DeepSetsActor, make_deepsets_policy

__all__ = ["DeepSetsActor", "make_deepsets_policy"]
