r"""The window of fixed-lag Gaussian BP as it slides: what the tracker
carries from step to step (:class:`WindowState`), one step's window of
space-time links and factors, and the bookkeeping that builds it, slides
it (:class:`SlidingWindow`, a part of
:class:`~tg_nebp.filters.FixedLagGaussianBP`)."""
import math
from typing import List, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.filters.gaussian.gaussian_bp import GaussianState, _inverse
from tg_nebp.filters.state import StateField
from tg_nebp.gaussian import bounded_inflation
from tg_nebp.models import MotionModel, inputs
from tg_nebp.nn.conv.gaussian_bp_conv import (FactorMessages, GaussianBelief,
                                              RangeMessages,
                                              as_factor_messages)

__all__ = ['WindowState', 'SlidingWindow']


class WindowState(NamedTuple):
    r"""What fixed-lag Gaussian BP carries from one time step to the next:
    the Gaussian that precedes the window (the fields of
    :class:`~tg_nebp.filters.GaussianState`: the filtered belief of the
    last step marginalized out, or the prior, :obj:`mean` :math:`(N, S)`,
    :obj:`cov` :math:`(N, S, S)`, :obj:`fresh`, :obj:`memory` and the
    :obj:`predicted` covariance that bounds its inflation), then the
    window of the :math:`W < L` steps after it: every node's means
    :obj:`window` :math:`(N, W, S)` (the linearization points; angles
    lifted), the links of every step :obj:`links` :math:`(2, E)` in
    space-time numbering (node :math:`i` at window step :math:`k` is
    :math:`kN + i`) with features :obj:`link_attr` :math:`(E, F)`, the
    time step of each step's transition :obj:`time_step` :math:`(W)` (NaN:
    the tracker's motion model), the nodes' known inputs :obj:`control`
    :math:`(N, W, C)` (NaN rows: none; :obj:`None` for a motion model
    without inputs), the last messages of the window's factors
    :obj:`messages` (the fields of
    :class:`~tg_nebp.nn.conv.RangeMessages` or
    :class:`~tg_nebp.nn.conv.FactorMessages`; :obj:`None` without links)
    on their message edges :obj:`message_index` :math:`(2, M)` (source,
    target; space-time numbering), and every node's first step in the
    window :obj:`start` :math:`(N)` (a node that joined a live session
    has no state before it; its Gaussian is the prior it joined with);
    with settled steps (:obj:`iterated`), the forward pass's filtered
    means :obj:`settled_mean` :math:`(N, C, S)` and covariances
    :obj:`settled_cov` :math:`(N, C, S, S)` of the window's first
    :math:`C` steps, where they still hold (:obj:`None`: none), and the
    states :obj:`entry_point` :math:`(N, S)` that the transition out of
    the Gaussian before the window is linearized at (the point of the
    step marginalized out, as the forward pass over the settled steps
    linearized it; :obj:`None`: the Gaussian's mean)."""
    mean: Tensor
    cov: Tensor
    fresh: Tensor
    memory: Optional[Tensor]
    predicted: Tensor
    window: Tensor
    links: Tensor
    link_attr: Tensor
    time_step: Tensor
    control: Optional[Tensor]
    messages: Optional[Tuple[Tensor, ...]]
    message_index: Optional[Tensor]
    start: Tensor
    settled_mean: Optional[Tensor] = None
    settled_cov: Optional[Tensor] = None
    entry_point: Optional[Tensor] = None

    FIELDS = dict(GaussianState.FIELDS,
                  window=StateField(('N', 'W', 'S')),
                  links=StateField(('2', 'E'), 'index'),
                  link_attr=StateField(('E', 'F')),
                  time_step=StateField(('W', ), 'nan'),
                  control=StateField(('N', 'W', 'C'), 'nan', optional=True),
                  messages=StateField(('M', '...'), optional=True,
                                      tuple=True),
                  message_index=StateField(('2', 'M'), 'index',
                                           optional=True),
                  start=StateField(('N', ), 'index'),
                  settled_mean=StateField(('N', 'C', 'S'), optional=True),
                  settled_cov=StateField(('N', 'C', 'S', 'S'), 'cov',
                                         optional=True),
                  entry_point=StateField(('N', 'S'), optional=True))


def renumbered(index: Tensor, num: int, num_new: int,
                node_map: Optional[Tensor] = None, shift: int = 0):
    # space-time indices (2, E) of 'num' nodes per step, k num + i, as
    # (k - shift) num_new + map[i]; the mask of the columns kept (both
    # ends at a step and node kept)
    if node_map is None and num_new == num:
        # the same nodes (a slide): k num + i - shift num, no division (a
        # long window's links and message edges are millions at scale)
        moved = index - shift * num
        keep = (moved >= 0).all(0)
        return moved[:, keep], keep
    slot, node = torch.div(index, num, rounding_mode='floor'), index % num
    if node_map is not None:
        node = node_map[node]
    slot = slot - shift
    keep = ((node >= 0) & (slot >= 0)).all(0)
    return (slot * num_new + node)[:, keep], keep


def _matched(old_index: Tensor, new_index: Tensor
             ) -> Tuple[Tensor, Tensor]:
    # the message edges of 'new_index' (2, M') that 'old_index' (2, M) has
    # too, by source and target: their positions in both
    if old_index.size(1) == 0 or new_index.size(1) == 0:
        empty = old_index.new_zeros(0)
        return empty, empty
    span = int(torch.cat([old_index, new_index], 1).max()) + 1
    old_key = old_index[0] * span + old_index[1]
    new_key = new_index[0] * span + new_index[1]
    order = torch.argsort(old_key)
    at = torch.searchsorted(old_key[order], new_key).clamp_max(
        old_key.numel() - 1)
    found = old_key[order][at] == new_key
    return found.nonzero().view(-1), order[at[found]]


class Window(NamedTuple):
    # one step's window: every node's prior at its first step (belief and
    # covariance) and that step, the motion models and inputs of its
    # transitions, the space-time links, anchor mask and factors
    prior: GaussianBelief
    prior_cov: Tensor
    start: Tensor
    motions: List[MotionModel]
    control: Optional[Tensor]
    links: Tensor
    link_attr: Tensor
    anchor: Tensor
    factors: object


class SlidingWindow:
    r"""The bookkeeping of :class:`~tg_nebp.filters.FixedLagGaussianBP`'s
    window as it slides (a part of the tracker, not a tracker of its own):
    the state before the first step, each step's window from the state
    (its priors, motion models and inputs, space-time links and factors),
    the messages and linearization points carried from the last step, and
    the slide that marginalizes the oldest step into the prior."""

    def _time_steps(self, state: WindowState,
                    motion: Optional[MotionModel]) -> Tensor:
        # every window step's time step, the new one's appended (NaN: the
        # tracker's own motion model)
        dt = math.nan
        if motion is not None and motion is not self.motion:
            dt = float(motion.params()['dt'])
        return torch.cat([state.time_step, state.time_step.new_full((1, ),
                                                                    dt)])

    def _motion_of(self, dt: float) -> MotionModel:
        return self.motion if math.isnan(dt) else \
            self.motion.with_time_step(dt)

    def _window(self, state: WindowState, edge_index: Tensor,
                edge_attr: Tensor, anchor: Tensor,
                motion: Optional[MotionModel],
                control: Optional[Tensor]) -> Window:
        # the window with the step joined: the prior of its first step
        # (the state's Gaussian, inflated unless fresh, predicted), its
        # transitions and its space-time links and factors
        num, size = state.mean.shape
        width = state.window.size(1) + 1
        motions = [self._motion_of(float(dt)) for dt in state.time_step]
        motions.append(self.motion if motion is None else motion)
        controls = state.control
        if controls is not None:
            new = (controls.new_full((num, 1, controls.size(-1)), math.nan)
                   if control is None else
                   control.to(controls).view(num, 1, -1))
            controls = torch.cat([controls, new], 1)
        mean, cov = state.mean, state.cov
        # with settled steps the steps marginalized out and the window are
        # one forward pass (kept from one step to the next): not inflated
        if not self._settles() and not bool(state.fresh.all()):
            inflated = bounded_inflation(
                cov, state.predicted,
                self.inflation_of(cov, state.memory, anchor))
            cov = torch.where(state.fresh.view(-1, 1, 1), cov, inflated)
        # every node's Gaussian predicted into its first window step (the
        # first, but for nodes that joined a live session since)
        entry = mean, cov
        for first in state.start.unique().tolist():
            moved = self.predict(mean, cov, anchor | (state.start != first),
                                 motions[first],
                                 self._control_at(controls, first, control),
                                 state.entry_point)
            entry = moved if first == 0 else tuple(
                torch.where((state.start == first).view(
                    (-1, ) + (1, ) * (m.dim() - 1)), m, e)
                for m, e in zip(moved, entry))
        mean, cov = entry
        info = torch.zeros_like(cov)
        agents = ~anchor
        info[agents] = _inverse(cov[agents])
        links = torch.cat([state.links, edge_index + (width - 1) * num], 1)
        # the links' features as the data gives them (the model's leading
        # columns, and any carried along)
        held = state.link_attr.to(edge_attr)
        if held.size(0) == 0:
            held = edge_attr[:0]
        link_attr = torch.cat([held, edge_attr])
        anchors = anchor.repeat(width)
        return Window(GaussianBelief(mean, info), cov, state.start, motions,
                       controls, links, link_attr, anchors,
                       self.conv.factors(links, anchors, size,
                                         slots=not self.rank_one))

    @staticmethod
    def _control_at(controls: Optional[Tensor], k: int,
                    given: Optional[Tensor] = None) -> Optional[Tensor]:
        # the known inputs of window step k (the step's own as given where
        # it is the newest of a one-step window: the motion model reads
        # them exactly as Gaussian BP hands them)
        if controls is None:
            return None
        if k == controls.size(1) - 1 and given is not None:
            return given
        return controls[:, k]

    def _carried(self, state: WindowState, window: Window,
                 anchor: Tensor):
        # the state's messages on the message edges of the window's
        # factors (by source and target), zero on the new step's, and the
        # mask of those without a previous message (the new step's)
        index = window.factors.index
        count = index.size(1)
        width = len(self.measurement.scope(state.mean.size(1)))
        dtype, device = state.mean.dtype, state.mean.device
        if self.rank_one:
            out = RangeMessages(torch.zeros(count, dtype=dtype, device=device),
                                torch.zeros(count, dtype=dtype,
                                            device=device),
                                torch.zeros(count, width, dtype=dtype,
                                            device=device))
        else:
            out = FactorMessages(
                torch.zeros(count, width, width, dtype=dtype, device=device),
                torch.zeros(count, width, dtype=dtype, device=device))
        if state.messages is None:
            return out, torch.ones(count, dtype=torch.bool, device=device)
        held = state.message_index.size(1)
        if held <= count and torch.equal(index[:, :held],
                                         state.message_index):
            # the window of the last step, slid: its message edges come
            # first, in order (the edges sorted by target, the new step's
            # targets last); a node that left or joined renumbers them
            rows = source = torch.arange(held, device=device)
        else:
            rows, source = _matched(state.message_index, index)
        fresh = torch.ones(count, dtype=torch.bool, device=device)
        fresh[rows] = False
        return type(out)(*(o.index_copy(0, rows, s[source].to(o))
                           for o, s in zip(out, state.messages))), fresh

    def _points(self, state: WindowState, window: Window,
                anchor: Tensor) -> Tensor:
        # the window's means to linearize at when a step starts: the last
        # step's, and the new step's prediction from its last
        if state.window.size(1) == 0:
            return window.prior.mean.unsqueeze(1)
        last = state.window[:, -1]
        agents = ~anchor
        moved = last.clone()
        k = state.window.size(1)
        given = inputs(None if window.control is None else
                       window.control[agents, k])
        moved[agents] = window.motions[k].mean(last[agents], **given)
        # a node that joins at this step starts at its prior
        moved = torch.where((window.start == k).view(-1, 1),
                            window.prior.mean, moved)
        return torch.cat([state.window, moved.unsqueeze(1)], 1)

    def _slide(self, state: WindowState, window: Window, messages,
               anchor: Tensor) -> WindowState:
        # the window's oldest step marginalized out: its filtered belief
        # from its prior and its final messages becomes the Gaussian before
        # the window (of the nodes there at that step; the others keep the
        # prior they joined with), and its links, messages and inputs leave
        num, size = state.mean.shape
        agents = ~anchor
        if state.settled_mean is not None:
            # the settled forward pass holds it
            first = GaussianBelief(torch.where(
                agents.view(-1, 1), state.settled_mean[:, 0],
                state.window[:, 0]), None)
            cov = state.settled_cov[:, 0]
        else:
            sums = self.conv.message_sums(as_factor_messages(messages),
                                          window.factors,
                                          window.anchor.numel())[:num]
            first = self.conv.updated(window.prior, state.window[:, 0],
                                      sums, anchor)
            cov = torch.zeros_like(first.info)
            cov[agents] = _inverse(first.info[agents])
        there = state.start == 0
        # on the lift of the window's means, not wrapped: the next window's
        # prior (from this mean) and the means carried over as its points
        # must not differ by a turn (a wrapped heading there pulled the
        # robots of the Gaussian range-bearing likelihood a turn away)
        mean = torch.where(there.view(-1, 1), first.mean, state.mean)
        cov = torch.where(there.view(-1, 1, 1), cov, state.cov)
        predicted = torch.where(there.view(-1, 1, 1), window.prior_cov,
                                state.predicted)
        # with settled steps the transition out of it is linearized where
        # the forward pass linearized it: at the step's point
        entry_point = None
        if self._settles():
            entry_point = torch.where(
                there.view(-1, 1), state.window[:, 0],
                state.mean if state.entry_point is None else
                state.entry_point)
        links, kept = renumbered(state.links, num, num, shift=1)
        index, carried = renumbered(state.message_index, num, num, shift=1)
        return WindowState(
            mean, cov, state.fresh & ~there, state.memory, predicted,
            state.window[:, 1:], links, state.link_attr[kept],
            state.time_step[1:],
            None if state.control is None else state.control[:, 1:],
            tuple(m[carried] for m in messages) if index.size(1) else None,
            index if index.size(1) else None,
            (state.start - 1).clamp_min(0),
            *self._cache_after_slide(state), entry_point)

    @staticmethod
    def _cache_after_slide(state: WindowState):
        # the settled forward pass without the step that left (none if it
        # held no other)
        if state.settled_mean is None or state.settled_mean.size(1) < 2:
            return None, None
        return state.settled_mean[:, 1:], state.settled_cov[:, 1:]

    def _settles(self) -> bool:
        # whether some steps of a full window are settled
        return self.iterated is not None and self.iterated < self.lag
