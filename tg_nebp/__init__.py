r"""tg_nebp: particle belief propagation and Neural Enhanced BP for
cooperative localization, as PyTorch Geometric layers."""
from tg_nebp import metrics
from tg_nebp.data import Realization
from tg_nebp.datasets import CooperativeLocalizationDataset, Scenario
from tg_nebp.filters import (NEBP, GaussianBP, GaussianNEBP, ParticleBP,
                             multinomial_resample, systematic_resample)
from tg_nebp.models import (ConstantVelocity, ConstantVelocityDrag,
                            GaussianRange, MeasurementModel, MotionModel,
                            NLOSRange, RangeModel, StudentTRange)
from tg_nebp.nn import (EquivariantNEBPConv, GaussianBPConv,
                        GaussianNEBPConv, NEBPConv, ParticleBPConv)
from tg_nebp.utils import weighted_moments

__version__ = '0.1.0'

__all__ = [
    'ParticleBPConv',
    'NEBPConv',
    'EquivariantNEBPConv',
    'GaussianBPConv',
    'GaussianNEBPConv',
    'ParticleBP',
    'NEBP',
    'GaussianBP',
    'GaussianNEBP',
    'CooperativeLocalizationDataset',
    'Scenario',
    'Realization',
    'MotionModel',
    'MeasurementModel',
    'RangeModel',
    'ConstantVelocityDrag',
    'ConstantVelocity',
    'GaussianRange',
    'StudentTRange',
    'NLOSRange',
    'multinomial_resample',
    'systematic_resample',
    'weighted_moments',
    'metrics',
    '__version__',
]
