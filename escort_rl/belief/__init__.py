"""Particle beliefs and the filters that update them: SIR, EnKF, SVGD and ESCORT."""

from escort_rl.belief.base import BeliefFilter, validate_update_inputs
from escort_rl.belief.checks import NonFiniteError
from escort_rl.belief.enkf import EnKFFilter
from escort_rl.belief.escort import ESCORTFilter, SVGDFilter
from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.belief.sir import SIRFilter, systematic_resample_indices

__all__ = [
    "BeliefFilter",
    "EnKFFilter",
    "ESCORTFilter",
    "NonFiniteError",
    "SVGDFilter",
    "ParticleBelief",
    "SIRFilter",
    "systematic_resample_indices",
    "validate_update_inputs",
]
