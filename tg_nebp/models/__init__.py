from .motion import ConstantVelocityDrag
from .measurement import GaussianRange

__all__ = ['ConstantVelocityDrag', 'GaussianRange']
