from .realization import Realization, num_steps_of, position_dim_of, scored_of
from .validation import (check_graph, check_link_features, check_particles,
                         check_prior, check_realization, check_anchor,
                         check_state_dim, check_control,
                         MAX_PRIOR_VARIANCE)

__all__ = [
    'Realization',
    'num_steps_of',
    'check_graph',
    'check_link_features',
    'check_particles',
    'check_prior',
    'check_realization',
    'check_anchor',
    'check_state_dim',
    'check_control',
    'MAX_PRIOR_VARIANCE',
    'position_dim_of',
    'scored_of',
]
