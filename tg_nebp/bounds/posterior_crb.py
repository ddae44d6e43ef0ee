from typing import Iterator, NamedTuple, Optional

import torch
from torch import Tensor

from tg_nebp.data.realization import Realization
from tg_nebp.data.realization import controls_of, position_dim_of
from tg_nebp.data.validation import (check_control, check_realization,
                                     check_state_dim)
from tg_nebp.gaussian import (GraphLayout, WoodburyPrior,
                              add_link_information, block_diagonal,
                              check_dense_joint, check_predicted_prior,
                              marginal_blocks, predict_joint, scope_index)
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

    Args:
        motion (MotionModel, optional): The motion model of the data.
            (default: :obj:`ConstantVelocityDrag()`)
        measurement (MeasurementModel, optional): The measurement model of
            the data. (default: :obj:`GaussianRange()`)

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
                 measurement: Optional[MeasurementModel] = None):
        super().__init__()
        self.motion, self.measurement = resolve_models(motion, measurement)

    def steps(self, data: Realization,
              generator: Optional[torch.Generator] = None
              ) -> Iterator[BoundStep]:
        r"""Runs the recursion lazily, yielding a :class:`BoundStep` per
        time step.

        Args:
            data (Realization): A single or batched realization with true
                :obj:`states`.
            generator (torch.Generator, optional): Source of the draws of a
                measurement model whose Fisher information is a Monte Carlo
                (none for the library's models). (default: :obj:`None`)
        """
        check_realization(data, self.measurement.features)
        states = getattr(data, 'states', None)
        if states is None:
            raise ValueError("the posterior CRB needs the true 'states' of "
                             "the realization")
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
            for g, nodes in enumerate(layout.agents):
                given = inputs(None if control is None else
                               control[nodes].double())
                cov = predict_joint(covs[g],
                                    self.motion.jacobian(previous[nodes],
                                                         **given),
                                    self.motion.noise_covariance(
                                        previous[nodes], **given))
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
            previous = truth
            yield BoundStep(t, out)

    def forward(self, data: Realization,
                generator: Optional[torch.Generator] = None) -> Tensor:
        r"""The bound covariances :math:`(N, T, S, S)` of a whole
        (batched) realization; :obj:`generator` as in :meth:`steps`."""
        return torch.stack([step.cov for step in self.steps(data,
                                                            generator)], 1)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(motion={self.motion}, '
                f'measurement={self.measurement})')
