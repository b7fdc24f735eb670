"""Particle beliefs and the filters that update them (SIR now; SVGD and ESCORT build on the same interface)."""

from escort_rl.belief.base import BeliefFilter, validate_update_inputs
from escort_rl.belief.particle_belief import ParticleBelief
from escort_rl.belief.sir import SIRFilter, systematic_resample_indices

__all__ = [
    "BeliefFilter",
    "ParticleBelief",
    "SIRFilter",
    "systematic_resample_indices",
    "validate_update_inputs",
]
