from .particle_bp_conv import ParticleBPConv
from .nebp_conv import NEBPConv

__all__ = ['ParticleBPConv', 'NEBPConv']
