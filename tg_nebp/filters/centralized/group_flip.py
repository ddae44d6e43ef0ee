r"""The flip of whole groups of agents across the agents they hang on: a
group that never ranges to an anchor and ranges to the rest through agents
on a line (a plane in 3-D) fits its links as well on the line's other
side, and a solver started on the wrong side stays there. A component of
:class:`~tg_nebp.filters.CentralizedSmoother` with :obj:`lag=None` (its
:obj:`flip`)."""
from typing import List, Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.data.validation import check_number
from tg_nebp.filters.centralized.particle_trajectory_search import (
    connected_groups, linked_agents)
from tg_nebp.filters.gaussian.trajectory_search import mirror_transforms
from tg_nebp.models import inputs

__all__ = ['GroupFlip']

#: The most Gauss-Newton steps that set a reflected velocity (a linear
#: motion model needs one; they stop at a change of 1e-9).
_CARRIED_STEPS = 10


class GroupFlip:
    r"""The flip of connected groups of agents that never range to an
    anchor across the hyperplane of their outside neighbours, step by
    step: the flip ambiguity of a group hinged on too few agents, the
    classic failure of range-only localization in sparse networks
    (`"Robust distributed network localization with noisy range
    measurements" <https://doi.org/10.1145/1031495.1031502>`_, Moore,
    Leonard, Rus and Teller, SenSys 2004), tried with the whole sequence's
    hindsight and kept only where the smoother's own cost says so (a
    component of :class:`~tg_nebp.filters.CentralizedSmoother` with
    :obj:`lag=None`, after the :obj:`exchange` and before the
    :obj:`search`).

    1. The groups: the agents that range to no anchor at any step, split
       into groups connected by their links (any step), those of two or
       more agents, the largest first. Such a group is placed only
       relative to other agents; a flip keeps every range within it (not
       a bearing, nor a unicycle's odometry turns, which a reflection
       contradicts: there the flip is tried and its cost refuses it). A
       single agent is left to the :obj:`search`, whose particles reach
       its mirror; a group's are out of their reach, since the search
       moves one agent at a time, its neighbours held.
    2. Each group in turn: at every step :math:`k`, its outside
       neighbours :math:`\mathcal{H}_k` (the agents outside it that it
       ranged to at step :math:`k`, or, where fewer than :math:`D`, at the
       nearest steps, their positions at step :math:`k` of the current
       solution) and the hyperplane that best fits them in least squares
       (the line in 2-D; the same fit as the mirror of
       :class:`~tg_nebp.filters.TrajectorySearch`). The flip
       keeps the group's ranges to its neighbours only as far as they lie
       on it, so a group whose neighbours lie off it by more than
       :obj:`spread` metres (the root mean square of their distances, the
       median over the steps) is not tried, nor one with fewer than
       :math:`D` outside neighbours over the whole sequence (a rotation,
       not a flip).
    3. The group's states at every step are reflected across its step's
       hyperplane (:meth:`MotionModel.rigidly_moved
       <tg_nebp.models.MotionModel.rigidly_moved>`: positions
       :math:`\mathbf{p} \mapsto \mathbf{R}_k \mathbf{p} + \mathbf{b}_k`,
       the velocity by :math:`\mathbf{R}_k`, a heading on the lift of the
       step before), the others keeping theirs. Where the hyperplane moves
       from step to step, a velocity so reflected does not carry the
       reflected positions along, so each velocity is then set by the
       motion model's own mean and Jacobian to carry its position to the
       next step's as the original's carried it, reflected (exact for a
       linear model). The whole sequence's Gauss-Newton iterations start
       from there, and the optimum they reach replaces the solution where
       its cost
       (:meth:`~tg_nebp.filters.CentralizedSmoother.sequence_cost`) is
       lower by more than :obj:`margin` nats (any finite cost where the
       solution's is NaN).

    The cost never rises. Each tried group costs one solve of the whole
    sequence. No random draws.

    Args:
        spread (float, optional): The metres by which a group's outside
            neighbours may lie off their hyperplane (root mean square, the
            median over the steps) for its flip to be tried.
            (default: :obj:`2.5`)
        margin (float, optional): The nats by which a flipped optimum must
            beat the kept one. (default: :obj:`10.0`)
    """
    def __init__(self, spread: float = 2.5, margin: float = 10.0):
        self.spread = check_number(spread, 'spread')
        self.margin = check_number(margin, 'margin')

    def flipped(self, smoother, base, slots: List, kept: Tuple) -> Tuple:
        r"""The smoother's whole-sequence solution :obj:`kept` (as its
        Gauss-Newton iterations return it: per step the agents' states
        :math:`(A, S)`, and the forward-backward pass there) after the
        flips that lower its cost, in the same form."""
        cost = float(smoother._cost_of(base, slots, kept[0]))
        if cost != cost:  # a NaN solution: any finite one is better
            cost = float('inf')
        for group in self.groups(slots, kept[0][0].size(0)):
            start = self.reflected(smoother, slots, kept[0], group)
            if start is None:
                continue
            trial = smoother._solve(base, slots, start)
            trial_cost = float(smoother._cost_of(base, slots, trial[0]))
            # a NaN cost never compares lower
            if trial_cost < cost - self.margin:
                kept, cost = trial, trial_cost
        return kept

    @staticmethod
    def groups(slots: List, count: int) -> List[Tensor]:
        r"""The :obj:`count` agents that range to no anchor at any step of
        :obj:`slots` (the smoother's steps), as groups connected by their
        links, those of two or more agents: the index tensors of their
        agents, ascending, the largest group first (the one of the lowest
        agent among equal sizes)."""
        device = slots[0].receiver.device
        anchored = torch.zeros(count, dtype=torch.bool, device=device)
        for slot in slots:
            # an anchor's end is -1 (its state is the link's 'known')
            anchored[slot.receiver[(slot.sender < 0) & (
                slot.receiver >= 0)]] = True
            anchored[slot.sender[(slot.receiver < 0) & (
                slot.sender >= 0)]] = True
        return [group for group in connected_groups(
            linked_agents(slots, count, device), ~anchored)
            if group.numel() > 1]

    def reflected(self, smoother, slots: List, points: List[Tensor],
                  group: Tensor) -> Optional[List[Tensor]]:
        r"""The solution :obj:`points` (per step the agents' states
        :math:`(A, S)`) with the agents of :obj:`group` reflected at every
        step across the hyperplane of their outside neighbours, or
        :obj:`None` where the flip is not tried (fewer than :math:`D`
        outside neighbours over the whole sequence, neighbours farther
        than :obj:`spread` off their hyperplane, or a solution that is
        not finite there)."""
        count, size = points[0].shape
        dim = smoother.measurement.position_dim(size)
        inside = torch.zeros(count, dtype=torch.bool,
                             device=points[0].device)
        inside[group] = True
        # each step's outside neighbours, as a mask over the agents
        outside = []
        for slot in slots:
            both = (slot.sender >= 0) & (slot.receiver >= 0)
            sender, receiver = slot.sender[both], slot.receiver[both]
            mask = torch.zeros_like(inside)
            mask[sender[inside[receiver] & ~inside[sender]]] = True
            mask[receiver[inside[sender] & ~inside[receiver]]] = True
            outside.append(mask)
        if int(torch.stack(outside).any(0).sum()) < dim:
            return None
        hinges, owner = [], []
        for k in range(len(slots)):
            # the nearest steps' neighbours where this step's are too few
            mask, reach = outside[k], 0
            while int(mask.sum()) < dim:
                reach += 1
                for near in (k - reach, k + reach):
                    if 0 <= near < len(slots):
                        mask = mask | outside[near]
            hinges.append(points[k][mask, :dim])
            owner.append(torch.full((int(mask.sum()), ), k,
                                    device=mask.device))
        hinge, owner = torch.cat(hinges), torch.cat(owner)
        if not bool(torch.isfinite(hinge).all()) or not all(
                bool(torch.isfinite(here[group]).all()) for here in points):
            return None  # a NaN solution has no hyperplane to flip across
        rotation, offset = mirror_transforms(hinge, owner, len(slots), dim)
        # a point's distance from the hyperplane is half its move by the
        # reflection
        off = 0.5 * (hinge - (rotation[owner] @ hinge.unsqueeze(-1)).squeeze(
            -1) - offset[owner]).norm(dim=-1)
        spread = (torch.zeros(len(slots), dtype=off.dtype,
                              device=off.device).index_add(
            0, owner, off.square()) / torch.bincount(
            owner, minlength=len(slots))).sqrt()
        if not float(spread.median()) <= self.spread:
            return None
        layout = smoother.motion.layout(size)
        flipped = []
        for k, here in enumerate(points):
            moved = smoother.motion.rigidly_moved(here[group], rotation[k],
                                                  offset[k])
            if flipped:
                # each angle (a heading) on the lift of the step before,
                # as the iterations' transitions take it: a reflection
                # wraps each step's on its own
                moved = layout.nearest(moved, flipped[-1][group])
            flipped.append(here.index_copy(0, group, moved))
        return self._carried(smoother, slots, points, flipped, group,
                             rotation, layout)

    @staticmethod
    def _carried(smoother, slots: List, points: List[Tensor],
                 flipped: List[Tensor], group: Tensor, rotation: Tensor,
                 layout) -> List[Tensor]:
        # the reflected states with the rest of each (a velocity: not the
        # position, nor an angle) set so that the motion model's mean
        # carries the reflected position to the next step's reflected one
        # as it carried the original, reflected: where the hyperplane
        # moves between steps, a velocity reflected by its own step's
        # rotation does not follow the reflected positions, and the
        # iterations' roll-out through the model leaves the reflection.
        # Gauss-Newton on the model's own mean and Jacobian (one step for
        # a linear model such as the constant-velocity one, a few with
        # drag); the last step's change as the step before's, the
        # hyperplane moving on as it moved
        dim = layout.position_dim
        rest = [i for i in range(dim, points[0].size(1))
                if i not in layout.angles]
        if not rest:
            return flipped
        rest = torch.tensor(rest, device=group.device)
        motion = smoother.motion
        for k in range(len(points) - 1):
            control = slots[k + 1].control  # the group's inputs only
            given = inputs(None if control is None else control[group])
            # the original's move off the model's mean, reflected
            wanted = (rotation[k] @ (points[k + 1][group, :dim] - motion.mean(
                points[k][group], **given)[:, :dim]).unsqueeze(-1)
                      ).squeeze(-1)

            def missed(states):
                return flipped[k + 1][group, :dim] - motion.mean(
                    states, **given)[:, :dim] - wanted

            reflected = moved = flipped[k][group]
            for _ in range(_CARRIED_STEPS):
                jacobian = motion.jacobian(moved, **given)[:, :dim][
                    ..., rest]
                change = (torch.linalg.pinv(jacobian) @ missed(
                    moved).unsqueeze(-1)).squeeze(-1)
                moved = moved.index_add(1, rest, change)
                if not float(change.abs().amax()) > 1e-9:
                    break
            # kept only where it carries no worse (a Jacobian that nearly
            # vanishes, as drag's at high speed, can throw it off)
            if not float(missed(moved).norm()) <= float(
                    missed(reflected).norm()):
                moved = reflected
            flipped[k] = flipped[k].index_copy(0, group, moved)
        if len(points) > 1:
            flipped[-1] = flipped[-1].index_copy(0, group, flipped[-1][
                group] + moved - reflected)
        return flipped

    def settings(self) -> dict:
        return dict(flip='group', spread=self.spread, margin=self.margin)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(spread={self.spread}, '
                f'margin={self.margin})')

    def __eq__(self, other) -> bool:
        return isinstance(other, GroupFlip) and \
            self.settings() == other.settings()
