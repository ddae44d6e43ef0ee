from .conv import *  # noqa: F401,F403
from .conv import __all__ as conv_all

__all__ = list(conv_all)
