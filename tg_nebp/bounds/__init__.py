r"""What no estimator can beat: the posterior Cramér-Rao bound of a
realization."""
from .posterior_crb import BoundStep, PosteriorCRB

__all__ = ['PosteriorCRB', 'BoundStep']
