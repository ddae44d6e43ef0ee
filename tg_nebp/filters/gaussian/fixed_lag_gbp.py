import math
from typing import Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.data.validation import check_number, check_positive_int
from tg_nebp.filters.gaussian.gaussian_bp import (GBP_RECOMMENDED, GaussianBP,
                                                  SolvedStep)
from tg_nebp.filters.gaussian.relocation import LinkSearch, relocation_step
from tg_nebp.filters.gaussian.trajectory_search import (TrajectorySearch,
                                                        WindowRelocation)
from tg_nebp.filters.gaussian.window_chain import SolvedWindow, WindowChains
from tg_nebp.filters.gaussian.window_state import (SlidingWindow, Window,
                                                   WindowState, renumbered)
from tg_nebp.filters.tracker import StepOutput
from tg_nebp.models import MeasurementModel, MotionModel
from tg_nebp.nn.conv.gaussian_bp_conv import GaussianBelief

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


class FixedLagGaussianBP(SlidingWindow, WindowChains, WindowRelocation,
                         GaussianBP):
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
            :class:`~tg_nebp.filters.GaussianBP` (an agent relocated by a
            :class:`~tg_nebp.filters.LinkSearch` rejoins the window:
            :meth:`reinitialized`); a
            :class:`~tg_nebp.filters.TrajectorySearch` searches the
            window's trajectories and moves an agent's whole window, its
            links kept.
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
    has_window = True

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
        hindsight = None
        if isinstance(self.relocation, TrajectorySearch):
            relocated, hindsight = self._relocated_window(
                state, window, belief, messages, points, anchor, graph_of,
                t, generator)
            if relocated is not None:
                state, window, belief, messages, covs, points = relocated
                settled = None, None  # its forward pass runs again
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
        if hindsight is not None:
            return solved._replace(search=self._newest_search(
                hindsight, solved, edge_index, edge_attr, anchor))
        return relocation_step(self, solved, edge_index, edge_attr, anchor,
                               state.fresh, graph_of, t)

    def _iterate_window(self, window: Window, belief: GaussianBelief,
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
                                     SolvedWindow(belief, covs))
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
                solved = SolvedWindow(GaussianBelief(*(
                    torch.where(rows.view((-1, ) + (1, ) * (n.dim() - 1)),
                                n, o) for n, o in zip(solved.belief,
                                                      belief))),
                    torch.where(still.view(-1, 1, 1, 1), solved.cov, covs))
                messages = type(messages)(*(
                    torch.where(edges.view((-1, ) + (1, ) * (n.dim() - 1)),
                                n, o)
                    for n, o in zip(new_messages, messages)))
            solved = SolvedWindow(*self.share(*solved))
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

    def window_messages(self, window: Window, belief: GaussianBelief,
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

    def _residual_messages(self, window: Window, belief: GaussianBelief,
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

    def _recomputed(self, window: Window, belief: GaussianBelief,
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
        links, kept = renumbered(state.links, num, count, node_map)
        messages, index = state.messages, state.message_index
        if index is not None:
            index, carried = renumbered(index, num, count, node_map)
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
        links, _ = renumbered(state.links, num, count)
        index = state.message_index
        if index is not None:
            index, _ = renumbered(index, num, count)
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
