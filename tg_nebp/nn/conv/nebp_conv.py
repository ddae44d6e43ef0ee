import math
from typing import Optional, Tuple, Union

import torch
from torch import Tensor
from torch_geometric import EdgeIndex
from torch_geometric.nn import MLP
from torch_geometric.nn.conv import MessagePassing
from torch_geometric.utils import scatter, segment

from tg_nebp.data.validation import (check_layer_inputs, check_number,
                                     check_position_dim,
                                     check_positive_int)
from tg_nebp.models import MeasurementModel
from tg_nebp.nn.conv.particle_bp_conv import ParticleBPConv
from tg_nebp.utils import (compute_dtype, floored_exp, log_normalize,
                           logaddexp, long_edge_index, plain_tensor,
                           weighted_moments)

__all__ = ['NEBPConv', 'node_embedding', 'embedding_dim']

MLP_OPTIONS = dict(act='leaky_relu', norm=None, plain_last=True)


def embedding_dim(position_dim: int = 2) -> int:
    r"""The size of a node embedding for positions of
    :obj:`position_dim` dimensions: the mean and the flattened covariance
    of a state of size :math:`S = 2D`, :math:`S + S^2` (20 in 2-D)."""
    size = 2 * position_dim
    return size + size * size


def edge_features(position_dim: int = 2) -> int:
    # what g_e reads of the two embeddings: mean difference, both
    # covariances (36 in 2-D)
    size = 2 * position_dim
    return size + 2 * size * size


def node_embedding(particles: Tensor, log_weights: Tensor) -> Tensor:
    r"""The paper's node embedding :math:`\mathbf{h}_i = [\hat{\mathbf{x}}_i^
    \top, \mathrm{vec}(\hat{\mathbf{C}}_i)^\top]^\top` :math:`(N, S +
    S^2)` (20 in 2-D): the weighted particle mean and covariance."""
    mean, cov = weighted_moments(particles, log_weights)
    return torch.cat([mean, cov.flatten(1)], dim=-1)


def check_embedding(embedding: Tensor, num_nodes: int,
                    position_dim: int = 2) -> None:
    r"""Checks that node embeddings are finite and of shape :math:`(N,
    S + S^2)`."""
    size = embedding_dim(position_dim)
    if embedding.shape != (num_nodes, size):
        raise ValueError(f"'embedding' must have shape [{num_nodes}, "
                         f"{size}], got {list(embedding.shape)}")
    bad = ~torch.isfinite(embedding).all(-1)
    if bool(bad.any()):
        raise ValueError(f"'embedding[{int(bad.nonzero()[0, 0])}]' holds a "
                         f"non-finite value")


def _log_relu(x: Tensor) -> Tensor:
    # log(relu(x)) with a zero (not NaN) gradient where relu(x) = 0
    return torch.where(x > 0, x.clamp_min(1e-30).log(), float('-inf'))


class NEBPConv(MessagePassing):
    r"""One iteration of Neural Enhanced Belief Propagation for cooperative
    localization, from the `"Neural Enhanced Belief Propagation for
    Cooperative Localization" <https://arxiv.org/abs/2105.12903>`_ paper.
    Its three steps are

    1. classical BP (:class:`ParticleBPConv`) gives the log-messages
       :math:`\log \boldsymbol{\phi}_{j \to i}` :math:`(K)` of every edge,
    2. the GNN computes messages from the node embeddings
       :math:`\mathbf{h}_i` with the BP message as edge attribute,

       .. math::
           \mathbf{m}_{j \to i} = g_e(\mathbf{h}_i, \mathbf{h}_j,
           \boldsymbol{a}_{j \to i}),

       and, for more than one iteration, updates the embeddings
       :math:`\mathbf{h}_i \leftarrow g_n(\mathbf{h}_i, \sum_{j}
       \mathbf{m}_{j \to i})`,
    3. the messages are corrected,
       :math:`\underline{\boldsymbol{\phi}}_{j \to i} = g_s(\mathbf{m}_{j
       \to i}) \, \boldsymbol{\phi}_{j \to i} + g_v(\mathbf{m}_{j \to i})`,
       in the log domain

       .. math::
           \log \underline{\boldsymbol{\phi}}_{j \to i} =
           \operatorname{logaddexp}\big(\log g_s + \log
           \boldsymbol{\phi}_{j \to i},\, \log g_v\big),

       and summed into the receivers' log-weights
       :math:`\log w_i + \sum_j \log \underline{\boldsymbol{\phi}}_{j \to
       i}`.

    :math:`g_s` ends in a sigmoid (a positive scalar), :math:`g_v` in a ReLU
    (a non-negative :math:`K`-vector), all MLPs have one hidden layer with
    leaky ReLU. Two choices where the paper is silent, both documented
    deviations that leave BP itself unchanged:

    * each BP message is scaled to mean one over its :math:`K` particles
      before it is corrected and used as the edge attribute
      :math:`\boldsymbol{a}_{j \to i}` (a per-edge constant, which does not
      change the BP belief), so :math:`g_v` and :math:`g_e` see the same scale
      for any :math:`K` and any network;
    * :math:`g_e` sees :math:`\mathbf{h}_i` and :math:`\mathbf{h}_j` through
      the difference of the means and both covariances (scaled by
      :obj:`feature_scale`), so a GNN trained on one area generalizes to
      another (the paper trains on :math:`[0, 60]^2` and tests on
      :math:`[0, 100]^2`).

    Like any :class:`torch.nn` layer it computes in its parameters' dtype
    (float32, or float64 after :obj:`conv.double()`): floating inputs are
    cast to it.

    Args:
        num_particles (int): :math:`K` (sizes :math:`g_e` and :math:`g_v`).
        message_dim (int, optional): Size of :math:`\mathbf{m}`.
            (default: :obj:`32`)
        hidden_dim (int, optional): Hidden layer size of every MLP.
            (default: :obj:`64`)
        correct_anchor_edges (bool, optional): Also correct the messages sent
            by anchors (the authors' code corrects agent-agent edges only).
            (default: :obj:`False`)
        node_update (bool, optional): Build :math:`g_n` (needed for more than
            one iteration). (default: :obj:`False`)
        measurement (MeasurementModel, optional): Measurement model of
            the BP messages. (default: :obj:`GaussianRange()`)
        feature_scale (float, optional): Divides the embedding features that
            enter :math:`g_e` and :math:`g_n`. (default: :obj:`10.0`)
        chunk_size (int, optional): Edge chunk of the BP messages.
            (default: :obj:`None`)
        num_samples (int or str, optional): Sender particles per receiver
            particle in the BP messages (see :class:`ParticleBPConv`).
            (default: :obj:`1`)
        position_dim (int, optional): The positions' dimension :math:`D`
            (2 or 3): it sizes the embeddings and :math:`g_e`, so a layer
            runs on states of size :math:`2D` only. (default: :obj:`2`)
        compile (bool, optional): Run the per-edge work (the BP messages
            and :meth:`corrected_messages`) through :func:`torch.compile`
            (fused kernels; the first calls compile). The aggregation stays
            a deterministic segment sum for receiver-sorted
            :class:`~torch_geometric.EdgeIndex` edges. Equal to the eager
            path within float tolerance. The whole layer also compiles
            without graph breaks (:obj:`torch.compile(conv)` with a plain
            :obj:`edge_index` and :obj:`validate=False`).
            (default: :obj:`False`)

    Shapes:
        - **input:**
          particles :math:`(|\mathcal{V}|, K, S)`, :math:`S = 2D`,
          log-weights :math:`(|\mathcal{V}|, K)`,
          edge indices :math:`(2, |\mathcal{E}|)`,
          link features :math:`(|\mathcal{E}|, F)` (the range first),
          anchor mask :math:`(|\mathcal{V}|)`,
          sender log-weights :math:`(|\mathcal{V}|, K)` *(optional)*,
          node embeddings :math:`(|\mathcal{V}|, S + S^2)` *(optional)*
        - **output:** updated log-weights :math:`(|\mathcal{V}|, K)` and node
          embeddings :math:`(|\mathcal{V}|, S + S^2)`
    """
    SUPPORTS_FUSED_EDGE_INDEX = True

    def __init__(self, num_particles: int, message_dim: int = 32,
                 hidden_dim: int = 64, correct_anchor_edges: bool = False,
                 node_update: bool = False,
                 measurement: Optional[MeasurementModel] = None,
                 feature_scale: float = 10.0,
                 chunk_size: Optional[int] = None, compile: bool = False,
                 num_samples: Union[int, str] = 1, position_dim: int = 2):
        super().__init__(aggr='add', node_dim=0)
        self.position_dim = check_position_dim(position_dim)
        if num_particles is not None:  # None: a correction for any K
            num_particles = check_positive_int(num_particles,
                                               'num_particles')
        message_dim = check_positive_int(message_dim, 'message_dim')
        hidden_dim = check_positive_int(hidden_dim, 'hidden_dim')
        feature_scale = check_number(feature_scale, 'feature_scale')
        self.num_particles = num_particles
        self.correct_anchor_edges = correct_anchor_edges
        self.feature_scale = feature_scale
        self.bp = ParticleBPConv(measurement, chunk_size=chunk_size,
                                 compile=compile, num_samples=num_samples)
        # dynamic: the number of edges changes at every time step
        self._corrected_messages = torch.compile(
            self.corrected_messages,
            dynamic=True) if compile else self.corrected_messages
        self.build_correction(message_dim, hidden_dim)
        size = embedding_dim(position_dim)
        self.g_n = MLP([size + message_dim, hidden_dim, size],
                       **MLP_OPTIONS) if node_update else None

    def build_correction(self, message_dim: int, hidden_dim: int) -> None:
        r"""Builds the correction's networks (in this order, which fixes
        their seeded initial weights): :math:`g_e` of the node features and
        the :math:`K` message values, the scale :math:`g_s`, and :math:`g_v`
        of :math:`K` offsets."""
        self.g_e = MLP([edge_features(self.position_dim) +
                        self.num_particles, hidden_dim, message_dim],
                       **MLP_OPTIONS)
        self.g_s = MLP([message_dim, hidden_dim, 1], **MLP_OPTIONS)
        self.g_v = MLP([message_dim, hidden_dim, self.num_particles],
                       **MLP_OPTIONS)

    def reset_parameters(self):
        super().reset_parameters()
        for network in self.children():  # the correction's networks
            if network is not self.bp:
                network.reset_parameters()

    def forward(
        self,
        particles: Tensor,
        log_weights: Tensor,
        edge_index: Tensor,
        edge_attr: Tensor,
        anchor: Tensor,
        sender_log_weights: Optional[Tensor] = None,
        embedding: Optional[Tensor] = None,
        validate: bool = True,
        sample_offsets: Optional[Tensor] = None,
        generator: Optional[torch.Generator] = None,
    ) -> Tuple[Tensor, Tensor]:
        r"""Runs one NEBP iteration.

        Args:
            particles (torch.Tensor): Particles (not differentiated).
            log_weights (torch.Tensor): Prediction log-weights.
            edge_index (torch.Tensor): Edges :math:`j \to i`.
            edge_attr (torch.Tensor): Link features, the range first.
            anchor (torch.Tensor): Bool mask of anchors.
            sender_log_weights (torch.Tensor, optional): The NEBP beliefs of
                the previous iteration; :obj:`log_weights` at the first.
                (default: :obj:`None`)
            embedding (torch.Tensor, optional): :math:`\mathbf{h}`; computed
                from the prediction at the first iteration.
                (default: :obj:`None`)
            validate (bool, optional): Check the inputs.
                (default: :obj:`True`)
            sample_offsets (torch.Tensor, optional): Offsets of the
                :math:`M`-sample BP messages (see :class:`ParticleBPConv`).
                (default: :obj:`None`)
            generator (torch.Generator, optional): Source of the offsets
                when they are not given. (default: :obj:`None`)
        """
        num_nodes = particles.size(0)
        if sender_log_weights is None:
            sender_log_weights = log_weights
        # like any torch.nn layer, compute in the parameters' dtype; the
        # checks see the values as computed (a float64 input may overflow
        # float32)
        parameter = next(self.parameters(), None)
        dtype = (parameter.dtype if parameter is not None else compute_dtype(
            particles, log_weights, sender_log_weights, edge_attr))
        if dtype not in (torch.float32, torch.float64):
            raise TypeError(f"NEBPConv computes in float32 or float64, its "
                            f"parameters are {dtype}")
        particles, log_weights, sender_log_weights, edge_attr = (
            t.to(dtype) if t.is_floating_point() else t
            for t in (particles, log_weights, sender_log_weights, edge_attr))
        if embedding is not None:
            embedding = embedding.to(dtype)
        if validate:
            check_layer_inputs(particles, log_weights, edge_index, edge_attr,
                               self.bp.measurement.features, anchor,
                               sender_log_weights,
                               state_dim=2 * self.position_dim,
                               negative_ranges=self.bp.measurement
                               .negative_ranges)
            if anchor is None:
                raise ValueError("'anchor' is required by NEBPConv")
            if embedding is not None:
                check_embedding(embedding, num_nodes, self.position_dim)
        if (self.num_particles is not None
                and particles.size(1) != self.num_particles):
            raise ValueError(f"'particles' holds K = {particles.size(1)} "
                             f"particles per node but this NEBPConv was "
                             f"built for K = {self.num_particles}")
        edge_index = long_edge_index(edge_index, particles.size(0))
        if embedding is None:
            embedding = node_embedding(particles, log_weights)

        # 1. classical BP messages
        _, log_phi = self.bp(particles, log_weights, edge_index, edge_attr,
                             sender_log_weights=sender_log_weights,
                             validate=False, sample_offsets=sample_offsets,
                             generator=generator)
        # 2. GNN messages and 3. corrected messages, per edge (the compiled
        # region takes plain tensors; aggregation stays a segment sum)
        log_corrected, message = self._corrected_messages(
            embedding, log_phi, plain_tensor(edge_index), anchor, particles,
            log_weights, edge_attr)
        out = self.propagate(edge_index, log_messages=log_corrected,
                             size=(num_nodes, num_nodes))
        out = out.masked_fill(anchor.view(-1, 1), 0.0)
        if self.g_n is not None:
            summed = scatter(message, edge_index[1], dim=0,
                             dim_size=num_nodes, reduce='sum')
            embedding = self.g_n(
                torch.cat([embedding / self.feature_scale, summed], -1))
        return log_weights + out, embedding

    def corrected_messages(self, embedding: Tensor, log_phi: Tensor,
                           edge_index: Tensor, anchor: Tensor,
                           particles: Tensor, log_weights: Tensor,
                           edge_attr: Tensor) -> Tuple[Tensor, Tensor]:
        r"""Steps 2 and 3 on every edge: returns the corrected
        log-messages :math:`(|\mathcal{E}|, K)` and the GNN messages
        :math:`\mathbf{m}` :math:`(|\mathcal{E}|, \mathrm{message\_dim})`
        from the node embeddings and the BP log-messages :obj:`log_phi`
        (the particles, prediction log-weights and link features are for
        corrections that read them; the paper's does not).
        With :obj:`compile=True` this is the :func:`torch.compile` region
        (no graph breaks): the per-edge-particle chain becomes a few fused
        kernels."""
        # scaled to mean one per edge: a per-edge constant, BP is unchanged
        log_phi = log_normalize(log_phi) + math.log(log_phi.size(1))
        message = self.edge_updater(edge_index, h=embedding, log_phi=log_phi)
        log_offset = _log_relu(self.g_v(message))
        return self.combine(message, log_phi, log_offset, edge_index,
                            anchor), message

    def combine(self, message: Tensor, log_phi: Tensor, log_offset: Tensor,
                edge_index: Tensor, anchor: Tensor) -> Tensor:
        r"""The corrected log-messages :math:`\operatorname{logaddexp}(\log
        g_s(\mathbf{m}) + \log \boldsymbol{\phi}, \log g_v)` from the
        mean-one BP log-messages and the log-offsets; anchors' messages
        stay BP's unless :obj:`correct_anchor_edges`."""
        log_scaled = torch.nn.functional.logsigmoid(
            self.g_s(message)) + log_phi
        log_corrected = logaddexp(log_scaled, log_offset)
        if not self.correct_anchor_edges:
            from_anchor = anchor[edge_index[0]].view(-1, 1)
            log_corrected = torch.where(from_anchor, log_phi, log_corrected)
        return log_corrected

    def edge_update(self, h_i: Tensor, h_j: Tensor,
                    log_phi: Tensor) -> Tensor:
        return self.g_e(torch.cat([self.embedding_features(h_i, h_j),
                                   floored_exp(log_phi)], dim=-1))

    def embedding_features(self, h_i: Tensor, h_j: Tensor) -> Tensor:
        r"""What :math:`g_e` reads of the two node embeddings
        :math:`(|\mathcal{E}|, S + 2 S^2)` (36 in 2-D): the difference of
        the means and both covariances, divided by
        :obj:`feature_scale`."""
        size = 2 * self.position_dim
        return torch.cat([h_j[:, :size] - h_i[:, :size], h_i[:, size:],
                          h_j[:, size:]], dim=-1) / self.feature_scale

    def message(self, log_messages: Tensor) -> Tensor:
        return log_messages

    def message_and_aggregate(self, edge_index: EdgeIndex,
                              log_messages: Tensor) -> Tensor:
        # receiver-sorted edges (the trackers pass them on CUDA): a
        # deterministic segment sum instead of atomic scatter-adds
        (ptr, _), _ = edge_index.get_csc()
        return segment(log_messages, ptr, reduce='sum')

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(num_particles='
                f'{self.num_particles}, correct_anchor_edges='
                f'{self.correct_anchor_edges})')
