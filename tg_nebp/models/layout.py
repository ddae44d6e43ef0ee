r"""What the entries of a state are (:class:`StateLayout`, as a motion model
declares them) and the wrapping of angles (:func:`wrap_angle`): what
metrics, figures and every tracker read a state by."""
import math
from typing import NamedTuple, Tuple

import torch
from torch import Tensor

__all__ = ['StateLayout', 'wrap_angle']


def wrap_angle(angles: Tensor) -> Tensor:
    r"""Angles wrapped to :math:`(-\pi, \pi]` (the gradient is one
    everywhere, so a wrapped residual differentiates as the raw one)."""
    return math.pi - torch.remainder(math.pi - angles, 2 * math.pi)


class StateLayout(NamedTuple):
    r"""What the entries of a state are, as a motion model declares them
    (:meth:`MotionModel.layout`): :obj:`size` entries, the first
    :obj:`position_dim` of which are the position (what metrics, figures,
    link search and the range geometry read) and :obj:`angles` the indices
    of the entries that are angles (a robot's heading), which wrap.

    Inside the trackers an angle lives on the real line (a lift: a state
    and its prediction, the particles of one belief, never differ by a
    turn), so that sums and means of one belief's angles are the
    arithmetic ones; every residual of an angle is wrapped
    (:func:`wrap_angle`), and so is every angle that a tracker reports
    (:meth:`wrap`)."""
    size: int
    position_dim: int
    angles: Tuple[int, ...] = ()

    def positions(self, states: Tensor) -> Tensor:
        r"""The positions :math:`(*, D)` of states :math:`(*, S)`."""
        return states[..., :self.position_dim]

    def wrap(self, states: Tensor) -> Tensor:
        r"""The states :math:`(*, S)` with their angles wrapped to
        :math:`(-\pi, \pi]` (the same tensor where there is none)."""
        if not self.angles:
            return states
        out = states.clone()
        index = list(self.angles)
        out[..., index] = wrap_angle(states[..., index])
        return out

    def nearest(self, states: Tensor, reference: Tensor) -> Tensor:
        r"""The :obj:`states` :math:`(*, S)` with their angles moved by
        whole turns to within :math:`\pi` of those of :obj:`reference`
        (broadcast against them): a wrapped report put back on the lift
        of a belief, so that the two never differ by a turn (the same
        tensor where there is no angle)."""
        if not self.angles:
            return states
        out = states.clone()
        index = list(self.angles)
        near = reference[..., index]
        out[..., index] = near + wrap_angle(states[..., index] - near)
        return out
