from .conv import (EquivariantNEBPConv, GaussianBPConv, GaussianNEBPConv,
                   NEBPConv, ParticleBPConv)

__all__ = ['ParticleBPConv', 'NEBPConv', 'EquivariantNEBPConv',
           'GaussianBPConv', 'GaussianNEBPConv']
