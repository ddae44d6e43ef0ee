from .resampling import multinomial_resample, systematic_resample, RESAMPLERS
from .particle_bp import ParticleBP, StepOutput, TrackOutput, weighted_moments

__all__ = [
    'ParticleBP',
    'StepOutput',
    'TrackOutput',
    'weighted_moments',
    'multinomial_resample',
    'systematic_resample',
    'RESAMPLERS',
]
