from .base import (MODELS, LinkPairRange, MeasurementModel, Model,
                   MotionModel, RangeModel, model_from_config, model_like,
                   redraw_negative, resolve_models)
from .motion import ConstantVelocity, ConstantVelocityDrag
from .measurement import GaussianRange, NLOSRange, StudentTRange

__all__ = [
    'Model',
    'MotionModel',
    'MeasurementModel',
    'RangeModel',
    'LinkPairRange',
    'MODELS',
    'model_from_config',
    'model_like',
    'resolve_models',
    'redraw_negative',
    'ConstantVelocityDrag',
    'ConstantVelocity',
    'GaussianRange',
    'StudentTRange',
    'NLOSRange',
]
