from .particle_bp_conv import ParticleBPConv
from .nebp_conv import NEBPConv
from .equivariant_nebp_conv import EquivariantNEBPConv

__all__ = ['ParticleBPConv', 'NEBPConv', 'EquivariantNEBPConv']
