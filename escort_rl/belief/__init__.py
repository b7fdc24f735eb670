"""Particle beliefs and the filters that update them: SIR, EnKF, SVGD and ESCORT, and resample-move SMC
(tempered, with MCMC moves) for references."""

from escort_rl.belief import resampling
from escort_rl.belief.base import BeliefFilter, validate_update_inputs
from escort_rl.belief.checks import NonFiniteError
from escort_rl.belief.enkf import EnKFFilter, EnKFParams
from escort_rl.belief.escort import ESCORTFilter, ESCORTParams, SVGDFilter, SVGDParams
from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.belief.resample_move import ResampleMoveFilter, ResampleMoveParams
from escort_rl.belief.sir import SIRFilter, SIRParams

__all__ = [
    "BeliefFilter",
    "EnKFFilter",
    "EnKFParams",
    "ESCORTFilter",
    "ESCORTParams",
    "NonFiniteError",
    "SVGDFilter",
    "SVGDParams",
    "ParticleBelief",
    "ResampleMoveFilter",
    "ResampleMoveParams",
    "SIRFilter",
    "SIRParams",
    "resampling",
    "validate_update_inputs",
]
