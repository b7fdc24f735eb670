"""Planners on the model protocol: POMCPOW, which plans on any filter's particle belief."""

from escort_rl.planners.planner_config import build_planner, load_planner_config, planner_domains
from escort_rl.planners.policy import POMCPOWPolicy
from escort_rl.planners.pomcpow import POMCPOW, Decision, POMCPOWParams
from escort_rl.planners.scripted import (
    ScriptedBeliefController,
    TrueStateController,
    pd_action,
    scripted_controller_for,
)

__all__ = ["POMCPOW", "Decision", "POMCPOWParams", "POMCPOWPolicy", "ScriptedBeliefController", "TrueStateController",
           "build_planner", "load_planner_config", "pd_action", "planner_domains", "scripted_controller_for"]
