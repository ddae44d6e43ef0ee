from .conv import NEBPConv, ParticleBPConv

__all__ = ['ParticleBPConv', 'NEBPConv']
