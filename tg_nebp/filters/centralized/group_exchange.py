r"""The exchange of whole groups of agents between the optima that a whole
sequence's smoother reached from several starts: where each start lost a
different group, neither optimum is the better basin of both, and one
agent at a time cannot move a group that is wrong together. A component
of :class:`~tg_nebp.filters.CentralizedSmoother` with :obj:`lag=None` and
several starts (its :obj:`exchange`)."""
from typing import List, Tuple

import torch
from torch import Tensor

from tg_nebp.data.validation import check_number, check_positive_int
from tg_nebp.filters.centralized.particle_trajectory_search import (
    connected_groups, linked_agents)

__all__ = ['GroupExchange']


class GroupExchange:
    r"""The exchange of connected groups of agents between the optima of a
    whole-sequence smoother's starts: a crossover of two solutions, each
    move a whole group's trajectories at once, kept only where the
    smoother's own cost says so (a component of
    :class:`~tg_nebp.filters.CentralizedSmoother` with :obj:`lag=None` and
    several :obj:`start` trackers, or several states given to its
    :meth:`~tg_nebp.filters.CentralizedSmoother.smoothed_from`).

    From the optimum of lowest cost :math:`\hat{\mathbf{x}}`, for each
    other start's optimum :math:`\tilde{\mathbf{x}}` in order of cost:

    1. the agents whose trajectories differ, farther than
       :obj:`separation` metres apart at some step,

       .. math::
           \mathcal{D} = \{a : \max_k \|\hat{\mathbf{p}}^{(k)}_a -
           \tilde{\mathbf{p}}^{(k)}_a\| > \delta\},

       are split into groups connected by their links (two agents of
       :math:`\mathcal{D}` that ranged to each other at some step are in
       one group): a group that ranged among itself is wrong, or right,
       together, and a move of one of its agents alone breaks its links;
    2. each group, the largest first, takes its trajectories from
       :math:`\tilde{\mathbf{x}}`, the others keeping theirs; the whole
       sequence's Gauss-Newton iterations start from there, and the
       optimum they reach replaces :math:`\hat{\mathbf{x}}` where its cost
       (:meth:`~tg_nebp.filters.CentralizedSmoother.sequence_cost`) is
       lower by more than :obj:`margin` nats (any finite cost where
       :math:`\hat{\mathbf{x}}`'s is NaN);
    3. the groups are found again and exchanged, at most :obj:`rounds`
       times, while a round takes one.

    The cost never rises, and groups whose two basins the data do not
    separate by the margin stay where the better optimum put them. Each
    tried group costs one solve of the whole sequence. No random draws.

    Args:
        separation (float, optional): The metres at some step by which an
            agent's trajectories in the two optima must differ for it to
            join a group. (default: :obj:`2.0`)
        margin (float, optional): The nats by which an exchanged optimum
            must beat the kept one. (default: :obj:`10.0`)
        rounds (int, optional): Rounds at most, each over the groups found
            again. (default: :obj:`2`)
    """
    def __init__(self, separation: float = 2.0, margin: float = 10.0,
                 rounds: int = 2):
        self.separation = check_number(separation, 'separation')
        self.margin = check_number(margin, 'margin')
        self.rounds = check_positive_int(rounds, 'rounds')

    def exchanged(self, smoother, base, slots: List, kept: Tuple,
                  others: List[List[Tensor]]) -> Tuple:
        r"""The smoother's whole-sequence solution :obj:`kept` (as its
        Gauss-Newton iterations return it: per step the agents' states
        :math:`(A, S)`, the optimum of lowest cost, and the
        forward-backward pass there) after the exchanges with the other
        starts' optima :obj:`others` (each per step :math:`(A, S)`, in
        order of cost), in the same form."""
        cost = float(smoother._cost_of(base, slots, kept[0]))
        if cost != cost:  # a NaN optimum: any finite one is better
            cost = float('inf')
        for other in others:
            for _ in range(self.rounds):
                taken = False
                for group in self.groups(smoother, slots, kept[0], other):
                    start = [here.index_copy(0, group, there[group]) for
                             here, there in zip(kept[0], other)]
                    trial = smoother._solve(base, slots, start)
                    trial_cost = float(smoother._cost_of(base, slots,
                                                         trial[0]))
                    # a NaN cost never compares lower
                    if trial_cost < cost - self.margin:
                        kept, cost, taken = trial, trial_cost, True
                if not taken:
                    break
        return kept

    def groups(self, smoother, slots: List, points: List[Tensor],
               other: List[Tensor]) -> List[Tensor]:
        r"""The agents of :obj:`points` whose trajectories differ from
        :obj:`other`'s (each per step :math:`(A, S)`) by more than
        :obj:`separation` metres at some step, as groups connected by
        their links in :obj:`slots` (the smoother's steps): the index
        tensors of their agents, ascending, the largest group first (the
        one of the lowest agent among equal sizes)."""
        count, size = points[0].shape
        dim = smoother.measurement.position_dim(size)
        apart = (torch.stack(points)[..., :dim] - torch.stack(other)[
            ..., :dim]).norm(dim=-1).amax(0) > self.separation
        return connected_groups(linked_agents(slots, count, apart.device),
                                apart)

    def settings(self) -> dict:
        return dict(exchange='group', separation=self.separation,
                    margin=self.margin, rounds=self.rounds)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(separation={self.separation}, '
                f'margin={self.margin}, rounds={self.rounds})')

    def __eq__(self, other) -> bool:
        return isinstance(other, GroupExchange) and \
            self.settings() == other.settings()
