r"""The centralized references: the iterated EKF over the joint of all
agents (or their marginals), the fixed-lag and full smoothers, and the
incremental smoother of the whole sequence (as iSAM2), and the full
smoother's search for better basins than its start's, exchange of groups
between its starts' optima and flip of groups hinged on a line."""
from .centralized_iekf import CentralizedIEKF, JointState
from .centralized_smoother import CentralizedSmoother
from .group_exchange import GroupExchange
from .group_flip import GroupFlip
from .incremental_smoother import IncrementalSmoother, SmootherState
from .particle_trajectory_search import (EscapeSweep,
                                         ParticleTrajectorySearch)

__all__ = [
    'CentralizedIEKF',
    'JointState',
    'CentralizedSmoother',
    'IncrementalSmoother',
    'SmootherState',
    'ParticleTrajectorySearch',
    'EscapeSweep',
    'GroupExchange',
    'GroupFlip',
]
