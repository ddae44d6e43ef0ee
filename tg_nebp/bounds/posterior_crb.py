from collections import deque
from typing import Iterator, List, NamedTuple, Optional

import torch
from torch import Tensor

from tg_nebp.data.realization import Realization
from tg_nebp.data.realization import controls_of, position_dim_of
from tg_nebp.data.validation import (check_control, check_lag,
                                     check_realization, check_state_dim)
from tg_nebp.gaussian import (GraphLayout, WoodburyPrior,
                              add_link_information, block_diagonal,
                              check_dense_joint, check_predicted_prior,
                              joint_cross, marginal_blocks, predict_joint,
                              rts_backward, scope_index)
from tg_nebp.models import (MeasurementModel, MotionModel, inputs,
                            resolve_models)

__all__ = ['PosteriorCRB', 'BoundStep']


class BoundStep(NamedTuple):
    r"""The bound at time index :obj:`t`: every node's marginal bound
    covariance :obj:`cov` :math:`(N, S, S)` (zero for anchors, which are
    known)."""
    t: int
    cov: Tensor


class PosteriorCRB(torch.nn.Module):
    r"""The posterior Cramér-Rao bound of a realization, from the
    `"Posterior Cramér-Rao Bounds for Discrete-Time Nonlinear Filtering"
    <https://doi.org/10.1109/78.668800>`_ paper (Tichavský, Muravchik and
    Nehorai, IEEE TSP 1998): no estimator of the agents' states from the
    measurements up to step :math:`n` has an error covariance below
    :math:`\mathbf{J}_n^{-1}`, the inverse of the joint Fisher information
    of all agents of a graph (anchors are known), which follows the
    recursion

    .. math::
        \mathbf{J}_0 = \boldsymbol{\Sigma}_0^{-1}, \quad
        \mathbf{J}_n = \big(\mathbf{Q}_n + \mathbf{F}_n \mathbf{J}_{n-1}^{-1}
        \mathbf{F}_n^\top\big)^{-1} + \mathbf{J}_{z,n},

    with :math:`\mathbf{F}_n` the motion model's Jacobian at the true state
    (:meth:`~tg_nebp.models.MotionModel.jacobian`; the first step's at the
    prior mean, as a realization does not store the true initial state),
    :math:`\mathbf{Q}_n` its driving-noise covariance
    (:meth:`~tg_nebp.models.MotionModel.noise_covariance`; both with the
    step's known inputs where the realization carries them: for odometry,
    the input noise propagated by the Jacobian in the input) and
    :math:`\mathbf{J}_{z,n}` the Fisher information of every link measured
    at step :math:`n`
    (:meth:`~tg_nebp.models.MeasurementModel.fisher_information`): for a
    range model :math:`I(d) \mathbf{u} \mathbf{u}^\top` on the two ends'
    position blocks (negated off the diagonal; :math:`\mathbf{u}` the unit
    vector between the true positions, :math:`I` the range likelihood's
    Fisher information, :math:`1 / \sigma^2` for the Gaussian). Every
    directed edge is its own measurement, and an anchor's link informs its
    agent only. The covariance form of the recursion holds for the
    singular driving noise of the constant-velocity models.

    One dense recursion per graph of a batch, in float64: the joint has
    :math:`(AS)^2` entries for :math:`A` agents with states of size
    :math:`S`, so a graph whose matrices do not fit in the free memory is
    refused before any work starts (on a machine with 20 GiB free, up to
    about 4,000 agents with :math:`S = 4`; the time grows as :math:`A^3`).

    From the bound covariance :math:`\mathbf{B}` of an agent's position:
    the RMSE floor :math:`\sqrt{\operatorname{tr} \mathbf{B}}`, and the
    outage of an efficient estimator, whose error is
    :math:`\mathcal{N}(\mathbf{0}, \mathbf{B})`
    (:func:`~tg_nebp.metrics.gaussian_outage`); its NEES is
    :math:`\chi^2_D`, so its :math:`\mathbb{P}(\text{accept } H_0)` is the
    confidence level. :func:`~tg_nebp.evaluation.bound_dataset` gives
    these for a dataset.

    **Smoothing.** With :obj:`lag` :math:`L > 1` the bound is that of the
    estimate of step :math:`n` from the measurements up to step
    :math:`n + L - 1` (a fixed-lag smoother whose window holds :math:`L`
    steps; the last :math:`L - 1` steps of a sequence, which have fewer
    later measurements, from all there are), and with :obj:`lag=None`
    from all measurements of the sequence (the full smoother's floor): the
    Rauch-Tung-Striebel backward pass
    (:func:`~tg_nebp.gaussian.rts_backward`) over the filtering
    recursion's joints, with the same Jacobians at the true states, as in
    `"Filtering, Predictive, and Smoothing Cramér-Rao Bounds for
    Discrete-Time Nonlinear Dynamic Systems"
    <https://doi.org/10.1016/S0005-1098(01)00122-8>`_ (Šimandl, Královec
    and Tichavský, Automatica 2001). It is exact for linear-Gaussian
    models and never above the filtering bound. The pass keeps the joints
    of the window (:math:`L` of them per graph; the whole sequence's with
    :obj:`lag=None`).

    Args:
        motion (MotionModel, optional): The motion model of the data.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): The measurement model of
            the data. (default: :obj:`GaussianRange()`)
        lag (int, optional): Steps of measurements the bound of a step
            reads, counting its own: :obj:`1` filters, :math:`L > 1` is a
            fixed-lag smoother's floor, :obj:`None` the full smoother's.
            (default: :obj:`1`)

    Shapes:
        - **input:** a :class:`~tg_nebp.data.Realization` with true
          :obj:`states` :math:`(N, T, S)`
        - **output:** bound covariances :math:`(N, T, S, S)`
    """
    #: Whether the bound reads a realization's known inputs (see
    #: :attr:`Tracker.use_control <tg_nebp.filters.Tracker.use_control>`):
    #: without them, the floor of an estimator without odometry.
    use_control: bool = True

    def __init__(self, motion: Optional[MotionModel] = None,
                 measurement: Optional[MeasurementModel] = None,
                 lag: Optional[int] = 1):
        super().__init__()
        self.motion, self.measurement = resolve_models(motion, measurement)
        self.lag = check_lag(lag)

    def steps(self, data: Realization,
              generator: Optional[torch.Generator] = None
              ) -> Iterator[BoundStep]:
        r"""Runs the recursion lazily, yielding a :class:`BoundStep` per
        time step, in order (a smoothing bound's as soon as its lag's
        measurements are in).

        Args:
            data (Realization): A single or batched realization with true
                :obj:`states`.
            generator (torch.Generator, optional): Source of the draws of a
                measurement model whose Fisher information is a Monte Carlo
                (none for the library's models). (default: :obj:`None`)
        """
        if self.lag == 1:
            for t, out, _ in self._filtering(data, generator):
                yield BoundStep(t, out)
            return
        # every graph's joints of the window: (agents, filtered, predicted,
        # cross) of each step, the last two of the transition into it
        window = deque(maxlen=self.lag)
        last, out = -1, None
        for last, out, joints in self._filtering(data, generator):
            window.append(joints)
            if len(window) == self.lag:
                yield BoundStep(last - self.lag + 1,
                                self._smoothed(window, 0, out)[0])
        # the window's later steps, from every measurement there is
        done = 1 if len(window) == self.lag else 0
        for k, bound in enumerate(self._smoothed(window, done, out), done):
            yield BoundStep(last - len(window) + 1 + k, bound)

    @staticmethod
    def _smoothed(window: deque, first: int, like: Tensor) -> List[Tensor]:
        # the marginal bounds of every node (:obj:`like`'s shape) at the
        # window's steps from 'first' on, given every step of the window:
        # one backward pass from its last step
        size = like.size(-1)
        outs = [torch.zeros_like(like) for _ in range(first, len(window))]
        for g, (nodes, cov, _, _) in enumerate(window[-1]):
            outs[-1][nodes] = marginal_blocks(cov, size)
            for step in range(len(window) - 2, first - 1, -1):
                filtered = window[step][g][1]
                _, _, predicted, cross = window[step + 1][g]
                _, cov = rts_backward(filtered, cross, predicted, cov)
                outs[step - first][nodes] = marginal_blocks(cov, size)
        return outs

    def _filtering(self, data: Realization,
                   generator: Optional[torch.Generator]):
        # the filtering recursion: per step its index, every node's
        # marginal bound and, per graph, (its agents, filtered joint,
        # predicted joint, cross covariance of the transition into the
        # step)
        check_realization(data, self.measurement.features,
                          self.measurement.negative_ranges)
        states = getattr(data, 'states', None)
        if states is None:
            raise ValueError("the posterior CRB needs the true 'states' of "
                             "the realization")
        unknown = torch.isnan(states).flatten(1).any(-1)
        if bool(unknown.any()):
            # its links' information is taken at the true positions of both
            # ends: without one end's truth there is no bound to compute
            raise ValueError(
                f"the posterior CRB needs every node's ground truth: node "
                f"{int(unknown.nonzero()[0])} has none (a node tracked "
                f"without truth)")
        size = states.size(-1)
        check_state_dim(size, self.motion, position_dim_of(data))
        if self.use_control:
            check_control(data, self.motion)
        check_predicted_prior(data, self.motion, 'the posterior CRB',
                              self.use_control)
        layout = GraphLayout.of(data)
        check_dense_joint(max(a.numel() for a in layout.agents), size,
                          'the posterior CRB', states.device)
        states = states.double()
        prior_cov = data.prior_cov.double()
        # the links inform the entries the likelihood reads: the update
        # works on those (a range model's positions), by Woodbury
        scope = self.measurement.scope(size)
        both = self.measurement.scope_of_both(size, states.device)
        covs = [block_diagonal(prior_cov[nodes]) for nodes in layout.agents]
        previous = data.prior_mean.double()
        for t, ((edge_index, edge_attr), control) in enumerate(zip(
                data.edges_by_step(), controls_of(data, self.use_control))):
            truth = states[:, t]
            src, dst = edge_index
            blocks = self.measurement.fisher_information(
                edge_attr.double(), truth[src], truth[dst], generator)
            edge_graph = layout.graph_of[dst]
            out = truth.new_zeros(data.num_nodes, size, size)
            joints = []
            for g, nodes in enumerate(layout.agents):
                given = inputs(None if control is None else
                               control[nodes].double())
                _, jacobian, noise = self.motion.linearize(previous[nodes],
                                                           **given)
                cov = predict_joint(covs[g], jacobian, noise)
                # the smoothers' backward pass reads the transition
                cross = (None if self.lag == 1 else
                         joint_cross(covs[g], jacobian))
                mine = edge_graph == g
                count = nodes.numel()
                info = cov.new_zeros(count * len(scope), count * len(scope))
                add_link_information(info, blocks[mine][:, both][:, :, both],
                                     layout.agent_index[src[mine]],
                                     layout.agent_index[dst[mine]])
                covs[g] = WoodburyPrior.of(cov, scope_index(
                    count, size, scope, cov.device)).updated(
                        info).covariance()
                out[nodes] = marginal_blocks(covs[g], size)
                joints.append((nodes, covs[g], cov, cross))
            previous = truth
            yield t, out, joints

    def forward(self, data: Realization,
                generator: Optional[torch.Generator] = None) -> Tensor:
        r"""The bound covariances :math:`(N, T, S, S)` of a whole
        (batched) realization; :obj:`generator` as in :meth:`steps`."""
        return torch.stack([step.cov for step in self.steps(data,
                                                            generator)], 1)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(motion={self.motion}, '
                f'measurement={self.measurement}, lag={self.lag})')
