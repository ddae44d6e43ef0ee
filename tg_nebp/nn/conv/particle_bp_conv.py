from typing import Callable, List, Optional, Tuple

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable
from torch_geometric import EdgeIndex
from torch_geometric.nn.conv import MessagePassing
from torch_geometric.utils import segment

from tg_nebp.data.validation import (check_anchor, check_graph,
                                     check_particles, check_positive_int,
                                     check_ranges)
from tg_nebp.models import GaussianRange
from tg_nebp.ops import fused_bp_available, fused_bp_segment_sum
from tg_nebp.utils import (compute_dtype, long_edge_index, plain_tensor,
                            sort_by_receiver)

__all__ = ['ParticleBPConv']

# Elements of one [chunk, K] temporary: bounds the peak memory of the per-edge
# work independently of E (the GPU amortizes kernel launches over more work).
CPU_CHUNK_ELEMENTS = 1 << 18
CUDA_CHUNK_ELEMENTS = 1 << 25


class ParticleBPConv(MessagePassing):
    r"""One particle belief propagation iteration for cooperative
    localization, from the `"Neural Enhanced Belief Propagation for
    Cooperative Localization" <https://arxiv.org/abs/2105.12903>`_ paper
    (equations (particleUpdate) and (bp_particle_weight_update)), in the log
    domain

    .. math::
        \log \phi_{j \to i}^{(k)} &= \log p\big(z_{j \to i} \,\big|\,
        \mathbf{x}_j^{(k)}, \mathbf{x}_i^{(k)}\big) +
        \log \tilde{w}_j^{(k)}

        \log \tilde{w}_i^{(k)} &\leftarrow \log w_i^{(k)} +
        \sum_{j \in \mathcal{N}(i)} \log \phi_{j \to i}^{(k)}

    where particle :math:`k` of the sender is paired with particle :math:`k`
    of the receiver (the message multiplication scheme of Meyer et al.), so
    the cost is :math:`O(|\mathcal{E}| K)`. The sum over incoming edges is a
    scatter (or, for an :class:`~torch_geometric.EdgeIndex` sorted by
    receiver, a deterministic segment) sum. Anchors send their known position
    (all :math:`K` particles at it) and never receive: their log-weights are
    returned unchanged. The layer computes in the promoted dtype of its
    inputs, at least float32 (half precision cannot hold log-weights), and
    takes int32 or int64 edge indices.

    Args:
        measurement (GaussianRange, optional): The measurement model that
            gives :math:`\log p(z_{j \to i} | \mathbf{x}_j, \mathbf{x}_i)`.
            (default: :obj:`GaussianRange()`)
        chunk_size (int, optional): Edges processed at once; bounds the
            temporary memory to about :obj:`chunk_size * K` floats whatever
            :math:`|\mathcal{E}|`. If :obj:`None`, :math:`2^{18} / K` on the
            CPU (cache-sized blocks) and :math:`2^{25} / K` on CUDA.
            (default: :obj:`None`)
        compile (bool, optional): Compute the messages of each chunk with a
            :func:`torch.compile`-fused kernel (the first calls compile);
            equal to the eager path within float tolerance. On CUDA without
            returned messages the fused Triton kernel is used either way.
            The whole layer also compiles without graph breaks
            (:obj:`torch.compile(conv)` with a plain :obj:`edge_index` and
            :obj:`validate=False`). (default: :obj:`False`)

    Shapes:
        - **input:**
          particles :math:`(|\mathcal{V}|, K, D)`,
          log-weights :math:`(|\mathcal{V}|, K)`,
          edge indices :math:`(2, |\mathcal{E}|)`,
          measured ranges :math:`(|\mathcal{E}|, 1)`,
          sender log-weights :math:`(|\mathcal{V}|, K)` *(optional)*,
          anchor mask :math:`(|\mathcal{V}|)` *(optional)*
        - **output:** updated log-weights :math:`(|\mathcal{V}|, K)` and
          edge log-messages :math:`(|\mathcal{E}|, K)`
    """
    SUPPORTS_FUSED_EDGE_INDEX = True

    def __init__(self, measurement: Optional[GaussianRange] = None,
                 chunk_size: Optional[int] = None, compile: bool = False):
        super().__init__(aggr='add', node_dim=0)
        if chunk_size is not None:
            chunk_size = check_positive_int(chunk_size, 'chunk_size')
        self.measurement = measurement or GaussianRange()
        self.chunk_size = chunk_size
        # dynamic: chunk lengths and edge counts change from call to call
        self._messages = torch.compile(
            self._log_messages,
            dynamic=True) if compile else self._log_messages

    def forward(
        self,
        particles: Tensor,
        log_weights: Tensor,
        edge_index: Tensor,
        edge_attr: Tensor,
        sender_log_weights: Optional[Tensor] = None,
        anchor: Optional[Tensor] = None,
        validate: bool = True,
        return_messages: bool = True,
    ) -> Tuple[Tensor, Optional[Tensor]]:
        r"""Runs the forward pass.

        Args:
            particles (torch.Tensor): Particles :math:`\mathbf{x}_i^{(k)}`;
                the first two state entries are the position.
            log_weights (torch.Tensor): Log-weights :math:`\log w_i^{(k)}`
                of the prediction message.
            edge_index (torch.Tensor): Edges :math:`j \to i`.
            edge_attr (torch.Tensor): Measured ranges :math:`z_{j \to i}`.
            sender_log_weights (torch.Tensor, optional): Log-weights
                :math:`\log \tilde{w}_j^{(t-1, k)}` of the beliefs that the
                senders transmit; :obj:`log_weights` at the first iteration.
                (default: :obj:`None`)
            anchor (torch.Tensor, optional): Bool mask of anchors, whose
                log-weights are kept. (default: :obj:`None`)
            validate (bool, optional): Check the inputs (trackers check once
                per sequence and pass :obj:`False`). (default: :obj:`True`)
            return_messages (bool, optional): Also return the edge
                log-messages :math:`(|\mathcal{E}|, K)`. If :obj:`False`,
                they are never materialized: the edges are sorted by
                receiver (free for an :class:`~torch_geometric.EdgeIndex`
                sorted by column, as the trackers pass) and summed block by
                block of whole receivers, so the memory beyond inputs and
                output stays about :obj:`chunk_size * K` floats; on CUDA a
                fused Triton kernel computes and sums them in one pass.
                Either way the sum is deterministic. (default: :obj:`True`)
        """
        if sender_log_weights is None:
            sender_log_weights = log_weights
        if validate:
            check_particles(particles, log_weights)
            check_particles(particles, sender_log_weights,
                            weights_name='sender_log_weights')
            check_graph(edge_index, particles.size(0))
            check_ranges(edge_attr, edge_index.size(1))
            if anchor is not None:
                check_anchor(anchor, particles.size(0))
        # one dtype for every operand lets the no-grad path work in place;
        # contiguous coordinate planes make every gather a dense [E, K] copy
        dtype = compute_dtype(particles, sender_log_weights, edge_attr)
        size = (particles.size(0), particles.size(0))
        edge_index = long_edge_index(edge_index, particles.size(0))
        node_args = dict(pos_x=particles[..., 0].to(dtype).contiguous(),
                         pos_y=particles[..., 1].to(dtype).contiguous(),
                         sender_log_weights=sender_log_weights.to(dtype),
                         ranges=edge_attr.to(dtype))
        if return_messages or torch.compiler.is_compiling():
            # a compiled graph fuses the messages into the scatter itself
            log_messages = self.edge_updater(edge_index, size=size,
                                             **node_args)
        else:
            # receiver-sorted edges let message_and_aggregate sum chunk by
            # chunk: no [E, K] tensor is ever allocated
            log_messages = None
            edge_index, node_args['ranges'] = sort_by_receiver(
                edge_index, size[0], node_args['ranges'])
        out = self.propagate(edge_index, log_messages=log_messages,
                             size=size, **node_args)
        if anchor is not None:
            out = out.masked_fill(anchor.view(-1, 1), 0.0)
        return log_weights + out, log_messages if return_messages else None

    def edge_update(self, pos_x: Tensor, pos_y: Tensor,
                    sender_log_weights: Tensor, ranges: Tensor,
                    edge_index_i: Tensor, edge_index_j: Tensor) -> Tensor:
        # plain tensors (not PyG's Index) into the compiled region
        src, dst = plain_tensor(edge_index_j), plain_tensor(edge_index_i)
        num_edges = dst.numel()
        chunk = self._chunk_edges(pos_x)
        if chunk >= num_edges or torch.compiler.is_compiling():
            # a compiled graph fuses the chain without temporaries
            return self._messages(pos_x, pos_y, sender_log_weights, ranges,
                                  src, dst)
        out = pos_x.new_empty((num_edges, pos_x.size(1)))
        for start in range(0, num_edges, chunk):
            part = slice(start, start + chunk)
            out[part] = self._messages(pos_x, pos_y, sender_log_weights,
                                       ranges[part], src[part], dst[part])
        return out

    def _log_messages(self, pos_x: Tensor, pos_y: Tensor,
                      sender_log_weights: Tensor, ranges: Tensor,
                      src: Tensor, dst: Tensor) -> Tensor:
        if torch.is_grad_enabled() and (pos_x.requires_grad
                                        or pos_y.requires_grad
                                        or ranges.requires_grad):
            diff = torch.stack([
                pos_x.index_select(0, src) - pos_x.index_select(0, dst),
                pos_y.index_select(0, src) - pos_y.index_select(0, dst),
            ], dim=-1)
            distances = torch.linalg.vector_norm(diff, dim=-1)  # grad 0 at 0
            log_lik = self.measurement.log_likelihood_of_distance(
                ranges, distances)
        else:  # in place on fresh temporaries: a third of the memory traffic
            dx = pos_x.index_select(0, src).sub_(pos_x.index_select(0, dst))
            dy = pos_y.index_select(0, src).sub_(pos_y.index_select(0, dst))
            distances = dx.mul_(dx).addcmul_(dy, dy).sqrt_()
            log_lik = self.measurement.log_likelihood_of_distance(
                ranges, distances, inplace=True)
        # in-place add stays differentiable in the sender log-weights
        return log_lik.add_(sender_log_weights.index_select(0, src))

    def message(self, log_messages: Tensor) -> Tensor:
        return log_messages

    def message_and_aggregate(self, edge_index: EdgeIndex, pos_x: Tensor,
                              pos_y: Tensor, sender_log_weights: Tensor,
                              ranges: Tensor,
                              log_messages: Optional[Tensor]) -> Tensor:
        # edges sorted by receiver: a deterministic segment sum (PyG calls
        # this for an EdgeIndex sorted by column)
        (ptr, src), _ = edge_index.get_csc()
        if log_messages is not None:
            return segment(log_messages, ptr, reduce='sum')
        src = plain_tensor(src)
        if (fused_bp_available(pos_x) and pos_x.dtype == torch.float32
                and type(self.measurement) is GaussianRange
                and not (torch.is_grad_enabled() and
                         (pos_x.requires_grad or pos_y.requires_grad
                          or sender_log_weights.requires_grad))):
            return fused_bp_segment_sum(pos_x, pos_y, sender_log_weights,
                                        ranges, src, ptr,
                                        self.measurement.sigma)
        # blocks of whole receivers holding about one chunk of edges each:
        # the peak temporary memory is one chunk, whatever E
        dst = plain_tensor(edge_index[1])
        bounds = self._receiver_blocks(ptr, self._chunk_edges(pos_x))
        inputs = (pos_x, pos_y, sender_log_weights, ranges)
        if len(bounds) > 2 and torch.is_grad_enabled() and any(
                t.requires_grad for t in inputs):
            # the Gaussian likelihood has a closed-form gradient; other
            # measurement models are differentiated by autograd per block
            sigma = self.measurement.sigma if type(
                self.measurement) is GaussianRange else None
            return _BlockwiseMessageSum.apply(self._messages, sigma, bounds,
                                              src, dst, ptr, *inputs)
        return _sum_blocks(self._messages, bounds, src, dst, ptr, *inputs)

    def _chunk_edges(self, pos_x: Tensor) -> int:
        if self.chunk_size is not None:
            return self.chunk_size
        elements = CUDA_CHUNK_ELEMENTS if pos_x.is_cuda else CPU_CHUNK_ELEMENTS
        return max(1, elements // max(pos_x.size(1), 1))

    @staticmethod
    def _receiver_blocks(ptr: Tensor, chunk: int) -> List[int]:
        # node boundaries at (about) every chunk-th edge; a receiver with more
        # than a chunk of edges forms a block of its own
        num_nodes, num_edges = ptr.numel() - 1, int(ptr[-1])
        if num_edges <= chunk or num_nodes <= 1:
            return [0, num_nodes]
        marks = torch.arange(chunk, num_edges, chunk, device=ptr.device)
        cuts = torch.searchsorted(ptr, marks, right=True) - 1
        inner = torch.unique(cuts[(cuts > 0) & (cuts < num_nodes)]).tolist()
        return [0] + inner + [num_nodes]

    def __repr__(self) -> str:
        return f'{self.__class__.__name__}({self.measurement})'


def _sum_blocks(messages: Callable, bounds: List[int], src: Tensor,
                dst: Tensor, ptr: Tensor, pos_x: Tensor, pos_y: Tensor,
                sender_log_weights: Tensor, ranges: Tensor) -> Tensor:
    # the segment sums of the receiver blocks [bounds[b], bounds[b + 1])
    sums = []
    for first, last in zip(bounds[:-1], bounds[1:]):
        begin, end = int(ptr[first]), int(ptr[last])
        block = messages(pos_x, pos_y, sender_log_weights,
                         ranges[begin:end], src[begin:end], dst[begin:end])
        sums.append(segment(block, ptr[first:last + 1] - begin, reduce='sum'))
    return sums[0] if len(sums) == 1 else torch.cat(sums)


class _BlockwiseMessageSum(torch.autograd.Function):
    r""":func:`_sum_blocks` with a backward pass that recomputes each block
    on its gathered rows and adds their gradients into one buffer per input:
    neither pass holds more than one block of :math:`(\mathrm{chunk}, K)`
    temporaries. (Autograd through the blocks would save them all, and
    recomputing them under plain autograd would allocate a node-sized
    gradient per block.) With :obj:`sigma` (a Gaussian range likelihood) the
    block gradients are closed-form; otherwise autograd differentiates the
    block."""
    @staticmethod
    def forward(ctx, messages, sigma, bounds, src, dst, ptr, *inputs):
        ctx.messages, ctx.sigma, ctx.bounds = messages, sigma, bounds
        ctx.save_for_backward(src, dst, ptr, *inputs)
        return _sum_blocks(messages, bounds, src, dst, ptr, *inputs)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        src, dst, ptr, *inputs = ctx.saved_tensors
        needs = ctx.needs_input_grad[6:]
        grads = [torch.zeros_like(t) if need else None
                 for t, need in zip(inputs, needs)]
        block_grads = (_gaussian_block_grads if ctx.sigma is not None else
                       _autograd_block_grads)
        bounds = ctx.bounds
        for first, last in zip(bounds[:-1], bounds[1:]):
            begin, end = int(ptr[first]), int(ptr[last])
            block_src, block_dst = src[begin:end], dst[begin:end]
            found = block_grads(ctx, inputs, needs, begin, end, block_src,
                                block_dst, grad_out.index_select(0, block_dst))
            for grad, (nodes, value) in zip(grads, found):
                if grad is None:
                    continue
                if nodes is None:  # per-edge: the ranges
                    grad[begin:end] = value
                else:
                    for index, part in zip(nodes, value):
                        grad.index_add_(0, index, part)
        return (None, None, None, None, None, None, *grads)


# The block gradient functions return, per input (particle x, particle y,
# sender log-weights, ranges), (row indices, parts) to add at those rows, or
# (None, block) for the per-edge ranges.


def _gaussian_block_grads(ctx, inputs, needs, begin, end, src, dst,
                          grad_messages):
    # messages m = -(z - d)^2 / (2 sigma^2) - log_norm + w_src with
    # d = |p_src - p_dst|: dm/dd = (z - d) / sigma^2, dd/dp_src = diff / d
    pos_x, pos_y, sender, ranges = inputs
    dx = pos_x.index_select(0, src) - pos_x.index_select(0, dst)
    dy = pos_y.index_select(0, src) - pos_y.index_select(0, dst)
    distances = torch.sqrt(dx * dx + dy * dy)
    per_distance = grad_messages * (ranges[begin:end] -
                                    distances) / ctx.sigma**2
    # zero (not NaN) where paired particles coincide, as autograd's norm
    per_coordinate = torch.where(distances > 0, per_distance / distances,
                                 torch.zeros_like(distances))
    grad_x, grad_y = per_coordinate * dx, per_coordinate * dy
    return ((src, dst), (grad_x, -grad_x)), ((src, dst), (grad_y, -grad_y)), \
        ((src, ), (grad_messages, )), \
        (None, -per_distance.sum(-1, keepdim=True) if needs[3] else None)


def _autograd_block_grads(ctx, inputs, needs, begin, end, src, dst,
                          grad_messages):
    # the block's senders and receivers as 2 * count local nodes
    count = end - begin
    nodes = torch.cat([src, dst])
    local = torch.arange(2 * count, device=nodes.device)
    with torch.enable_grad():
        leaves = [t.index_select(0, nodes).requires_grad_(need)
                  for t, need in zip(inputs[:3], needs)]
        block_ranges = inputs[3][begin:end].detach().requires_grad_(needs[3])
        block = ctx.messages(*leaves, block_ranges, local[:count],
                             local[count:])
        wanted = [t for t in (*leaves, block_ranges) if t.requires_grad]
        found = iter(torch.autograd.grad(block, wanted, grad_messages))
    grads = [next(found) if need else None for need in needs]
    return (((nodes, ), (grads[0], )), ((nodes, ), (grads[1], )),
            ((nodes, ), (grads[2], )), (None, grads[3]))
