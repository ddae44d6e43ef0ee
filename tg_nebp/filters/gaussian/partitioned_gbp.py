r"""One network's agents spread over the ranks of a :obj:`torchrun` job:
Gaussian BP (and fixed-lag Gaussian BP) partitioned in space, every rank
iterating its own agents and exchanging the beliefs on the partition
borders after every iteration (a window's: every step of it).

Each rank holds the agents it owns (a strip of the area, :func:`strips`)
and a halo: the other ends of every link that touches its agents, with
those links. It computes every message of the factors that touch its
agents, in both directions, so the message from its agent to a halo node
(the reverse message that the next iteration removes) is its own; after
every iteration it receives the halo's beliefs from their owners
(:class:`PartitionedGaussianBP`). The nodes and links keep the order they
have in the whole network, so every agent sums its messages in the same
order, and each rank's agents get what one process gives them, bit for
bit."""
from typing import List, NamedTuple, Optional, Tuple

import torch
import torch.distributed as dist
from torch import Tensor

from tg_nebp.data.realization import Realization, position_dim_of
from tg_nebp.filters.gaussian.fixed_lag_gbp import FixedLagGaussianBP
from tg_nebp.filters.gaussian.gaussian_bp import GaussianBP
from tg_nebp.nn.conv.gaussian_bp_conv import GaussianBelief

__all__ = ['Partition', 'strips', 'partition', 'PartitionedTracker',
           'PartitionedGaussianBP', 'PartitionedFixedLagGaussianBP']


class Partition(NamedTuple):
    r"""One rank's part of a network (:func:`partition`): the nodes it
    holds, by their number in the whole network (:obj:`nodes`, sorted),
    which of them it owns (:obj:`owned`), and per rank the rows it sends
    there (:obj:`send`: its agents in that rank's halo) and receives from
    there (:obj:`receive`: that rank's agents in its halo), in the same
    order on both sides."""
    nodes: Tensor
    owned: Tensor
    send: List[Tensor]
    receive: List[Tensor]


def strips(data: Realization, num_parts: int) -> Tensor:
    r"""The part of every node :math:`(N)`: strips of equal node counts
    along the first coordinate of the prior means (a spatial partition, so
    that few links cross it)."""
    order = torch.argsort(data.prior_mean[:, 0], stable=True)
    part = torch.empty_like(order)
    part[order] = torch.arange(order.numel()) * num_parts // order.numel()
    return part


def _held(data: Realization, owner: Tensor, rank: int) -> Tensor:
    # the nodes a rank holds: its own and the other ends of their links
    mine = owner == rank
    src, dst = data.edge_index
    touches = mine[src] | mine[dst]
    held = mine.clone()
    held[src[touches]] = True
    held[dst[touches]] = True
    return held


def partition(data: Realization, owner: Tensor, rank: int,
              num_parts: Optional[int] = None
              ) -> Tuple[Realization, Partition]:
    r"""The realization that rank :obj:`rank` tracks (its nodes and every
    link that touches one of its own, numbered in the whole network's
    order) and its :class:`Partition`, for the parts :obj:`owner`
    :math:`(N)` (:func:`strips`) of :obj:`num_parts` ranks (the process
    group's size; by default the parts that :obj:`owner` names). A rank
    that would own no agent is refused up front, with the same
    :class:`ValueError` on every rank (each holds the whole network), so
    that no rank waits on a collective that another never joins."""
    if num_parts is None:
        num_parts = int(owner.max()) + 1
    if not 0 <= rank < num_parts or bool((owner < 0).any()) or \
            bool((owner >= num_parts).any()):
        raise ValueError(f"rank {rank} and the parts of 'owner' "
                         f"({int(owner.min())}-{int(owner.max())}) must lie "
                         f"in 0-{num_parts - 1} ({num_parts} ranks)")
    agents = ~data.anchor
    owned = torch.zeros(num_parts, dtype=torch.long).index_add_(
        0, owner[agents], torch.ones_like(owner[agents]))
    idle = (owned == 0).nonzero().view(-1).tolist()
    if idle:
        raise ValueError(f"ranks {idle} of {num_parts} own no agent (the "
                         f"network has {data.num_nodes} nodes, "
                         f"{int(agents.sum())} of them agents): every rank "
                         f"needs one; run at most {int(agents.sum())} ranks "
                         f"or give those ranks agents")
    held = [_held(data, owner, q) for q in range(num_parts)]
    nodes = held[rank].nonzero().view(-1)
    number = torch.full_like(owner, -1)
    number[nodes] = torch.arange(nodes.numel())
    mine = owner == rank
    src, dst = data.edge_index
    links = mine[src] | mine[dst]
    part = Realization(
        prior_mean=data.prior_mean[nodes], prior_cov=data.prior_cov[nodes],
        anchor=data.anchor[nodes],
        edge_index=number[data.edge_index[:, links]],
        edge_attr=data.edge_attr[links], edge_time=data.edge_time[links],
        num_steps=data.num_time_steps, num_nodes=nodes.numel())
    for key in ('states', 'control'):  # true states, known inputs
        value = getattr(data, key, None)
        if value is not None:
            setattr(part, key, value[nodes])
    if getattr(data, 'position_dim', None) is not None:
        part.position_dim = position_dim_of(data)
    send, receive = [], []
    for q in range(num_parts):
        if q == rank:
            send.append(nodes.new_zeros(0))
            receive.append(nodes.new_zeros(0))
            continue
        # agents of one rank in the other's halo, in node order
        send.append(number[(mine & held[q]).nonzero().view(-1)])
        receive.append(number[((owner == q) & held[rank]).nonzero().view(
            -1)])
    return part, Partition(nodes, mine[nodes], send, receive)


class PartitionedTracker:
    r"""The base of the partitioned trackers (put before the tracker it
    partitions, :class:`PartitionedGaussianBP`,
    :class:`PartitionedFixedLagGaussianBP`): what a rank adds to a Gaussian
    BP tracker, its :obj:`plan` (:class:`Partition`) and process
    :obj:`group`, the check that a realization is its part of one network,
    the exchange of its halo's rows with their owners and the stop decided
    over all ranks
    (:meth:`~tg_nebp.filters.PartitionedTracker.largest_moves`). The other
    arguments are the tracker's."""

    def __init__(self, plan: Partition, group=None, **options):
        super().__init__(**options)
        if dist.is_initialized():
            ranks = dist.get_world_size(group)
            if len(plan.send) != ranks:
                raise ValueError(f"the plan is for {len(plan.send)} ranks "
                                 f"but the process group has {ranks}: "
                                 f"partition() with num_parts={ranks}")
        self.plan = plan
        self.group = group

    def relocate_with(self, relocation):
        r"""Refuses a relocation (:class:`~tg_nebp.filters.LinkSearch`):
        a rank would search halo agents whose links it sees only in part,
        and move agents that other ranks hold as they were, so the ranks
        would no longer track as one process."""
        if relocation is not None:
            raise ValueError(f"'relocation' is not available to a "
                             f"partitioned tracker ({type(self).__name__}): "
                             f"the ranks would not track as one process; "
                             f"relocate in one process")
        return super().relocate_with(relocation)

    def check(self, data: Realization) -> None:
        r"""The realization checks of every tracker, and that it is one
        network (its part of one) and this rank's part of it."""
        super().check(data)
        if getattr(data, 'batch', None) is not None:
            raise ValueError("a partitioned Gaussian BP tracks one network, "
                             "not a batch")
        if data.num_nodes != self.plan.nodes.numel():
            raise ValueError(f"the realization holds {data.num_nodes} nodes "
                             f"but this rank's part has "
                             f"{self.plan.nodes.numel()}: track the "
                             f"realization that partition() gave with it")

    def _exchange_rows(self, rows: Tensor) -> Tensor:
        # every node's row with the halo's replaced by their owners'
        # (point-to-point)
        requests, received = [], []
        for q, (send, receive) in enumerate(zip(self.plan.send,
                                                self.plan.receive)):
            if send.numel():
                requests.append(dist.isend(rows[send].contiguous(), q,
                                           group=self.group))
            if receive.numel():
                buffer = rows.new_empty(receive.numel(), rows.size(1))
                requests.append(dist.irecv(buffer, q, group=self.group))
                received.append((receive, buffer))
        for request in requests:
            request.wait()
        rows = rows.clone()
        for receive, buffer in received:
            rows[receive] = buffer
        return rows

    def largest_moves(self, step: Tensor, graph_of: Tensor,
                      num_graphs: int) -> Tensor:
        r"""The largest move of a belief mean over all ranks (an
        all-reduce), so that every rank stops its iterations together."""
        largest = super().largest_moves(step, graph_of, num_graphs)
        dist.all_reduce(largest, dist.ReduceOp.MAX, group=self.group)
        return largest


class PartitionedGaussianBP(PartitionedTracker, GaussianBP):
    r"""Gaussian BP on one rank's part of a network (:func:`partition`),
    in a :obj:`torch.distributed` process group (gloo on CPU, nccl on a
    GPU): after every iteration the halo nodes' beliefs are replaced by
    their owners' (point-to-point), and a step's iterations stop when the
    largest move over all ranks is within the tolerance (an all-reduce).
    The other arguments are :class:`GaussianBP`'s. One network at a time
    (no batch).

    Args:
        plan (Partition): This rank's part.
        group (optional): The process group. (default: the default group)
    """
    def exchanged_bytes(self, state_dim: int, dtype=torch.float64) -> int:
        r"""The bytes this rank sends in one iteration: the mean and
        information of each of its agents in another rank's halo."""
        rows = sum(int(send.numel()) for send in self.plan.send)
        size = torch.finfo(dtype).bits // 8
        return rows * (state_dim + state_dim * state_dim) * size

    def iterate(self, prior, belief, *args):
        r"""One iteration of Gaussian BP on this rank's part, then the halo's
        beliefs from their owners (:meth:`exchange`)."""
        new, messages, memory = super().iterate(prior, belief, *args)
        return self.exchange(new), messages, memory

    def adapted_noise(self, memory, belief, *args):
        r"""The noise adaptation's memory after the step's links, the
        halo's replaced by their owners' (a rank sees a halo node's links
        in part; the scales temper the messages to the halo, which the
        extrinsic beliefs of the next iteration remove)."""
        return self._exchange_rows(super().adapted_noise(memory, belief,
                                                         *args))

    def exchange(self, belief: GaussianBelief) -> GaussianBelief:
        r"""The beliefs with the halo's replaced by their owners'."""
        size = belief.mean.size(-1)
        rows = self._exchange_rows(torch.cat([belief.mean,
                                              belief.info.flatten(1)], -1))
        return GaussianBelief(rows[:, :size],
                              rows[:, size:].view(-1, size, size))


class PartitionedFixedLagGaussianBP(PartitionedTracker,
                                    FixedLagGaussianBP):
    r"""Fixed-lag Gaussian BP (:class:`FixedLagGaussianBP`) on one rank's
    part of a network (:func:`partition`), in a :obj:`torch.distributed`
    process group: after every solve of the agents' chains (a step's
    first and every iteration's) the halo nodes' windows (their beliefs
    and covariances at every step of the window) are replaced by their
    owners' (:meth:`~tg_nebp.filters.PartitionedFixedLagGaussianBP.share`),
    and a step's iterations stop when the largest move over all ranks is
    within the tolerance. Each rank slides its own window; the halo's
    marginalized priors follow from the windows it received, so that every
    rank's agents get what one process gives them, bit for bit. The other
    arguments are :class:`FixedLagGaussianBP`'s. One network at a time (no
    batch).

    Args:
        plan (Partition): This rank's part.
        group (optional): The process group. (default: the default group)
    """
    def exchanged_bytes(self, state_dim: int, width: int,
                        dtype=torch.float64) -> int:
        r"""The bytes this rank sends in one iteration with a window of
        :obj:`width` steps: for each of its agents in another rank's halo,
        its mean, information and covariance at every step."""
        rows = sum(int(send.numel()) for send in self.plan.send)
        size = torch.finfo(dtype).bits // 8
        return rows * width * (state_dim + 2 * state_dim * state_dim) * size

    def share(self, belief: GaussianBelief, covs: Tensor):
        r"""The window's beliefs (step-major rows) and covariances
        :math:`(N, W, S, S)` with the halo nodes' replaced by their
        owners': every step of a node's window in one row."""
        num, width, size = covs.shape[:3]
        parts = [belief.mean.view(width, num, size).transpose(0, 1),
                 belief.info.view(width, num, size, size).transpose(0, 1),
                 covs]
        rows = self._exchange_rows(torch.cat(
            [part.reshape(num, -1) for part in parts], -1))
        mean, info, cov = rows.split(
            [width * size, width * size * size, width * size * size], -1)
        return (GaussianBelief(
            mean.reshape(num, width, size).transpose(0, 1).reshape(-1, size),
            info.reshape(num, width, size, size).transpose(0, 1).reshape(
                -1, size, size)),
            cov.reshape(num, width, size, size))
