from collections import deque
from typing import Iterator, List, NamedTuple, Optional, Sequence, Tuple, \
    Union

import torch
from torch import Tensor

from tg_nebp.data.realization import Realization, num_steps_of
from tg_nebp.data.validation import check_lag
from tg_nebp.filters.centralized.centralized_iekf import CentralizedIEKF
from tg_nebp.filters.centralized.group_exchange import GroupExchange
from tg_nebp.filters.centralized.group_flip import GroupFlip
from tg_nebp.filters.centralized.particle_trajectory_search import \
    ParticleTrajectorySearch
from tg_nebp.filters.tracker import StepOutput, Tracker, TrackOutput
from tg_nebp.gaussian import (GraphLayout, WoodburyPrior, block_diagonal,
                              check_dense_joint, check_predicted_prior,
                              joint_cross, marginal_blocks, predict_joint,
                              rts_backward, scope_index)
from tg_nebp.models import MeasurementModel, MotionModel, inputs

__all__ = ['CentralizedSmoother']


class _Slot(NamedTuple):
    # one step of a graph's window: its links (ranges, agent indices of
    # sender and receiver, -1 for an anchor, whose state 'known' gives)
    # and the agents' known inputs of the transition into it
    z: Tensor
    sender: Tensor
    receiver: Tensor
    known: Tensor
    control: Optional[Tensor]


class _Base(NamedTuple):
    # what precedes a graph's window: the filtered Gaussian of the step
    # before its first (or the prior) and the point the transition out of
    # it is linearized at
    mean: Tensor
    cov: Tensor
    point: Tensor


class _Pass(NamedTuple):
    # one forward-backward pass over a window linearized at its points:
    # per step the prediction (mean, covariance, cross covariance of the
    # transition into it), the filtered Gaussian and the smoothed one, the
    # means as offsets from the points
    predicted: List[Tuple[Tensor, Tensor, Tensor]]
    filtered: List[Tuple[Tensor, Tensor]]
    smoothed: List[Tuple[Tensor, Tensor]]


def _check_component(value, name: str, kind: type, does: str,
                     lag: Optional[int]):
    # a component of the whole sequence's smoother: None, or a 'kind' with
    # lag=None
    if value is None:
        return
    if not isinstance(value, kind):
        raise TypeError(f"'{name}' must be a {kind.__name__} or None, got "
                        f"{type(value).__name__}")
    if lag is not None:
        raise ValueError(f"'{name}' {does}: it needs lag=None, got "
                         f"lag={lag}")


#: The Gauss-Newton iterations of the whole sequence's smoother by default
#: (it stops early at its tolerance).
WHOLE_SEQUENCE_ITERATIONS = 50


class CentralizedSmoother(CentralizedIEKF):
    r"""The centralized Gauss-Newton smoother over a window of steps, the
    reference that fixed-lag Gaussian BP
    (:class:`~tg_nebp.filters.FixedLagGaussianBP`) is measured against:
    one joint Gaussian over all agents of a graph at each of the last
    :obj:`lag` steps. Every step it finds the maximum a posteriori states
    of the window,

    .. math::
        \min_{\mathbf{x}_{n-L+1:n}} \tfrac{1}{2} \|\mathbf{x}_{n-L+1} -
        \boldsymbol{\mu}^-_{n-L+1}\|^2_{(\mathbf{P}^-_{n-L+1})^{-1}} +
        \sum_k \tfrac{1}{2} \|\mathbf{x}_k -
        f(\mathbf{x}_{k-1})\|^2_{\mathbf{Q}_k^{-1}} - \sum_k \sum_{j \to i}
        \log p\big(z^{(k)}_{j \to i} \,\big|\, d_{ji}(\mathbf{x}_k)\big),

    by Gauss-Newton: each iteration linearizes every motion and
    measurement factor of the window at the current states and solves
    the linearized problem exactly by a Kalman filter and a
    Rauch-Tung-Striebel backward pass (the iterated Kalman smoother of
    `"The Iterated Kalman Smoother as a Gauss-Newton Method"
    <https://doi.org/10.1137/0804035>`_, Bell, SIAM J. Optim. 1994; the
    covariance form takes the singular driving noise of the
    constant-velocity models and of odometry), with the step halved until
    the cost decreases. The cost is that of the window's first state and
    every transition's driving noise (:math:`\mathbf{x}_k =
    f(\mathbf{x}_{k-1}) + \mathbf{L}_k \mathbf{w}_k`, :math:`\mathbf{Q}_k =
    \mathbf{L}_k \mathbf{L}_k^\top`, :math:`\mathbf{w}_k` white): a trial
    is rolled out through the motion model, so every iterate lies on the
    model's own trajectories, where a singular noise keeps it. A start off
    them (a filter's estimates, another method's) is first followed along
    a trajectory: each transition's noise moves the state rolled out so
    far as close to the start's next as the noise reaches.
    Each update is the centralized IEKF's
    (:class:`~tg_nebp.filters.CentralizedIEKF`: the measurement model's own
    likelihood, Woodbury on the entries the links inform). When the window
    slides, its oldest step is marginalized out: its filtered Gaussian
    at the solution, predicted into the next step (the Schur complement of
    the linearized window), is the next window's prior.

    Each step yields the newest state (the filtered estimate, its past
    relinearized) and the whole window (:obj:`window_mean`,
    :obj:`window_cov`: the smoothed estimates of the last :math:`L`
    steps); :class:`~tg_nebp.filters.Smoothed` reads each step's at lag
    :math:`L`. With :obj:`lag=1` it is the centralized IEKF (equal to
    rounding once the iterations converge). With :obj:`lag=None` it is the
    full batch smoother: the whole sequence is one window, started from
    the filtered estimates of :obj:`lag=1` (or from other trackers',
    :obj:`start`, the optimum of lowest cost kept, and groups of agents
    taken from the others' where that costs less, :obj:`exchange`, a
    :class:`~tg_nebp.filters.GroupExchange`), then searched for
    better basins (:obj:`search`, a
    :class:`~tg_nebp.filters.ParticleTrajectorySearch`), and every step's
    smoothed estimate is yielded at the end.

    Float64 inside, dense :math:`(AS)^2` joints per step of the window;
    time grows as :math:`L A^3` per iteration. Offline only (no live
    session): it is the reference. No random draws but the search's.

    Args:
        lag (int, optional): Steps in the window :math:`L` (the newest
            counted), or :obj:`None` for all. (default: :obj:`5`)
        num_iterations (int, optional): Gauss-Newton iterations per time
            step (per sequence with :obj:`lag=None`); :obj:`None` for 5 per
            step in a window and 50 for the whole sequence (which stop
            early at the :obj:`tolerance`: a whole sequence's iterations
            move every step at once, and 5 of them can leave a stretch of
            it far from the optimum, as on MILUV's drone).
            (default: :obj:`None`)
        motion (MotionModel, optional): Motion model with an
            additive-Gaussian-noise form.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): Measurement model whose
            likelihood the smoother maximizes.
            (default: :obj:`GaussianRange()`)
        max_halvings (int, optional): Halvings of a Gauss-Newton step before
            the iterations stop at the current point. (default: :obj:`10`)
        tolerance (float, optional): The iterations stop after a step
            whose largest entry is at most this. (default: :obj:`1e-6`)
        start (Tracker or sequence of Tracker, optional): With
            :obj:`lag=None`, a tracker whose estimates of the whole
            sequence start the iterations, for example
            ``Smoothed(IncrementalSmoother())`` (the incremental smoother's
            at the last step: the past relinearized as every step arrived,
            which keeps fewer of the filter's lost agents), or several:
            the iterations run from each, and each graph keeps the optimum
            of lowest cost (:meth:`sequence_cost`; the first of equal
            ones), so a start in a better basin than the others' wins
            outright. :obj:`None` starts from the filtered estimates of
            :obj:`lag=1`. They draw from the same :obj:`generator`, in
            turn. (default: :obj:`None`)
        search (ParticleTrajectorySearch, optional): With :obj:`lag=None`,
            the search of every agent's trajectory for a better basin
            than its start's, after the iterations converge (its sweeps
            draw from the :obj:`generator`); :obj:`None` keeps the start's
            basin. (default: :obj:`None`)
        exchange (GroupExchange, optional): With :obj:`lag=None` and
            several starts (:obj:`start` trackers, or the states given to
            :meth:`smoothed_from`), the exchange of connected groups of
            agents between their optima, from the one of lowest cost,
            before the :obj:`search`: where each start lost a different
            group; :obj:`None` keeps the optimum of lowest cost as it is.
            (default: :obj:`None`)
        flip (GroupFlip, optional): With :obj:`lag=None`, the flip of
            connected groups of agents that range to no anchor across
            their outside neighbours' line, after the :obj:`exchange` and
            before the :obj:`search`: a group on the mirror of its
            position in every start; :obj:`None` flips none.
            (default: :obj:`None`)

    Shapes:
        - **input:** a :class:`~tg_nebp.data.Realization`
        - **output:** :class:`~tg_nebp.filters.TrackOutput` with mean
          :math:`(N, T, S)` and covariance :math:`(N, T, S, S)` (the
          filtered estimates; the full smoother's smoothed ones)
    """
    #: The offline reference keeps no state between steps and does not run
    #: live (:class:`~tg_nebp.filters.TrackingSession` refuses it).
    state_type = None

    def __init__(self, lag: Optional[int] = 5,
                 num_iterations: Optional[int] = None,
                 motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None,
                 max_halvings: int = 10, tolerance: float = 1e-6,
                 start: Union[None, Tracker, Sequence[Tracker]] = None,
                 search: Optional[ParticleTrajectorySearch] = None,
                 exchange: Optional[GroupExchange] = None,
                 flip: Optional[GroupFlip] = None):
        lag = check_lag(lag)
        if start is not None:
            starts = (start, ) if isinstance(start, Tracker) else start
            if not isinstance(starts, (list, tuple)) or not starts:
                raise TypeError(f"'start' must be a Tracker, a non-empty "
                                f"sequence of them or None, got "
                                f"{type(start).__name__}")
            for index, one in enumerate(starts):
                if not isinstance(one, Tracker):
                    raise TypeError(f"'start[{index}]' must be a Tracker, "
                                    f"got {type(one).__name__}")
            if lag is not None:
                raise ValueError(f"'start' starts the whole sequence's "
                                 f"smoother: it needs lag=None, got "
                                 f"lag={lag}")
        _check_component(search, 'search', ParticleTrajectorySearch,
                         "escapes the whole sequence's smoother", lag)
        _check_component(exchange, 'exchange', GroupExchange,
                         "exchanges groups between the whole sequence's "
                         "optima", lag)
        _check_component(flip, 'flip', GroupFlip,
                         "flips groups of the whole sequence's solution",
                         lag)
        if num_iterations is None:
            num_iterations = WHOLE_SEQUENCE_ITERATIONS if lag is None else 5
        super().__init__(num_iterations, motion, measurement,
                         max_halvings=max_halvings, tolerance=tolerance)
        self.lag = lag
        self.start = start if start is None or isinstance(
            start, Tracker) else tuple(start)
        self.search = search
        self.exchange = exchange
        self.flip = flip

    @property
    def starts(self) -> Tuple[Tracker, ...]:
        r"""The trackers whose estimates start the whole sequence's
        iterations (none: the filter's)."""
        if self.start is None:
            return ()
        return (self.start, ) if isinstance(self.start, Tracker) else \
            self.start

    def initial_state(self, data, generator=None):
        raise NotImplementedError(
            'CentralizedSmoother does not run live: it is the offline '
            'reference (FixedLagGaussianBP runs live)')

    def steps(self, data: Realization,
              generator=None) -> Iterator[StepOutput]:
        r"""Runs the time loop lazily, yielding a
        :class:`~tg_nebp.filters.StepOutput` per time step with the
        window's smoothed estimates (every step's at the end with
        :obj:`lag=None`).

        Args:
            data (Realization): A single or batched realization.
            generator (torch.Generator or list, optional): The draws of
                the :obj:`search` (the smoother draws nothing without
                one), one generator for all graphs or one per graph.
                (default: :obj:`None`)
        """
        self.check(data)
        check_predicted_prior(data, self.motion, 'the centralized smoother',
                              self.use_control)
        layout = GraphLayout.of(data)
        size = data.prior_mean.size(1)
        check_dense_joint(max(a.numel() for a in layout.agents), size,
                          'the centralized smoother', data.prior_mean.device)
        if self.lag is None:
            yield from self._batch(data, layout, generator=generator)
            return
        for t, means, covs in self._windows(data, layout, self.lag):
            yield self._output(t, data, layout, means, covs)

    def _windows(self, data: Realization, layout: GraphLayout, lag: int):
        # the time loop with windows of 'lag' steps: per step its index
        # and, per graph, the window's solution (W, A, S) (angles lifted)
        # and smoothed marginal covariances (W, A, S, S)
        known = data.prior_mean.double()
        prior_cov = data.prior_cov.double()
        size = known.size(1)
        bases = [_Base(known[nodes], block_diagonal(prior_cov[nodes]),
                       known[nodes]) for nodes in layout.agents]
        windows = [deque() for _ in layout.agents]
        points = [deque() for _ in layout.agents]
        for t, slots in enumerate(self._slots(data, layout)):
            means, covs = [], []
            for g in range(len(layout.agents)):
                windows[g].append(slots[g])
                # a new step starts at its prediction from the last one
                if points[g]:
                    points[g].append(self.motion.mean(
                        points[g][-1], **inputs(slots[g].control)))
                else:
                    points[g].append(self._predicted(
                        bases[g], slots[g].control)[0])
                solved, final = self._solve(bases[g], list(windows[g]),
                                            list(points[g]))
                points[g] = deque(solved)
                means.append(torch.stack(solved))
                covs.append(torch.stack([marginal_blocks(cov, size)
                                         for _, cov in final.smoothed]))
                if len(windows[g]) == lag:  # the oldest step leaves
                    offset, cov = final.filtered[0]
                    bases[g] = _Base(solved[0] + offset, cov, solved[0])
                    windows[g].popleft()
                    points[g].popleft()
            yield t, means, covs

    def smoothed_from(self, data: Realization,
                      start: Union[Tensor, Sequence[Tensor]],
                      generator: Optional[torch.Generator] = None
                      ) -> TrackOutput:
        r"""The whole sequence's maximum a posteriori states of a single
        realization by the Gauss-Newton iterations of :obj:`lag=None`,
        started from the states :obj:`start` :math:`(N, T, S)` (another
        method's estimates, or the truth, to find the optimum of its
        basin) instead of the filter's: the smoothed means and covariances
        (anchors at their known states). The optimum is the start's basin's:
        started from its filter, the full smoother keeps an agent that the
        filter lost where the filter left it, unless the :obj:`search`
        moves it (drawing from :obj:`generator`).

        Args:
            data (Realization): A single realization.
            start (Tensor or sequence of Tensor): The states
                :math:`(N, T, S)` that start the iterations, or several
                (a list or tuple of them), each starting them as several
                :obj:`start` trackers do: the optimum of lowest cost is
                kept, with an :obj:`exchange` the groups it takes from the
                others'.
            generator (torch.Generator, optional): The :obj:`search`'s
                draws. (default: :obj:`None`)
        """
        given = [start] if isinstance(start, Tensor) else start
        if not isinstance(given, (list, tuple)) or not given:
            raise ValueError(f"'start' must be a tensor of shape (N, T, S) "
                             f"or a non-empty list or tuple of them, got "
                             f"{type(start).__name__}")
        layout = None
        for index, one in enumerate(given):
            layout = self._single(data, one, 'start' if isinstance(
                start, Tensor) else f'start[{index}]')
        means, covs = [], []
        # per start, per step, per graph, a window of one step (as the
        # filter's)
        for output in self._batch(data, layout, [
                [[state.unsqueeze(0)] for state in one.to(
                    data.prior_mean.device).double()[
                    layout.agents[0]].unbind(1)] for one in given],
                generator):
            means.append(output.mean)
            covs.append(output.cov)
        return TrackOutput(torch.stack(means, 1), torch.stack(covs, 1))

    def sequence_cost(self, data: Realization, states: Tensor) -> Tensor:
        r"""The whole sequence's cost at the states :obj:`states`
        :math:`(N, T, S)` of a single realization's nodes (the agents'
        read; on the motion model's trajectories, as every smoothed track
        is): the negative log-posterior that :obj:`lag=None` minimizes, up
        to a constant, as its iterations weigh it (each transition by the
        driving noise that makes it). Lower is a better basin: what the
        :obj:`search` compares."""
        layout = self._single(data, states, 'states')
        base, slots, (points, ) = self._problem(data, layout, [[
            [state.unsqueeze(0)] for state in
            states.to(data.prior_mean.device).double()[
                layout.agents[0]].unbind(1)]])[0]
        return self._cost_of(base, slots, points)

    def _single(self, data: Realization, states, name: str) -> GraphLayout:
        # the layout of a single realization, checked as the time loop
        # checks it, whose agents' whole-sequence 'states' (N, T, S) are
        # given as 'name'
        self.check(data)
        check_predicted_prior(data, self.motion, 'the centralized smoother',
                              self.use_control)
        if self.lag is not None:
            raise ValueError(f"'{name}' is the whole sequence's: it needs "
                             f"lag=None, got lag={self.lag}")
        layout = GraphLayout.of(data)
        if len(layout.agents) != 1:
            raise ValueError(f"a single realization is needed, got a batch "
                             f"of {len(layout.agents)}")
        shape = (data.num_nodes, num_steps_of(data), data.prior_mean.size(1))
        if not isinstance(states, Tensor) or tuple(states.shape) != shape:
            raise ValueError(f"'{name}' must be a tensor of shape (N, T, S) "
                             f"= {shape}, got "
                             f"{getattr(states, 'shape', states)!r}")
        if not bool(torch.isfinite(states[layout.agents[0]]).all()):
            raise ValueError(f"'{name}' must be finite at every agent")
        return layout

    def _batch(self, data: Realization, layout: GraphLayout,
               start: Optional[List[List[List[Tensor]]]] = None,
               generator: Optional[torch.Generator] = None
               ) -> Iterator[StepOutput]:
        # the full smoother: Gauss-Newton over every step at once, from the
        # filter's estimates (or the start trackers', or from 'start': per
        # start, per step, per graph, its agents' states as a window of one
        # step), the groups exchanged, then the search's escapes
        size = data.prior_mean.size(1)
        means, covs = [], []
        # one generator per graph (as the evaluation passes them), or one
        # for all
        generators = (generator if isinstance(generator, (list, tuple))
                      else [generator] * len(layout.agents))
        for (base, mine, starts), drawn in zip(
                self._problem(data, layout, start, generator), generators):
            solutions = [self._solve(base, mine, points) for points in
                         starts]
            solved, final = solutions[0]
            if len(solutions) > 1:
                costs = [float(self._cost_of(base, mine, one)) for one, _
                         in solutions]
                # the first of equal costs (sorted keeps it), a NaN last
                order = sorted(range(len(costs)), key=lambda k: (
                    costs[k] != costs[k], costs[k]))
                solved, final = solutions[order[0]]
                if self.exchange is not None:
                    solved, final = self.exchange.exchanged(
                        self, base, mine, (solved, final),
                        [solutions[k][0] for k in order[1:]])
            if self.flip is not None:
                solved, final = self.flip.flipped(self, base, mine,
                                                  (solved, final))
            if self.search is not None:
                solved, final = self.search.escaped(
                    self, base, mine, (solved, final), drawn)
            means.append(torch.stack(solved))
            covs.append(torch.stack([marginal_blocks(cov, size)
                                     for _, cov in final.smoothed]))
        output = self._output(means[0].size(0) - 1, data, layout, means,
                              covs)
        for t in range(output.window_mean.size(1)):
            yield StepOutput(t, output.window_mean[:, t],
                             output.window_cov[:, t])

    def _problem(self, data: Realization, layout: GraphLayout,
                 start: Optional[List[List[List[Tensor]]]] = None,
                 generator=None):
        # per graph the whole sequence's problem: the Gaussian before it
        # (the prior), every step's links and the starts of the iterations
        # (one per start tracker, or the filter's estimates, unless
        # 'start' gives them: per start, per step, per graph, its agents'
        # states as a window of one step)
        if start is not None:
            starts = [self._lifted(data, layout, one) for one in start]
        elif self.start is None:
            starts = [[means for _, means, _ in
                       self._windows(data, layout, 1)]]
        else:
            starts = []
            for tracker in self.starts:
                means = tracker(data, generator).mean.to(
                    data.prior_mean.device).double()
                starts.append(self._lifted(data, layout, [
                    [means[nodes, t].unsqueeze(0) for nodes in
                     layout.agents] for t in range(means.size(1))]))
        known = data.prior_mean.double()
        prior_cov = data.prior_cov.double()
        slots = list(self._slots(data, layout))
        return [(_Base(known[nodes], block_diagonal(prior_cov[nodes]),
                       known[nodes]), [step[g] for step in slots],
                 [[step[g][0] for step in lifted] for lifted in starts])
                for g, nodes in enumerate(layout.agents)]

    def _lifted(self, data: Realization, layout: GraphLayout,
                start: List[List[Tensor]]) -> List[List[Tensor]]:
        # a given start with its angles lifted along the sequence, as the
        # filter's are: each step within half a turn of the one before,
        # the first of the prior's mean
        nearest = self.motion.layout(data.prior_mean.size(1)).nearest
        lifted = [[data.prior_mean.double()[nodes].unsqueeze(0)
                   for nodes in layout.agents]]
        for step in start:
            lifted.append([nearest(here.double(), before) for
                           here, before in zip(step, lifted[-1])])
        return lifted[1:]

    def _slots(self, data: Realization, layout: GraphLayout):
        # every step's links per graph, as the IEKF's update reads them
        known = data.prior_mean.double()
        for (edge_index, edge_attr), control in zip(
                data.edges_by_step(), self.controls_of(data)):
            src, dst = edge_index
            edge_graph = layout.graph_of[dst]
            slots = []
            for g, nodes in enumerate(layout.agents):
                mine = edge_graph == g
                slots.append(_Slot(
                    edge_attr[mine].double(), layout.agent_index[src[mine]],
                    layout.agent_index[dst[mine]], known[src[mine]],
                    None if control is None else control[nodes].double()))
            yield slots

    def _output(self, t: int, data: Realization, layout: GraphLayout,
                means: List[Tensor], covs: List[Tensor]) -> StepOutput:
        # every node's window (anchors: their known state, zero covariance)
        # and the newest step, angles wrapped
        known = data.prior_mean.double()
        width, size = means[0].size(0), known.size(1)
        window_mean = known.unsqueeze(1).repeat(1, width, 1)
        window_cov = known.new_zeros(known.size(0), width, size, size)
        for g, nodes in enumerate(layout.agents):
            window_mean[nodes] = means[g].transpose(0, 1)
            window_cov[nodes] = covs[g].transpose(0, 1)
        window_mean = self.motion.layout(size).wrap(window_mean)
        return StepOutput(t, window_mean[:, -1], window_cov[:, -1],
                          window_mean=window_mean, window_cov=window_cov)

    def _predicted(self, base: _Base, control: Optional[Tensor],
                   motion: Optional[MotionModel] = None):
        # the prediction out of a Gaussian linearized at its point by
        # 'motion' (the tracker's by default): the mean, covariance,
        # Jacobian and cross covariance
        motion = self.motion if motion is None else motion
        given = inputs(control)
        moved, jacobian, noise = motion.linearize(base.point, **given)
        # the mean's offset from the point carried through the Jacobian (a
        # zero offset adds zeros: the IEKF's prediction exactly)
        mean = moved + (
            jacobian @ (base.mean - base.point).unsqueeze(-1)).squeeze(-1)
        cov = predict_joint(base.cov, jacobian, noise)
        return mean, cov, joint_cross(base.cov, jacobian)

    def _forward_backward(self, base: _Base, slots: List[_Slot],
                          points: List[Tensor]) -> _Pass:
        # the window linearized at 'points': a Kalman filter whose updates
        # are the IEKF's Gauss-Newton systems at the points, then the
        # backward pass; the means as offsets from the points, so that a
        # window of one step takes the IEKF's step exactly
        count, size = points[0].shape
        scope = scope_index(count, size, self.measurement.scope(size),
                            points[0].device)
        predicted, filtered = [], []
        for slot, here in zip(slots, points):
            mean, prior_cov, cross = self._predicted(base, slot.control)
            update, grad, _ = self._linearized(
                here, WoodburyPrior.of(prior_cov, scope),
                torch.linalg.cholesky(prior_cov), mean, slot.z, slot.sender,
                slot.receiver, slot.known)
            offset = update.solve(grad.view(-1))
            cov = update.covariance()
            predicted.append(((mean - here).view(-1), prior_cov, cross))
            filtered.append((offset, cov))
            base = _Base(here + offset.view_as(here), cov, here)
        smoothed = [filtered[-1]]
        for k in range(len(slots) - 2, -1, -1):
            _, predicted_cov, cross = predicted[k + 1]
            offset, cov = rts_backward(
                filtered[k][1], cross, predicted_cov, smoothed[0][1],
                filtered[k][0], predicted[k + 1][0], smoothed[0][0])
            smoothed.insert(0, (offset, cov))
        shape = points[0].shape
        return _Pass(predicted,
                     [(o.view(shape), c) for o, c in filtered],
                     [(o.view(shape), c) for o, c in smoothed])

    def _noise_factors(self, slots: List[_Slot], points: List[Tensor]):
        # per transition into window step k > 0, linearized at the agents'
        # step k - 1: the Jacobian F, a square root L of the driving noise
        # (Q = L L^T; zero columns where Q is singular) and its
        # pseudo-inverse, which maps a move off f(x_{k-1}) to the noise
        # that makes it
        out = []
        for k in range(1, len(slots)):
            given = inputs(slots[k].control)
            values, vectors = torch.linalg.eigh(self.motion.noise_covariance(
                points[k - 1], **given))
            keep = values > values.amax(-1, keepdim=True) * 1e-12
            root = values.clamp_min(0).sqrt()
            inverse = torch.where(keep, 1 / torch.where(keep, root, 1.0),
                                  0.0)
            out.append((self.motion.jacobian(points[k - 1], **given),
                        vectors * root.unsqueeze(-2),
                        inverse.unsqueeze(-1) * vectors.transpose(-1, -2)))
        return out

    def _noises(self, slots: List[_Slot], points: List[Tensor],
                factors) -> List[Tensor]:
        # the driving noise of every transition of the window at 'points'
        # (the move off f(x_{k-1}) mapped by the pseudo-inverse of its
        # noise's square root: the part the noise reaches)
        return [(inverse @ (points[k] - self.motion.mean(
            points[k - 1], **inputs(slots[k].control))).unsqueeze(-1)
                 ).squeeze(-1)
                for k, (_, _, inverse) in enumerate(factors, 1)]

    def _rolled_out(self, slots: List[_Slot], first: Tensor,
                    noises: List[Tensor], factors) -> List[Tensor]:
        # the window's states from its first step's and every transition's
        # driving noise: on the motion model's own trajectory, so that a
        # singular noise (a constant-velocity model's, odometry's) is kept
        # exactly
        states = [first]
        for k, (noise, (_, root, _)) in enumerate(zip(noises, factors), 1):
            states.append(self.motion.mean(states[-1],
                                           **inputs(slots[k].control)) +
                          (root @ noise.unsqueeze(-1)).squeeze(-1))
        return states

    def _followed(self, slots: List[_Slot], points: List[Tensor], factors
                  ) -> Tuple[List[Tensor], List[Tensor]]:
        # the motion model's trajectory that follows 'points' from their
        # first step, and its driving noises: each transition's the part of
        # the move from the state before, as rolled out, to the given state
        # that the noise reaches. A given state off the model's
        # trajectories (a filter's estimates, a reflected group) leaves an
        # error that the next steps correct, where the noises of the given
        # states' own moves, rolled out, would add the errors up (tens of
        # metres over a long sequence); on a trajectory both are the given
        # states
        states, noises = [points[0]], []
        for k, (_, root, inverse) in enumerate(factors, 1):
            mean = self.motion.mean(states[-1], **inputs(slots[k].control))
            noises.append((inverse @ (points[k] - mean).unsqueeze(-1)
                           ).squeeze(-1))
            states.append(mean + (root @ noises[-1].unsqueeze(-1)
                                  ).squeeze(-1))
        return states, noises

    def _window_cost(self, slots: List[_Slot], states: List[Tensor],
                     noises: List[Tensor], factor: Tensor,
                     prior: Tensor) -> Tensor:
        # the negative log-posterior of the window (up to a constant): the
        # first step's prior and links (the IEKF's cost of a step), every
        # transition's driving noise (white, unit variance) and links
        first = slots[0]
        cost = self._cost(states[0], prior, factor, first.z, first.sender,
                          first.receiver, first.known)
        for k in range(1, len(slots)):
            slot = slots[k]
            cost = cost + 0.5 * noises[k - 1].square().sum()
            cost = cost - self._log_likelihood(states[k], slot.z,
                                               slot.sender, slot.receiver,
                                               slot.known)
        return cost

    def _cost_of(self, base: _Base, slots: List[_Slot],
                 points: List[Tensor]) -> Tensor:
        # the window's cost at 'points' (on the motion model's
        # trajectories, as every iterate is), as the iterations weigh it
        prior, prior_cov, _ = self._predicted(base, slots[0].control)
        factors = self._noise_factors(slots, points)
        return self._window_cost(slots, points, self._noises(
            slots, points, factors), torch.linalg.cholesky(prior_cov), prior)

    def _solve(self, base: _Base, slots: List[_Slot], points: List[Tensor],
               iterations: Optional[int] = None
               ) -> Tuple[List[Tensor], _Pass]:
        # Gauss-Newton over the window from 'points' with step halving:
        # the solution and the forward-backward pass at it. The window is
        # parametrized by its first state and the driving noise of every
        # transition; each step is the iterated Kalman smoother's, mapped
        # to them, and a trial is rolled out through the motion model
        prior, prior_cov, _ = self._predicted(base, slots[0].control)
        factor = torch.linalg.cholesky(prior_cov)
        for _ in range(self.num_iterations if iterations is None
                       else iterations):
            factors = self._noise_factors(slots, points)
            points, noises = self._followed(slots, points, factors)
            cost = self._window_cost(slots, points, noises, factor, prior)
            step = [offset for offset, _ in
                    self._forward_backward(base, slots, points).smoothed]
            moves = [(inverse @ (step[k] - (jacobian @ step[k - 1].unsqueeze(
                -1)).squeeze(-1)).unsqueeze(-1)).squeeze(-1)
                for k, (jacobian, _, inverse) in enumerate(factors, 1)]
            scale = 1.0
            for _ in range(self.max_halvings + 1):
                trial_noises = [n + scale * m for n, m in zip(noises, moves)]
                trial = self._rolled_out(slots, points[0] + scale * step[0],
                                         trial_noises, factors)
                if bool(self._window_cost(slots, trial, trial_noises, factor,
                                          prior) <= cost):
                    break
                scale = 0.5 * scale
            else:  # no decrease along the Gauss-Newton direction: converged
                break
            moved = max(float((t - p).abs().amax())
                        for t, p in zip(trial, points))
            points = trial
            if moved <= self.tolerance:
                break
        return points, self._forward_backward(base, slots, points)

    def settings(self) -> dict:
        starts = [tracker.settings() for tracker in self.starts]
        return dict(super().settings(), lag=self.lag, **(
            {} if not starts else dict(start=starts[0] if isinstance(
                self.start, Tracker) else starts)), **(
            {} if self.search is None else
            dict(search=self.search.settings())), **(
            {} if self.exchange is None else
            dict(exchange=self.exchange.settings())), **(
            {} if self.flip is None else dict(flip=self.flip.settings())))

    def __repr__(self) -> str:
        start = '' if self.start is None else f', start={self.start!r}'
        search = '' if self.search is None else f', search={self.search}'
        exchange = '' if self.exchange is None else \
            f', exchange={self.exchange}'
        flip = '' if self.flip is None else f', flip={self.flip}'
        return (f'{self.__class__.__name__}(lag={self.lag}, num_iterations='
                f'{self.num_iterations}, motion={self.motion}, '
                f'measurement={self.measurement}{start}{search}{exchange}'
                f'{flip})')
