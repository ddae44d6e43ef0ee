import math
from typing import NamedTuple, Optional, Tuple

import torch
from torch import Tensor
from torch.nn import GRUCell, Linear, Sequential, SiLU
from torch_geometric.nn.conv import MessagePassing

from tg_nebp.data.validation import check_positive_int
from tg_nebp.models import MeasurementModel
from tg_nebp.nn.conv.gaussian_bp_conv import (FactorMessages, Factors,
                                              GaussianBelief, GaussianBPConv,
                                              Linearization,
                                              position_covariance,
                                              tempered_messages)

__all__ = ['GaussianNEBPConv', 'CorrectionFeatures', 'EDGE_FEATURES',
           'NODE_FEATURES', 'INFLATION_FEATURES', 'bounded_log']

#: The invariant features of a message edge :math:`s \to t` that the
#: correction reads (see GaussianNEBPConv).
EDGE_FEATURES = ('residual', 'spread_s', 'spread_t', 'strength',
                 'anchor_s', 'iteration')
#: The invariant features of a node that the correction reads.
NODE_FEATURES = ('degree', 'anchors', 'spread', 'elongation', 'consistency',
                 'history')
#: The features of an agent that its inflation reads besides its
#: embedding (see GaussianNEBPConv.inflation).
INFLATION_FEATURES = ('spread', 'elongation', 'consistency', 'history')
# the memory's last two columns: this iteration's consistency and its
# average over past steps (the rest is the node embedding)
_CONSISTENCY, _HISTORY = -2, -1
# the weight of the newest step in the consistency history
_HISTORY_RATE = 0.2


def bounded_log(raw: Tensor, low: float, high: float) -> Tensor:
    r"""A smooth map of :obj:`raw` onto :math:`(\ell, h)`, :math:`\ell < 0
    < h`, that is exactly 0 at 0: :math:`(h - \ell) (\sigma(x + c) -
    \sigma(c))` with :math:`\sigma(c) = -\ell / (h - \ell)`. The log of
    a learned weight or inflation: at zero output the correction is the
    identity, bit for bit."""
    width = high - low
    shift = math.log(-low / high)  # sigma(shift) = -low / width
    return width * (torch.sigmoid(raw + shift) - torch.sigmoid(
        torch.full_like(raw, shift)))


class CorrectionFeatures(NamedTuple):
    r"""What :class:`GaussianNEBPConv` reads in one iteration: the
    message edges' features :obj:`edge` :math:`(M, 6)`
    (``EDGE_FEATURES``), the nodes' :obj:`node` :math:`(N, 6)`
    (``NODE_FEATURES``) and every node's mean squared normalized
    residual over its links, :obj:`consistency` :math:`(N)`."""
    edge: Tensor
    node: Tensor
    consistency: Tensor


def _check_range(bounds, name: str) -> Tuple[float, float]:
    # a positive (low, high) around 1
    if len(tuple(bounds)) != 2:
        raise ValueError(f"'{name}' must be (low, high), got {bounds!r}")
    low, high = (float(b) for b in bounds)
    if not 0 < low < 1 < high < math.inf:
        raise ValueError(f"'{name}' must be (low, high) with 0 < low < 1 < "
                         f"high, got {tuple(bounds)}")
    return low, high


def _trace_product(a: Tensor, b: Tensor) -> Tensor:
    # tr(A B) of symmetric matrices, one per row
    return (a * b).sum((-1, -2))


def _quadratic(matrix: Tensor, vector: Tensor) -> Tensor:
    # v^T A v, one per row
    return (vector.unsqueeze(-2) @ matrix @ vector.unsqueeze(-1)).view(-1)


class GaussianNEBPConv(MessagePassing):
    r"""The learned correction of Gaussian belief propagation, in the spirit
    of `"Neural Enhanced Belief Propagation for Cooperative Localization"
    <https://arxiv.org/abs/2105.12903>`_ (Liang and Meyer, 2021), who
    correct particle BP's messages with a graph neural network run beside
    it: here the network runs beside
    :class:`~tg_nebp.nn.conv.GaussianBPConv` and corrects what it
    computes, keeping every belief a valid Gaussian.

    In every iteration, Gaussian BP's message :math:`(\boldsymbol{\Lambda}_{
    f \to t}, \boldsymbol{\eta}_{f \to t})` on every message edge
    :math:`s \to t` is tempered by a learned positive weight,

    .. math::
        \tilde{\boldsymbol{\Lambda}}_{f \to t} = w_{st}
        \boldsymbol{\Lambda}_{f \to t}, \quad
        \tilde{\boldsymbol{\eta}}_{f \to t} = w_{st}
        \boldsymbol{\eta}_{f \to t}, \quad
        w_{st} = \exp\big(b(\mathbf{v}_w^\top \mathbf{e}_{st};
        \log w_\mathrm{min}, \log w_\mathrm{max})\big),

    (the message's mean unchanged, its information scaled: a weight below
    one discounts a link that disagrees with its ends' beliefs, such as an
    NLOS range, or information counted again around a loop), and the
    tempered messages are what the beliefs sum and what the next
    iteration's extrinsic beliefs remove. Before every prediction the
    tracker inflates each agent's covariance by its own learned
    :math:`\kappa_i = \exp\big(b(\psi_\kappa(\mathbf{h}_i,
    \mathbf{n}_i); \log \kappa_\mathrm{min}, \log
    \kappa_\mathrm{max})\big)` (:meth:`inflation`), in place of one
    global inflation; :math:`b` maps onto its bounds smoothly and is 0 at
    0 (:func:`~tg_nebp.nn.conv.bounded_log`). Both are positive, so
    information stays symmetric positive definite for any weights of the
    network. The
    weights stay at most slightly above one: a Gaussian BP message is
    never worth more than its factor's information (the loops already
    count some twice), and larger weights let training buy a small
    negative log-likelihood now with a lost agent later.

    The network reads only what the agents have locally, as invariants:
    every message edge's squared residual normalized by its predicted
    spread, computed from the measurement model's own linearization
    (gradient :math:`\mathbf{g}` and curvature :math:`\mathbf{W}` of the
    factor) and the ends' position covariances :math:`\boldsymbol{\Sigma}
    = \mathrm{diag}(\boldsymbol{\Sigma}_s, \boldsymbol{\Sigma}_t)`,

    .. math::
        \chi^2_{st} = \frac{\mathbf{g}^\top \boldsymbol{\Sigma}
        \mathbf{g}}{c (1 + c)}, \quad c = \mathrm{tr}(\mathbf{W}
        \boldsymbol{\Sigma}),

    which is :math:`r^2 / (\sigma^2 + \mathbf{u}^\top
    (\boldsymbol{\Sigma}_s + \boldsymbol{\Sigma}_t) \mathbf{u})` for a
    Gaussian range (the residual :math:`r` of the averaged ranges of a
    pair), with its sign (a range longer than the means' distance is
    positive); the ends' spreads along the link
    :math:`\mathrm{tr}(\mathbf{W}_{ss} \boldsymbol{\Sigma}_s)`,
    :math:`\mathrm{tr}(\mathbf{W}_{tt} \boldsymbol{\Sigma}_t)`; the
    message's information relative to the target's,
    :math:`\mathrm{tr}(\boldsymbol{\Lambda}_{f \to t}
    \boldsymbol{\Sigma}_t)`; whether the source is an anchor; the
    iteration's index; and per node its degree, anchors in reach, the
    size and elongation of its position covariance, the mean
    :math:`\chi^2` of its links and its average over past steps
    (``EDGE_FEATURES``, ``NODE_FEATURES``). Traces, quadratic
    forms and counts do not change when the scene is rotated or
    translated, and sums over neighbours do not depend on the numbering:
    the correction is invariant to rigid motions and permutations, so it
    trains on small networks and runs on large ones.

    A node embedding :math:`\mathbf{h}_i` (the :obj:`memory`, carried
    over iterations and steps) is updated in every iteration as in a
    gated message passing neural network (`"Neural Message Passing for
    Quantum Chemistry" <https://arxiv.org/abs/1704.01212>`_),

    .. math::
        \mathbf{e}_{st} &= \phi_e(\mathbf{f}_{st}, \mathbf{h}_s,
        \mathbf{h}_t), \\
        \mathbf{h}_t &\leftarrow \mathrm{GRU}\Big(\Big[
        \frac{1}{|\mathcal{N}(t)|} \sum_{s} \mathbf{e}_{st},
        \mathbf{n}_t\Big], \mathbf{h}_t\Big),

    with an MLP :math:`\phi_e`; the GRU keeps the embeddings bounded over
    any number of iterations and steps. The output layers
    :math:`\mathbf{v}_w` and :math:`\psi_\kappa`'s last start at zero
    (:meth:`reset_correction`), so an untrained correction is Gaussian BP
    exactly (weights 1, no inflation; bit for bit its general messages,
    to rounding the rank-one ones of a range model): training starts from
    it. The
    network runs in its parameters' dtype; the beliefs keep theirs.

    Args:
        measurement (MeasurementModel, optional): The measurement model of
            Gaussian BP. (default: :obj:`GaussianRange()`)
        ends (str, optional): As in
            :class:`~tg_nebp.nn.conv.GaussianBPConv`.
            (default: :obj:`"both"`)
        damping (float, optional): As in
            :class:`~tg_nebp.nn.conv.GaussianBPConv`. (default: :obj:`0.0`)
        hidden_dim (int, optional): The size of the node embeddings and
            hidden layers. (default: :obj:`32`)
        num_iterations (int, optional): The iterations per step the
            iteration feature is scaled by. (default: :obj:`20`)
        weight_range (tuple, optional): :math:`(w_\mathrm{min},
            w_\mathrm{max})`, around 1. (default: :obj:`(0.02, 1.1)`)
        inflation_range (tuple, optional): :math:`(\kappa_\mathrm{min},
            \kappa_\mathrm{max})`, around 1. (default: :obj:`(0.8, 10)`)

    Shapes:
        - **input:** as :class:`~tg_nebp.nn.conv.GaussianBPConv`, and the
          memory :math:`(|\mathcal{V}|, H + 2)`
        - **output:** beliefs, means :math:`(|\mathcal{V}|, S)` and
          information :math:`(|\mathcal{V}|, S, S)`, the tempered messages
          :math:`(M, R, R)`, :math:`(M, R)`, and the memory
          :math:`(|\mathcal{V}|, H + 2)`
    """
    def __init__(self, measurement: Optional[MeasurementModel] = None,
                 ends: str = 'both', damping: float = 0.0,
                 hidden_dim: int = 32, num_iterations: int = 20,
                 weight_range: Tuple[float, float] = (0.02, 1.1),
                 inflation_range: Tuple[float, float] = (0.8, 10.0)):
        super().__init__(aggr='mean', node_dim=0)
        self.bp = GaussianBPConv(measurement, ends, damping)
        self.hidden_dim = check_positive_int(hidden_dim, 'hidden_dim')
        self.num_iterations = check_positive_int(num_iterations,
                                                 'num_iterations')
        self.weight_range = _check_range(weight_range, 'weight_range')
        self.inflation_range = _check_range(inflation_range,
                                            'inflation_range')
        hidden = self.hidden_dim
        edges, nodes = len(EDGE_FEATURES), len(NODE_FEATURES)
        self.edge_mlp = Sequential(Linear(edges + 2 * hidden, hidden), SiLU(),
                                   Linear(hidden, hidden), SiLU())
        self.node_update = GRUCell(hidden + nodes, hidden)
        self.weight_head = Linear(hidden, 1)
        self.inflation_mlp = Sequential(Linear(hidden +
                                               len(INFLATION_FEATURES),
                                               hidden),
                                        SiLU(), Linear(hidden, 1))
        self.reset_correction()

    @property
    def measurement(self) -> MeasurementModel:
        return self.bp.measurement

    @property
    def ends(self) -> str:
        return self.bp.ends

    @property
    def damping(self) -> float:
        return self.bp.damping

    def factors(self, edge_index: Tensor, anchor: Tensor,
                state_dim: int) -> Factors:
        r"""Gaussian BP's :meth:`~tg_nebp.nn.conv.GaussianBPConv.factors`
        of the links, which the iterations of a step share."""
        return self.bp.factors(edge_index, anchor, state_dim, slots=True)

    def restricted_factors(self, factors: Factors, keep: Tensor,
                           state_dim: int) -> Factors:
        r"""Gaussian BP's :meth:`restricted_factors
        <tg_nebp.nn.conv.GaussianBPConv.restricted_factors>`."""
        return self.bp.restricted_factors(factors, keep, state_dim)

    def reset_correction(self) -> None:
        r"""Sets the output layers to zero: every weight 1 and every
        inflation 1, Gaussian BP exactly (the embeddings still learn)."""
        for layer in (self.weight_head, self.inflation_mlp[-1]):
            torch.nn.init.zeros_(layer.weight)
            torch.nn.init.zeros_(layer.bias)

    def initial_memory(self, num_nodes: int,
                       device=None) -> Tensor:
        r"""The memory of :obj:`num_nodes` nodes before the first step:
        zero embeddings and consistency, in the parameters' dtype, on
        :obj:`device` (the parameters' by default)."""
        weight = self.weight_head.weight
        return torch.zeros(num_nodes, self.hidden_dim + 2, dtype=weight.dtype,
                           device=weight.device if device is None else
                           device)

    def features(self, belief: GaussianBelief, anchor: Tensor,
                 factors: Factors, linearization: Linearization,
                 messages: FactorMessages, iteration: int,
                 memory: Tensor) -> CorrectionFeatures:
        r"""The invariant inputs of the correction in one iteration
        (:class:`~tg_nebp.nn.conv.CorrectionFeatures`), from the beliefs
        (the linearization point), the factors' linearization and Gaussian
        BP's messages."""
        width = linearization.grad.size(-1) // 2
        cov = position_covariance(belief, width, anchor)
        source, target = factors.index
        cov_s, cov_t = cov[source], cov[target]
        info, grad = linearization.info, linearization.grad
        grad_s, grad_t = grad[:, :width], grad[:, width:]
        spread_s = _trace_product(info[:, :width, :width], cov_s)
        spread_t = _trace_product(info[:, width:, width:], cov_t)
        spread = spread_s + spread_t
        tiny = torch.finfo(spread.dtype).tiny
        chi2 = ((_quadratic(cov_s, grad_s) + _quadratic(cov_t, grad_t)) /
                (spread * (1 + spread)).clamp_min(tiny))
        # the sign of the residual: positive where the factor pushes its
        # ends apart (a range longer than the means' distance), along the
        # positions (the first entries of the factor's scope)
        dim = self.measurement.position_dim(belief.mean.size(-1))
        apart = (grad_s[:, :dim] * (belief.mean[source, :dim] -
                                    belief.mean[target, :dim])).sum(-1)
        # (the square root's slope is infinite at zero: floored)
        residual = torch.where(apart < 0, -1.0, 1.0).to(chi2) * (
            chi2.clamp_min(1e-12).sqrt())
        strength = _trace_product(messages.info, cov_t)
        count = belief.mean.size(0)
        ones = torch.ones_like(chi2)
        degree = ones.new_zeros(count).index_add_(0, target, ones)
        anchors = ones.new_zeros(count).index_add_(
            0, target, anchor[source].to(ones))
        consistency = chi2.new_zeros(count).index_add_(0, target, chi2)
        consistency = consistency / degree.clamp_min(1)
        edge = torch.stack([
            torch.asinh(residual), torch.log1p(spread_s),
            torch.log1p(spread_t), torch.log1p(strength),
            anchor[source].to(chi2),
            ones * (iteration / self.num_iterations)], -1)
        history = memory[:, _HISTORY].to(chi2)
        node = torch.cat([torch.stack([torch.log1p(degree),
                                       torch.log1p(anchors)], -1),
                          self._shape(cov, anchor),
                          torch.stack([torch.asinh(consistency),
                                       torch.asinh(history)], -1)], -1)
        return CorrectionFeatures(edge, node, consistency)

    @staticmethod
    def _shape(cov: Tensor, anchor: Tensor) -> Tensor:
        # the size (log of the mean variance) and elongation (log of the
        # geometric over the arithmetic mean of the variances, at most 0)
        # of every position covariance; zero for anchors
        eye = torch.eye(cov.size(-1), dtype=cov.dtype, device=cov.device)
        safe = torch.where(anchor.view(-1, 1, 1), eye, cov)
        mean_variance = safe.diagonal(dim1=-2, dim2=-1).mean(-1)
        size = torch.log(mean_variance)
        elongation = torch.logdet(safe) / cov.size(-1) - size
        out = torch.stack([size, elongation], -1)
        return out.masked_fill(anchor.view(-1, 1), 0.0)

    def _corrected(self, belief: GaussianBelief, edge_index: Tensor,
                   edge_attr: Tensor, anchor: Tensor, memory: Tensor,
                   messages, generator, factors: Factors, iteration: int,
                   fresh: Optional[Tensor] = None):
        # Gaussian BP's messages at the beliefs (those of the message
        # edges 'fresh' had no previous one: not damped), the correction's
        # features and its edge embeddings (what the weights are read from)
        linearization = self.bp.linearize(belief, edge_index, edge_attr,
                                          factors, generator)
        new = self.bp.messages(belief, anchor, factors, linearization,
                               messages, fresh)
        features = self.features(belief, anchor, factors, linearization,
                                 new, iteration, memory)
        source, target = factors.index
        hidden = memory[:, :self.hidden_dim]
        edge = self.edge_mlp(torch.cat([
            features.edge.to(self.weight_head.weight.dtype),
            hidden[source], hidden[target]], -1))
        return new, features, edge

    def weights(self, belief: GaussianBelief, edge_index: Tensor,
                edge_attr: Tensor, anchor: Tensor, memory: Tensor,
                messages, factors: Factors, iteration: int,
                generator: Optional[torch.Generator] = None,
                validate: bool = True) -> Tensor:
        r"""The weight :math:`(M)` the correction gives every message edge
        of :obj:`factors` in an iteration :obj:`iteration` from the
        beliefs :obj:`belief`, the nodes' :obj:`memory` and the last
        :obj:`messages` (the arguments of :meth:`forward`): the power of
        the likelihood its tempered messages stand for, which a method
        that scores the exact likelihood of the links (a relocation's
        search, hybrid BP's particles) raises each link's to;
        :obj:`validate` as in :meth:`forward`."""
        inputs = self.bp.prepare(belief, belief, edge_index, edge_attr,
                                 anchor, messages, factors, validate)
        _, belief, edge_index, edge_attr, messages, factors = inputs
        _, _, edge = self._corrected(belief, edge_index, edge_attr, anchor,
                                     memory, messages, generator, factors,
                                     iteration)
        return self.message_weights(edge).to(belief.mean).view(-1)

    def forward(self, prior: GaussianBelief, belief: GaussianBelief,
                edge_index: Tensor, edge_attr: Tensor, anchor: Tensor,
                memory: Tensor, messages: Optional[FactorMessages] = None,
                generator: Optional[torch.Generator] = None,
                factors: Optional[Factors] = None, iteration: int = 0,
                validate: bool = True
                ) -> Tuple[GaussianBelief, FactorMessages, Tensor]:
        r"""Runs one corrected iteration.

        :obj:`prior`, :obj:`belief`, :obj:`edge_index`,
        :obj:`edge_attr`, :obj:`anchor`, :obj:`messages`,
        :obj:`generator`, :obj:`factors` and :obj:`validate` are those of
        :meth:`GaussianBPConv.forward
        <tg_nebp.nn.conv.GaussianBPConv.forward>` (the previous
        :obj:`messages` are the tempered ones this layer returned).

        Args:
            memory (torch.Tensor): The nodes' memory
                (:meth:`initial_memory` before the first step).
            iteration (int, optional): The iteration's index within its
                time step. (default: :obj:`0`)
        """
        inputs = self.bp.prepare(prior, belief, edge_index, edge_attr,
                                 anchor, messages, factors, validate)
        prior, belief, edge_index, edge_attr, messages, factors = inputs
        if validate:
            self._check_memory(memory, belief.mean.size(0))
        tempered, memory = self.corrected_messages(
            belief, edge_index, edge_attr, anchor, memory, messages, factors,
            iteration, generator)
        return (self.bp.beliefs(prior, belief, tempered, factors, anchor),
                tempered, memory)

    def corrected_messages(self, belief: GaussianBelief, edge_index: Tensor,
                           edge_attr: Tensor, anchor: Tensor, memory: Tensor,
                           messages, factors: Factors, iteration: int,
                           generator: Optional[torch.Generator] = None,
                           fresh: Optional[Tensor] = None
                           ) -> Tuple[FactorMessages, Tensor]:
        r"""The tempered messages of one iteration and the memory after
        it, without the beliefs (the first part of :meth:`forward`; its
        inputs as :meth:`GaussianBPConv.prepare
        <tg_nebp.nn.conv.GaussianBPConv.prepare>` gives them): what a
        tracker that sums the messages into beliefs of its own uses
        (:class:`~tg_nebp.filters.FixedLagGaussianNEBP`, whose beliefs
        are each agent's chain over the window). The message edges of the
        mask :obj:`fresh` :math:`(M)` have no previous message (not
        damped)."""
        new, features, edge = self._corrected(
            belief, edge_index, edge_attr, anchor, memory, messages,
            generator, factors, iteration, fresh)
        hidden = memory[:, :self.hidden_dim]
        node = features.node.to(edge)
        gathered = self.propagate(factors.index, edge=edge,
                                  size=(node.size(0), node.size(0)))
        hidden = self.node_update(torch.cat([gathered, node], -1), hidden)
        tempered = tempered_messages(
            new, self.message_weights(edge).to(new.eta).view(-1))
        memory = torch.cat([hidden, features.consistency.to(edge).view(
            -1, 1), memory[:, _HISTORY:]], -1)
        return tempered, memory

    def _check_memory(self, memory: Tensor, num_nodes: int) -> None:
        # one row per node, in the parameters' dtype and on their device
        weight = self.weight_head.weight
        if not isinstance(memory, Tensor):
            raise TypeError(f"'memory' must be a tensor, got "
                            f"{type(memory).__name__}")
        if memory.shape != (num_nodes, self.hidden_dim + 2):
            raise ValueError(f"'memory' must have shape "
                             f"{[num_nodes, self.hidden_dim + 2]}, got "
                             f"{list(memory.shape)}")
        if memory.dtype != weight.dtype or memory.device != weight.device:
            raise ValueError(f"'memory' must be {weight.dtype} on "
                             f"{weight.device} (the parameters'), got "
                             f"{memory.dtype} on {memory.device}")

    def message_weights(self, edge: Tensor) -> Tensor:
        r"""The positive weight :math:`w_{st}` :math:`(M, 1)` of every
        message edge from its embedding :math:`\mathbf{e}_{st}`, inside
        :obj:`weight_range` (1 where the head is zero)."""
        low, high = self.weight_range
        return torch.exp(bounded_log(self.weight_head(edge), math.log(low),
                                     math.log(high)))

    def message(self, edge: Tensor) -> Tensor:
        return edge

    def inflation(self, cov: Tensor, memory: Tensor,
                  anchor: Tensor) -> Tensor:
        r"""Every node's learned inflation :math:`\kappa_i` :math:`(N)`
        of its belief covariance :obj:`cov` :math:`(N, S, S)` before the
        next prediction, from its memory (embedding, consistency and its
        history) and its covariance's size and elongation
        (``INFLATION_FEATURES``); 1 for anchors."""
        dtype = self.weight_head.weight.dtype
        width = len(self.measurement.scope(cov.size(-1)))
        shape = self._shape(cov[:, :width, :width], anchor).to(dtype)
        consistency = torch.asinh(memory[:, [_CONSISTENCY, _HISTORY]])
        raw = self.inflation_mlp(torch.cat(
            [memory[:, :self.hidden_dim], shape, consistency], -1)).view(-1)
        low, high = self.inflation_range
        kappa = torch.exp(bounded_log(raw, math.log(low), math.log(high)))
        return kappa.to(cov).masked_fill(anchor, 1.0)

    def end_step(self, memory: Tensor) -> Tensor:
        r"""The memory after a time step: the consistency of its last
        iteration joins the history (an exponential average over
        steps)."""
        history = torch.lerp(memory[:, _HISTORY], memory[:, _CONSISTENCY],
                             _HISTORY_RATE)
        return torch.cat([memory[:, :_HISTORY], history.unsqueeze(-1)], -1)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}({self.measurement}, '
                f'ends={self.bp.ends!r}, damping={self.bp.damping}, '
                f'hidden_dim={self.hidden_dim})')
