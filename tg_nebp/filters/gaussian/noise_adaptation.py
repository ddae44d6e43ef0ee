r"""Each agent's measurement noise scale, estimated online from its own
links' innovations: the calibration of a Gaussian tracker that needs no
ground truth (:class:`NoiseAdaptation`)."""
from typing import Optional

import torch
from torch import Tensor

from tg_nebp.data.validation import check_number
from tg_nebp.gaussian import unit_vectors
from tg_nebp.models import MeasurementModel, RangeModel
from tg_nebp.nn.conv.gaussian_bp_conv import (Factors, GaussianBelief,
                                              position_covariance)

__all__ = ['NoiseAdaptation']

# the columns of a node's memory: the faded sums of its links' weighted
# scale statistics and of their weights, and the scale they give
_SUM, _COUNT, _SCALE = range(3)
#: The largest noise scale :class:`NoiseAdaptation` accepts as a bound.
MAX_SCALE = 1e4


class NoiseAdaptation:
    r"""Every agent's measurement noise scale :math:`s_i \geq 1`,
    estimated from the innovations of its own links against their
    predicted spread (an adaptive noise estimate in the manner of
    `Mehra (1970) <https://doi.org/10.1109/TAC.1970.1099422>`_), and
    every message to the agent tempered by :math:`1 / s_i`: a model whose
    noise is too small for the data gets the noise the data show, without
    ground truth.

    At every step, before the links are used, each link's log-likelihood
    gradient :math:`\mathbf{g}` and Fisher information :math:`\mathbf{I}`
    about the scoped states of its two ends (the measurement role's
    :meth:`~tg_nebp.models.MeasurementModel.linearize` and
    :meth:`~tg_nebp.models.MeasurementModel.fisher_information`, at the
    predicted means) make the scale statistic

    .. math::
        e = \frac{\mathbf{g}^\top \mathbf{I}^{+} \mathbf{g} -
        \mathrm{tr}(\mathbf{P} \mathbf{I})}{r},
        \qquad \rho = \frac{r}{r + \mathrm{tr}(\mathbf{P} \mathbf{I})},

    with :math:`\mathbf{P}` the two ends' predicted covariances (zero for
    an anchor) and :math:`r` the rank of :math:`\mathbf{I}` (for a
    :class:`~tg_nebp.models.RangeModel`, whose information lies along the
    link, the same in closed form: :math:`e = s^2 / I(d) - I(d) q`,
    :math:`\rho = 1 / (1 + I(d) q)` with the score :math:`s`, the range's
    Fisher information :math:`I(d)` and the predicted variance :math:`q` of
    the distance): if the noise
    is :math:`s` times the model's (in variance), the linearized score has
    covariance :math:`s \mathbf{I} + \mathbf{I} \mathbf{P} \mathbf{I}`,
    so :math:`\mathbb{E}[e] = s`; :math:`\rho` is the noise's share of the
    innovation, the weight of the link in the estimate (a link whose
    innovation is mostly the prediction's spread says little about the
    noise). Every agent at either end of a link sums its links'
    :math:`\rho e` and :math:`\rho` with a fading :obj:`memory`, starting
    from :obj:`prior_count` links at :math:`e = 1`, and

    .. math::
        s_i = \mathrm{clip}\left(\frac{\sum \rho e + n_0}{\sum \rho +
        n_0}, 1, s_\mathrm{max}\right).

    It only inflates: the statistic of a link between two agents
    understates the spread (their errors are correlated, and a filter of
    marginals keeps no cross-covariance), so it would deflate a correct
    model (measured: :doc:`/results`). Distributed: an agent reads its
    links and its neighbours' predicted beliefs only, which Gaussian BP's
    messages already carry.

    Args:
        memory (float, optional): The fading factor per step
            :math:`\lambda \in (0, 1)`: the estimate's memory is about
            :math:`1 / (1 - \lambda)` steps. (default: :obj:`0.9`)
        prior_count (float, optional): The weight :math:`n_0` of the
            prior scale 1. (default: :obj:`5.0`)
        max_scale (float, optional): The largest scale
            :math:`s_\mathrm{max}`. (default: :obj:`100.0`)
    """
    def __init__(self, memory: float = 0.9, prior_count: float = 5.0,
                 max_scale: float = 100.0):
        self.memory = check_number(memory, 'memory', minimum=0.0,
                                   maximum=1.0)
        if not 0 < self.memory < 1:
            raise ValueError(f"'memory' must lie strictly between 0 and 1, "
                             f"got {memory}")
        self.prior_count = check_number(prior_count, 'prior_count',
                                        minimum=0.0)
        self.max_scale = check_number(max_scale, 'max_scale', minimum=1.0,
                                      maximum=MAX_SCALE)

    def initial_memory(self, num_nodes: int, device=None) -> Tensor:
        r"""Every node's memory :math:`(N, 3)` (float64) before its first
        step: no link seen, scale 1."""
        memory = torch.zeros(num_nodes, 3, dtype=torch.float64,
                             device=device)
        memory[:, _SCALE] = 1.0
        return memory

    def statistics(self, measurement: MeasurementModel,
                   belief: GaussianBelief, edge_index: Tensor,
                   edge_attr: Tensor, anchor: Tensor,
                   generator: Optional[torch.Generator] = None):
        r"""Every link's scale statistic :math:`e` and weight :math:`\rho`
        :math:`(E)` at the predicted :obj:`belief` (means and
        information), for links :obj:`edge_index` :math:`(2, E)` (sender,
        receiver) with features :obj:`edge_attr`."""
        size = belief.mean.size(-1)
        width = len(measurement.scope(size))
        src, dst = edge_index
        mean = belief.mean
        cov = position_covariance(belief, width, anchor)
        if isinstance(measurement, RangeModel):
            return self._range_statistics(measurement, mean, cov, edge_index,
                                          edge_attr, generator)
        both = measurement.scope_of_both(size, mean.device)
        grad = measurement.likelihood_gradient(edge_attr, mean[src],
                                               mean[dst])[:, both]
        info = measurement.fisher_information(
            edge_attr, mean[src], mean[dst],
            generator)[:, both.view(-1, 1), both]
        # tr(P I) of the block-diagonal P of the two ends
        spread = ((cov[src] * info[:, :width, :width]).sum((-1, -2)) +
                  (cov[dst] * info[:, width:, width:]).sum((-1, -2)))
        # g' I^+ g over the directions that the link informs
        values, vectors = torch.linalg.eigh(info)
        kept = values > values.amax(-1, keepdim=True).clamp_min(0) * 1e-9
        along = (vectors.transpose(-1, -2) @ grad.unsqueeze(-1)).squeeze(-1)
        score = torch.where(kept, along.square() / torch.where(
            kept, values, torch.ones_like(values)), 0.0).sum(-1)
        rank = kept.sum(-1).to(score)
        informative = rank > 0
        rank = rank.clamp_min(1)
        statistic = torch.where(informative, (score - spread) / rank, 0.0)
        weight = torch.where(informative, rank / (rank + spread), 0.0)
        return statistic, weight

    @staticmethod
    def _range_statistics(measurement: RangeModel, mean: Tensor, cov: Tensor,
                          edge_index: Tensor, edge_attr: Tensor,
                          generator: Optional[torch.Generator] = None):
        # the rank-one form of a range's: its Fisher information is I(d)
        # along [u; -u], so g' I^+ g = s^2 / I(d) and tr(P I) = I(d) q,
        # q = u' (P_j + P_i) u, without a matrix per link
        src, dst = edge_index
        dim = measurement.position_dim(mean.size(-1))
        distances, unit = unit_vectors(mean[src, :dim] - mean[dst, :dim])
        score, _ = measurement.robust_weights(edge_attr,
                                              distances.view(-1, 1))
        score = score.view(-1)
        info = measurement.range_information(edge_attr, distances, generator)
        spread = sum((unit.unsqueeze(-2) @ cov[end, :dim, :dim] @
                      unit.unsqueeze(-1)).view(-1) for end in (src, dst))
        informative = (info > 0) & (distances > 0)
        safe = torch.where(informative, info, torch.ones_like(info))
        statistic = torch.where(
            informative, score.square() / safe - safe * spread, 0.0)
        weight = torch.where(informative, 1 / (1 + safe * spread), 0.0)
        return statistic, weight

    def updated(self, memory: Tensor, measurement: MeasurementModel,
                belief: GaussianBelief, edge_index: Tensor,
                edge_attr: Tensor, anchor: Tensor,
                generator: Optional[torch.Generator] = None) -> Tensor:
        r"""The :obj:`memory` :math:`(N, 3)` after a step's links
        (:meth:`statistics` at the predicted :obj:`belief`): the sums
        faded and every agent's links added at both of their ends, the
        scale recomputed. Anchors keep scale 1."""
        statistic, weight = self.statistics(measurement, belief, edge_index,
                                            edge_attr, anchor, generator)
        ends = edge_index.reshape(-1)
        sums = memory[:, :_SCALE] * self.memory
        sums = sums.index_add(0, ends, torch.stack(
            [weight * statistic, weight], -1).to(sums).repeat(2, 1))
        scale = ((sums[:, _SUM] + self.prior_count) /
                 (sums[:, _COUNT] + self.prior_count).clamp_min(
                     torch.finfo(sums.dtype).tiny))
        scale = scale.clamp(1.0, self.max_scale).masked_fill(anchor, 1.0)
        return torch.cat([sums, scale.unsqueeze(-1)], -1)

    @staticmethod
    def message_weights(memory: Tensor, factors: Factors) -> Tensor:
        r"""The weight :math:`1 / s_t` :math:`(M)` of every message edge
        of :obj:`factors`, by its target's scale."""
        return 1.0 / memory[factors.index[1], _SCALE]

    @staticmethod
    def scale(memory: Tensor) -> Tensor:
        r"""Every node's noise scale :math:`s_i` :math:`(N)`."""
        return memory[:, _SCALE]

    def settings(self) -> dict:
        return dict(memory=self.memory, prior_count=self.prior_count,
                    max_scale=self.max_scale)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(memory={self.memory}, '
                f'prior_count={self.prior_count}, '
                f'max_scale={self.max_scale})')
