from .particle_bp_conv import ParticleBPConv
from .nebp_conv import NEBPConv
from .equivariant_nebp_conv import EquivariantNEBPConv
from .gaussian_bp_conv import (FactorMessages, Factors, GaussianBelief,
                               GaussianBPConv)

__all__ = ['ParticleBPConv', 'NEBPConv', 'EquivariantNEBPConv',
           'GaussianBPConv', 'GaussianBelief', 'FactorMessages', 'Factors']
