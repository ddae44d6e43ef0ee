import math
from typing import List, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.data.validation import check_number, check_positive_int
from tg_nebp.filters.gaussian_bp import (GBP_RECOMMENDED, GaussianBP,
                                         GaussianState, SolvedStep,
                                         _inverse)
from tg_nebp.filters.relocation import LinkSearch, relocation_step
from tg_nebp.filters.state import StateField
from tg_nebp.filters.tracker import StepOutput
from tg_nebp.gaussian import (bounded_inflation, rts_backward,
                              rts_backward_chain)
from tg_nebp.models import MeasurementModel, MotionModel, inputs
from tg_nebp.nn.conv.gaussian_bp_conv import (FactorMessages,
                                              GaussianBelief, RangeMessages,
                                              as_factor_messages)
from tg_nebp.utils import symmetrize

__all__ = ['FixedLagGaussianBP', 'WindowState', 'SCHEDULES',
           'FIXED_LAG_RECOMMENDED', 'WINDOW_GBP_RECOMMENDED']

#: The orders of a step's iterations over the window (the :obj:`schedule`
#: of :class:`FixedLagGaussianBP`): every factor and agent each iteration,
#: or only those around the agents that moved.
SCHEDULES = ('sweep', 'residual')


#: Gaussian BP's recommended configuration as a window takes it: without
#: its :obj:`report_inflation` (a window reports its beliefs as they are).
WINDOW_GBP_RECOMMENDED = {key: value for key, value in GBP_RECOMMENDED.items()
                          if key != 'report_inflation'}
#: The settled steps of a window longer than 5 steps in
#: :meth:`~tg_nebp.filters.FixedLagGaussianBP.recommended`: the newest 5
#: steps iterated, the older settled and relinearized as iSAM2
#: relinearizes (threshold 0.1, every 10th step), their filter inflated by
#: 1.1. Chosen on MRCLAM sequence 6 (the development sequence) and the
#: validation realizations of robots_train (the results page, *Settled
#: steps*).
FIXED_LAG_RECOMMENDED = dict(iterated=5, relinearize_threshold=0.1,
                             relinearize_skip=10, settled_inflation=1.1)


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


def _renumbered(index: Tensor, num: int, num_new: int,
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


class _Chain(NamedTuple):
    # the forward pass of agents' time chains: their first window steps,
    # priors there (belief, covariance), every filtered step (mean,
    # covariance), the prediction into every step after the first that
    # the pass computed (belief, covariance, cross covariance with the
    # step before), the belief of the last step it filtered and the prior
    # of the step after the filtered ones (or None: the window ends)
    start: Tensor
    entry: GaussianBelief
    entry_cov: Tensor
    filtered: List[Tuple[Tensor, Tensor]]
    predicted: List[Tuple[GaussianBelief, Tensor, Tensor]]
    last: Optional[GaussianBelief]
    after: Optional[Tuple[GaussianBelief, Tensor]]


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
    chain.

    A long window need not iterate all of it: with :obj:`iterated`
    :math:`K < L` only the newest :math:`K` steps are iterated, and the
    older steps of the window are *settled*: their range messages are
    held as linear factors (information form), every agent's chain over
    them is a Kalman filter linearized about the window's points (each
    transition linearized at the point of the step it leaves, as the
    messages are; each filtered covariance inflated, bounded, by
    :obj:`settled_inflation`) whose prediction is the prior of the newest
    steps, and after the iterations one backward pass carries the result
    into them. The filter is kept in the state from one time step to the
    next (a step that becomes settled adds one step to it; the step
    marginalized out of the window is its first, so the prior before the
    window is not inflated again, and its transition stays linearized at
    its point, :obj:`WindowState.entry_point`). At every
    :obj:`relinearize_skip`-th time step, the messages of the factors of
    a settled node whose smoothed mean moved by more than
    :obj:`relinearize_threshold` from the point they were linearized at
    are computed again from the smoothed beliefs there (its point moves,
    and so does the linearization of its transition), and the filter
    runs again from the oldest such step: the window's
    marginal prior relinearized where the estimate moved (the fixed-lag
    counterpart of the fluid relinearization of iSAM2, `"iSAM2:
    Incremental Smoothing and Mapping Using the Bayes Tree"
    <https://doi.org/10.1177/0278364911430419>`_, Kaess et al., IJRR
    2012), so a wrong mode of the first steps is left once later steps
    tell (a window that marginalizes its steps out keeps it). Where no
    message depends on a belief (linear links from anchors) the result is
    the full iteration's; elsewhere a settled message changes at a
    relinearization, not at every iteration. An iteration then costs
    :math:`K` steps' messages and chains; the settled steps cost one
    filtered step and one backward pass per time step, and a
    relinearization filters again from the oldest step it changed.

    Live (:class:`~tg_nebp.filters.TrackingSession`), a node that
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
        iterated (int, optional): Newest steps :math:`K` of the window
            that the iterations revisit; the older are settled (above).
            :obj:`None`: every step. (default: :obj:`None`)
        relinearize_threshold (float, optional): A settled node whose
            smoothed mean moved by more than this (largest entry) from the
            point its messages were linearized at has its factors'
            messages computed again there; :obj:`None` holds them as they
            left the iterations. (default: :obj:`0.1`, iSAM2's)
        relinearize_skip (int, optional): Relinearize at the time steps
            :math:`t` that this divides (iSAM2's skip): each
            relinearization filters the settled steps again from the
            oldest it changed. (default: :obj:`10`, iSAM2's)
        settled_inflation (float, optional): The inflation :math:`\kappa`
            of every settled step's filtered covariance before its
            prediction (bounded as :class:`~tg_nebp.filters.GaussianBP`
            bounds its inflation); :obj:`1` is none. (default: :obj:`1`)

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
                 relocation: Optional[LinkSearch] = None,
                 iterated: Optional[int] = None,
                 relinearize_threshold: Optional[float] = 0.1,
                 relinearize_skip: int = 10, settled_inflation: float = 1.0):
        super().__init__(num_iterations, motion, measurement, ends, damping,
                         tolerance, inflation, compile, relocation)
        self.lag = check_positive_int(lag, 'lag')
        self.iterated = None if iterated is None else check_positive_int(
            iterated, 'iterated')
        self.relinearize_threshold = (
            None if relinearize_threshold is None else check_number(
                relinearize_threshold, 'relinearize_threshold',
                inclusive=True))
        self.relinearize_skip = check_positive_int(relinearize_skip,
                                                   'relinearize_skip')
        self.settled_inflation = check_number(
            settled_inflation, 'settled_inflation', 1.0, inclusive=True)
        if schedule not in SCHEDULES:
            raise ValueError(f"'schedule' must be one of {list(SCHEDULES)}, "
                             f"got {schedule!r}")
        if schedule == 'residual' and tolerance is None:
            raise ValueError("'schedule' 'residual' needs a 'tolerance' (the "
                             "move that keeps an agent iterating)")
        self.schedule = schedule

    @classmethod
    def recommended(cls, **overrides) -> 'FixedLagGaussianBP':
        r""":meth:`GaussianBP.recommended
        <tg_nebp.filters.GaussianBP.recommended>`'s configuration over the
        window; a window of more than 5 steps iterates its newest 5 and
        settles the others (:obj:`FIXED_LAG_RECOMMENDED`: on MRCLAM
        sequence 6 at lag 80, 3, 5 and 10 iterated steps gave about the
        same smoothed RMSE, and on the validation realizations of
        robots_train at lag 20 3 steps were 1.27 times the smoothing
        bound and 5 steps 1.12; the settled inflation 1.1 is the smallest
        of 1, 1.1 and 1.2 with P(accept 0.95) of at least 0.85 on
        sequence 6). The window reports its beliefs as they are (no
        :obj:`report_inflation`: a window's revised covariances fall short
        of the joint's in another way). :obj:`overrides` replace or add
        constructor arguments."""
        # any integer type (a NumPy count too) settles a long window
        lag = check_positive_int(overrides.get('lag', 5), 'lag')
        settled = FIXED_LAG_RECOMMENDED if lag > 5 else {}
        return cls(**{**WINDOW_GBP_RECOMMENDED, **settled, **overrides})

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
        split = 0 if self.iterated is None else max(width - self.iterated,
                                                    0)
        agents = (~anchor).nonzero().view(-1)
        settled = None, None  # no settled step: no forward pass to keep
        # a learned correction's memory: every agent's, on each of its
        # rows of the window (the iterated ones)
        memory = None if state.memory is None else state.memory.repeat(
            width - split, 1)
        if state.messages is None and width == 1:
            # no message yet: a window of one step is its prior
            belief = window.prior
            covs = window.prior_cov.unsqueeze(1)
            belief, messages, covs, memory = self._iterate_window(
                window, belief, messages, fresh, covs, anchor, graph_of,
                num_graphs, generator, memory)
            points = belief.mean.view(width, num, size).transpose(0, 1)
        elif split == 0:
            points = self._points(state, window, anchor)
            belief, covs = self.share(*self._solve(window, points, messages,
                                                   agents))
            belief, messages, covs, memory = self._iterate_window(
                window, belief, messages, fresh, covs, anchor, graph_of,
                num_graphs, generator, memory)
            points = belief.mean.view(width, num, size).transpose(0, 1)
        else:
            belief, messages, covs, points, settled, memory = \
                self._settled_and_iterated(
                    state, window, self._points(state, window, anchor),
                    messages, fresh, split, anchor, graph_of, num_graphs,
                    generator, t, memory)
        layout = self.motion.layout(size)
        means = belief.mean.view(width, num, size).transpose(0, 1)
        output = StepOutput(t, layout.wrap(means[:, -1]), covs[:, -1],
                            window_mean=layout.wrap(means),
                            window_cov=covs,
                            window_start=state.start if bool(
                                state.start.any()) else None)
        # the memory carried on: that of the agents' newest rows
        state = WindowState(state.mean, state.cov, state.fresh,
                            None if memory is None else memory[-num:],
                            state.predicted, points, window.links,
                            window.link_attr, self._time_steps(state, motion),
                            window.control, tuple(messages),
                            window.factors.index, state.start, *settled,
                            state.entry_point)
        # the newest step's nodes, factors and messages, in its numbering:
        # the window's last block (its factors are those of the step's
        # links alone, in the same order)
        newest = slice((width - 1) * num, width * num)
        factors = self.conv.restricted_factors(
            window.factors, torch.arange(width * num, device=anchor.device)
            >= newest.start, size)
        into = window.factors.index[1] >= newest.start
        last = type(messages)(*(part[into] for part in messages))
        solved = SolvedStep(output, state, GaussianBelief(
            belief.mean[newest], belief.info[newest]), factors, last)
        if width == self.lag:
            solved = solved._replace(state=self._slide(state, window,
                                                       messages, anchor))
        if self.relocation is None:
            return solved
        return relocation_step(self, solved, edge_index, edge_attr, anchor,
                               state.fresh, graph_of, t)

    def _settled_and_iterated(self, state: WindowState, window: _Window,
                              points: Tensor, messages, fresh: Tensor,
                              split: int, anchor: Tensor, graph_of: Tensor,
                              num_graphs: int, generator, t: int,
                              memory: Optional[Tensor] = None):
        # a step of a window whose first 'split' steps are settled: their
        # messages held, the forward pass over them (continued from the
        # state's where it holds) is the prior of the newest steps, the
        # iterations run over the newest steps alone, and the backward
        # pass carries the result into the settled steps once. The
        # settled messages with an end that moved by more than the
        # threshold from its point are then relinearized at the smoothed
        # beliefs (its point moves there), at every relinearize_skip-th
        # time step t. Returns the window's beliefs, messages,
        # covariances, points, the settled steps' filtered means and
        # covariances that still hold, and the iterated rows' 'memory'
        num, width, size = points.shape
        agents = (~anchor).nonzero().view(-1)
        held = 0 if state.settled_mean is None else min(
            state.settled_mean.size(1), split)
        cached = None if held == 0 else (
            state.settled_mean[agents, :held],
            state.settled_cov[agents, :held])
        # the forward pass reads the sums of the steps after the held ones
        chain = self._filtered(window, points, self._sums(
            window, messages, agents, num, width, held), agents, split,
            cached, settled=True)
        newest = self._newest(window, chain, agents, split)
        rows = torch.arange(width * num, device=anchor.device) >= split * num
        kept = rows[window.factors.index[1]]
        iterated = type(messages)(*(m[kept] for m in messages))
        belief, covs = self.share(*self._solve(newest, points[:, split:],
                                               iterated, agents))
        belief, iterated, covs, memory = self._iterate_window(
            newest, belief, iterated, fresh[kept], covs, anchor, graph_of,
            num_graphs, generator, memory)
        position = kept.nonzero().view(-1)
        messages = type(messages)(*(m.index_copy(0, position, i) for m, i in
                                    zip(messages, iterated)))
        points = torch.cat([points[:, :split], belief.mean.view(
            width - split, num, size).transpose(0, 1)], 1)
        filtered_mean = torch.stack([m for m, _ in chain.filtered], 1)
        filtered_cov = torch.stack([c for _, c in chain.filtered], 1)
        mean, info, cov = self._settled_smoothed(
            window, agents, chain, points[agents, :split + 1], filtered_mean,
            filtered_cov,
            belief.mean[:num][agents], covs[agents, 0])
        settled = GaussianBelief(
            points[:, :split].transpose(0, 1).clone(
                memory_format=torch.contiguous_format),
            points.new_zeros(split, num, size, size))
        settled_cov = points.new_zeros(num, split, size, size)
        settled.mean[:, agents] = mean.transpose(0, 1)
        settled.info[:, agents] = info.transpose(0, 1)
        settled_cov[agents] = cov
        belief, covs = self.share(GaussianBelief(
            torch.cat([settled.mean.view(-1, size), belief.mean]),
            torch.cat([settled.info.view(-1, size, size), belief.info])),
            torch.cat([settled_cov, covs], 1))
        messages, points, holds = (messages, points, split) if \
            t % self.relinearize_skip else self._relinearized(
                window, belief, messages, points, split, anchor, generator)
        # the fewest over the ranks of a partitioned run (each forward
        # pass restarts where every other does)
        holds = split - int(self.largest_moves(
            points.new_full((1, ), float(split - holds)),
            torch.zeros(1, dtype=torch.long, device=points.device), 1)[0])
        if holds == 0:
            return belief, messages, covs, points, (None, None), memory
        cache_mean = points.new_zeros(num, holds, size)
        cache_cov = points.new_zeros(num, holds, size, size)
        cache_mean[agents] = filtered_mean[:, :holds]
        cache_cov[agents] = filtered_cov[:, :holds]
        return (belief, messages, covs, points, (cache_mean, cache_cov),
                memory)

    def _settled_smoothed(self, window: _Window, agents: Tensor,
                          chain: _Chain, points: Tensor, filtered_mean,
                          filtered_cov, mean: Tensor, cov: Tensor):
        # the backward pass over the settled steps of the agents (their
        # filtered means (A, s, S) and covariances (A, s, S, S)) from the
        # smoothed Gaussian of the step after them (mean, cov): the
        # transitions of all steps at once, then the Rauch-Tung-Striebel
        # pass over the chain at once. Returns the smoothed means,
        # information and covariances (A, s, ...); a step before an
        # agent's first holds its prior
        count = filtered_mean.size(1)
        # the transitions as the forward pass linearized them: at the
        # points (the last row of the points is not read)
        linearized = self._linearized_motion(window, points, agents)
        ahead, ahead_cov, cross = self._transition(
            linearized, points[:, :-1], (filtered_mean, filtered_cov))
        mean, cov = rts_backward_chain(filtered_mean, filtered_cov,
                                       ahead.mean, ahead_cov, cross, mean,
                                       cov)
        info = _inverse(cov)
        absent = (chain.start.view(-1, 1) > torch.arange(
            count, device=agents.device)).view(-1, count, 1, 1)
        return (torch.where(absent.squeeze(-1), chain.entry.mean.unsqueeze(1),
                            mean),
                torch.where(absent, chain.entry.info.unsqueeze(1), info),
                torch.where(absent, chain.entry_cov.unsqueeze(1), cov))

    def _newest(self, window: _Window, chain: _Chain, agents: Tensor,
                split: int) -> _Window:
        # the window of the steps after the first 'split' (settled): every
        # agent's prior at its first step there is the forward pass's
        # prediction (the prior it joined with, if later)
        num = window.start.numel()
        prior, prior_cov = chain.after
        mean, info = (part.clone() for part in window.prior)
        cov = window.prior_cov.clone()
        mean[agents], info[agents], cov[agents] = prior.mean, prior.info, \
            prior_cov
        keep = torch.arange(window.anchor.numel(),
                            device=window.anchor.device) >= split * num
        links = keep[window.links[1]]
        return _Window(
            GaussianBelief(mean, info), cov,
            (window.start - split).clamp_min(0), window.motions[split:],
            None if window.control is None else window.control[:, split:],
            window.links[:, links] - split * num, window.link_attr[links],
            window.anchor[split * num:],
            self.conv.restricted_factors(window.factors, keep,
                                         mean.size(-1)))

    def _relinearized(self, window: _Window, belief: GaussianBelief,
                      messages, points: Tensor, split: int, anchor: Tensor,
                      generator):
        # the settled steps' messages of the factors with an end whose
        # smoothed mean moved by more than the threshold from its point,
        # recomputed from the smoothed beliefs (once; the points of those
        # ends move to their means). Returns the messages, the points and
        # the count of settled steps before the first that moved (their
        # forward pass holds)
        num, width, size = points.shape
        if self.relinearize_threshold is None:
            return messages, points, split
        settled = belief.mean[:split * num].view(split, num, size).transpose(
            0, 1)
        moved = ~((settled - points[:, :split]).abs().amax(-1) <=
                  self.relinearize_threshold) & ~anchor.view(-1, 1)
        steps = moved.any(0).nonzero().view(-1)
        if steps.numel() == 0:
            return messages, points, split
        rows = torch.cat([moved.t().reshape(-1), moved.new_zeros(
            (width - split) * num)])
        chosen = rows[window.factors.ends].any(1)
        points = torch.cat([torch.where(moved.unsqueeze(-1), settled,
                                        points[:, :split]),
                            points[:, split:]], 1)
        holds = int(steps[0])
        if not bool(chosen.any()):
            return messages, points, holds
        messages, _ = self._recomputed(
            window, belief, messages, chosen, torch.zeros(
                messages[0].size(0), dtype=torch.bool, device=chosen.device),
            generator)
        return messages, points, holds

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
        return _Window(GaussianBelief(mean, info), cov, state.start, motions,
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

    def _carried(self, state: WindowState, window: _Window,
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
        chain = self._filtered(window, points, self._sums(
            window, messages, rows, num, width), rows, width)
        means, infos, covs = self._smoothed(chain, chain.last.mean,
                                            chain.last.info,
                                            chain.filtered[-1][1])
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

    def _sums(self, window: _Window, messages, rows: Tensor, num: int,
              width: int, first: int = 0) -> Tensor:
        # every node's summed messages at every window step (W, N, R^2 + R)
        # (only the rows' where they are few, and zero before step 'first':
        # a kept forward pass reads only the steps after it)
        factors = window.factors
        into = None
        if 2 * rows.numel() < num:
            solved = torch.zeros(num, dtype=torch.bool, device=rows.device)
            solved[rows] = True
            into = solved.repeat(width)[factors.index[1]]
        if first > 0:
            later = factors.index[1] >= first * num
            into = later if into is None else into & later
        if into is not None:
            messages = type(messages)(*(m[into] for m in messages))
            factors = factors._replace(index=factors.index[:, into])
        return self.conv.message_sums(as_factor_messages(messages), factors,
                                      num * width).view(width, num, -1)

    def _filtered(self, window: _Window, points: Tensor, sums: Tensor,
                  rows: Tensor, count: int,
                  cached: Optional[Tuple[Tensor, Tensor]] = None,
                  settled: bool = False) -> _Chain:
        # the forward pass of the agents 'rows' over the window's first
        # 'count' steps (each update Gaussian BP's belief of the step),
        # continued after the filtered means and covariances 'cached' of
        # its first steps where given, and the prediction into the step
        # after them where the window has one. The transitions are
        # linearized at the points (all at once: a settled step's point
        # moves only where it is relinearized, and the filter runs again
        # from there); settled steps' filtered covariances are inflated
        # (bounded) by the settled inflation: a Kalman filter linearized
        # about the points, whose steps hold from one time step to the
        # next
        start = window.start.index_select(0, rows)
        entry = GaussianBelief(*(part.index_select(0, rows)
                                 for part in window.prior))
        entry_cov = window.prior_cov.index_select(0, rows)
        here = points.index_select(0, rows)
        known = torch.zeros_like(start, dtype=torch.bool)
        reach = min(count + 1, here.size(1))
        held = 0 if cached is None else cached[0].size(1)
        base = max(held - 1, 0)  # the step the first transition leaves
        motion = self._motion_factors(window, here[:, base:reach], rows,
                                      base)
        prior, cov = entry, entry_cov
        filtered = [] if cached is None else list(zip(cached[0].unbind(1),
                                                      cached[1].unbind(1)))
        predicted, last = [], None
        for k in range(held, reach):
            if k > 0:
                linearized, point = motion[k - base], here[:, k - 1]
                prior, cov, cross = self._transition(linearized, point,
                                                     filtered[-1])
                predicted.append((prior, cov, cross))
                entering = start >= k
                if bool(entering.any()):  # not yet in the window: its prior
                    prior = GaussianBelief(*(
                        torch.where(entering.view(
                            (-1, ) + (1, ) * (e.dim() - 1)), e, p)
                        for e, p in zip(entry, prior)))
                    cov = torch.where(entering.view(-1, 1, 1), entry_cov,
                                      cov)
            if k == count:  # the step after them: its prior only
                return _Chain(start, entry, entry_cov, filtered, predicted,
                              last, (prior, cov))
            last = self.conv.updated(prior, here[:, k],
                                     sums[k].index_select(0, rows), known)
            filtered_cov = _inverse(last.info)
            if settled and self.settled_inflation != 1.0:
                filtered_cov = bounded_inflation(
                    filtered_cov, cov, filtered_cov.new_full(
                        filtered_cov.shape[:1], self.settled_inflation))
            filtered.append((last.mean, filtered_cov))
        return _Chain(start, entry, entry_cov, filtered, predicted, last,
                      None)

    @staticmethod
    def _smoothed(chain: _Chain, mean: Tensor, info: Tensor, cov: Tensor):
        # the backward pass over the chain's filtered steps from the
        # smoothed Gaussian (mean, info, cov) of the step its last
        # prediction reaches: every step's smoothed means, information and
        # covariances, that step's last
        means, infos, covs = [mean], [info], [cov]
        start, entry, entry_cov = chain.start, chain.entry, chain.entry_cov
        for k in range(len(chain.predicted) - 1, -1, -1):
            (belief, belief_cov), (ahead, ahead_cov, cross) = \
                chain.filtered[k], chain.predicted[k]
            mean, cov = rts_backward(belief_cov, cross, ahead_cov, covs[0],
                                     belief, ahead.mean, means[0])
            info = _inverse(cov)
            absent = start > k
            if bool(absent.any()):  # not yet in the window: its prior
                mean = torch.where(absent.view(-1, 1), entry.mean, mean)
                info = torch.where(absent.view(-1, 1, 1), entry.info, info)
                cov = torch.where(absent.view(-1, 1, 1), entry_cov, cov)
            means.insert(0, mean)
            infos.insert(0, info)
            covs.insert(0, cov)
        return means, infos, covs

    def _motion_factors(self, window: _Window, points: Tensor,
                        rows: Tensor, first: int = 0
                        ) -> List[Optional[Tuple[Tensor, ...]]]:
        # the window's transitions out of steps first, first + 1, ...
        # linearized at the agents' 'points' (A, P, S) of steps first, ...,
        # first + P - 1: entry j > 0 is the f, F and Q of the transition
        # into step first + j
        if points.size(1) < 2:
            return [None]
        return [None] + list(zip(*(part.unbind(1) for part in
                                   self._linearized_motion(
                                       window, points, rows, first))))

    @staticmethod
    def _linearized_motion(window: _Window, points: Tensor, rows: Tensor,
                           first: int = 0) -> Tuple[Tensor, ...]:
        # the f, F and Q (A, P - 1, ...) of the transitions out of steps
        # first, ..., first + P - 2 linearized at the agents' 'points' (A,
        # P, S) of those steps (the last is not read): one call of the
        # model for all steps where they share it
        here = points[:, :-1]
        count = here.size(1)
        steps = slice(first + 1, first + 1 + count)
        control = (None if window.control is None else
                   window.control.index_select(0, rows)[:, steps])
        motions = window.motions[steps]
        if motions.count(motions[0]) == count:
            return motions[0].linearize(here, **inputs(control))
        return tuple(torch.stack(part, 1) for part in zip(*(
            motion.linearize(here[:, k], **inputs(
                None if control is None else control[:, k]))
            for k, motion in enumerate(motions))))

    @staticmethod
    def _transition(linearized: Tuple[Tensor, ...], point: Tensor,
                    previous: tuple):
        # the prior of a window step from the filtered mean and covariance
        # of the step before through the motion factor linearized at
        # 'point' (its f, F and Q): the prediction, its covariance and the
        # cross covariance P F^T, of the agents (of their steps, with a
        # dimension of steps)
        filtered_mean, cov = previous
        moved_mean, jacobian, noise = linearized
        mean = moved_mean + (
            jacobian @ (filtered_mean - point).unsqueeze(-1)).squeeze(-1)
        cross = cov @ jacobian.transpose(-1, -2)
        moved = jacobian @ cross + noise
        moved = symmetrize(moved)
        return GaussianBelief(mean, _inverse(moved)), moved, cross

    def _iterate_window(self, window: _Window, belief: GaussianBelief,
                        messages, fresh: Tensor, covs: Tensor,
                        anchor: Tensor, graph_of: Tensor, num_graphs: int,
                        generator, memory: Optional[Tensor] = None):
        # the iterations of one step over the window: the range messages
        # of every step from the current beliefs (window_messages, with
        # the rows' memory), then the agents' chains solved (all, or as
        # the schedule picks); a graph whose window means all moved by at
        # most the tolerance in an iteration keeps that iteration's
        # beliefs and memory and stops (each graph of a batch as alone)
        num, size = anchor.numel(), belief.mean.size(-1)
        width = belief.mean.size(0) // num
        done = torch.zeros(num_graphs, dtype=torch.bool,
                           device=anchor.device)
        moving = ~anchor  # every agent at the first iteration
        for iteration in range(self.num_iterations):
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
                new_messages, new_memory = self.window_messages(
                    window, belief, messages, fresh, memory, iteration,
                    generator)
                solved = self._solve(window, points, new_messages,
                                     (~anchor).nonzero().view(-1))
                rows = still.repeat(width)
                if memory is not None:
                    memory = torch.where(rows.view(-1, 1), new_memory,
                                         memory)
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
        return belief, messages, covs, memory

    def window_messages(self, window: _Window, belief: GaussianBelief,
                        messages, fresh: Tensor, memory: Optional[Tensor],
                        iteration: int, generator):
        r"""The messages of every factor of the window in one iteration
        of the sweep, from the window's beliefs :obj:`belief` (its
        space-time rows, step-major) and the previous :obj:`messages`
        (:obj:`fresh` marks the message edges without one), and the rows'
        :obj:`memory` after it: Gaussian BP's messages
        (:meth:`GaussianBPConv.step_messages
        <tg_nebp.nn.conv.GaussianBPConv.step_messages>`), the memory
        (:obj:`None`) unchanged. A learned correction tempers them
        (:class:`~tg_nebp.filters.FixedLagGaussianNEBP`)."""
        return self.conv.step_messages(
            belief, window.links, window.link_attr, window.anchor,
            window.factors, messages, generator, fresh), memory

    @property
    def rank_one(self) -> bool:
        r"""Whether the window's messages are rank-one (the conv's
        :attr:`~tg_nebp.nn.conv.GaussianBPConv.rank_one`, a range model's)
        rather than general."""
        return self.conv.rank_one

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
        messages, factors = self._recomputed(window, belief, messages,
                                             chosen, fresh, generator)
        solve[factors.index[1] % num] = True
        return messages, solve

    def _recomputed(self, window: _Window, belief: GaussianBelief,
                    messages, chosen: Tensor, fresh: Tensor, generator):
        # the messages of the window's factors 'chosen' (P) computed again
        # from the beliefs (those factors' links alone), the others kept
        # (fresh (M): the message edges without a previous message); and
        # the factors computed
        factors, links, kept = self.conv.factor_subset(
            window.factors, chosen, belief.mean.size(-1))
        computed = self.conv.step_messages(
            belief, window.links[:, links], window.link_attr[links],
            window.anchor, factors, type(messages)(*(m[kept]
                                                     for m in messages)),
            generator, fresh[kept])
        position = kept.nonzero().view(-1)
        return type(messages)(*(m.index_copy(0, position, c) for m, c in
                                zip(messages, computed))), factors

    def _slide(self, state: WindowState, window: _Window, messages,
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
        links, kept = _renumbered(state.links, num, num, shift=1)
        index, carried = _renumbered(state.message_index, num, num, shift=1)
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
            shapes = ([(), (), (reach, )] if self.rank_one else
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
        if state.settled_mean is not None and (
                sizes['C'] > width or
                state.settled_cov.shape[:2] != state.settled_mean.shape[:2]):
            raise ValueError(f"the state's 'settled_mean' holds "
                             f"{sizes['C']} steps of a window of {width}")
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
            memory=None if state.memory is None else state.memory[keep],
            window=state.window[keep], links=links,
            link_attr=state.link_attr[kept],
            control=None if state.control is None else state.control[keep],
            messages=messages, message_index=index, start=state.start[keep],
            settled_mean=None, settled_cov=None,
            entry_point=None if state.entry_point is None else
            state.entry_point[keep])

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
            memory=None if state.memory is None else torch.cat(
                [state.memory, joined.memory]),
            predicted=torch.cat([state.predicted, joined.predicted]),
            window=torch.cat([state.window, joined.mean.unsqueeze(1).expand(
                -1, width, -1)]),
            links=links, control=control, message_index=index,
            start=torch.cat([state.start, torch.full_like(joined.start,
                                                          width)]),
            settled_mean=None, settled_cov=None,
            entry_point=None if state.entry_point is None else
            torch.cat([state.entry_point, joined.mean]))

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
            start=torch.where(nodes, width, state.start),
            settled_mean=None, settled_cov=None,
            entry_point=None if state.entry_point is None else
            torch.where(nodes.view(-1, 1), mean, state.entry_point))

    def settings(self) -> dict:
        return dict(super().settings(), lag=self.lag,
                    schedule=self.schedule, iterated=self.iterated,
                    relinearize_threshold=self.relinearize_threshold,
                    relinearize_skip=self.relinearize_skip,
                    settled_inflation=self.settled_inflation)

    def __repr__(self) -> str:
        return (super().__repr__()[:-1] +
                f', lag={self.lag}, schedule={self.schedule!r}, '
                f'iterated={self.iterated}, relinearize_threshold='
                f'{self.relinearize_threshold}, relinearize_skip='
                f'{self.relinearize_skip}, settled_inflation='
                f'{self.settled_inflation})')
