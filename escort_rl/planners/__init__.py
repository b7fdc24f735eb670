"""Planners on the model protocol: POMCPOW, which plans on any filter's particle belief."""

from escort_rl.planners.planner_config import build_planner, load_planner_config, planner_domains
from escort_rl.planners.policy import POMCPOWPolicy
from escort_rl.planners.pomcpow import POMCPOW, Decision

__all__ = ["POMCPOW", "Decision", "POMCPOWPolicy", "build_planner", "load_planner_config", "planner_domains"]
