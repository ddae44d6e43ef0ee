r"""The models a tracker or bound takes when given none: the paper's.
Apart from the roles (:mod:`tg_nebp.models.base`), which the concrete
models import, so that no module of the roles imports a model."""
from typing import Optional

from tg_nebp.models.base import MeasurementModel, MotionModel
from tg_nebp.models.measurement import GaussianRange
from tg_nebp.models.motion import ConstantVelocityDrag

__all__ = ['resolve_models']


def resolve_models(motion: Optional[MotionModel] = None,
                   measurement: Optional[MeasurementModel] = None):
    r"""The motion and measurement models of a tracker or bound: the given
    ones, checked to be of their roles, or the paper's
    (:class:`~tg_nebp.models.ConstantVelocityDrag`,
    :class:`~tg_nebp.models.GaussianRange`); the measurement model bound
    to the motion model's state layout where that model declares one
    (:meth:`MeasurementModel.bind`)."""
    models = (motion or ConstantVelocityDrag(),
              measurement or GaussianRange())
    for name, model, role in zip(('motion', 'measurement'), models,
                                 (MotionModel, MeasurementModel)):
        if not isinstance(model, role):
            raise TypeError(f"'{name}' must be a {role.__name__}, got "
                            f"{model!r}")
    motion, measurement = models
    # a motion model of its own layout tells the measurement model where
    # the position (and heading) are
    if motion.state_dim is not None:
        measurement = measurement.bind(motion.layout(motion.state_dim))
    return motion, measurement
