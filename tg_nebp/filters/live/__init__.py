r"""The live session: any tracker stepped one time step at a time as
measurements arrive, nodes joining and leaving (priors and anchors by
identifier), its state saved and resumed."""
from .session_inputs import AgentPrior, AnchorAt
from .session import TrackingSession

__all__ = [
    'TrackingSession',
    'AgentPrior',
    'AnchorAt',
]
