from .layout import StateLayout, wrap_angle
from .registry import MODELS, Model, model_from_config, model_like
from .base import (LinkPairRange, MeasurementModel, MotionModel, RangeModel,
                   links_within_range, redraw_negative)
from .motion import ConstantVelocity, ConstantVelocityDrag, UnicycleOdometry
from .measurement import (GaussianRange, NLOSRange, StudentTRange,
                          StudentTRangeBySensor)
from .range_bearing import (GaussianRangeBearing, RangeBearingModel,
                            StudentTRangeBearing)
from .defaults import resolve_models
from tg_nebp.utils import inputs

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
    'StudentTRangeBySensor',
    'StateLayout',
    'wrap_angle',
    'inputs',
    'links_within_range',
    'UnicycleOdometry',
    'RangeBearingModel',
    'GaussianRangeBearing',
    'StudentTRangeBearing',
]
