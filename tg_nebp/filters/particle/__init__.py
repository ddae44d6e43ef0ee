r"""The particle methods: particle BP (the paper's), NEBP (particle BP
whose messages a learned correction adjusts) and the resamplers they use
(pure functions in a registry)."""
from .resampling import (RESAMPLERS, effective_sample_size,
                         multinomial_resample, residual_resample,
                         silverman_bandwidth, stratified_resample,
                         systematic_resample)
from .particle_bp import ParticleBP, ParticleState
from .nebp import NEBP

__all__ = [
    'ParticleBP',
    'ParticleState',
    'NEBP',
    'multinomial_resample',
    'systematic_resample',
    'stratified_resample',
    'residual_resample',
    'effective_sample_size',
    'silverman_bandwidth',
    'RESAMPLERS',
]
