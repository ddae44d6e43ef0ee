import math
from typing import List, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.data.validation import check_positive_int
from tg_nebp.filters.gaussian_bp import (GaussianBP, GaussianState,
                                         SolvedStep, _inverse)
from tg_nebp.filters.relocation import LinkSearch, relocation_step
from tg_nebp.filters.state import StateField
from tg_nebp.filters.tracker import StepOutput
from tg_nebp.gaussian import bounded_inflation, rts_backward
from tg_nebp.models import MeasurementModel, MotionModel, inputs
from tg_nebp.nn.conv.gaussian_bp_conv import (FactorMessages,
                                              GaussianBelief, RangeMessages,
                                              as_factor_messages)
from tg_nebp.utils import symmetrize

__all__ = ['FixedLagGaussianBP', 'WindowState', 'SCHEDULES']

#: The orders of a step's iterations over the window (the :obj:`schedule`
#: of :class:`FixedLagGaussianBP`): every factor and agent each iteration,
#: or only those around the agents that moved.
SCHEDULES = ('sweep', 'residual')


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
    has no state before it; its Gaussian is the prior it joined with)."""
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
                  start=StateField(('N', ), 'index'))


def _renumbered(index: Tensor, num: int, num_new: int,
                node_map: Optional[Tensor] = None, shift: int = 0):
    # space-time indices (2, E) of 'num' nodes per step, k num + i, as
    # (k - shift) num_new + map[i]; the mask of the columns kept (both
    # ends at a step and node kept)
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


class _Window(NamedTuple):
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


class _Solved(NamedTuple):
    # the window's beliefs (space-time rows, slot-major) and covariances
    # (N, W, S, S)
    belief: GaussianBelief
    cov: Tensor


class FixedLagGaussianBP(GaussianBP):
    r"""Fixed-lag Gaussian belief propagation over the space-time factor
    graph: every agent keeps its states of the last :obj:`lag` steps as
    variables, tied by motion factors between consecutive states and by
    the range factors of every step in the window, and Gaussian BP
    relinearizes and iterates all of them at every step. This is the
    space-time graph of the GBP literature (the Robot Web of `"Distributed
    Simultaneous Localisation and Mapping for Mobile Robots with Gaussian
    Belief Propagation" <https://arxiv.org/abs/2202.03314>`_, Murai,
    Ortiz, Saeedi, Kelly and Davison, IEEE T-RO 2024, keeps a window per
    robot). Messages travel along the links of each step (the
    :class:`~tg_nebp.nn.conv.GaussianBPConv` of
    :class:`~tg_nebp.filters.GaussianBP`, both ends, extrinsic) and along
    each agent's own time chain, which the agent solves exactly: its
    window's posterior given the prior of the window's first step, its
    motion factors linearized at the current means (the motion role's
    :meth:`~tg_nebp.models.MotionModel.mean`,
    :meth:`~tg_nebp.models.MotionModel.jacobian` and
    :meth:`~tg_nebp.models.MotionModel.noise_covariance`: a user's model
    works) and the summed range messages of each step, by a Kalman filter
    and a Rauch-Tung-Striebel backward pass
    (:func:`~tg_nebp.gaussian.rts_backward`; covariance form, so the
    singular driving noise of the constant-velocity models and of
    odometry is fine). That chain is a tree, so its part of the messages
    is exact: each iteration is one sweep of the space messages and the
    exact time marginals,

    .. math::
        p(\mathbf{x}_{i,n-L+1:n}) \propto p(\mathbf{x}_{i,n-L+1}) \prod_k
        p(\mathbf{x}_{i,k} | \mathbf{x}_{i,k-1}) \prod_k \prod_{f \ni i}
        m_{f \to (i,k)}(\mathbf{x}_{i,k}),

    and a range message to a step :math:`k` of agent :math:`i` reads the
    source's marginal at :math:`k` without the factor's previous message
    (the extrinsic belief; a message on one step's block comes off that
    block's marginal exactly). Every step: the new step's links join the
    window (its messages start at zero, the older ones carry on), the
    iterations run until no mean of the window moves by more than
    :obj:`tolerance` (each graph of a batch on its own, as
    :class:`~tg_nebp.filters.GaussianBP`), and once the window holds
    :obj:`lag` steps the oldest is marginalized out: its filtered belief
    (prior and its final messages), inflated as
    :class:`~tg_nebp.filters.GaussianBP` inflates (bounded), predicted
    into the next step, is the next window's prior (each agent its own,
    in information form).

    Each step yields the newest state (the filtered estimate, its past
    relinearized) and the window (:obj:`window_mean`, :obj:`window_cov`
    of :class:`~tg_nebp.filters.StepOutput`); the estimate of the window's
    oldest step is final (:class:`~tg_nebp.filters.Smoothed` reads it).
    With :obj:`lag=1` it is :class:`~tg_nebp.filters.GaussianBP` bit for
    bit (the same arithmetic: a new step's messages start at zero and are
    not damped at their first iteration). The cost per iteration is the
    messages of :math:`L` steps' links plus each agent's :math:`O(L S^3)`
    chain. Live (:class:`~tg_nebp.filters.TrackingSession`), a node that
    joins enters the window at the next step (its rows before it hold its
    prior predicted into that step), and a node that leaves takes its
    links of the window along.

    Args:
        lag (int, optional): Steps :math:`L` in the window, the newest
            counted. (default: :obj:`5`)
        num_iterations (int, optional): Iterations per time step (at most,
            with :obj:`tolerance`). (default: :obj:`20`)
        motion (MotionModel, optional): Motion model with an
            additive-Gaussian-noise form.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): Measurement model.
            (default: :obj:`GaussianRange()`)
        ends, damping, tolerance, inflation, compile, relocation: As
            :class:`~tg_nebp.filters.GaussianBP` (a relocated agent rejoins
            the window: :meth:`reinitialized`).
        schedule (str, optional): :obj:`"sweep"` sends every factor's
            messages and solves every agent's chain at every iteration;
            :obj:`"residual"` only those that can have changed: the
            factors of the window with an end at an agent whose window
            means moved by more than :obj:`tolerance` in the last
            iteration (every agent at the first), and the chains of those
            agents and of every agent such a factor informs. The others
            keep their beliefs and messages, which a sweep would change by
            what moves of at most the tolerance make of them: the cost of
            an iteration follows the agents still moving, not the network
            (with :obj:`lag=1`, Gaussian BP with residual scheduling).
            Needs a :obj:`tolerance`. (default: :obj:`"sweep"`)

    Shapes:
        - **input:** a :class:`~tg_nebp.data.Realization`
        - **output:** :class:`~tg_nebp.filters.TrackOutput` with mean
          :math:`(N, T, S)` and covariance :math:`(N, T, S, S)` (the
          filtered estimates)
    """
    state_type = WindowState

    def __init__(self, lag: int = 5, num_iterations: int = 20,
                 motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None,
                 ends: str = 'both', damping: float = 0.0,
                 tolerance: Optional[float] = 0.01, inflation: float = 1.0,
                 compile: bool = False, schedule: str = 'sweep',
                 relocation: Optional[LinkSearch] = None):
        super().__init__(num_iterations, motion, measurement, ends, damping,
                         tolerance, inflation, compile, relocation)
        self.lag = check_positive_int(lag, 'lag')
        if schedule not in SCHEDULES:
            raise ValueError(f"'schedule' must be one of {list(SCHEDULES)}, "
                             f"got {schedule!r}")
        if schedule == 'residual' and tolerance is None:
            raise ValueError("'schedule' 'residual' needs a 'tolerance' (the "
                             "move that keeps an agent iterating)")
        self.schedule = schedule

    def initial_state(self, data, generator=None) -> WindowState:
        r"""The state before the first step of the nodes of :obj:`data`:
        :class:`~tg_nebp.filters.GaussianBP`'s, with an empty window."""
        base = super().initial_state(data, generator)
        num, size = data.prior_mean.shape
        control_dim = self.motion.control_dim
        return WindowState(
            *base, base.mean.new_zeros(num, 0, size),
            torch.zeros(2, 0, dtype=torch.long, device=base.mean.device),
            base.mean.new_zeros(0, len(self.measurement.features)),
            base.mean.new_zeros(0),
            None if control_dim == 0 else
            base.mean.new_zeros(num, 0, control_dim), None, None,
            torch.zeros(num, dtype=torch.long, device=base.mean.device))

    def solve_step(self, state: WindowState, edge_index: Tensor,
                   edge_attr: Tensor, anchor: Tensor, t: int,
                   generator=None, motion: Optional[MotionModel] = None,
                   graph_of: Optional[Tensor] = None, num_graphs: int = 1,
                   control: Optional[Tensor] = None) -> SolvedStep:
        r"""One time step (:meth:`~tg_nebp.filters.Tracker.step` returns
        the first two fields: the output and the state): the step's links
        :obj:`edge_index`
        :math:`(2, E)` (sorted by receiver), features :obj:`edge_attr`
        :math:`(E, F)`, motion model :obj:`motion` (the tracker's by
        default) and known inputs :obj:`control` :math:`(N, C)` join the
        window, the iterations run over the window, and a full window's
        oldest step is marginalized out. Returns the step's
        :class:`~tg_nebp.filters.StepOutput` (the newest state, and the
        window) and the state after it; :obj:`graph_of` and
        :obj:`num_graphs` as :class:`~tg_nebp.filters.GaussianBP`. The
        rest of the :class:`~tg_nebp.filters.SolvedStep` is the newest
        step's: its nodes' final beliefs (their marginals in the window),
        the factors of its links and their last messages."""
        num, size = state.mean.shape
        if graph_of is None:
            graph_of = torch.zeros_like(anchor, dtype=torch.long)
        width = state.window.size(1) + 1
        window = self._window(state, edge_index.long(), edge_attr.double(),
                              anchor, motion, control)
        # the messages of the older steps carry on; the new step's start
        # at zero
        messages, fresh = self._carried(state, window, anchor)
        if state.messages is None and width == 1:
            # no message yet: a window of one step is its prior
            belief = window.prior
            covs = window.prior_cov.unsqueeze(1)
        else:
            points = self._points(state, window, anchor)
            solved = self._solve(window, points, messages,
                                 (~anchor).nonzero().view(-1))
            belief, covs = self.share(solved.belief, solved.cov)
        belief, messages, covs = self._iterate_window(
            window, belief, messages, fresh, covs, anchor, graph_of,
            num_graphs, generator)
        layout = self.motion.layout(size)
        means = belief.mean.view(width, num, size).transpose(0, 1)
        output = StepOutput(t, layout.wrap(means[:, -1]), covs[:, -1],
                            window_mean=layout.wrap(means),
                            window_cov=covs)
        state = WindowState(state.mean, state.cov, state.fresh, state.memory,
                            state.predicted, means, window.links,
                            window.link_attr, self._time_steps(state, motion),
                            window.control, tuple(messages),
                            window.factors.index, state.start)
        # the newest step's nodes, factors and messages, in its numbering
        newest = slice((width - 1) * num, width * num)
        factors = self.conv.factors(edge_index.long(), anchor, size)
        into = (window.factors.index[1] >= newest.start).nonzero().view(-1)
        rows, found = _matched(
            window.factors.index[:, into] - newest.start, factors.index)
        last = type(messages)(*(part.new_zeros(
            (factors.index.size(1), ) + part.shape[1:]).index_copy(
                0, rows, part[into[found]]) for part in messages))
        solved = SolvedStep(output, state, GaussianBelief(
            belief.mean[newest], belief.info[newest]), factors, last)
        if width == self.lag:
            solved = solved._replace(state=self._slide(state, window,
                                                       messages, anchor))
        if self.relocation is None:
            return solved
        return relocation_step(self, solved, edge_index, edge_attr, anchor,
                               state.fresh, graph_of, t)

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
                control: Optional[Tensor]) -> _Window:
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
        if not bool(state.fresh.all()):
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
                                 self._control_at(controls, first, control))
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
        return _Window(GaussianBelief(mean, info), cov, state.start, motions,
                       controls, links, link_attr, anchors,
                       self.conv.factors(links, anchors, size))

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

    def _carried(self, state: WindowState, window: _Window,
                 anchor: Tensor):
        # the state's messages on the message edges of the window's
        # factors (by source and target), zero on the new step's, and the
        # mask of those without a previous message (the new step's)
        index = window.factors.index
        count = index.size(1)
        width = len(self.measurement.scope(state.mean.size(1)))
        dtype, device = state.mean.dtype, state.mean.device
        if self.conv.rank_one:
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
        rows, source = _matched(state.message_index, index)
        fresh = torch.ones(count, dtype=torch.bool, device=device)
        fresh[rows] = False
        return type(out)(*(o.index_copy(0, rows, s[source].to(o))
                           for o, s in zip(out, state.messages))), fresh

    def _points(self, state: WindowState, window: _Window,
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

    def _solve(self, window: _Window, points: Tensor, messages,
               rows: Tensor, into: Optional[_Solved] = None) -> _Solved:
        # the windows of the agents 'rows' given their first step's prior,
        # their motion factors linearized at 'points' (N, W, S) and the
        # summed messages of each step: a Kalman filter (each update
        # Gaussian BP's belief of the step) and the backward pass. The
        # other nodes keep theirs in 'into' (by default their points and
        # no information: anchors, known states)
        num, width, size = points.shape
        factors = window.factors
        if 2 * rows.numel() < num:  # the sums of the rows' steps only
            solved = torch.zeros(num, dtype=torch.bool, device=rows.device)
            solved[rows] = True
            into_rows = solved.repeat(width)[factors.index[1]]
            messages = type(messages)(*(m[into_rows] for m in messages))
            factors = factors._replace(index=factors.index[:, into_rows])
        sums = self.conv.message_sums(as_factor_messages(messages), factors,
                                      num * width).view(width, num, -1)

        def agents(tensor: Tensor) -> Tensor:
            return tensor.index_select(0, rows)

        start = agents(window.start)
        entry = GaussianBelief(*map(agents, window.prior))
        entry_cov = agents(window.prior_cov)
        here = agents(points)
        known = torch.zeros_like(start, dtype=torch.bool)
        motion = self._motion_factors(window, here, rows)
        prior, cov = entry, entry_cov
        filtered, predicted = [], []
        for k in range(width):
            if k > 0:
                prior, cov, cross = self._transition(
                    motion[k], here[:, k - 1], filtered[-1])
                predicted.append((prior.mean, cov, cross))
                entering = start >= k
                if bool(entering.any()):  # not yet in the window: its prior
                    prior = GaussianBelief(*(
                        torch.where(entering.view(
                            (-1, ) + (1, ) * (e.dim() - 1)), e, p)
                        for e, p in zip(entry, prior)))
                    cov = torch.where(entering.view(-1, 1, 1), entry_cov,
                                      cov)
            belief = self.conv.updated(prior, here[:, k], agents(sums[k]),
                                       known)
            filtered.append((belief, _inverse(belief.info)))
        means = [filtered[-1][0].mean]
        infos = [filtered[-1][0].info]
        covs = [filtered[-1][1]]
        for k in range(width - 2, -1, -1):
            (belief, belief_cov), (ahead, ahead_cov, cross) = \
                filtered[k], predicted[k]
            mean, cov = rts_backward(belief_cov, cross, ahead_cov, covs[0],
                                     belief.mean, ahead, means[0])
            info = _inverse(cov)
            absent = start > k
            if bool(absent.any()):  # not yet in the window: its prior
                mean = torch.where(absent.view(-1, 1), entry.mean, mean)
                info = torch.where(absent.view(-1, 1, 1), entry.info, info)
                cov = torch.where(absent.view(-1, 1, 1), entry_cov, cov)
            means.insert(0, mean)
            infos.insert(0, info)
            covs.insert(0, cov)
        # every node of every window step
        if into is None:
            mean = points.transpose(0, 1).clone(
                memory_format=torch.contiguous_format)
            info = points.new_zeros(width, num, size, size)
            cov = points.new_zeros(num, width, size, size)
        else:
            mean = into.belief.mean.view(width, num, size).clone()
            info = into.belief.info.view(width, num, size, size).clone()
            cov = into.cov.clone()
        mean[:, rows] = torch.stack(means)
        info[:, rows] = torch.stack(infos)
        cov[rows] = torch.stack(covs, 1)
        return _Solved(GaussianBelief(mean.view(-1, size),
                                      info.view(-1, size, size)), cov)

    def _motion_factors(self, window: _Window, points: Tensor,
                        rows: Tensor) -> List[Tuple[Tensor, ...]]:
        # every transition of the window linearized at the agents' 'points'
        # (A, W, S): per window step k > 0 their f, F and Q at step k - 1
        # (one call of the model for all steps where they share it)
        here = points[:, :-1]
        count = here.size(1)
        if count == 0:
            return []
        control = (None if window.control is None else
                   window.control.index_select(0, rows)[:, 1:])
        groups = [list(range(count))]
        if any(m is not window.motions[1] for m in window.motions[1:]):
            groups = [[k] for k in range(count)]
        out = [None] * count
        for group in groups:
            motion = window.motions[group[0] + 1]
            given = inputs(None if control is None else control[:, group])
            at = here[:, group]
            linearized = (motion.mean(at, **given),
                          motion.jacobian(at, **given),
                          motion.noise_covariance(at, **given))
            for j, k in enumerate(group):
                out[k] = tuple(part[:, j] for part in linearized)
        return [None] + out

    @staticmethod
    def _transition(linearized: Tuple[Tensor, ...], point: Tensor,
                    previous: tuple):
        # the prior of a window step from the filtered belief of the step
        # before through the motion factor linearized at 'point' (its f, F
        # and Q): the prediction, its covariance and the cross covariance
        # P F^T, of the agents
        belief, cov = previous
        moved_mean, jacobian, noise = linearized
        mean = moved_mean + (
            jacobian @ (belief.mean - point).unsqueeze(-1)).squeeze(-1)
        cross = cov @ jacobian.transpose(-1, -2)
        moved = jacobian @ cross + noise
        moved = symmetrize(moved)
        return GaussianBelief(mean, _inverse(moved)), moved, cross

    def _iterate_window(self, window: _Window, belief: GaussianBelief,
                        messages, fresh: Tensor, covs: Tensor,
                        anchor: Tensor, graph_of: Tensor, num_graphs: int,
                        generator):
        # the iterations of one step over the window: the range messages
        # of every step from the current beliefs, then the agents' chains
        # solved (all, or as the schedule picks); a graph whose window
        # means all moved by at most the tolerance in an iteration keeps
        # that iteration's beliefs and stops (each graph of a batch as
        # alone)
        num, size = anchor.numel(), belief.mean.size(-1)
        width = belief.mean.size(0) // num
        done = torch.zeros(num_graphs, dtype=torch.bool,
                           device=anchor.device)
        moving = ~anchor  # every agent at the first iteration
        for _ in range(self.num_iterations):
            still = ~done[graph_of]  # the nodes whose graphs iterate
            points = belief.mean.view(width, num, size).transpose(0, 1)
            if self.schedule == 'residual':
                # nothing of a converged graph moves: it keeps its own
                messages, solve = self._residual_messages(
                    window, belief, messages, fresh, moving & still,
                    generator)
                solved = self._solve(window, points, messages,
                                     (solve & ~anchor).nonzero().view(-1),
                                     _Solved(belief, covs))
            else:
                new_messages = self.conv.step_messages(
                    belief, window.links, window.link_attr, window.anchor,
                    window.factors, messages, generator, fresh)
                solved = self._solve(window, points, new_messages,
                                     (~anchor).nonzero().view(-1))
                rows = still.repeat(width)
                edges = rows[window.factors.index[1]]
                solved = _Solved(GaussianBelief(*(
                    torch.where(rows.view((-1, ) + (1, ) * (n.dim() - 1)),
                                n, o) for n, o in zip(solved.belief,
                                                      belief))),
                    torch.where(still.view(-1, 1, 1, 1), solved.cov, covs))
                messages = type(messages)(*(
                    torch.where(edges.view((-1, ) + (1, ) * (n.dim() - 1)),
                                n, o)
                    for n, o in zip(new_messages, messages)))
            solved = _Solved(*self.share(*solved))
            fresh = torch.zeros_like(fresh)
            move = (solved.belief.mean - belief.mean).abs().amax(-1).view(
                width, num).amax(0)
            belief, covs = solved
            if self.tolerance is None:
                continue
            # NaN compares false: a diverged agent keeps moving, and its
            # graph is not converged
            moving = ~(move <= self.tolerance) & ~anchor
            largest = self.largest_moves(move, graph_of, num_graphs)
            done = done | (largest <= self.tolerance)
            if bool(done.all()):
                break
        return belief, messages, covs

    def share(self, belief: GaussianBelief,
              covs: Tensor) -> Tuple[GaussianBelief, Tensor]:
        r"""The window's beliefs (space-time rows, step-major) and
        covariances :math:`(N, W, S, S)` after a solve of the agents'
        chains (a step's first, and every iteration's), as the next
        iteration reads them: unchanged here; a rank of a partitioned run
        (:class:`~tg_nebp.filters.PartitionedFixedLagGaussianBP`) takes its
        halo's from their owners."""
        return belief, covs

    def _residual_messages(self, window: _Window, belief: GaussianBelief,
                           messages, fresh: Tensor, moving: Tensor,
                           generator):
        # the residual schedule's messages: those of the factors with an
        # end at an agent of 'moving' (N) recomputed, the others kept; and
        # the agents whose chains to solve (those agents and every agent
        # such a factor informs)
        num = moving.numel()
        size = belief.mean.size(-1)
        chosen = moving.repeat(belief.mean.size(0) // num)[
            window.factors.ends].any(1)
        solve = moving.clone()
        if 2 * int(chosen.sum()) > chosen.numel():
            # most factors: all computed (each message as alone), the
            # others' kept
            kept = chosen[window.factors.link]
            computed = self.conv.step_messages(
                belief, window.links, window.link_attr, window.anchor,
                window.factors, messages, generator, fresh)
            solve[window.factors.index[1, kept] % num] = True
            return type(messages)(*(
                torch.where(kept.view((-1, ) + (1, ) * (n.dim() - 1)), n, o)
                for n, o in zip(computed, messages))), solve
        factors, links, kept = self.conv.factor_subset(window.factors,
                                                       chosen, size)
        computed = self.conv.step_messages(
            belief, window.links[:, links], window.link_attr[links],
            window.anchor, factors, type(messages)(*(m[kept]
                                                     for m in messages)),
            generator, fresh[kept])
        solve[factors.index[1] % num] = True
        position = kept.nonzero().view(-1)
        return type(messages)(*(m.index_copy(0, position, c) for m, c in
                                zip(messages, computed))), solve

    def _slide(self, state: WindowState, window: _Window, messages,
               anchor: Tensor) -> WindowState:
        # the window's oldest step marginalized out: its filtered belief
        # from its prior and its final messages becomes the Gaussian before
        # the window (of the nodes there at that step; the others keep the
        # prior they joined with), and its links, messages and inputs leave
        num, size = state.mean.shape
        sums = self.conv.message_sums(as_factor_messages(messages),
                                      window.factors,
                                      window.anchor.numel())[:num]
        first = self.conv.updated(window.prior, state.window[:, 0], sums,
                                  anchor)
        cov = torch.zeros_like(first.info)
        agents = ~anchor
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
        links, kept = _renumbered(state.links, num, num, shift=1)
        index, carried = _renumbered(state.message_index, num, num, shift=1)
        return WindowState(
            mean, cov, state.fresh & ~there, state.memory, predicted,
            state.window[:, 1:], links, state.link_attr[kept],
            state.time_step[1:],
            None if state.control is None else state.control[:, 1:],
            tuple(m[carried] for m in messages) if index.size(1) else None,
            index if index.size(1) else None,
            (state.start - 1).clamp_min(0))

    def check_state(self, state: WindowState, anchor: Tensor,
                    state_size: int, dtype: torch.dtype):
        r""":meth:`Tracker.check_state
        <tg_nebp.filters.Tracker.check_state>`, and the window ties
        together: fewer than :obj:`lag` steps, links and message edges
        between its nodes, messages on every message edge and every
        node's first step within the window."""
        sizes = super().check_state(state, anchor, state_size, dtype)
        width, count = sizes['W'], anchor.numel() * sizes['W']
        features = len(self.measurement.features)
        if sizes['F'] != features:
            raise ValueError(f"the state's 'link_attr' has {sizes['F']} "
                             f"features per link, expected {features}")
        if state.messages is not None:
            # the conv's kind of message (the template holds none)
            reach = len(self.measurement.scope(state_size))
            shapes = ([(), (), (reach, )] if self.conv.rank_one else
                      [(reach, reach), (reach, )])
            found = [tuple(m.shape[1:]) for m in state.messages]
            if found != shapes:
                raise ValueError(f"the state's 'messages' have shapes "
                                 f"{found} after their count, expected "
                                 f"{shapes}")
        if width >= self.lag:
            raise ValueError(f"the state's 'window' holds {width} steps; a "
                             f"window of lag {self.lag} carries at most "
                             f"{self.lag - 1}")
        for name in ('links', 'message_index'):
            index = getattr(state, name)
            if index is not None and index.numel() and \
                    int(index.max()) >= count:
                raise ValueError(f"the state's '{name}' names node "
                                 f"{int(index.max())} of a window of "
                                 f"{count}")
        if (state.messages is None) != (state.message_index is None):
            raise ValueError("the state's 'messages' and 'message_index' "
                             "come together")
        if state.start.numel() and int(state.start.max()) > width:
            raise ValueError(f"the state's 'start' names a step after the "
                             f"window of {width}")
        return sizes

    def select_state(self, state: WindowState, keep: Tensor,
                     anchor: Tensor) -> WindowState:
        r"""The state of the nodes :obj:`keep` :math:`(N)` (a mask; the
        others leave): their rows, and the window's links and messages
        between them (renumbered)."""
        num = keep.numel()
        node_map = torch.full((num, ), -1, dtype=torch.long,
                              device=keep.device)
        count = int(keep.sum())
        node_map[keep] = torch.arange(count, device=keep.device)
        links, kept = _renumbered(state.links, num, count, node_map)
        messages, index = state.messages, state.message_index
        if index is not None:
            index, carried = _renumbered(index, num, count, node_map)
            messages = tuple(m[carried] for m in messages)
            if index.size(1) == 0:
                messages = index = None
        return state._replace(
            mean=state.mean[keep], cov=state.cov[keep],
            fresh=state.fresh[keep], predicted=state.predicted[keep],
            window=state.window[keep], links=links,
            link_attr=state.link_attr[kept],
            control=None if state.control is None else state.control[keep],
            messages=messages, message_index=index, start=state.start[keep])

    def join_state(self, state: WindowState,
                   joined: WindowState) -> WindowState:
        r"""The state of the nodes of :obj:`state` followed by those of
        :obj:`joined` (an :meth:`initial_state`): the joining nodes enter
        the window at the next step (their rows before it hold their
        prior, never measured), the links and messages renumbered."""
        num, width = state.window.shape[:2]
        count = num + joined.mean.size(0)
        links, _ = _renumbered(state.links, num, count)
        index = state.message_index
        if index is not None:
            index, _ = _renumbered(index, num, count)
        control = state.control
        if control is not None:
            control = torch.cat([control, control.new_full(
                (joined.mean.size(0), width, control.size(-1)), math.nan)])
        return state._replace(
            mean=torch.cat([state.mean, joined.mean]),
            cov=torch.cat([state.cov, joined.cov]),
            fresh=torch.cat([state.fresh, joined.fresh]),
            predicted=torch.cat([state.predicted, joined.predicted]),
            window=torch.cat([state.window, joined.mean.unsqueeze(1).expand(
                -1, width, -1)]),
            links=links, control=control, message_index=index,
            start=torch.cat([state.start, torch.full_like(joined.start,
                                                          width)]))

    def reinitialized(self, state: WindowState, nodes: Tensor, mean: Tensor,
                      cov: Tensor) -> WindowState:
        r"""The :obj:`state` with the :obj:`nodes` (a mask :math:`(N)`)
        started afresh from the Gaussians of their rows of :obj:`mean`
        :math:`(N, S)` and :obj:`cov` :math:`(N, S, S)` (see
        :meth:`GaussianBP.reinitialized
        <tg_nebp.filters.GaussianBP.reinitialized>`): as a node that
        joins, each enters the window at the next step with that prior,
        and its links and messages in the window are dropped (they were
        linearized at the states it is taken off)."""
        num, width = state.window.shape[:2]
        ends_kept = ~nodes[state.links % num].any(0)
        messages, index = state.messages, state.message_index
        if index is not None:
            carried = ~nodes[index % num].any(0)
            messages = tuple(m[carried] for m in messages)
            index = index[:, carried]
            if index.size(1) == 0:
                messages = index = None
        rows = nodes.view(-1, 1, 1)
        return state._replace(
            mean=torch.where(nodes.view(-1, 1), mean, state.mean),
            cov=torch.where(rows, cov, state.cov), fresh=state.fresh | nodes,
            predicted=torch.where(rows, cov, state.predicted),
            window=torch.where(rows, mean.unsqueeze(1), state.window),
            links=state.links[:, ends_kept],
            link_attr=state.link_attr[ends_kept], messages=messages,
            message_index=index,
            start=torch.where(nodes, width, state.start))

    def settings(self) -> dict:
        return dict(super().settings(), lag=self.lag,
                    schedule=self.schedule)

    def __repr__(self) -> str:
        return (super().__repr__()[:-1] +
                f', lag={self.lag}, schedule={self.schedule!r})')
