from .particle_bp_conv import ParticleBPConv
from .nebp_conv import NEBPConv
from .equivariant_nebp_conv import EquivariantNEBPConv
from .gaussian_bp_conv import (FactorMessages, Factors, GaussianBelief,
                               GaussianBPConv, Linearization, RangeMessages,
                               position_covariance)
from .gaussian_nebp_conv import (CorrectionFeatures, GaussianNEBPConv,
                                 bounded_log)
from .hybrid_bp_conv import HybridBPConv, SourceBeliefs

__all__ = ['ParticleBPConv', 'NEBPConv', 'EquivariantNEBPConv',
           'GaussianBPConv', 'GaussianBelief', 'FactorMessages',
           'RangeMessages', 'Factors', 'Linearization', 'GaussianNEBPConv',
           'CorrectionFeatures', 'bounded_log', 'position_covariance',
           'HybridBPConv', 'SourceBeliefs']
