from .particle_bp_conv import ParticleBPConv

__all__ = ['ParticleBPConv']
