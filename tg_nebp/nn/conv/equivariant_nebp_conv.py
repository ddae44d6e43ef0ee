import math
from typing import Optional, Tuple, Union

import torch
from torch import Tensor
from torch_geometric.nn import MLP

from tg_nebp.data.validation import check_positive_int
from tg_nebp.models import MeasurementModel
from tg_nebp.nn.conv.nebp_conv import MLP_OPTIONS, NEBPConv, edge_features
from tg_nebp.utils import floored_exp, log_normalize, weighted_moments

__all__ = ['EquivariantNEBPConv']



def particle_features(position_dim: int) -> int:
    # the per-particle features: whitened position (D), log-message below
    # its maximum (1), range residual (1)
    return position_dim + 2


def message_summaries(position_dim: int) -> int:
    # the per-edge summaries of the message: weighted mean (D) and second
    # moments (D (D + 1) / 2) of the whitened positions, effective sample
    # size over K (1)
    return position_dim + position_dim * (position_dim + 1) // 2 + 1

# log-messages further below the maximum read as this (finite features for
# -inf messages; such particles carry no weight anyway)
LOG_MESSAGE_FLOOR = -30.0
# the initial log-offset (the bias of g_v's output layer): offsets start at
# 5 % of the mean-one message, a mild floor under every particle
INITIAL_LOG_OFFSET = math.log(0.05)


class EquivariantNEBPConv(NEBPConv):
    r"""A particle-equivariant Neural Enhanced BP iteration: the correction
    of :class:`~tg_nebp.nn.conv.NEBPConv` (from the `"Neural Enhanced
    Belief Propagation for Cooperative Localization"
    <https://arxiv.org/abs/2105.12903>`_ paper) with networks that never
    see a particle index, so one set of weights runs at any particle count
    :math:`K` and permuting a node's particles permutes its corrected
    messages the same way.

    The paper's :math:`g_e` reads the :math:`K`-vector BP message and its
    :math:`g_v` writes a :math:`K`-vector of offsets, so they exist for one
    :math:`K` and tie offset :math:`k` to particle index :math:`k` of an
    unordered set. Here, with :math:`\bar{\boldsymbol{\phi}}_{j \to i}` the
    BP message scaled to mean one over the receiver's particles,
    :math:`\pi^{(k)} \propto w_i^{(k)} \bar{\phi}_{j \to i}^{(k)}` the
    message-weighted prediction of the receiver, and
    :math:`\mathbf{u}_i^{(k)} = \mathbf{L}_i^{-1} (\mathbf{p}_i^{(k)} -
    \hat{\mathbf{p}}_i)` the receiver's particle positions whitened by its
    prediction mean and covariance :math:`\mathbf{L}_i \mathbf{L}_i^\top`,

    .. math::
        \mathbf{m}_{j \to i} &= g_e\big(\mathbf{h}_i, \mathbf{h}_j,
        \textstyle \sum_k \pi^{(k)} \mathbf{u}_i^{(k)}, \sum_k \pi^{(k)}
        \mathbf{u}_i^{(k)} \mathbf{u}_i^{(k)\top},
        \big(K \sum_k (\pi^{(k)})^2\big)^{-1}\big)

        \underline{\phi}_{j \to i}^{(k)} &= g_s(\mathbf{m}_{j \to i}) \,
        \bar{\phi}_{j \to i}^{(k)} + g_v\big(\mathbf{m}_{j \to i},
        \mathbf{u}_i^{(k)}, \log \bar{\phi}_{j \to i}^{(k)} - \max_l \log
        \bar{\phi}_{j \to i}^{(l)}, r_{j \to i}^{(k)}\big)

    in the log domain, with the range residual :math:`r_{j \to i}^{(k)} =
    (z_{j \to i} - \|\mathbf{p}_i^{(k)} - \hat{\mathbf{p}}_j\|) / s_j`
    scaled by the sender's position spread :math:`s_j = (\frac{1}{2}
    \operatorname{tr} \hat{\mathbf{C}}_{j,\mathrm{pos}} + 1\,
    \mathrm{m}^2)^{1/2}`. :math:`g_e` is a summary of permutation-invariant
    inputs; :math:`g_s` ends in a sigmoid (a scale in :math:`(0, 1)`), as
    in the paper. :math:`g_v` is one small MLP applied to every particle
    with shared weights, and it writes the log of a positive offset where
    the paper's ends in a ReLU: a ReLU on a shared head dies. Once its
    output is negative for every particle no gradient reaches it again; a
    layer trained that way had every offset at zero, which leaves BP's
    beliefs unchanged (the scale alone is a per-edge constant). The offsets
    start at 5 % of the mean-one message. Its first layer is split into an
    edge part, computed once per edge, and a particle part, so the
    per-particle work is
    :math:`O(|\mathcal{E}| K \cdot \mathrm{particle\_dim})`. Everything
    else (BP messages, embeddings, :math:`g_n`, anchors, aggregation,
    dtypes) is :class:`NEBPConv`'s.

    A zero offset and unit scale give BP's beliefs. The BP messages
    themselves are permutation-equivariant only when they marginalize over
    every sender particle (:obj:`num_samples="all"`); with fewer samples,
    which sender particles a receiver particle meets depends on the order.

    Args:
        message_dim (int, optional): Size of :math:`\mathbf{m}`.
            (default: :obj:`32`)
        hidden_dim (int, optional): Hidden layer size of :math:`g_e`,
            :math:`g_s` and :math:`g_n`. (default: :obj:`64`)
        particle_dim (int, optional): Hidden layer size of the
            per-particle :math:`g_v`. (default: :obj:`32`)
        correct_anchor_edges (bool, optional): Also correct the messages
            sent by anchors. (default: :obj:`False`)
        node_update (bool, optional): Build :math:`g_n`.
            (default: :obj:`False`)
        measurement (MeasurementModel, optional): Measurement model of the
            BP messages. (default: :obj:`GaussianRange()`)
        feature_scale (float, optional): Divides the embedding features
            that enter :math:`g_e` and :math:`g_n`. (default: :obj:`10.0`)
        chunk_size (int, optional): Edge chunk of the BP messages.
            (default: :obj:`None`)
        num_samples (int or str, optional): Sender particles per receiver
            particle in the BP messages (see :class:`ParticleBPConv`).
            (default: :obj:`1`)
        position_dim (int, optional): The positions' dimension :math:`D`
            (see :class:`NEBPConv`). (default: :obj:`2`)
        compile (bool, optional): See :class:`NEBPConv`.
            (default: :obj:`False`)

    Shapes:
        - **input:**
          particles :math:`(|\mathcal{V}|, K, S)` for any :math:`K`,
          :math:`S = 2D`,
          log-weights :math:`(|\mathcal{V}|, K)`,
          edge indices :math:`(2, |\mathcal{E}|)`,
          link features :math:`(|\mathcal{E}|, F)` (the range first),
          anchor mask :math:`(|\mathcal{V}|)`,
          sender log-weights :math:`(|\mathcal{V}|, K)` *(optional)*,
          node embeddings :math:`(|\mathcal{V}|, S + S^2)` *(optional)*
        - **output:** updated log-weights :math:`(|\mathcal{V}|, K)` and node
          embeddings :math:`(|\mathcal{V}|, S + S^2)`
    """
    def __init__(self, message_dim: int = 32, hidden_dim: int = 64,
                 particle_dim: int = 32, correct_anchor_edges: bool = False,
                 node_update: bool = False,
                 measurement: Optional[MeasurementModel] = None,
                 feature_scale: float = 10.0,
                 chunk_size: Optional[int] = None, compile: bool = False,
                 num_samples: Union[int, str] = 1, position_dim: int = 2):
        self.particle_dim = particle_dim
        super().__init__(None, message_dim, hidden_dim, correct_anchor_edges,
                         node_update, measurement, feature_scale, chunk_size,
                         compile, num_samples, position_dim)

    def build_correction(self, message_dim: int, hidden_dim: int) -> None:
        r"""Builds :math:`g_e` (node features and message summaries),
        :math:`g_s`, and the per-particle :math:`g_v` as an edge part, a
        particle part and a shared output layer."""
        particle_dim = check_positive_int(self.particle_dim, 'particle_dim')
        dim = self.position_dim
        self.g_e = MLP([edge_features(dim) + message_summaries(dim),
                        hidden_dim, message_dim], **MLP_OPTIONS)
        self.g_s = MLP([message_dim, hidden_dim, 1], **MLP_OPTIONS)
        self.g_v_edge = torch.nn.Linear(message_dim, particle_dim)
        self.g_v_particle = torch.nn.Linear(particle_features(dim),
                                            particle_dim, bias=False)
        self.g_v_out = torch.nn.Linear(particle_dim, 1)
        torch.nn.init.constant_(self.g_v_out.bias, INITIAL_LOG_OFFSET)

    def reset_parameters(self):
        super().reset_parameters()
        torch.nn.init.constant_(self.g_v_out.bias, INITIAL_LOG_OFFSET)

    def corrected_messages(self, embedding: Tensor, log_phi: Tensor,
                           edge_index: Tensor, anchor: Tensor,
                           particles: Tensor, log_weights: Tensor,
                           edge_attr: Tensor) -> Tuple[Tensor, Tensor]:
        r"""The corrected log-messages :math:`(|\mathcal{E}|, K)` and the
        GNN messages :math:`(|\mathcal{E}|, \mathrm{message\_dim})` (see the
        class docstring)."""
        num_particles = log_phi.size(1)
        # scaled to mean one per edge: a per-edge constant, BP is unchanged
        log_phi = log_normalize(log_phi) + math.log(num_particles)
        src, dst = edge_index[0], edge_index[1]
        dim = self.position_dim
        positions = particles[..., :dim]
        mean, cov = weighted_moments(positions, log_weights)
        whitened = _whiten(positions, mean, cov)  # [N, K, D]
        u = whitened.index_select(0, dst)  # [E, K, D]

        # the message-weighted prediction of the receiver, summarized
        pi = floored_exp(log_normalize(log_weights.index_select(0, dst) +
                                       log_phi))
        first = torch.einsum('ek,ekd->ed', pi, u)
        upper = torch.triu_indices(dim, dim, device=u.device)
        second = torch.einsum('ek,ekd,ekf->edf', pi, u, u)[
            :, upper[0], upper[1]]
        power = pi.square().sum(-1)
        ess = pi.sum(-1).square() / (power * num_particles).clamp_min(
            torch.finfo(power.dtype).tiny)
        summaries = torch.cat([first, second, ess.unsqueeze(-1)], -1)
        message = self.g_e(torch.cat([
            self.embedding_features(embedding.index_select(0, dst),
                                    embedding.index_select(0, src)),
            summaries], -1))

        # per-particle features: finite where the message is -inf
        top = log_phi.amax(-1, keepdim=True)
        top = top.masked_fill(torch.isneginf(top), 0.0)
        below = (log_phi - top).clamp_min(LOG_MESSAGE_FLOOR) / 10.0
        spread = (cov.diagonal(dim1=-2, dim2=-1).sum(-1) / dim + 1.0).sqrt()
        sender_mean = mean.index_select(0, src).unsqueeze(1)
        distance = (positions.index_select(0, dst) - sender_mean).norm(
            dim=-1)
        residual = ((edge_attr[:, :1] - distance) /
                    spread.index_select(0, src).unsqueeze(-1))
        features = torch.cat([u, below.unsqueeze(-1),
                              residual.unsqueeze(-1)], -1)
        log_offset = _ParticleMLP.apply(self.g_v_edge(message), features,
                                        self.g_v_particle.weight,
                                        self.g_v_out.weight,
                                        self.g_v_out.bias)
        return self.combine(message, log_phi, log_offset, edge_index,
                            anchor), message

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(message_dim='
                f'{self.g_s.channel_list[0]}, particle_dim='
                f'{self.particle_dim}, correct_anchor_edges='
                f'{self.correct_anchor_edges})')


# elements of the [edges, K, particle_dim] hidden layer per chunk: a few MB,
# so each chunk stays in cache between the per-particle steps
HIDDEN_CHUNK = 1 << 20
LEAKY_SLOPE = 0.01  # torch.nn.functional.leaky_relu's default, as MLP_OPTIONS


class _ParticleMLP(torch.autograd.Function):
    r"""g_v on every particle: :math:`\mathbf{w}_o^\top
    \operatorname{LeakyReLU}(\mathbf{a}_e + \mathbf{W}_p
    \mathbf{f}_e^{(k)}) + b_o` :math:`(E, K)` from the edge part
    :math:`\mathbf{a}` :math:`(E, P)` and the particle features
    :math:`\mathbf{f}` :math:`(E, K, F)`. Run over chunks of edges and
    recomputed in the backward pass (closed form), the
    :math:`(E, K, P)` hidden layer is never stored: written whole it is
    hundreds of MB at K = 5,000, and the passes over it dominated a
    training step."""
    @staticmethod
    def forward(ctx, edge_part: Tensor, features: Tensor, weight_p: Tensor,
                weight_o: Tensor, bias_o: Tensor) -> Tensor:
        ctx.save_for_backward(edge_part, features, weight_p, weight_o)
        out = features.new_empty(features.shape[:2])
        for rows in _chunks(features, weight_p):
            hidden = torch.nn.functional.leaky_relu_(_preactivation(
                edge_part[rows], features[rows], weight_p), LEAKY_SLOPE)
            out[rows] = hidden @ weight_o[0] + bias_o
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        edge_part, features, weight_p, weight_o = ctx.saved_tensors
        grad_edge = torch.empty_like(edge_part)
        grad_features = (torch.empty_like(features)
                         if ctx.needs_input_grad[1] else None)
        grad_p = torch.zeros_like(weight_p)
        grad_o = torch.zeros_like(weight_o)
        for rows in _chunks(features, weight_p):
            pre = _preactivation(edge_part[rows], features[rows], weight_p)
            outer = grad[rows].unsqueeze(-1)  # [c, K, 1]
            grad_o += (torch.nn.functional.leaky_relu(pre, LEAKY_SLOPE) *
                       outer).sum((0, 1))
            # d hidden / d pre: 1 above zero, the slope below
            grad_pre = torch.where(pre > 0, outer, outer * LEAKY_SLOPE) * \
                weight_o[0]
            grad_edge[rows] = grad_pre.sum(1)
            grad_p += grad_pre.flatten(0, 1).t() @ features[rows].flatten(
                0, 1)
            if grad_features is not None:
                grad_features[rows] = grad_pre @ weight_p
        return (grad_edge, grad_features, grad_p, grad_o,
                grad.sum().view(1))


def _chunks(features: Tensor, weight_p: Tensor):
    # slices of edges whose hidden layer holds about HIDDEN_CHUNK elements
    num_edges, num_particles = features.shape[:2]
    step = max(HIDDEN_CHUNK // max(num_particles * weight_p.size(0), 1), 1)
    return [slice(start, start + step)
            for start in range(0, num_edges, step)]


def _preactivation(edge_part: Tensor, features: Tensor,
                   weight_p: Tensor) -> Tensor:
    # a_e + W_p f of a chunk of edges [c, K, P]
    return torch.baddbmm(edge_part.unsqueeze(1), features,
                         weight_p.t().expand(len(edge_part), -1, -1))


def _whiten(positions: Tensor, mean: Tensor, cov: Tensor) -> Tensor:
    # L^-1 (p - mean) with L L^T = cov + a jitter relative to its trace (and
    # an absolute floor for anchors, whose particles all sit at the mean)
    dim = cov.size(-1)
    scale = cov.diagonal(dim1=-2, dim2=-1).sum(-1) / dim
    jitter = (scale * 1e-6 + 1e-12).view(-1, 1, 1)
    eye = torch.eye(dim, dtype=cov.dtype, device=cov.device)
    root = torch.linalg.cholesky(cov + jitter * eye)
    centered = (positions - mean.unsqueeze(1)).transpose(1, 2)  # [N, D, K]
    return torch.linalg.solve_triangular(root, centered,
                                         upper=False).transpose(1, 2)
