from typing import Iterator, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.data.realization import Realization
from tg_nebp.data.validation import check_number, check_positive_int
from tg_nebp.filters.state import StateField
from tg_nebp.filters.tracker import StepOutput, Tracker
from tg_nebp.gaussian import (GraphLayout, WoodburyPrior,
                              add_link_information, block_diagonal,
                              check_dense_joint, check_predicted_prior,
                              joined_joint, marginal_blocks, predict_joint,
                              scope_index)
from tg_nebp.models import MeasurementModel, MotionModel, inputs
from tg_nebp.utils import symmetrize

__all__ = ['CentralizedIEKF', 'JointState']


class JointState(NamedTuple):
    r"""What the centralized IEKF carries from one time step to the
    next: every node's :obj:`mean` :math:`(N, S)` (float64; an anchor's
    known state) and, per graph, the :obj:`joints` covariance
    :math:`(A S, A S)` of its agents in node order."""
    mean: Tensor
    joints: Tuple[Tensor, ...]

    FIELDS = dict(mean=StateField(('N', 'S')),
                  joints=StateField(('*', '*'), 'cov', tuple=True))


class CentralizedIEKF(Tracker):
    r"""The centralized iterated extended Kalman filter: one joint Gaussian
    over all agents of a graph, the reference that message passing is
    measured against (it sits on the posterior Cramér-Rao bound of the
    paper's test network). At every time step it

    1. predicts with the motion model's mean and Jacobian
       (:meth:`~tg_nebp.models.MotionModel.mean`,
       :meth:`~tg_nebp.models.MotionModel.jacobian`,
       :meth:`~tg_nebp.models.MotionModel.noise_covariance`):
       :math:`\boldsymbol{\mu}^- = f(\boldsymbol{\mu})`,
       :math:`\mathbf{P}^- = \mathbf{F} \mathbf{P} \mathbf{F}^\top +
       \mathbf{Q}`;
    2. finds the maximum a posteriori state of the step,

       .. math::
           \hat{\mathbf{x}} = \arg\min_{\mathbf{x}} \tfrac{1}{2}
           (\mathbf{x} - \boldsymbol{\mu}^-)^\top (\mathbf{P}^-)^{-1}
           (\mathbf{x} - \boldsymbol{\mu}^-) - \sum_{j \to i} \log
           p\big(z_{j \to i} \,\big|\, d_{ji}(\mathbf{x})\big),

       by :obj:`num_iterations` Gauss-Newton steps, each
       :math:`\mathbf{x} \leftarrow \mathbf{x} + \alpha
       \mathbf{H}^{-1} \mathbf{g}` with :math:`\mathbf{g}` the gradient of
       the log-posterior and :math:`\mathbf{H} = (\mathbf{P}^-)^{-1} +
       \sum \mathbf{W}_{ji}`, both from the measurement model's own
       likelihood (:meth:`~tg_nebp.models.MeasurementModel.linearize`: for a
       range model the scores and robust weights of
       :meth:`~tg_nebp.models.RangeModel.robust_weights`, :math:`1 /
       \sigma^2` for the Gaussian, iteratively reweighted least squares for
       the Student-t; Fisher scoring for other models), and the step
       :math:`\alpha` halved until the cost decreases;
    3. takes :math:`\mathbf{P} = \mathbf{H}^{-1}` at the solution as the
       covariance.

    Every measured range is its own term (both directions of a link, and
    anchors' ranges, which inform their agent only). With
    :obj:`marginal=True` only every agent's marginal is kept after the
    update (the cross-agent covariances are dropped before the next
    prediction): the best that a distributed filter, which keeps marginals
    only, can reach.

    Float64 inside, one dense :math:`(AS)^2` joint per graph of a batch
    (:math:`A` agents, states of size :math:`S`): a graph too large for the
    free memory is refused before any work starts; time grows as
    :math:`A^3`. No random draws: :obj:`generator` is accepted and unused.

    Args:
        num_iterations (int, optional): Gauss-Newton iterations per time
            step. (default: :obj:`5`)
        motion (MotionModel, optional): Motion model with an
            additive-Gaussian-noise form.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): Measurement model whose
            likelihood the update maximizes. (default: :obj:`GaussianRange()`)
        marginal (bool, optional): Keep only the agents' marginals between
            steps. (default: :obj:`False`)
        max_halvings (int, optional): Halvings of a Gauss-Newton step before
            the iterations stop at the current point. (default: :obj:`10`)
        tolerance (float, optional): The iterations stop after a step
            whose largest entry is at most this (metres, metres per
            second). (default: :obj:`1e-6`)

    Shapes:
        - **input:** a :class:`~tg_nebp.data.Realization`
        - **output:** :class:`~tg_nebp.filters.TrackOutput` with mean
          :math:`(N, T, S)` and covariance :math:`(N, T, S, S)` (anchors:
          their known state, zero covariance)
    """
    state_type = JointState

    def __init__(self, num_iterations: int = 5,
                 motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None,
                 marginal: bool = False, max_halvings: int = 10,
                 tolerance: float = 1e-6):
        super().__init__(motion, measurement)
        if not isinstance(marginal, bool):
            raise TypeError(f"'marginal' must be a bool, got {marginal!r}")
        self.num_iterations = check_positive_int(num_iterations,
                                                 'num_iterations')
        self.max_halvings = check_positive_int(max_halvings, 'max_halvings')
        self.marginal = marginal
        self.tolerance = check_number(tolerance, 'tolerance', inclusive=True)

    def steps(self, data: Realization,
              generator=None) -> Iterator[StepOutput]:
        r"""Runs the time loop lazily, yielding a
        :class:`~tg_nebp.filters.StepOutput` per time step (without
        particles): :meth:`step` over the realization's links.

        Args:
            data (Realization): A single or batched realization.
            generator: Unused (the filter draws nothing).
                (default: :obj:`None`)
        """
        self.check(data)
        state = self.initial_state(data)
        # the nodes stay: one layout for every step
        layout = GraphLayout.of(data)
        for t, ((edge_index, edge_attr), control) in enumerate(zip(
                data.edges_by_step(), self.controls_of(data))):
            output, state = self.step(state, edge_index, edge_attr,
                                      data.anchor, t, layout=layout,
                                      control=control)
            yield output

    def initial_state(self, data: Realization,
                      generator=None) -> JointState:
        r"""The state before the first step of the nodes of :obj:`data`
        (its :obj:`prior_mean`, :obj:`prior_cov`, :obj:`anchor` and
        graphs are read): every node's prior mean in float64 and, per
        graph, the block-diagonal joint of its agents' prior covariances;
        a joint too large for the free memory is refused
        (:func:`~tg_nebp.gaussian.check_dense_joint`). No draws."""
        check_predicted_prior(data, self.motion, 'the centralized IEKF',
                              self.use_control)
        layout = GraphLayout.of(data)
        check_dense_joint(max(a.numel() for a in layout.agents),
                          data.prior_mean.size(1), 'the centralized IEKF',
                          data.prior_mean.device)
        prior_cov = symmetrize(data.prior_cov.double())
        return JointState(data.prior_mean.double(), tuple(
            block_diagonal(prior_cov[nodes]) for nodes in layout.agents))

    def step(self, state: JointState, edge_index: Tensor, edge_attr: Tensor,
             anchor: Tensor, t: int, generator=None,
             motion: Optional[MotionModel] = None,
             layout: Optional[GraphLayout] = None,
             control: Optional[Tensor] = None
             ) -> Tuple[StepOutput, JointState]:
        r"""One time step of every graph, the arithmetic that the offline
        loop (:meth:`steps`) and a live session
        (:class:`~tg_nebp.filters.TrackingSession`) share: the prediction
        by :obj:`motion` (the tracker's by default) and the update with
        the links :obj:`edge_index` :math:`(2, E)`, features
        :obj:`edge_attr` :math:`(E, F)`, and every node's known input
        :obj:`control` :math:`(N, C)` (see
        :class:`~tg_nebp.models.MotionModel`). Returns the step's
        :class:`~tg_nebp.filters.StepOutput` (time index :obj:`t`:
        every node's mean, its angles wrapped, and marginal covariance)
        and the state after it. :obj:`layout` places the agents of every
        graph of a batch (:meth:`GraphLayout.of
        <tg_nebp.gaussian.GraphLayout.of>`; one graph by default)."""
        if layout is None:
            layout = GraphLayout.of_nodes(anchor)
        size = state.mean.size(1)
        src, dst = edge_index
        edge_graph = layout.graph_of[dst]
        mean = state.mean.clone()  # anchors keep their known state
        cov = mean.new_zeros(mean.size(0), size, size)
        joints = []
        for g, nodes in enumerate(layout.agents):
            mine = edge_graph == g
            # the senders' known positions where they are anchors
            known = state.mean[src[mine]]
            mean[nodes], joint = self.update(
                *self.predict(state.mean[nodes], state.joints[g], motion,
                              None if control is None else control[nodes]),
                edge_attr[mine].double(), layout.agent_index[src[mine]],
                layout.agent_index[dst[mine]], known)
            cov[nodes] = marginal_blocks(joint, size)
            joints.append(block_diagonal(cov[nodes]) if self.marginal else
                          joint)
        mean = self.motion.layout(size).wrap(mean)
        return StepOutput(t, mean, cov), JointState(mean, tuple(joints))

    def check_state(self, state: JointState, anchor: Tensor,
                    state_size: int, dtype: torch.dtype):
        r""":meth:`Tracker.check_state
        <tg_nebp.filters.Tracker.check_state>`, and the joints cover the
        agents' states: one (a session holds one graph), of
        :math:`A S` rows."""
        sizes = super().check_state(state, anchor, state_size, dtype)
        rows = int((~anchor).sum()) * state_size
        if len(state.joints) != 1 or state.joints[0].size(0) != rows:
            raise ValueError(f"the state's 'joints' cover "
                             f"{[j.size(0) for j in state.joints]} rows, "
                             f"expected one joint of {rows} (the agents' "
                             f"states)")
        return sizes

    def select_state(self, state: JointState, keep: Tensor,
                     anchor: Tensor) -> JointState:
        r"""The state of the nodes :obj:`keep` :math:`(N)` of one graph:
        their means and the joint of the agents that stay (a Gaussian's
        marginal: the leaving agents' rows and columns dropped)."""
        size = state.mean.size(1)
        stays = keep[~anchor].repeat_interleave(size)
        joint, = state.joints
        return JointState(state.mean[keep], (joint[stays][:, stays], ))

    def join_state(self, state: JointState,
                   joined: JointState) -> JointState:
        r"""The state of one graph's nodes followed by the joining ones
        (an :meth:`initial_state`): the joint extended by theirs, with no
        correlation between them."""
        (joint, ), (new, ) = state.joints, joined.joints
        return JointState(torch.cat([state.mean, joined.mean]), (
            joined_joint(joint, new, state.mean.size(1),
                         'the centralized IEKF'), ))

    def predict(self, mean: Tensor, cov: Tensor,
                motion: Optional[MotionModel] = None,
                control: Optional[Tensor] = None):
        r"""The prediction of the agents' means :math:`(A, S)` and joint
        covariance :math:`(AS, AS)` by :obj:`motion` (the tracker's motion
        model by default) with the agents' known inputs :obj:`control`
        :math:`(A, C)`."""
        motion = self.motion if motion is None else motion
        given = inputs(None if control is None else control.to(mean))
        moved, jacobian, noise = motion.linearize(mean, **given)
        return moved, predict_joint(cov, jacobian, noise)

    @staticmethod
    def _ends(state: Tensor, sender: Tensor, receiver: Tensor,
              known: Tensor):
        # the states [E, S] of the links' two ends: the agents' from
        # 'state' [A, S], a known end's (index -1: an anchor sender, or a
        # neighbour held fixed while one agent is searched) from 'known'
        at_sender = torch.where((sender >= 0).view(-1, 1),
                                state[sender.clamp_min(0)], known)
        at_receiver = torch.where((receiver >= 0).view(-1, 1),
                                  state[receiver.clamp_min(0)], known)
        return at_sender, at_receiver

    def _log_likelihood(self, state: Tensor, z: Tensor, *links) -> Tensor:
        # the log-likelihood of a step's links at the agents' 'state': the
        # measurement model's own
        sender, receiver = self._ends(state, *links)
        return self.measurement.log_likelihood(
            z, sender.unsqueeze(1), receiver.unsqueeze(1)).sum()

    def _cost(self, state: Tensor, prior: Tensor, factor: Tensor,
              z: Tensor, *links) -> Tensor:
        # the negative log-posterior of the step (up to a constant), the
        # prior by its covariance's Cholesky factor
        offset = (state - prior).view(-1, 1)
        return 0.5 * (offset * torch.cholesky_solve(offset, factor)).sum() - \
            self._log_likelihood(state, z, *links)

    def _link_system(self, state: Tensor, z: Tensor, sender: Tensor,
                     receiver: Tensor, known: Tensor) -> Tuple[Tensor, Tensor]:
        # the links' Gauss-Newton terms at 'state' [A, S], from the
        # measurement model's own linearization: their curvature on the
        # entries the likelihood reads [A R, A R] and the gradient of
        # their log-likelihood there [A, R]
        grads, blocks = self.measurement.linearize(
            z, *self._ends(state, sender, receiver, known))
        return self._link_terms(state, grads, blocks, sender, receiver)

    def _link_terms(self, state: Tensor, grads: Tensor, blocks: Tensor,
                    sender: Tensor, receiver: Tensor) -> Tuple[Tensor, Tensor]:
        # the links' linearization (the measurement model's gradients and
        # information blocks per link) gathered on the agents of 'state'
        count, size = state.shape
        width = len(self.measurement.scope(size))
        info = add_link_information(
            state.new_zeros(count * width, count * width), blocks, sender,
            receiver)
        grads = grads.view(-1, 2, width)
        links = grads.new_zeros(count, width)
        # (the receivers' first: the sums of the links into an agent in
        # the order they always had)
        for end, index in ((1, receiver), (0, sender)):
            agent = index >= 0
            links.index_add_(0, index[agent], grads[agent, end])
        return info, links

    def _linearized(self, state: Tensor, woodbury: WoodburyPrior,
                    factor: Tensor, prior: Tensor, z: Tensor, sender: Tensor,
                    receiver: Tensor, known: Tensor):
        # the Gauss-Newton system of the log-posterior at 'state': its
        # inverse as a Woodbury update of the prior covariance with the
        # links' curvature on the entries the likelihood reads, the
        # gradient, and the links' own terms (_link_system)
        count, size = state.shape
        system = self._link_system(state, z, sender, receiver, known)
        update = woodbury.updated(system[0])
        offset = (state - prior).view(-1, 1)
        grad = -torch.cholesky_solve(offset, factor).view(count, size)
        grad[:, list(self.measurement.scope(size))] += system[1]
        return update, grad, system

    def update(self, mean: Tensor, cov: Tensor, z: Tensor, sender: Tensor,
               receiver: Tensor, known: Tensor):
        r"""The update of the predicted agents' means :math:`(A, S)` and
        joint covariance :math:`(AS, AS)` with the ranges :obj:`z`
        :math:`(E, F)` of the links from :obj:`sender` to :obj:`receiver`
        :math:`(E)` (agent indices, :math:`-1` for an anchor, whose state
        :obj:`known` :math:`(E, S)` gives): Gauss-Newton with step halving
        on the step's MAP cost; returns the estimate and its covariance.
        The links inform the entries the likelihood reads (a range model's
        positions), so every Gauss-Newton system is solved as a Woodbury
        update of the prior covariance on those entries
        (:class:`~tg_nebp.gaussian.WoodburyUpdate`): one Cholesky
        factorization of the prior per step, no inverse of the joint."""
        state, update, _ = self._map_update(mean, cov, z, sender, receiver,
                                            known)
        return state, update.covariance()

    def _map_update(self, mean: Tensor, cov: Tensor, z: Tensor,
                    sender: Tensor, receiver: Tensor, known: Tensor):
        # update()'s Gauss-Newton iterations: the solution, the system
        # at it (WoodburyUpdate) and the links' own terms there
        factor, failed = torch.linalg.cholesky_ex(cov)
        if bool(failed.any()):
            raise ValueError(f"a joint covariance of size {cov.size(-1)} is "
                             f"not positive definite (leading minor "
                             f"{int(failed)}): the problem is degenerate")
        links = (z, sender, receiver, known)
        # the prior covariance at the entries the links inform, the same
        # in every Gauss-Newton system of the step
        woodbury = WoodburyPrior.of(cov, scope_index(
            mean.size(0), mean.size(1), self.measurement.scope(mean.size(1)),
            cov.device))
        state = mean
        cost = self._cost(state, mean, factor, *links)
        for _ in range(self.num_iterations):
            update, grad, _ = self._linearized(state, woodbury, factor,
                                               mean, *links)
            step = update.solve(grad.view(-1)).view_as(state)
            for _ in range(self.max_halvings + 1):
                trial = state + step
                trial_cost = self._cost(trial, mean, factor, *links)
                if bool(trial_cost <= cost):
                    break
                step = 0.5 * step
            else:  # no decrease along the Gauss-Newton direction: converged
                break
            state, cost = trial, trial_cost
            if bool(step.abs().amax() <= self.tolerance):
                break
        update, _, system = self._linearized(state, woodbury, factor, mean,
                                             *links)
        return state, update, system

    def settings(self) -> dict:
        return dict(iterations=self.num_iterations,
                    measurement=self.measurement.config(),
                    marginal=self.marginal)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(num_iterations='
                f'{self.num_iterations}, motion={self.motion}, '
                f'measurement={self.measurement}, marginal={self.marginal})')
