from .conv import (EquivariantNEBPConv, GaussianBPConv, NEBPConv,
                   ParticleBPConv)

__all__ = ['ParticleBPConv', 'NEBPConv', 'EquivariantNEBPConv',
           'GaussianBPConv']
