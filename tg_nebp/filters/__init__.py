from .resampling import (RESAMPLERS, effective_sample_size,
                         multinomial_resample,
                         residual_resample, silverman_bandwidth,
                         stratified_resample, systematic_resample)
from .state import FIELD_KINDS, StateField, check_state
from .tracker import Smoothed, StepOutput, Tracker, TrackOutput
from .particle_bp import ParticleBP, ParticleState
from .nebp import NEBP
from .centralized_iekf import CentralizedIEKF, JointState
from .centralized_smoother import CentralizedSmoother
from .incremental_smoother import IncrementalSmoother, SmootherState
from .gaussian_bp import (GBP_RECOMMENDED, GaussianBP, GaussianState,
                          SolvedStep)
from .gaussian_nebp import GaussianNEBP, LearnedCorrection
from .fixed_lag_gbp import (FIXED_LAG_RECOMMENDED, FixedLagGaussianBP,
                            WindowState)
from .fixed_lag_gaussian_nebp import FixedLagGaussianNEBP
from .relocation import LinkSearch, SearchResult
from .noise_adaptation import NoiseAdaptation
from .hybrid_bp import HYBRID_RECOMMENDED, HybridBP
from .session import TrackingSession
from .session_inputs import AgentPrior, AnchorAt
from .partitioned_gbp import (Partition, PartitionedFixedLagGaussianBP,
                              PartitionedGaussianBP, PartitionedTracker,
                              partition, strips)
from tg_nebp.data.validation import check_state_dim
from tg_nebp.utils import weighted_moments

__all__ = [
    'Tracker',
    'ParticleBP',
    'NEBP',
    'CentralizedIEKF',
    'CentralizedSmoother',
    'IncrementalSmoother',
    'SmootherState',
    'Smoothed',
    'GaussianBP',
    'GaussianNEBP',
    'LearnedCorrection',
    'FixedLagGaussianBP',
    'FixedLagGaussianNEBP',
    'FIXED_LAG_RECOMMENDED',
    'WindowState',
    'HybridBP',
    'HYBRID_RECOMMENDED',
    'LinkSearch',
    'SearchResult',
    'NoiseAdaptation',
    'SolvedStep',
    'PartitionedGaussianBP',
    'PartitionedFixedLagGaussianBP',
    'PartitionedTracker',
    'TrackingSession',
    'GaussianState',
    'JointState',
    'ParticleState',
    'AgentPrior',
    'AnchorAt',
    'Partition',
    'partition',
    'strips',
    'GBP_RECOMMENDED',
    'StepOutput',
    'TrackOutput',
    'StateField',
    'FIELD_KINDS',
    'check_state',
    'check_state_dim',
    'weighted_moments',
    'multinomial_resample',
    'systematic_resample',
    'stratified_resample',
    'residual_resample',
    'effective_sample_size',
    'silverman_bandwidth',
    'RESAMPLERS',
]
