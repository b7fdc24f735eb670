"""Policy and belief modules: the DeepSets policy on particle beliefs, DVRL (a learned belief), ESCORT-latent
(ESCORT over DVRL's learned latent) and a GRU actor-critic on frames."""

from escort_rl.modules.deepsets import DeepSetsActor, DeepSetsCritic, DeepSetsNet, make_deepsets_policy, policy_outputs
from escort_rl.modules.dvrl import DVRL, DVRLState
from escort_rl.modules.dvrl_torchrl import DVRLPolicy, make_dvrl_primer
from escort_rl.modules.escort_latent import ESCORTLatent
from escort_rl.modules.frame_gru import FrameGRU, FrameGRUPolicy
from escort_rl.modules.recurrent import make_recurrent_actor_critic

__all__ = ["DVRL", "DVRLPolicy", "DVRLState", "DeepSetsActor", "DeepSetsCritic",
           "DeepSetsNet", "ESCORTLatent", "FrameGRU", "FrameGRUPolicy",
           "make_deepsets_policy", "make_dvrl_primer", "make_recurrent_actor_critic", "policy_outputs"]
