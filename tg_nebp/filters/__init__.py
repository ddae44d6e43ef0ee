from .resampling import multinomial_resample, systematic_resample, RESAMPLERS
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
    'RESAMPLERS',
]
