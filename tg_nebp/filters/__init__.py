r"""The trackers: the time loop that every method shares
(:class:`Tracker`, the state of a tracker between steps), and its four
families, each a subpackage: ``tg_nebp.filters.particle`` (particle
BP, NEBP, the resamplers), ``tg_nebp.filters.gaussian`` (Gaussian BP,
its learned correction, their windows, hybrid BP, and the relocation, the
noise adaptation and the partitioned runs they take),
``tg_nebp.filters.centralized`` (the IEKF and the smoothers, the
references) and ``tg_nebp.filters.live`` (the live session). Every
public name is importable from here."""
import importlib
import sys

from .state import FIELD_KINDS, StateField, check_state
from .tracker import Smoothed, StepOutput, Tracker, TrackOutput
# every family's public names, listed once in its own __all__
from . import centralized, gaussian, live, particle
from .particle import *  # noqa: F401,F403
from .gaussian import *  # noqa: F401,F403
from .centralized import *  # noqa: F401,F403
from .live import *  # noqa: F401,F403
from tg_nebp.data.validation import check_state_dim
from tg_nebp.utils import weighted_moments

# the modules as they were before the families became subpackages
# (tg_nebp.filters.gaussian_bp is tg_nebp.filters.gaussian.gaussian_bp):
# the same module objects under their old names, so that an import of
# the old path keeps working
_FAMILIES = {
    'particle': ('particle_bp', 'nebp', 'resampling'),
    'gaussian': ('gaussian_bp', 'gaussian_nebp', 'fixed_lag_gbp',
                 'fixed_lag_gaussian_nebp', 'hybrid_bp', 'relocation',
                 'noise_adaptation', 'partitioned_gbp'),
    'centralized': ('centralized_iekf', 'centralized_smoother',
                    'incremental_smoother'),
    'live': ('session', 'session_inputs'),
}
for _family, _names in _FAMILIES.items():
    for _name in _names:
        _module = importlib.import_module(f'{__name__}.{_family}.{_name}')
        sys.modules[f'{__name__}.{_name}'] = _module
        globals()[_name] = _module
del _family, _names, _name, _module

# the shared time loop's names, then every family's
__all__ = [
    'Tracker',
    'StepOutput',
    'TrackOutput',
    'Smoothed',
    'StateField',
    'FIELD_KINDS',
    'check_state',
    'check_state_dim',
    'weighted_moments',
] + particle.__all__ + gaussian.__all__ + centralized.__all__ + live.__all__
