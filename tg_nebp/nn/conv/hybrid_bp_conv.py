from typing import NamedTuple, Optional, Tuple

import torch
from torch import Tensor
from torch_geometric.nn.conv import MessagePassing

from tg_nebp.models import GaussianRange, MeasurementModel, RangeModel
from tg_nebp.nn.conv.gaussian_bp_conv import (Factors, GaussianBelief,
                                              as_factor_messages,
                                              marginal_information)
from tg_nebp.utils import log_normalize, symmetrize

__all__ = ['HybridBPConv', 'SourceBeliefs']

# message edges per block of the per-particle evaluations: at K = 50 a
# block's (M, K) temporaries are 1.6 MB in float64
CHUNK_SIZE = 4096


class SourceBeliefs(NamedTuple):
    r"""Every message edge's source as its message reads it
    (:meth:`HybridBPConv.sources`): the source's state :obj:`state`
    :math:`(M, S)` (its extrinsic mean on the factor's scope, its belief
    mean elsewhere), the extrinsic information :obj:`info` :math:`(M, R,
    R)` on the scope (an identity for an anchor, never read), its inverse
    :obj:`cov` (zero for an anchor) and whether it is an anchor
    (:obj:`known` :math:`(M)`, a known state)."""
    state: Tensor
    info: Tensor
    cov: Tensor
    known: Tensor


class HybridBPConv(MessagePassing):
    r"""One weighting of every agent's particle belief by the messages of
    Gaussian belief propagation, evaluated exactly at the receiver's
    particles: the message layer of hybrid BP
    (:class:`~tg_nebp.filters.HybridBP`), where the agents exchange
    Gaussian beliefs (as :class:`~tg_nebp.nn.conv.GaussianBPConv`) but
    each agent weighs its own :math:`K` particles by the true likelihood
    of its links, so that its belief may hold several modes (the mirror
    positions of an agent measured by nodes on a line, the arc of an agent
    with one neighbour) that a Gaussian belief cannot.

    A factor :math:`f` between a source :math:`s` and a target agent
    :math:`t` (the link's ranges measured at either end, summed, as in
    Gaussian BP with :obj:`ends="both"`) sends :math:`t` the likelihood
    of its links with the source's state integrated out against the
    source's **extrinsic** Gaussian belief :math:`\mathcal{N}(
    \boldsymbol{\mu}_s, \boldsymbol{\Lambda}_s^{-1})` on the factor's
    scope (the source's final Gaussian BP belief without this factor's
    message to it, so that the target does not receive its own
    information back). At the target's particle
    :math:`\mathbf{x}_t^{(k)}` the integral is taken with the source's
    side of the likelihood expanded to second order at
    :math:`\boldsymbol{\mu}_s` (the measurement model's own
    :meth:`~tg_nebp.models.MeasurementModel.log_likelihood` :math:`\ell`
    and :meth:`~tg_nebp.models.MeasurementModel.linearize`: the gradient
    :math:`\mathbf{g}` and curvature :math:`\mathbf{W}` on the source's
    scope), the target's side exactly:

    .. math::
        \log m_{f \to t}(\mathbf{x}_t^{(k)}) = \ell +
        \tfrac{1}{2} \mathbf{g}^\top (\boldsymbol{\Lambda}_s +
        \mathbf{W})^{-1} \mathbf{g} - \tfrac{1}{2} \log
        \frac{|\boldsymbol{\Lambda}_s + \mathbf{W}|}
        {|\boldsymbol{\Lambda}_s|},

    with :math:`\ell`, :math:`\mathbf{g}`, :math:`\mathbf{W}` at
    :math:`(\boldsymbol{\mu}_s, \mathbf{x}_t^{(k)})`, summed over the
    factor's links: for a Gaussian range this is the range's likelihood
    with the source's variance along the link added,
    :math:`\mathcal{N}(z; \|\mathbf{p}_t^{(k)} - \boldsymbol{\mu}_s\|,
    \sigma^2 + \mathbf{u}^\top \boldsymbol{\Sigma}_s \mathbf{u})`. An
    anchor source is known: its message is :math:`\ell`. Every agent's
    belief is its prior log-weights plus its incoming messages,
    normalized (:obj:`aggr="add"` over the message edges, which are
    :func:`~tg_nebp.utils.link_factors`'s).

    Args:
        measurement (MeasurementModel, optional): The measurement model.
            (default: :obj:`GaussianRange()`)
        chunk_size (int, optional): Message edges per block of the
            per-particle evaluations (bounds their memory at
            :math:`O(\text{chunk} \cdot K R^2)`, whatever the network's
            size, so that the time grows linearly in the links: a large
            network's temporaries would otherwise be fresh pages of memory
            at every operation); :obj:`None` for all at once.
            (default: :obj:`4096`)

    Shapes:
        - **input:**
          particles :math:`(|\mathcal{V}|, K, S)`,
          prior log-weights :math:`(|\mathcal{V}|, K)`,
          source beliefs (:class:`~tg_nebp.nn.conv.SourceBeliefs`, one
          per message edge :math:`M`), the step's
          :class:`~tg_nebp.nn.conv.Factors`, link features
          :math:`(|\mathcal{E}|, F)` and links :math:`(2,
          |\mathcal{E}|)`
        - **output:** normalized belief log-weights
          :math:`(|\mathcal{V}|, K)` and the log-messages :math:`(M, K)`
    """
    def __init__(self, measurement: Optional[MeasurementModel] = None,
                 chunk_size: Optional[int] = CHUNK_SIZE):
        super().__init__(aggr='add', node_dim=0)
        self.measurement = measurement or GaussianRange()
        if not isinstance(self.measurement, MeasurementModel):
            raise TypeError(f"'measurement' must be a MeasurementModel, got "
                            f"{self.measurement!r}")
        if chunk_size is not None and (not isinstance(chunk_size, int) or
                                       isinstance(chunk_size, bool) or
                                       chunk_size < 1):
            raise ValueError(f"'chunk_size' must be a positive integer or "
                             f"None, got {chunk_size!r}")
        self.chunk_size = chunk_size

    def sources(self, belief: GaussianBelief, factors: Factors, messages,
                anchor: Tensor) -> SourceBeliefs:
        r"""Every message edge's source as its message reads it: the
        source's final Gaussian BP :obj:`belief` (information form, one row
        per node) marginalized onto the factor's scope, without the
        factor's last message to the source (:obj:`messages` on the message
        edges of :obj:`factors`, the reverse edge's; none where the source
        is an anchor or the factor sends it nothing)."""
        size = belief.mean.size(-1)
        width = len(self.measurement.scope(size))
        info, eta = marginal_information(belief.info, belief.mean, width,
                                         anchor)
        source = factors.index[0]
        known = anchor[source]
        info, eta = info[source], eta[source]
        back = factors.reverse
        if messages is not None and back.numel():
            messages = as_factor_messages(messages)
            has = (back >= 0).view(-1, 1)
            info = info - torch.where(has.view(-1, 1, 1),
                                      messages.info[back.clamp_min(0)], 0.0)
            eta = eta - torch.where(has, messages.eta[back.clamp_min(0)], 0.0)
        eye = torch.eye(width, dtype=info.dtype, device=info.device)
        info = torch.where(known.view(-1, 1, 1), eye, info)
        # the extrinsic mean on the scope; the rest of the state as believed
        cov = torch.linalg.inv(info).masked_fill(known.view(-1, 1, 1), 0.0)
        mean = (cov @ eta.unsqueeze(-1)).squeeze(-1)
        state = belief.mean[source].clone()
        state[:, :width] = torch.where(known.view(-1, 1), state[:, :width],
                                       mean)
        return SourceBeliefs(state, info, symmetrize(cov), known)

    @staticmethod
    def pairs(factors: Factors) -> Tuple[Tensor, Tensor]:
        r"""Every (message edge, link) pair of the same factor, as two index
        vectors sorted by message edge: a message edge reads each of its
        factor's links (the two ranges of a pair). The methods below compute them unless given
        (:obj:`pairs`), as a caller that evaluates many candidates on one
        step's factors passes them once."""
        return _pairs(factors)

    def ranges(self, factors: Factors, edge_attr: Tensor,
               pairs: Optional[Tuple[Tensor, Tensor]] = None) -> Tensor:
        r"""Every message edge's range :math:`(M)`: the mean first feature
        (the range) of its factor's links."""
        edge, link = pairs or _pairs(factors)
        count = factors.index.size(1)
        total = edge_attr.new_zeros(count).index_add(0, edge,
                                                     edge_attr[link, 0])
        number = edge_attr.new_zeros(count).index_add(
            0, edge, torch.ones_like(edge, dtype=edge_attr.dtype))
        return total / number.clamp_min(1)

    def forward(self, particles: Tensor, log_weights: Tensor,
                sources: SourceBeliefs, factors: Factors, edge_index: Tensor,
                edge_attr: Tensor, tempering: Optional[Tensor] = None
                ) -> Tuple[Tensor, Tensor]:
        r"""The agents' belief log-weights and every message edge's
        log-message at its target's particles (see the class), each
        raised to its message edge's power :obj:`tempering` :math:`(M)`
        where given (a learned correction's weights: the likelihood that
        its tempered Gaussian messages stand for)."""
        num_nodes = particles.size(0)
        messages = self.log_messages(particles, sources, factors,
                                     edge_index, edge_attr)
        if tempering is not None:
            messages = messages * tempering.to(messages).view(-1, 1)
        summed = self.propagate(factors.index, log_message=messages,
                                size=(num_nodes, num_nodes))
        return log_normalize(log_weights + summed), messages

    def message(self, log_message: Tensor) -> Tensor:
        return log_message

    @property
    def rank_one(self) -> bool:
        r"""Whether the messages take the closed form of a range model
        (its factors lie along their links: :math:`\mathbf{W} = w
        \mathbf{u} \mathbf{u}^\top`, :math:`\mathbf{g} = s \mathbf{u}`
        with :math:`s`, :math:`w` the model's
        :meth:`~tg_nebp.models.RangeModel.robust_weights`, and
        :math:`v = \mathbf{u}^\top \boldsymbol{\Sigma}_s \mathbf{u}`),
        :math:`\log m = \ell + \frac{1}{2} s^2 v / (1 + w v) -
        \frac{1}{2} \log(1 + w v)`: a :class:`~tg_nebp.models.RangeModel`
        that linearizes as every range model does."""
        return (isinstance(self.measurement, RangeModel) and
                type(self.measurement).linearize is RangeModel.linearize)

    def log_messages(self, particles: Tensor, sources: SourceBeliefs,
                     factors: Factors, edge_index: Tensor,
                     edge_attr: Tensor,
                     pairs: Optional[Tuple[Tensor, Tensor]] = None
                     ) -> Tensor:
        r"""The log-message :math:`(M, K)` of every message edge of
        :obj:`factors` at its target's particles."""
        blocks = [self._block_log_messages(particles, *block[:3],
                                           edge_index, edge_attr)
                  for block in self._blocks(sources, factors, pairs)]
        return torch.cat(blocks) if len(blocks) > 1 else blocks[0]

    def _block_log_messages(self, particles: Tensor, sources: SourceBeliefs,
                            index: Tensor, pairs: Tuple[Tensor, Tensor],
                            edge_index: Tensor, edge_attr: Tensor) -> Tensor:
        # the log-messages of one block of message edges (their sources,
        # (source, target) index and pairs)
        if self.rank_one:
            value, score, weight, unit = self._range_terms(
                particles, sources, index[1], edge_attr, pairs)
            spread = ((unit.unsqueeze(-2) @ sources.cov.unsqueeze(1)) @
                      unit.unsqueeze(-1)).view(unit.shape[:2])
            grows = 1 + weight * spread
            return (value + 0.5 * score.square() * spread / grows -
                    0.5 * torch.log(grows))
        count, num = index.size(1), particles.size(1)
        width = sources.info.size(-1)
        edge, link = pairs
        value, grad, curv = self._linearized(
            particles, sources, index, edge, link, edge_index, edge_attr,
            width, 'source')
        return _integrated(
            particles.new_zeros(count, num).index_add(0, edge, value),
            particles.new_zeros(count, num, width).index_add(0, edge, grad),
            particles.new_zeros(count, num, width, width).index_add(
                0, edge, curv), sources)

    def _blocks(self, sources: SourceBeliefs, factors: Factors,
                pairs: Optional[Tuple[Tensor, Tensor]]):
        # the message edges in blocks of chunk_size: each block's sources,
        # (source, target) index, pairs (their edges counted from the
        # block's first) and its rows among the message edges
        edge, link = pairs or _pairs(factors)
        count = factors.index.size(1)
        size = self.chunk_size or max(count, 1)
        starts = list(range(0, max(count, 1), size))
        bounds = torch.searchsorted(edge, torch.tensor(
            starts + [count], device=edge.device)).tolist()
        for block, start in enumerate(starts):
            end = min(start + size, count)
            low, high = bounds[block], bounds[block + 1]
            yield (SourceBeliefs(*(part[start:end] for part in sources)),
                   factors.index[:, start:end],
                   (edge[low:high] - start, link[low:high]),
                   slice(start, end))

    def target_linearization(self, particles: Tensor,
                             sources: SourceBeliefs, factors: Factors,
                             edge_index: Tensor, edge_attr: Tensor,
                             pairs: Optional[Tuple[Tensor, Tensor]] = None,
                             tempering: Optional[Tensor] = None
                             ) -> Tuple[Tensor, Tensor]:
        r"""The gradient :math:`(N, K, R)` and curvature :math:`(N, K, R,
        R)` of every agent's links' log-likelihood with respect to its own
        scope at each of its :obj:`particles`, the sources at their
        extrinsic means (the measurement model's
        :meth:`~tg_nebp.models.MeasurementModel.linearize`): a Gauss-Newton
        step of each particle towards what its links alone say. Each
        message edge's terms are multiplied by its :obj:`tempering`
        :math:`(M)` where given (see :meth:`forward`)."""
        num_nodes, num = particles.shape[:2]
        width = sources.info.size(-1)
        grad = particles.new_zeros(num_nodes, num, width)
        curv = particles.new_zeros(num_nodes, num, width, width)
        for block, index, (edge, link), rows in self._blocks(
                sources, factors, pairs):
            target = index[1]
            power = (None if tempering is None else
                     tempering[rows].to(particles))
            if self.rank_one:
                _, score, weight, unit = self._range_terms(
                    particles, block, target, edge_attr, (edge, link),
                    value=False)
                if power is not None:
                    score = score * power.view(-1, 1)
                    weight = weight * power.view(-1, 1)
                # d grows with the target's position against u (u: to the
                # source)
                grad = grad.index_add(0, target, -score.unsqueeze(-1) * unit)
                curv = curv.index_add(
                    0, target, weight.view(weight.shape + (1, 1)) *
                    unit.unsqueeze(-1) * unit.unsqueeze(-2))
                continue
            _, g, w = self._linearized(particles, block, index, edge, link,
                                       edge_index, edge_attr, width,
                                       'target')
            if power is not None:
                g = g * power[edge].view(-1, 1, 1)
                w = w * power[edge].view(-1, 1, 1, 1)
            grad = grad.index_add(0, target[edge], g)
            curv = curv.index_add(0, target[edge], w)
        return grad, curv

    def _range_terms(self, particles: Tensor, sources: SourceBeliefs,
                     target: Tensor, edge_attr: Tensor,
                     pairs: Tuple[Tensor, Tensor], value: bool = True):
        # a range model's terms per message edge (its target node) at its
        # target's particles (M, K): the log-likelihood (zero without
        # 'value'), score and robust weight of its links at the distance
        # to the source's extrinsic mean (summed over the factor's links),
        # and the unit vectors (M, K, R) to the source
        width = sources.info.size(-1)
        offset = (sources.state[:, :width].unsqueeze(1) -
                  particles[target, :, :width])
        distance = offset.norm(dim=-1)
        unit = offset / distance.clamp_min(
            torch.finfo(offset.dtype).tiny).unsqueeze(-1)
        edge, link = pairs
        z, at = edge_attr[link], distance[edge]
        total = torch.zeros_like(distance)
        if value:
            total = total.index_add(
                0, edge, self.measurement.log_likelihood_of_distance(z, at))
        s, w = self.measurement.robust_weights(z, at)
        return (total, torch.zeros_like(distance).index_add(0, edge, s),
                torch.zeros_like(distance).index_add(0, edge, w), unit)

    def _linearized(self, particles: Tensor, sources: SourceBeliefs,
                    index: Tensor, edge: Tensor, link: Tensor,
                    edge_index: Tensor, edge_attr: Tensor, width: int,
                    side: str):
        # the log-likelihood (P, K) of every (message edge, link) pair at
        # (source's extrinsic state, target's particles) and its gradient
        # (P, K, R) and curvature (P, K, R, R) on the scope of the source's
        # or the target's side
        num, size = particles.size(1), particles.size(-1)
        target = particles[index[1, edge]]  # (P, K, S)
        source = sources.state[edge].unsqueeze(1).expand(-1, num, -1)
        # the source measured it or was measured: its role in the link
        is_sender = (edge_index[0, link] == index[0, edge]).view(
            -1, 1, 1)
        sender = torch.where(is_sender, source, target)
        receiver = torch.where(is_sender, target, source)
        z = edge_attr[link]
        value = self.measurement.log_likelihood(z, sender, receiver)
        grad, curv = self.measurement.linearize(
            z.repeat_interleave(num, 0), sender.reshape(-1, size),
            receiver.reshape(-1, size))
        grad = grad.view(-1, num, 2 * width)
        curv = curv.view(-1, num, 2 * width, 2 * width)
        # the side's half of [x_sender; x_receiver]
        first = is_sender if side == 'source' else ~is_sender
        half = torch.where(first.view(-1, 1, 1), 0, width)
        rows = (half + torch.arange(width, device=particles.device)
                ).expand(-1, num, -1)
        grad = grad.gather(2, rows)
        curv = curv.gather(2, rows.unsqueeze(-1).expand(-1, -1, -1,
                                                        2 * width))
        curv = curv.gather(3, rows.unsqueeze(-2).expand(-1, -1, width, -1))
        return value, grad, curv

    def __repr__(self) -> str:
        return f'{self.__class__.__name__}({self.measurement})'


def _pairs(factors: Factors) -> Tuple[Tensor, Tensor]:
    # every (message edge, link) pair of the same factor, sorted by message
    # edge: the message edge reads each of its factor's links (the two
    # ranges of a pair)
    links = torch.arange(factors.factor.numel(),
                         device=factors.factor.device)
    order = torch.argsort(factors.link, stable=True)
    count = torch.bincount(factors.link, minlength=factors.ends.size(0))
    first = torch.cumsum(count, 0) - count
    edges, pairs = [], []
    for k in range(int(count.max()) if count.numel() else 0):
        has = count[factors.factor] > k
        pairs.append(links[has])
        edges.append(order[first[factors.factor[has]] + k])
    if not pairs:
        empty = factors.factor.new_zeros(0)
        return empty, empty
    # sorted by message edge: the blocks of message edges take theirs as
    # one slice
    edges, pairs = torch.cat(edges), torch.cat(pairs)
    order = torch.argsort(edges, stable=True)
    return edges[order], pairs[order]


def _integrated(value: Tensor, grad: Tensor, curv: Tensor,
                sources: SourceBeliefs) -> Tensor:
    # the log-likelihood summed over each message edge's links with the
    # source's state integrated out against its extrinsic Gaussian: the
    # second-order expansion on the source's side, in closed form
    info = sources.info.unsqueeze(1)
    lower, _ = torch.linalg.cholesky_ex(info + curv)
    solved = torch.cholesky_solve(grad.unsqueeze(-1), lower).squeeze(-1)
    prior_lower, _ = torch.linalg.cholesky_ex(sources.info)
    log_det = 2 * (torch.log(lower.diagonal(dim1=-2, dim2=-1)).sum(-1) -
                   torch.log(prior_lower.diagonal(dim1=-2, dim2=-1)).sum(
                       -1).unsqueeze(-1))
    integrated = value + 0.5 * (grad * solved).sum(-1) - 0.5 * log_det
    return torch.where(sources.known.view(-1, 1), value, integrated)
