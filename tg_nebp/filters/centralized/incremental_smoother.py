import math
from typing import Iterator, List, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.data.realization import Realization
from tg_nebp.data.validation import check_number, check_positive_int
from tg_nebp.filters.centralized.centralized_smoother import (
                                                              CentralizedSmoother,
                                                              _Base, _Slot)
from tg_nebp.filters.state import StateField
from tg_nebp.filters.tracker import StepOutput
from tg_nebp.gaussian import (GraphLayout, WoodburyPrior, block_diagonal,
                              check_dense_joint, check_predicted_prior,
                              joined_joint, joint_cross, marginal_blocks,
                              scope_index)
from tg_nebp.models import MotionModel, MeasurementModel, inputs
from tg_nebp.utils import symmetrize

__all__ = ['IncrementalSmoother', 'SmootherState']


class SmootherState(NamedTuple):
    r"""What the incremental smoother carries from one time step to the
    next in a live session (:class:`~tg_nebp.filters.TrackingSession`):
    the whole history since the session started or its nodes last
    changed. Every node's newest estimate :obj:`mean` :math:`(N, S)` (an
    anchor's known state), the Gaussian before the history (its mean
    :obj:`prior` :math:`(N, S)`, also its linearization point, and the
    joint covariance :obj:`joints` of the agents), every step's
    linearization points :obj:`points` and offsets :obj:`deltas`
    :math:`(N, T, S)` (the estimate of step :math:`k` is their sum; angles
    lifted), the links of every step :obj:`links` :math:`(2, E)` (node
    indices), their step :obj:`link_step` :math:`(E)` and features
    :obj:`link_attr` :math:`(E, F)`, each step's time step
    :obj:`time_step` :math:`(T)` (NaN: the tracker's motion model), the
    agents' known inputs :obj:`control` :math:`(N, T, C)` (NaN rows: none;
    :obj:`None` without inputs) and the newest step's filtered joint
    covariance :obj:`newest` (the prior's before the first step). The
    linear factors and the elimination are rebuilt from these where a
    session continues from a saved state."""
    mean: Tensor
    prior: Tensor
    joints: Tuple[Tensor, ...]
    points: Tensor
    deltas: Tensor
    links: Tensor
    link_step: Tensor
    link_attr: Tensor
    time_step: Tensor
    control: Optional[Tensor]
    newest: Tuple[Tensor, ...]

    FIELDS = dict(mean=StateField(('N', 'S')), prior=StateField(('N', 'S')),
                  joints=StateField(('*', '*'), 'cov', tuple=True),
                  points=StateField(('N', 'T', 'S')),
                  deltas=StateField(('N', 'T', 'S')),
                  links=StateField(('2', 'E'), 'index'),
                  link_step=StateField(('E', ), 'index'),
                  link_attr=StateField(('E', 'F')),
                  time_step=StateField(('T', ), 'nan'),
                  control=StateField(('N', 'T', 'C'), 'nan', optional=True),
                  newest=StateField(('*', '*'), 'cov', tuple=True))


class _Chain:
    r"""One graph's whole sequence as the incremental smoother holds it:
    per step :math:`k` its links, the linearization point of its joint
    state, the linear factors there (the transition into it, its links)
    and the Kalman filter's and the backward pass's quantities of the
    linear system at the points (offsets from the points, flattened)."""

    def __init__(self, base: _Base, scope: Tensor):
        self.base = base
        self.scope = scope
        self.slots: List[_Slot] = []
        # the motion model of the transition into each step (a live
        # session's time step)
        self.motions: List[MotionModel] = []
        self.points: List[Tensor] = []
        # the transition into step k linearized at step k - 1's point:
        # f(x), its Jacobian and noise covariance (step 0: None, the
        # prior's prediction is fixed)
        self.motion: List[Optional[Tuple[Tensor, Tensor, Tensor]]] = []
        # the links of step k linearized at its point (information on
        # the scope's entries, gradient of their log-likelihood)
        self.links: List[Tuple[Tensor, Tensor]] = []
        # the prediction of step k (mean offset from its point, covariance)
        self.predicted: List[Tuple[Tensor, Tensor]] = []
        # the filtered Gaussian of step k (offset, covariance)
        self.filtered: List[Tuple[Tensor, Tensor]] = []
        # the backward pass's gain of step k (into k + 1; None for the
        # newest) and the smoothed offset of step k from its point
        self.gains: List[Optional[Tensor]] = []
        self.deltas: List[Tensor] = []

    def __len__(self) -> int:
        return len(self.points)


class IncrementalSmoother(CentralizedSmoother):
    r"""The centralized smoother of the whole sequence, incremental as
    iSAM2 is (`"iSAM2: Incremental Smoothing and Mapping Using the Bayes
    Tree" <https://doi.org/10.1177/0278364911430419>`_, Kaess et al., IJRR
    2012): every step it returns the maximum a posteriori states of all
    steps so far,

    .. math::
        \min_{\mathbf{x}_{0:n}} \tfrac{1}{2} \|\mathbf{x}_0 -
        \boldsymbol{\mu}^-_0\|^2_{(\mathbf{P}^-_0)^{-1}} + \sum_{k \geq 1}
        \tfrac{1}{2} \|\mathbf{x}_k - f(\mathbf{x}_{k-1})
        \|^2_{\mathbf{Q}_k^{-1}} - \sum_k \sum_{j \to i} \log
        p\big(z^{(k)}_{j \to i} \,\big|\, \mathbf{x}_k\big),

    as the linearization points :math:`\bar{\mathbf{x}}_k` plus the
    solution :math:`\boldsymbol{\delta}_k` of the problem linearized
    there, without solving it afresh. The states of one step (all agents of
    a graph) are one variable of a time chain, and the chain's
    elimination order is time's, so the linear system is solved by a
    Kalman filter (the elimination, oldest first) and a
    Rauch-Tung-Striebel backward pass (the back-substitution):

    1. a new step is predicted from the last filtered Gaussian and
       updated as the centralized IEKF updates
       (:class:`~tg_nebp.filters.CentralizedIEKF`: Gauss-Newton with step
       halving on the step's MAP cost); its solution is its point. Only
       the newest step is eliminated;
    2. the back-substitution runs from the newest step into the past
       while the offsets it changes move by more than
       :obj:`wildfire_threshold` (iSAM2's partial back-substitution);
    3. every step whose offset exceeds :obj:`relinearize_threshold`
       (metres, radians, metres per second: the largest entry) is
       relinearized at :math:`\bar{\mathbf{x}}_k + \boldsymbol{\delta}_k`
       (iSAM2's fluid relinearization: its motion and link factors are
       linearized again, the others kept), and the chain is eliminated
       again from the oldest such step on; 2 and 3 repeat at most
       :obj:`relinearizations` times, at every :obj:`relinearize_skip`-th
       step (iSAM2's relinearization skip; the other steps take 1 and 2)
       and at the last step of a sequence offline.

    Each step yields the newest states (the filtered estimate, its past
    relinearized: iSAM2's estimate of the newest variables right after
    its update) with their marginal covariances; the last step of a
    sequence adds every step's smoothed estimate (a full
    back-substitution with covariances, the window :obj:`window_mean` of
    every step), which :class:`~tg_nebp.filters.Smoothed` reads. With
    thresholds of zero and enough relinearizations it converges to the
    batch smoother's solution (:class:`~tg_nebp.filters.CentralizedSmoother`
    with :obj:`lag=None`); on a linear-Gaussian problem both are the
    Rauch-Tung-Striebel smoother.

    Covariance form, as the batch smoother (the singular driving noise of
    the constant-velocity models and odometry); float64 inside, dense
    :math:`(AS)^2` joints per step; memory grows with the sequence, the
    time of a step with the steps its relinearization reaches. Offline
    (:meth:`steps`) and live (:meth:`initial_state`, :meth:`step`: a
    :class:`~tg_nebp.filters.TrackingSession`, :obj:`tg-nebp track
    --method iekf --lag all --incremental`; its state
    :class:`SmootherState` holds the history); no random draws.

    Args:
        relinearize_threshold (float, optional): A step whose offset from
            its point has an entry above this is relinearized.
            (default: :obj:`0.03`)
        wildfire_threshold (float, optional): The back-substitution stops
            at the first older step whose offset moved by at most this.
            (default: :obj:`0.001`)
        relinearizations (int, optional): Rounds of relinearization and
            back-substitution per step. (default: :obj:`1`)
        relinearize_skip (int, optional): Relinearize at every this many
            steps (iSAM2's default). (default: :obj:`10`)
        num_iterations (int, optional): Gauss-Newton iterations of the
            newest step's update (the relinearization refines it later).
            (default: :obj:`2`)
        motion (MotionModel, optional): Motion model with an
            additive-Gaussian-noise form.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): Measurement model whose
            likelihood the smoother maximizes.
            (default: :obj:`GaussianRange()`)
        max_halvings (int, optional): Halvings of the newest step's
            Gauss-Newton step. (default: :obj:`10`)
        tolerance (float, optional): The newest step's iterations stop after
            a step whose largest entry is at most this.
            (default: :obj:`1e-6`)

    Shapes:
        - **input:** a :class:`~tg_nebp.data.Realization`
        - **output:** :class:`~tg_nebp.filters.TrackOutput` with mean
          :math:`(N, T, S)` and covariance :math:`(N, T, S, S)` (the
          filtered estimates; :class:`~tg_nebp.filters.Smoothed` gives
          the smoothed ones)
    """
    def __init__(self, relinearize_threshold: float = 0.03,
                 wildfire_threshold: float = 0.001,
                 relinearizations: int = 1, relinearize_skip: int = 10,
                 num_iterations: int = 2,
                 motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None,
                 max_halvings: int = 10, tolerance: float = 1e-6):
        super().__init__(None, num_iterations, motion, measurement,
                         max_halvings=max_halvings, tolerance=tolerance)
        self.relinearize_threshold = check_number(
            relinearize_threshold, 'relinearize_threshold', inclusive=True)
        self.wildfire_threshold = check_number(
            wildfire_threshold, 'wildfire_threshold', inclusive=True)
        self.relinearizations = check_positive_int(relinearizations,
                                                   'relinearizations')
        self.relinearize_skip = check_positive_int(relinearize_skip,
                                                   'relinearize_skip')

    state_type = SmootherState

    def initial_state(self, data: Realization,
                      generator=None) -> SmootherState:
        r"""The state before the first step of the nodes of :obj:`data`
        (its :obj:`prior_mean`, :obj:`prior_cov`, :obj:`anchor` and
        graphs are read): no history, the prior in float64 and, per graph,
        the block-diagonal joint of its agents' prior covariances (a joint
        too large for the free memory is refused). No draws."""
        check_predicted_prior(data, self.motion, 'the incremental smoother',
                              self.use_control)
        layout = GraphLayout.of(data)
        known = data.prior_mean.double()
        check_dense_joint(max(a.numel() for a in layout.agents),
                          known.size(1), 'the incremental smoother',
                          known.device)
        prior_cov = symmetrize(data.prior_cov.double())
        return self._fresh(known, tuple(block_diagonal(prior_cov[nodes])
                                        for nodes in layout.agents))

    def step(self, state: SmootherState, edge_index: Tensor,
             edge_attr: Tensor, anchor: Tensor, t: int, generator=None,
             motion: Optional[MotionModel] = None,
             control: Optional[Tensor] = None
             ) -> Tuple[StepOutput, SmootherState]:
        r"""One time step of a live session's graph: the new step joins
        the history (predicted by :obj:`motion`, the tracker's by
        default, with the agents' known inputs :obj:`control` :math:`(N,
        C)`, updated with the links :obj:`edge_index` :math:`(2, E)` and
        features :obj:`edge_attr` :math:`(E, F)`), then the past is
        back-substituted and relinearized as offline (:meth:`steps`).
        Returns the newest states (time index :obj:`t`: every node's mean,
        angles wrapped, and marginal covariance) and the state after the
        step. The history lives in the state; the tracker keeps the
        elimination of the state it returned last, and rebuilds it from
        any other (a saved session's)."""
        motion = self.motion if motion is None else motion
        chain = self._live_chain(state, anchor)
        layout = GraphLayout.of_nodes(anchor)
        nodes = layout.agents[0]
        src, dst = edge_index
        known = state.mean
        slot = _Slot(edge_attr.double(), layout.agent_index[src],
                     layout.agent_index[dst], known[src],
                     None if control is None else control[nodes].double())
        self._live = None  # a step that fails leaves no chain behind
        self._add(chain, slot, motion)
        count, size = known.shape
        steps = len(chain)
        points = known.unsqueeze(1).repeat(1, steps, 1)
        points[nodes] = torch.stack(chain.points, 1)
        deltas = known.new_zeros(count, steps, size)
        deltas[nodes] = torch.stack([delta.view(-1, size)
                                     for delta in chain.deltas], 1)
        mean = known.clone()
        mean[nodes] = points[nodes, -1] + deltas[nodes, -1]
        mean = self.motion.layout(size).wrap(mean)
        dt = math.nan if motion is self.motion else \
            float(motion.params()['dt'])
        history = state.control
        if control is not None or history is not None:
            width = (control if control is not None else history).size(-1)
            if history is None:
                history = known.new_full((count, steps - 1, width), math.nan)
            now = known.new_full((count, 1, width), math.nan) \
                if control is None else control.double().unsqueeze(1)
            history = torch.cat([history, now], 1)
        joint = chain.filtered[-1][1]
        new = SmootherState(
            mean, state.prior, state.joints, points, deltas,
            torch.cat([state.links, edge_index], 1),
            torch.cat([state.link_step,
                       state.link_step.new_full((src.numel(), ), steps - 1)]),
            torch.cat([state.link_attr, edge_attr.to(state.link_attr)]),
            torch.cat([state.time_step, state.time_step.new_full((1, ), dt)]),
            history, (joint, ))
        cov = known.new_zeros(count, size, size)
        cov[nodes] = marginal_blocks(joint, size)
        self._live = (new, chain)
        return StepOutput(t, mean, cov), new

    def _motion_of(self, dt: float) -> MotionModel:
        return self.motion if math.isnan(dt) else \
            self.motion.with_time_step(dt)

    def _live_chain(self, state: SmootherState, anchor: Tensor) -> _Chain:
        # the chain of the state this tracker returned last, or one rebuilt
        # from 'state': every step's factors linearized at its points and
        # eliminated, the offsets as the state holds them
        live = getattr(self, '_live', None)
        if live is not None and live[0] is state:
            return live[1]
        layout = GraphLayout.of_nodes(anchor)
        nodes = layout.agents[0]
        size = state.mean.size(1)
        chain = _Chain(_Base(state.prior[nodes], state.joints[0],
                             state.prior[nodes]),
                       scope_index(nodes.numel(), size,
                                   self.measurement.scope(size),
                                   state.mean.device))
        src, dst = state.links
        steps = state.points.size(1)
        for k in range(steps):
            mine = state.link_step == k
            chain.slots.append(_Slot(
                state.link_attr[mine].double(), layout.agent_index[src[mine]],
                layout.agent_index[dst[mine]], state.mean[src[mine]],
                None if state.control is None else
                state.control[nodes, k].double()))
            chain.motions.append(self._motion_of(float(state.time_step[k])))
            chain.points.append(state.points[nodes, k])
            chain.deltas.append(state.deltas[nodes, k].reshape(-1))
        for field in (chain.motion, chain.links, chain.predicted,
                      chain.filtered, chain.gains):
            field.extend([None] * steps)
        if steps:
            self._linearize(chain, list(range(steps)))
        for k in range(steps):
            self._eliminate(chain, k)
        return chain

    def check_state(self, state: SmootherState, anchor: Tensor,
                    state_size: int, dtype: torch.dtype):
        r""":meth:`Tracker.check_state
        <tg_nebp.filters.Tracker.check_state>`, and what ties the fields
        together: one joint each (a session holds one graph) of :math:`A
        S` rows, links between the nodes at the steps held with the
        measurement model's features."""
        sizes = super().check_state(state, anchor, state_size, dtype)
        rows = int((~anchor).sum()) * state_size
        for name in ('joints', 'newest'):
            joints = getattr(state, name)
            if len(joints) != 1 or joints[0].size(0) != rows:
                raise ValueError(f"the state's {name!r} cover "
                                 f"{[j.size(0) for j in joints]} rows, "
                                 f"expected one joint of {rows} (the "
                                 f"agents' states)")
        steps = state.points.size(1)
        features = len(self.measurement.features)
        if state.link_attr.size(1) != features:
            raise ValueError(f"the state's 'link_attr' has "
                             f"{state.link_attr.size(1)} features per link, "
                             f"the measurement model reads {features}")
        if state.links.numel() and int(state.links.max()) >= anchor.numel():
            raise ValueError(f"the state's 'links' name node "
                             f"{int(state.links.max())} of "
                             f"{anchor.numel()}")
        if state.link_step.numel() and int(state.link_step.max()) >= steps:
            raise ValueError(f"the state's 'link_step' names step "
                             f"{int(state.link_step.max())} of {steps}")
        return sizes

    def select_state(self, state: SmootherState, keep: Tensor,
                     anchor: Tensor) -> SmootherState:
        r"""The state of the nodes :obj:`keep` :math:`(N)` of one graph: a
        change of the nodes ends the smoothing of the past (its estimates
        are final), and the history starts again from the newest
        estimates and the marginal of their filtered joint on the agents
        that stay."""
        size = state.mean.size(1)
        stays = keep[~anchor].repeat_interleave(size)
        joint, = state.newest
        return self._fresh(state.mean[keep], (joint[stays][:, stays], ))

    def join_state(self, state: SmootherState,
                   joined: SmootherState) -> SmootherState:
        r"""The state of one graph's nodes followed by the joining ones
        (an :meth:`initial_state`): as :meth:`select_state`, the history
        starts again, from the newest joint extended by theirs, with no
        correlation between them."""
        (joint, ), (new, ) = state.newest, joined.joints
        return self._fresh(torch.cat([state.mean, joined.mean]), (
            joined_joint(joint, new, state.mean.size(1),
                         'the incremental smoother'), ))

    def _fresh(self, mean: Tensor,
               joints: Tuple[Tensor, ...]) -> SmootherState:
        # a state without history: the Gaussian of 'mean' and the joints
        # of its graphs' agents
        count, size = mean.shape
        empty = mean.new_zeros(count, 0, size)
        return SmootherState(
            mean, mean, joints, empty, empty,
            torch.zeros(2, 0, dtype=torch.long, device=mean.device),
            torch.zeros(0, dtype=torch.long, device=mean.device),
            mean.new_zeros(0, len(self.measurement.features)),
            mean.new_zeros(0), None, joints)

    def steps(self, data: Realization,
              generator=None) -> Iterator[StepOutput]:
        r"""Runs the time loop lazily, yielding a
        :class:`~tg_nebp.filters.StepOutput` per time step: the newest
        states and, with the last step, every step's smoothed estimate
        (:obj:`window_mean`, :obj:`window_cov` of every step; the others'
        windows hold the newest step alone).

        Args:
            data (Realization): A single or batched realization.
            generator: Unused (the smoother draws nothing).
                (default: :obj:`None`)
        """
        self.check(data)
        state = self.initial_state(data)
        layout = GraphLayout.of(data)
        size = state.mean.size(1)
        read = self.measurement.scope(size)
        chains = [_Chain(_Base(state.prior[nodes], joint, state.prior[nodes]),
                         scope_index(nodes.numel(), size, read,
                                     joint.device))
                  for nodes, joint in zip(layout.agents, state.joints)]
        steps = list(self._slots(data, layout))
        for t, slots in enumerate(steps):
            moved = [self._add(chain, slot, self.motion)
                     for chain, slot in zip(chains, slots)]
            means = [(chain.points[-1] + chain.deltas[-1].view_as(
                chain.points[-1])).unsqueeze(0) for chain in chains]
            covs = [marginal_blocks(chain.filtered[-1][1], size).unsqueeze(0)
                    for chain in chains]
            output = self._output(t, data, layout, means, covs)
            if t == len(steps) - 1:
                # the sequence ends: one more round of relinearization
                # (whatever the skip), then every step's smoothed estimate;
                # the newest states stay those of a live session
                for chain, pending in zip(chains, moved):
                    self._rounds(chain, pending)
                means, covs = zip(*(self._smoothed(chain, size)
                                    for chain in chains))
                window = self._output(t, data, layout, list(means),
                                      list(covs))
                output = window._replace(mean=output.mean, cov=output.cov)
            yield output

    def _add(self, chain: _Chain, slot: _Slot,
             motion: MotionModel) -> List[int]:
        # a new step: its prediction, the IEKF's update (its point), its
        # elimination, then the back-substitution and, at every
        # relinearize_skip-th step, relinearization; the steps whose
        # offsets exceed the threshold after it
        chain.slots.append(slot)
        chain.motions.append(motion)
        if chain.points:
            chain.motion.append(self._motion_factor(
                chain.points[-1], slot.control, motion))
        else:
            chain.motion.append(None)
        prediction = self._prediction(chain, len(chain))
        mean, cov, _ = prediction
        point, _, system = self._map_update(mean.view_as(chain.base.mean),
                                            cov, *slot[:4])
        chain.points.append(point)
        chain.links.append(system)
        chain.predicted.append(None)
        chain.filtered.append(None)
        chain.gains.append(None)
        chain.deltas.append(torch.zeros_like(point).view(-1))
        newest = len(chain) - 1
        self._eliminate(chain, newest, prediction)
        moved = self._back_substitute(chain, newest)
        if newest % self.relinearize_skip:
            return moved
        return self._rounds(chain, moved)

    def _rounds(self, chain: _Chain, moved: List[int]) -> List[int]:
        # the rounds of relinearization of the steps 'moved', elimination
        # from the oldest of them and back-substitution
        for _ in range(self.relinearizations):
            if not moved:
                break
            self._relinearize(chain, moved)
            oldest = min(moved)
            for k in range(oldest, len(chain)):
                self._eliminate(chain, k)
            moved = self._back_substitute(chain, oldest)
        return moved

    @staticmethod
    def _motion_factor(point: Tensor, control: Optional[Tensor],
                       motion: MotionModel):
        # the transition by 'motion' out of 'point' [*, A, S]: f, its
        # Jacobian and noise covariance
        return motion.linearize(point, **inputs(control))

    def _prediction(self, chain: _Chain, k: int):
        # the prediction of step k [A S], its covariance and the cross
        # covariance of step k - 1 and it, from the filtered Gaussian of
        # step k - 1 (step 0: from the prior, no cross covariance)
        if k == 0:
            mean, cov, _ = self._predicted(chain.base, chain.slots[0].control,
                                           chain.motions[0])
            return mean.view(-1), cov, None
        offset, cov = chain.filtered[k - 1]
        moved, jacobian, noise = chain.motion[k]
        mean = moved + (jacobian @ offset.view_as(moved).unsqueeze(-1)
                        ).squeeze(-1)
        # P F^T, then F (P F^T) + Q: the block-diagonal F applied twice
        cross = joint_cross(cov, jacobian)
        count, size = moved.shape
        predicted = (jacobian @ cross.view(count, size, -1)).view_as(cov)
        blocks = predicted.view(count, size, count, size)
        index = torch.arange(count, device=cov.device)
        blocks[index, :, index, :] += noise
        return mean.view(-1), symmetrize(predicted), cross

    def _eliminate(self, chain: _Chain, k: int, prediction=None):
        # the Kalman filter's step k of the system linearized at the
        # points: the prediction (given where already made), the update
        # with the links' factor (the IEKF's Woodbury form) and the
        # backward gain of step k - 1
        here = chain.points[k]
        mean, cov, cross = self._prediction(chain, k) if prediction is None \
            else prediction
        offset = mean - here.view(-1)
        factor = torch.linalg.cholesky(cov)
        info, links = chain.links[k]
        update = WoodburyPrior.of(cov, chain.scope).updated(info)
        grad = torch.cholesky_solve(offset.view(-1, 1), factor).view_as(here)
        grad[:, list(self.measurement.scope(here.size(1)))] += links
        chain.predicted[k] = (offset, cov)
        chain.filtered[k] = (update.solve(grad.view(-1)),
                             update.covariance())
        if k > 0:
            chain.gains[k - 1] = torch.cholesky_solve(
                cross.transpose(0, 1), factor).transpose(0, 1)

    def _back_substitute(self, chain: _Chain, oldest: int) -> List[int]:
        # the smoothed offsets from the newest step back: every step from
        # 'oldest' on (eliminated again), the older ones until one moves
        # by at most the wildfire threshold; the steps visited whose
        # offset exceeds the relinearization threshold
        newest = len(chain) - 1
        chain.deltas[newest] = chain.filtered[newest][0]
        moved = []
        for k in range(newest, -1, -1):
            if k < newest:
                delta = chain.filtered[k][0] + chain.gains[k] @ (
                    chain.deltas[k + 1] - chain.predicted[k + 1][0])
                change = float(torch.linalg.vector_norm(
                    delta - chain.deltas[k], math.inf))
                chain.deltas[k] = delta
            if float(torch.linalg.vector_norm(chain.deltas[k], math.inf)) > \
                    self.relinearize_threshold:
                moved.append(k)
            if k < oldest and change <= self.wildfire_threshold:
                break
        return moved

    def _relinearize(self, chain: _Chain, moved: List[int]):
        # the points of the steps 'moved' set to their estimates and the
        # factors that read them linearized there
        for k in moved:
            chain.points[k] = chain.points[k] + chain.deltas[k].view_as(
                chain.points[k])
            chain.deltas[k] = torch.zeros_like(chain.deltas[k])
        self._linearize(chain, moved)

    def _linearize(self, chain: _Chain, steps: List[int]):
        # the links of 'steps' and the transitions out of them linearized
        # at their points (the transition into a step is linearized at the
        # step before), each model called once for all the steps (once
        # per motion model of a live session's time steps)
        ends = [self._ends(chain.points[k], *chain.slots[k][1:4])
                for k in steps]
        grads, blocks = self.measurement.linearize(
            torch.cat([chain.slots[k].z for k in steps]),
            *(torch.cat(end) for end in zip(*ends)))
        counts = [chain.slots[k].z.size(0) for k in steps]
        for k, grad, block in zip(steps, grads.split(counts),
                                  blocks.split(counts)):
            slot = chain.slots[k]
            chain.links[k] = self._link_terms(chain.points[k], grad, block,
                                              slot.sender, slot.receiver)
        leaving = {}
        for k in steps:
            if k + 1 < len(chain):
                leaving.setdefault(id(chain.motions[k + 1]), []).append(k)
        for group in leaving.values():
            controls = [chain.slots[k + 1].control for k in group]
            factors = self._motion_factor(
                torch.stack([chain.points[k] for k in group]),
                None if controls[0] is None else torch.stack(controls),
                chain.motions[group[0] + 1])
            for k, *factor in zip(group, *factors):
                chain.motion[k + 1] = tuple(factor)

    def _smoothed(self, chain: _Chain, size: int) -> Tuple[Tensor, Tensor]:
        # every step's smoothed estimate [T, A, S] and marginal covariances
        # [T, A, S, S]: the full back-substitution of the linear system
        # at the points, with the Rauch-Tung-Striebel covariances
        newest = len(chain) - 1
        offset, cov = chain.filtered[newest]
        means, covs = [offset], [cov]
        for k in range(newest - 1, -1, -1):
            gain = chain.gains[k]
            predicted_offset, predicted_cov = chain.predicted[k + 1]
            filtered_offset, filtered_cov = chain.filtered[k]
            means.insert(0, filtered_offset + gain @ (
                means[0] - predicted_offset))
            covs.insert(0, symmetrize(filtered_cov + gain @ (
                covs[0] - predicted_cov) @ gain.transpose(0, 1)))
        return (torch.stack([point + offset.view_as(point) for point, offset
                             in zip(chain.points, means)]),
                torch.stack([marginal_blocks(cov, size) for cov in covs]))

    def settings(self) -> dict:
        return dict(super().settings(), incremental=True,
                    relinearize_threshold=self.relinearize_threshold,
                    wildfire_threshold=self.wildfire_threshold,
                    relinearizations=self.relinearizations,
                    relinearize_skip=self.relinearize_skip)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(relinearize_threshold='
                f'{self.relinearize_threshold}, wildfire_threshold='
                f'{self.wildfire_threshold}, relinearizations='
                f'{self.relinearizations}, relinearize_skip='
                f'{self.relinearize_skip}, num_iterations='
                f'{self.num_iterations}, motion={self.motion}, '
                f'measurement={self.measurement})')
