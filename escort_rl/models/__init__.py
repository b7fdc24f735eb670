"""POMDP models: the protocol, the paper's domains and a linear-Gaussian test model."""

from escort_rl.models.light_dark import LightDark10D
from escort_rl.models.linear_gaussian import LinearGaussian
from escort_rl.models.protocol import POMDPModel, check_model

__all__ = ["LightDark10D", "LinearGaussian", "POMDPModel", "check_model"]
