"""POMDP models: the protocol, the paper's domains, a linear-Gaussian test model and a 1-D
Light-Dark planning problem (``LightDark1D``, not one of the benchmark domains). Each model owns its
parameters in one frozen dataclass, ``<Model>Params``."""

from escort_rl.models.hidden_goal import HiddenGoal, HiddenGoalParams
from escort_rl.models.kidnapped_robot import KidnappedRobot20D, KidnappedRobot20DParams
from escort_rl.models.light_dark import LightDark10D, LightDark10DParams
from escort_rl.models.light_dark_1d import LightDark1D, LightDark1DParams
from escort_rl.models.light_dark_continuous import LightDark10DContinuous
from escort_rl.models.linear_gaussian import LinearGaussian, LinearGaussianParams
from escort_rl.models.multi_target import MultiTargetTracking20D
from escort_rl.models.multi_target_params import MultiTargetTracking20DParams
from escort_rl.models.popgym_cartpole import POPGymCartPole, POPGymCartPoleParams
from escort_rl.models.popgym_models import popgym_model_class
from escort_rl.models.popgym_pendulum import POPGymPendulum, POPGymPendulumParams
from escort_rl.models.protocol import POMDPModel, check_model, has_goal, position_dims, position_error, velocity_dims
from escort_rl.models.task_spaces import TaskSpaces

# The paper's domains by their config name (``configs/env/<name>.yaml``).
DOMAINS = {"lightdark10d": LightDark10D, "kidnapped20d": KidnappedRobot20D, "mtt20d": MultiTargetTracking20D}
# Every domain with a gymnasium id (escort_rl/envs/registration.py): the paper's and their variants.
GYM_DOMAINS = {**DOMAINS, "lightdark10d_continuous": LightDark10DContinuous}

__all__ = ["DOMAINS", "GYM_DOMAINS", "HiddenGoal", "HiddenGoalParams", "KidnappedRobot20D",
           "KidnappedRobot20DParams", "LightDark10D", "LightDark10DContinuous", "LightDark10DParams", "LightDark1D",
           "LightDark1DParams", "LinearGaussian", "LinearGaussianParams", "MultiTargetTracking20D",
           "MultiTargetTracking20DParams", "POMDPModel", "POPGymCartPole", "POPGymCartPoleParams", "POPGymPendulum",
           "POPGymPendulumParams", "TaskSpaces", "check_model", "has_goal", "popgym_model_class", "position_dims",
           "position_error", "velocity_dims"]
