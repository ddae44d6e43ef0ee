from .resampling import (RESAMPLERS, effective_sample_size, multinomial_resample,
                         residual_resample, silverman_bandwidth,
                         stratified_resample, systematic_resample)
from .particle_bp import ParticleBP, StepOutput, TrackOutput
from .nebp import NEBP
from tg_nebp.utils import weighted_moments

__all__ = [
    'ParticleBP',
    'NEBP',
    'StepOutput',
    'TrackOutput',
    'weighted_moments',
    'multinomial_resample',
    'systematic_resample',
    'stratified_resample',
    'residual_resample',
    'effective_sample_size',
    'silverman_bandwidth',
    'RESAMPLERS',
]
