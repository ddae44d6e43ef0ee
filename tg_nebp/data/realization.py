r"""The data model of :mod:`tg_nebp`.

**Snapshot** (one time step, what the convolutions consume) is a
:class:`torch_geometric.data.Data` with

* :obj:`edge_index` :obj:`[2, E]`: edge :obj:`j -> i` (:obj:`edge_index[0] = j`,
  :obj:`edge_index[1] = i`) means that agent :obj:`i` measured its range to
  node :obj:`j` (:obj:`j` may be an anchor; anchors never receive),
* :obj:`edge_attr` :obj:`[E, 1]`: the measured ranges in metres,
* :obj:`anchor` :obj:`[N]` bool: static nodes with perfectly known position,
* :obj:`pos` :obj:`[N, D]`: true positions (ground truth, for training and
  metrics only; trackers never read it),
* :obj:`batch` :obj:`[N]` when taken from a batch of realizations.

The filter state lives on the nodes: :obj:`particles` :obj:`[N, K, 2D]` and
:obj:`log_weights` :obj:`[N, K]` (state :math:`[\mathbf{p}, \mathbf{v}]`,
position then velocity, :math:`D = 2` or :math:`3` entries each: in 2-D
:math:`[p_x, p_y, v_x, v_y]`).

**Realization** (:math:`T` snapshots over the same :math:`N` nodes) is ONE
:class:`Realization`, so that PyG's :class:`~torch_geometric.loader.DataLoader`
batches realizations of different sizes into one disjoint graph:

* :obj:`states` :obj:`[N, T, 2D]`: true states at time steps :math:`1..T`
  (an agent's row all NaN: a node without ground truth, tracked and used
  but not scored: :func:`scored_of`),
* :obj:`edge_index` :obj:`[2, E_total]`, :obj:`edge_attr` :obj:`[E_total, 1]`:
  the edges of all time steps concatenated,
* :obj:`edge_time` :obj:`[E_total]`: the time index :math:`t \in [0, T)` of
  every edge (time step :math:`t + 1`),
* :obj:`anchor` :obj:`[N]`, :obj:`prior_mean` :obj:`[N, 2D]` and
  :obj:`prior_cov` :obj:`[N, 2D, 2D]`: the prior at time 0 (an anchor's prior
  mean is its known position with zero velocity and zero covariance),
* :obj:`num_steps`: :math:`T` (a tensor :obj:`[B]` in a batch; all graphs of
  a batch share :math:`T`),
* optionally :obj:`control` :obj:`[N, T, C]`: every agent's known input
  (odometry) of every step, for a motion model that takes one (a row of NaN:
  no input for that agent and step; anchors' rows are NaN),
* optionally :obj:`position_dim`: :math:`D` for a state layout other than
  :math:`[\mathbf{p}, \mathbf{v}]` (a robot's :math:`[x, y, \theta]`:
  :obj:`position_dim = 2`, the first :math:`D` entries being the position;
  without it the position is the first half of a state).

:meth:`Realization.snapshot` returns the snapshot at time :obj:`t` of a
single or a batched realization.
"""
import numbers

import torch
from torch_geometric.data import Data

__all__ = ['Realization', 'num_steps_of', 'position_dim_of', 'controls_of',
           'scored_of']


def scored_of(data: Data) -> torch.Tensor:
    r"""The nodes :math:`(N)` whose estimates a metric or a loss scores:
    the agents with ground truth (a real recording's node without it, its
    :obj:`states` row NaN, is tracked and its links used, but it has no
    error to count)."""
    known = ~torch.isnan(data.states).flatten(1).any(-1)
    return ~data.anchor & known


def position_dim_of(data: Data) -> int:
    r"""The dimension :math:`D` of the positions of a single or batched
    realization: its :obj:`position_dim` where it declares one (equal
    across a batch), else half its state size."""
    declared = getattr(data, 'position_dim', None)
    if declared is None:  # [p, v]: the first half of a state
        states = getattr(data, 'prior_mean', None)
        if states is None:
            states = data.states
        return states.size(-1) // 2
    dims = torch.as_tensor(declared).view(-1)
    if dims.numel() == 0 or bool((dims != dims[0]).any()):
        raise ValueError(f"'position_dim' must be equal across a batch, got "
                         f"{dims.tolist()}")
    return int(dims[0])


def controls_of(data: Data, use: bool = True) -> list:
    r"""The known inputs of every step of a single or batched
    realization (:meth:`Realization.controls_by_step`), or :math:`T`
    :obj:`None` where :obj:`use` is off (a method told to ignore them)."""
    if not use:
        return [None] * num_steps_of(data)
    return Realization.controls_by_step(data)


def num_steps_of(data: Data) -> int:
    r"""Returns the number of time steps :math:`T` of a single or batched
    realization, checking that all graphs of a batch agree."""
    try:
        steps = torch.as_tensor(data.num_steps).view(-1)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"'num_steps' must be an integer, got "
                         f"{data.num_steps!r}") from None
    if steps.is_floating_point() or steps.is_complex() \
            or steps.dtype == torch.bool:
        raise ValueError(f"'num_steps' must be an integer, got "
                         f"{steps.tolist()}")
    if steps.numel() == 0 or bool((steps != steps[0]).any()):
        raise ValueError(f"'num_steps' must be equal across a batch, got "
                         f"{steps.tolist()}")
    return int(steps[0])


class Realization(Data):
    r"""One cooperative-localization sequence: :math:`T` time steps of range
    measurements over :math:`N` nodes, stored as a single graph so that
    :class:`~torch_geometric.loader.DataLoader` batches sequences of different
    network sizes (see the module docstring for the fields).

    Batching needs no override of
    :meth:`~torch_geometric.data.Data.__inc__` or
    :meth:`~torch_geometric.data.Data.__cat_dim__`:
    :obj:`edge_index` is incremented by the number of nodes, every node and
    edge field (:obj:`states`, :obj:`prior_cov`, :obj:`edge_time`, ...) is
    concatenated along its first dimension, and the integer
    :obj:`num_steps` is stacked to :obj:`[B]`.
    """
    def __setattr__(self, key, value):
        # one type everywhere (a [1] tensor, as collation and slicing give),
        # so generated, loaded and hand-built realizations batch together
        if key in ('num_steps', 'position_dim') and isinstance(
                value, numbers.Integral) \
                and not isinstance(value, bool):
            value = torch.tensor([int(value)])
        super().__setattr__(key, value)

    @property
    def num_time_steps(self) -> int:
        r"""The number of time steps :math:`T` as an :obj:`int`
        (:obj:`num_steps` stores it as a tensor, one entry per graph of a
        batch)."""
        return num_steps_of(self)

    def snapshot(self, t: int) -> Data:
        r"""Returns the snapshot at time index :obj:`t` (time step
        :math:`t + 1`) as a :class:`~torch_geometric.data.Data` with
        :obj:`edge_index`, :obj:`edge_attr`, :obj:`anchor`, :obj:`pos` (if
        true states are stored), :obj:`control` :math:`(N, C)` (if known
        inputs are) and :obj:`batch` (if batched).

        Args:
            t (int): Time index in :math:`[0, T)`.
        """
        if isinstance(t, torch.Tensor) and t.numel() == 1 and not (
                t.is_floating_point() or t.is_complex()
                or t.dtype == torch.bool):
            t = int(t)
        if not isinstance(t, numbers.Integral) or isinstance(t, bool):
            raise TypeError(f"'t' must be an integer time index, got "
                            f"{t!r}")
        steps = num_steps_of(self)
        if not 0 <= t < steps:
            raise ValueError(f"'t' = {t} is outside [0, {steps})")
        mask = self.edge_time == t
        snap = Data(edge_index=self.edge_index[:, mask],
                    edge_attr=self.edge_attr[mask], anchor=self.anchor,
                    num_nodes=self.num_nodes)
        states = getattr(self, 'states', None)
        if states is not None:
            snap.pos = states[:, t, :position_dim_of(self)]
        control = getattr(self, 'control', None)
        if control is not None:
            snap.control = control[:, t]
        batch = getattr(self, 'batch', None)
        if batch is not None:
            snap.batch = batch
            snap.ptr = self.ptr
        return snap

    def controls_by_step(self) -> list:
        r"""The known inputs of every time step, a list of :math:`T`
        tensors :math:`(N, C)` (:obj:`control` split by step), or of
        :math:`T` :obj:`None` for a realization without inputs."""
        control = getattr(self, 'control', None)
        if control is None:
            return [None] * num_steps_of(self)
        return list(control.unbind(1))

    def edges_by_step(self) -> list:
        r"""Splits the edges by time step in one pass: a list of :math:`T`
        :obj:`(edge_index, edge_attr)` pairs, each sorted by receiver (so that
        aggregation can use a deterministic segment sum)."""
        steps = num_steps_of(self)
        # one sort by (time, receiver) instead of T boolean masks
        # in int64: int8/int16 time indices would overflow the key
        edge_time = self.edge_time.long()
        key = edge_time * self.num_nodes + self.edge_index[1].long()
        order = torch.argsort(key, stable=True)
        counts = torch.bincount(edge_time, minlength=steps).tolist()
        return list(zip(self.edge_index[:, order].split(counts, dim=1),
                        self.edge_attr[order].split(counts, dim=0)))
