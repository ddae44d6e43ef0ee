from .conv import EquivariantNEBPConv, NEBPConv, ParticleBPConv

__all__ = ['ParticleBPConv', 'NEBPConv', 'EquivariantNEBPConv']
