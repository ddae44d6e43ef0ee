r"""The Gaussian methods: Gaussian BP and its learned correction, their
windows (fixed-lag Gaussian BP, the correction inside a window), hybrid
BP (particles inside Gaussian BP), and what every Gaussian tracker takes:
the relocation of a lost agent, the noise adaptation, and one network's
agents spread over the ranks of a process group."""
from .noise_adaptation import NoiseAdaptation
from .relocation import LinkSearch, SearchResult
from .trajectory_search import (TrajectoryResult, TrajectorySearch,
                                WindowRelocation)
from .gaussian_bp import (GBP_RECOMMENDED, GaussianBP, GaussianState,
                          SolvedStep)
from .gaussian_nebp import GaussianNEBP, LearnedCorrection
from .window_state import SlidingWindow, WindowState
from .window_chain import WindowChains
from .fixed_lag_gbp import FIXED_LAG_RECOMMENDED, FixedLagGaussianBP
from .fixed_lag_gaussian_nebp import FixedLagGaussianNEBP
from .hybrid_bp import HYBRID_RECOMMENDED, HybridBP
from .partitioned_gbp import (Partition, PartitionedFixedLagGaussianBP,
                              PartitionedGaussianBP, PartitionedTracker,
                              partition, strips)

__all__ = [
    'GaussianBP',
    'GaussianState',
    'SolvedStep',
    'GBP_RECOMMENDED',
    'GaussianNEBP',
    'LearnedCorrection',
    'FixedLagGaussianBP',
    'FixedLagGaussianNEBP',
    'FIXED_LAG_RECOMMENDED',
    'WindowState',
    'SlidingWindow',
    'WindowChains',
    'HybridBP',
    'HYBRID_RECOMMENDED',
    'LinkSearch',
    'SearchResult',
    'TrajectorySearch',
    'TrajectoryResult',
    'WindowRelocation',
    'NoiseAdaptation',
    'PartitionedGaussianBP',
    'PartitionedFixedLagGaussianBP',
    'PartitionedTracker',
    'Partition',
    'partition',
    'strips',
]
