from typing import Callable, List, Optional, Tuple, Union

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable
from torch_geometric import EdgeIndex
from torch_geometric.nn.conv import MessagePassing
from torch_geometric.utils import segment

from tg_nebp.data.validation import (check_edge_log_weights,
                                     check_layer_inputs, check_positive_int)
from tg_nebp.models import GaussianRange, MeasurementModel, RangeModel
from tg_nebp.ops import fused_bp_available, fused_bp_segment_sum
from tg_nebp.utils import (compute_dtype, logsumexp, long_edge_index,
                           plain_tensor, sort_by_receiver)

__all__ = ['ParticleBPConv']

# Elements of one [chunk, K] temporary: bounds the peak memory of the per-edge
# work independently of E (the GPU amortizes kernel launches over more work).
CPU_CHUNK_ELEMENTS = 1 << 18
CUDA_CHUNK_ELEMENTS = 1 << 25
# Samples of an M-sample message reduced by one logsumexp (a stack of them):
# enough to amortize the reduction's passes over the stack. A chain of
# pairwise logaddexp was 3x slower on the CPU (a scalar log1p per element).
SAMPLE_GROUP = 16


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
    the cost is :math:`O(|\mathcal{E}| K)`: a one-sample estimate of the
    marginalized message :math:`\phi_{j \to i}(\mathbf{x}_i^{(k)}) =
    \sum_{l} \tilde{w}_j^{(l)} p(z_{j \to i} | \mathbf{x}_j^{(l)},
    \mathbf{x}_i^{(k)})`. With :obj:`num_samples` :math:`M > 1` each
    receiver particle averages over :math:`M` sender particles
    :math:`l_m = (k + o_j + \lfloor (m - 1) K / M \rfloor) \bmod K`,

    .. math::
        \log \hat{\phi}_{j \to i}^{(k)} = \log \frac{K}{M}
        \sum_{m=1}^{M} \tilde{w}_j^{(l_m)} \, p\big(z_{j \to i} \,\big|\,
        \mathbf{x}_j^{(l_m)}, \mathbf{x}_i^{(k)}\big),

    with one offset :math:`o_j` per sender and step drawn uniformly from
    :math:`\{0, \dots, K - 1\}` (:meth:`draw_offsets`): systematic sampling
    over the sender's particle order. The :math:`M` spacings
    :math:`\lfloor (m - 1) K / M \rfloor` are distinct, so for every
    :math:`k` each sender particle :math:`l` is among the :math:`l_m` for
    exactly :math:`M` of the :math:`K` offsets, with probability
    :math:`M / K`, and :math:`\mathbb{E} \hat{\phi} = \phi`: unbiased, at
    cost :math:`O(|\mathcal{E}| K M)`. For particles in random order (as
    multinomial resampling leaves them) the :math:`l_m` hold a uniformly
    random :math:`M`-subset of the particles; for sorted ones (systematic
    resampling) they are spread over the order, as in stratified sampling.
    Every sample is a strided window of the sender's row rolled once by
    :math:`o_j`: no gather per sample. :math:`M = K`
    (:obj:`"all"`) takes every particle and is the exact message; the
    constant :math:`\log (K / M)` is dropped (normalization removes it).
    :math:`M = 1` is the paper's pairing (:math:`o_j = 0`). The sum over
    incoming edges is a
    scatter (or, for an :class:`~torch_geometric.EdgeIndex` sorted by
    receiver, a deterministic segment) sum. Anchors send their known position
    (all :math:`K` particles at it) and never receive: their log-weights are
    returned unchanged. The layer computes in the promoted dtype of its
    inputs, at least float32 (half precision cannot hold log-weights), and
    takes int32 or int64 edge indices.

    Args:
        measurement (MeasurementModel, optional): The measurement model
            that gives :math:`\log p(\mathbf{z}_{j \to i} | \mathbf{x}_j,
            \mathbf{x}_i)`. A :class:`~tg_nebp.models.RangeModel` gets the
            coordinate-plane path and the fast pieces it provides (in-place,
            closed-form gradient, fused kernel); any other model gets its
            :meth:`~tg_nebp.models.MeasurementModel.log_likelihood` on the
            gathered state entries and gradients by autograd.
            (default: :obj:`GaussianRange()`)
        chunk_size (int, optional): Edges processed at once; bounds the
            temporary memory to about :obj:`chunk_size * K` floats whatever
            :math:`|\mathcal{E}|` (times :math:`\min(M, 16)` for the
            stacked samples of :math:`M`-sample messages). If :obj:`None`,
            :math:`2^{18} / K` on the CPU (cache-sized blocks) and
            :math:`2^{25} / K` on CUDA, divided by :math:`\min(M, 16) / 4`
            for :math:`M > 4`. (default: :obj:`None`)
        num_samples (int or str, optional): Sender particles :math:`M` per
            receiver particle; :obj:`1` is the paper's pairing,
            :obj:`"all"` the exact message. (default: :obj:`1`)
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
          link features :math:`(|\mathcal{E}|, F)` (the range first),
          sender log-weights :math:`(|\mathcal{V}|, K)` *(optional)*,
          anchor mask :math:`(|\mathcal{V}|)` *(optional)*
        - **output:** updated log-weights :math:`(|\mathcal{V}|, K)` and
          edge log-messages :math:`(|\mathcal{E}|, K)`
    """
    SUPPORTS_FUSED_EDGE_INDEX = True

    def __init__(self, measurement: Optional[MeasurementModel] = None,
                 chunk_size: Optional[int] = None, compile: bool = False,
                 num_samples: Union[int, str] = 1):
        super().__init__(aggr='add', node_dim=0)
        if chunk_size is not None:
            chunk_size = check_positive_int(chunk_size, 'chunk_size')
        if num_samples != 'all':
            num_samples = check_positive_int(num_samples, 'num_samples')
        self.num_samples = num_samples
        self.measurement = measurement or GaussianRange()
        if not isinstance(self.measurement, MeasurementModel):
            raise TypeError(f"'measurement' must be a MeasurementModel, got "
                            f"{self.measurement!r}")
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
        sample_offsets: Optional[Tensor] = None,
        generator: Optional[torch.Generator] = None,
        edge_sender_log_weights: Optional[Tensor] = None,
    ) -> Tuple[Tensor, Optional[Tensor]]:
        r"""Runs the forward pass.

        Args:
            particles (torch.Tensor): Particles :math:`\mathbf{x}_i^{(k)}`;
                the first two state entries are the position.
            log_weights (torch.Tensor): Log-weights :math:`\log w_i^{(k)}`
                of the prediction message.
            edge_index (torch.Tensor): Edges :math:`j \to i`.
            edge_attr (torch.Tensor): Link features
                :math:`\mathbf{z}_{j \to i}`, the measured range first.
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
            sample_offsets (torch.Tensor, optional): The offsets
                :math:`o_j` :math:`(|\mathcal{V}|)` of the
                :math:`M`-sample messages (the trackers draw them per graph);
                drawn with :obj:`generator` by :meth:`draw_offsets` if
                :obj:`None`. (default: :obj:`None`)
            generator (torch.Generator, optional): Source of the offsets.
                (default: :obj:`None`)
            edge_sender_log_weights (torch.Tensor, optional): The senders'
                log-weights per edge :math:`(|\mathcal{E}|, K)`, in place of
                :obj:`sender_log_weights`: extrinsic beliefs, each sender's
                belief without the message it had from the edge's factor
                (see :class:`~tg_nebp.filters.ParticleBP` with
                :obj:`ends="both"`). The messages are then materialized
                (memory :math:`O(|\mathcal{E}| K)`). (default: :obj:`None`)
        """
        if sender_log_weights is None:
            sender_log_weights = log_weights
        model = self.measurement
        if validate:
            check_layer_inputs(particles, log_weights, edge_index, edge_attr,
                               model.features, anchor, sender_log_weights,
                               negative_ranges=model.negative_ranges)
        # one dtype for every operand lets the no-grad path work in place;
        # contiguous coordinate planes (the state entries that the model
        # reads) make every gather a dense [E, K] copy
        dtype = compute_dtype(particles, sender_log_weights, edge_attr)
        size = (particles.size(0), particles.size(0))
        edge_index = long_edge_index(edge_index, particles.size(0))
        planes = tuple(particles[..., d].to(dtype).contiguous()
                       for d in model.scope(particles.size(-1)))
        if sample_offsets is None:
            sample_offsets = self.draw_offsets(particles.size(0),
                                               particles.size(1),
                                               generator=generator,
                                               device=particles.device)
        elif validate:
            self._check_offsets(sample_offsets, particles.size(0),
                                particles.size(1))
        node_args = dict(planes=planes,
                         sender_log_weights=sender_log_weights.to(dtype),
                         link_features=edge_attr.to(dtype),
                         offsets=sample_offsets)
        path = self._path(return_messages or
                          edge_sender_log_weights is not None, planes[0], (
            *planes, node_args['sender_log_weights'],
            node_args['link_features']), sample_offsets is not None)
        if path == 'messages':
            if validate and edge_sender_log_weights is not None:
                check_edge_log_weights(edge_sender_log_weights,
                                       edge_index.size(1), particles.size(1))
            log_messages = self.edge_updater(
                edge_index, size=size, edge_weights=(
                    None if edge_sender_log_weights is None else
                    edge_sender_log_weights.to(dtype)), **node_args)
        else:
            # receiver-sorted edges let message_and_aggregate sum block by
            # block: no [E, K] tensor is ever allocated
            log_messages = None
            edge_index, node_args['link_features'] = sort_by_receiver(
                edge_index, size[0], node_args['link_features'])
        out = self.propagate(edge_index, log_messages=log_messages,
                             path=path, size=size, **node_args)
        if anchor is not None:
            out = out.masked_fill(anchor.view(-1, 1), 0.0)
        return log_weights + out, log_messages if return_messages else None

    def samples_for(self, num_particles: int) -> int:
        r"""The number of sender samples :math:`M` for :math:`K` =
        :obj:`num_particles`."""
        if self.num_samples == 'all':
            return num_particles
        if self.num_samples > num_particles:
            raise ValueError(f"'num_samples' = {self.num_samples} exceeds "
                             f"the K = {num_particles} particles per node")
        return self.num_samples

    def draw_offsets(self, num_nodes: int, num_particles: int,
                     generator: Optional[torch.Generator] = None,
                     device=None) -> Optional[Tensor]:
        r"""The offsets :math:`o_j` :math:`(N)` of the :math:`M`-sample
        messages, uniform on :math:`\{0, \dots, K - 1\}` (zeros without a
        random draw for :math:`M = K`, where every offset gives the same
        samples); :obj:`None` for the paper's pairing (:math:`M = 1`)."""
        samples = self.samples_for(num_particles)
        if samples == 1:
            return None
        if samples == num_particles:
            return torch.zeros(num_nodes, dtype=torch.long, device=device)
        return torch.randint(num_particles, (num_nodes, ),
                             generator=generator, device=device)

    def _check_offsets(self, offsets: Tensor, num_nodes: int,
                       num_particles: int) -> None:
        if self.samples_for(num_particles) == 1:
            raise ValueError("'sample_offsets' given, but num_samples = 1 "
                             "pairs the particles")
        if not isinstance(offsets, Tensor):
            raise TypeError(f"'sample_offsets' must be an integer tensor of "
                            f"shape [{num_nodes}], got a "
                            f"{type(offsets).__name__}")
        if offsets.shape != (num_nodes, ) or offsets.is_floating_point():
            raise ValueError(f"'sample_offsets' must be an integer tensor of "
                             f"shape [{num_nodes}], got {offsets.dtype} "
                             f"{list(offsets.shape)}")
        bad = (offsets < 0) | (offsets >= num_particles)
        if bool(bad.any()):
            j = int(bad.nonzero()[0, 0])
            raise ValueError(f"'sample_offsets[{j}]' = {int(offsets[j])} "
                             f"must lie in [0, {num_particles})")

    def _path(self, return_messages: bool, like: Tensor,
              inputs: Tuple[Tensor, ...], sampled: bool = False) -> str:
        r"""The one place that chooses how the messages are computed:
        :obj:`"messages"` (materialized :math:`(E, K)`, returned or fused by
        a compiled graph), :obj:`"fused"` (the model's formula in the Triton
        kernel: CUDA, float32, no gradient), :obj:`"closed-form"` (blocks
        with the model's closed-form gradient), :obj:`"autograd"` (blocks
        differentiated by autograd per block) or :obj:`"blocks"` (blocks, no
        gradient)."""
        model = self.measurement
        if return_messages or torch.compiler.is_compiling():
            return 'messages'
        grad = torch.is_grad_enabled() and any(t.requires_grad
                                               for t in inputs)
        if grad:
            return ('closed-form' if isinstance(model, RangeModel)
                    and model.provides('distance_gradient') and not sampled
                    else 'autograd')
        if (not sampled and fused_bp_available(like)
                and like.dtype == torch.float32
                and isinstance(model, RangeModel) and len(inputs) == 4
                and model.provides('fused_log_pdf')):
            # the kernel computes 2-D distances: two planes, the sender
            # weights and the link features
            return 'fused'
        return 'blocks'

    def edge_update(self, planes: Tuple[Tensor, ...],
                    sender_log_weights: Tensor, link_features: Tensor,
                    offsets: Optional[Tensor], edge_index_i: Tensor,
                    edge_index_j: Tensor,
                    edge_weights: Optional[Tensor] = None) -> Tensor:
        # plain tensors (not PyG's Index) into the compiled region
        src, dst = plain_tensor(edge_index_j), plain_tensor(edge_index_i)
        num_edges = dst.numel()
        chunk = self._chunk_edges(planes[0], offsets)
        if chunk >= num_edges or torch.compiler.is_compiling():
            # a compiled graph fuses the chain without temporaries
            return self._messages(planes, sender_log_weights, link_features,
                                  src, dst, offsets, edge_weights)
        out = planes[0].new_empty((num_edges, planes[0].size(1)))
        for start in range(0, num_edges, chunk):
            part = slice(start, start + chunk)
            out[part] = self._messages(
                planes, sender_log_weights, link_features[part], src[part],
                dst[part], offsets,
                None if edge_weights is None else edge_weights[part])
        return out

    def _log_messages(self, planes: Tuple[Tensor, ...],
                      sender_log_weights: Tensor, link_features: Tensor,
                      src: Tensor, dst: Tensor,
                      offsets: Optional[Tensor] = None,
                      edge_weights: Optional[Tensor] = None) -> Tensor:
        # the senders' log-weights: per node, or per edge (extrinsic)
        weights = (sender_log_weights.index_select(0, src)
                   if edge_weights is None else edge_weights)
        if offsets is None:
            return self._paired_log_messages(planes, link_features, src,
                                             dst, planes, weights,
                                             weights_gathered=True)
        # M-sample messages: sample m reads the sender's particles from
        # offset o_j + floor(m K / M) on, a window of the sender's row
        # rolled by o_j and written twice; groups of samples are reduced by
        # one logsumexp each, the groups by a running one
        num_particles = planes[0].size(1)
        index = _rolled_twice_index(offsets.index_select(0, src),
                                    num_particles)
        senders = [p.index_select(0, src).gather(1, index)
                   for p in planes] + [weights.gather(1, index)]
        receivers = tuple(p.index_select(0, dst) for p in planes)
        num_samples = self.samples_for(num_particles)

        def sample(m: int) -> Tensor:
            start = m * num_particles // num_samples
            window = [s[:, start:start + num_particles] for s in senders]
            return self._paired_log_messages(receivers, link_features, None,
                                             None, window[:-1], window[-1])

        total = None
        for first in range(0, num_samples, SAMPLE_GROUP):
            group = range(first, min(first + SAMPLE_GROUP, num_samples))
            part = logsumexp(torch.stack([sample(m) for m in group]))
            total = part if total is None else logsumexp(
                torch.stack([total, part]))
        return total

    def _paired_log_messages(self, planes: Tuple[Tensor, ...],
                             link_features: Tensor, src: Tensor, dst: Tensor,
                             sender_planes: Tuple[Tensor, ...],
                             sender_weights: Tensor,
                             weights_gathered: bool = False) -> Tensor:
        # the paired messages log p(z | x_j^(k), x_i^(k)) + log w_j^(k):
        # receivers from 'planes' at dst, senders from 'sender_planes' and
        # 'sender_weights' at src; a None index means that the tensors are
        # edge rows already (fresh sender rows, which may be overwritten),
        # as the weights are when 'weights_gathered'
        def at(tensor, index):
            return tensor if index is None else tensor.index_select(0, index)

        model = self.measurement
        grad = torch.is_grad_enabled() and (
            link_features.requires_grad or any(
                p.requires_grad for p in (*planes, *sender_planes)))
        if not isinstance(model, RangeModel):
            sender = torch.stack([at(p, src) for p in sender_planes], -1)
            receiver = torch.stack([at(p, dst) for p in planes], -1)
            log_lik = model.log_likelihood(link_features, sender, receiver)
            expected = sender.shape[:-1]
        elif grad:
            # a range model's planes are the positions, in any dimension
            diff = torch.stack([
                at(s, src) - at(p, dst)
                for s, p in zip(sender_planes, planes)], dim=-1)
            distances = torch.linalg.vector_norm(diff, dim=-1)  # grad 0 at 0
            log_lik = model.log_likelihood_of_distance(link_features,
                                                       distances)
            expected = distances.shape
        else:  # in place on fresh temporaries: a third of the memory traffic
            distances = None
            for sender, pos in zip(sender_planes, planes):
                if src is None:  # views of shared sender rows: not in place
                    delta = sender - at(pos, dst)
                else:
                    delta = sender.index_select(0, src).sub_(at(pos, dst))
                distances = (delta.mul_(delta) if distances is None else
                             distances.addcmul_(delta, delta))
            distances = distances.sqrt_()
            expected = distances.shape
            log_lik = (model.log_likelihood_of_distance_(
                link_features, distances)
                       if model.provides('log_likelihood_of_distance_') else
                       model.log_likelihood_of_distance(link_features,
                                                        distances))
        if log_lik.shape != expected:  # a user's model, caught here
            raise ValueError(
                f"the measurement model {model!r} returned log-likelihoods "
                f"of shape {list(log_lik.shape)}; expected "
                f"{list(expected)}, one per link and particle")
        # in-place add stays differentiable in the sender log-weights
        return log_lik.add_(sender_weights if weights_gathered else
                            at(sender_weights, src))

    def message(self, log_messages: Tensor) -> Tensor:
        return log_messages

    def message_and_aggregate(self, edge_index: EdgeIndex,
                              planes: Tuple[Tensor, ...],
                              sender_log_weights: Tensor,
                              link_features: Tensor,
                              offsets: Optional[Tensor],
                              log_messages: Optional[Tensor],
                              path: str) -> Tensor:
        # edges sorted by receiver: a deterministic segment sum (PyG calls
        # this for an EdgeIndex sorted by column)
        (ptr, src), _ = edge_index.get_csc()
        if log_messages is not None:
            return segment(log_messages, ptr, reduce='sum')
        src = plain_tensor(src)
        model = self.measurement
        if path == 'fused':
            return fused_bp_segment_sum(planes[0], planes[1],
                                        sender_log_weights,
                                        link_features[:, 0], src, ptr,
                                        model.fused_log_pdf,
                                        model.fused_constants())
        # blocks of whole receivers holding about one chunk of edges each:
        # the peak temporary memory is one chunk, whatever E
        dst = plain_tensor(edge_index[1])
        bounds = self._receiver_blocks(ptr,
                                       self._chunk_edges(planes[0], offsets))
        # the offsets of M-sample messages ride last (no gradient)
        inputs = (*planes, sender_log_weights, link_features) + (
            () if offsets is None else (offsets, ))
        if path in ('closed-form', 'autograd') and len(bounds) > 2:
            gradients = (_range_block_grads if path == 'closed-form' else
                         _autograd_block_grads)
            return _BlockwiseMessageSum.apply(self._messages, model,
                                              gradients, len(planes), bounds,
                                              src, dst, ptr, *inputs)
        return _sum_blocks(self._messages, len(planes), bounds, src, dst,
                           ptr, *inputs)

    def _chunk_edges(self, like: Tensor,
                     offsets: Optional[Tensor] = None) -> int:
        if self.chunk_size is not None:
            return self.chunk_size
        elements = CUDA_CHUNK_ELEMENTS if like.is_cuda else CPU_CHUNK_ELEMENTS
        if offsets is not None:
            # the [group, chunk, K] stack of an M-sample message holds at
            # most four chunks' worth
            group = min(self.samples_for(like.size(1)), SAMPLE_GROUP)
            elements = elements * 4 // max(group, 4)
        return max(1, elements // max(like.size(1), 1))

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


def _rolled_twice_index(offsets: Tensor, num_particles: int) -> Tensor:
    # [E, 2K] columns that roll row e left by offsets[e] and write it twice,
    # so that every cyclic window is a strided view. A gather with it has a
    # scatter-add into [E, K] as its backward (indexing windows of an
    # unfolded view would materialize the [E, K, 2K] unfolded gradient)
    columns = torch.arange(2 * num_particles, device=offsets.device)
    return (offsets.view(-1, 1) + columns).remainder_(num_particles)


def _sum_blocks(messages: Callable, num_planes: int, bounds: List[int],
                src: Tensor, dst: Tensor, ptr: Tensor,
                *inputs: Tensor) -> Tensor:
    # the segment sums of the receiver blocks [bounds[b], bounds[b + 1]);
    # inputs: the coordinate planes, the sender log-weights, link features
    # and, for M-sample messages, the offsets
    planes, sender = inputs[:num_planes], inputs[num_planes]
    link_features = inputs[num_planes + 1]
    offsets = (inputs[num_planes + 2] if len(inputs) > num_planes + 2 else
               None)
    sums = []
    for first, last in zip(bounds[:-1], bounds[1:]):
        begin, end = int(ptr[first]), int(ptr[last])
        block = messages(planes, sender, link_features[begin:end],
                         src[begin:end], dst[begin:end], offsets)
        sums.append(segment(block, ptr[first:last + 1] - begin, reduce='sum'))
    return sums[0] if len(sums) == 1 else torch.cat(sums)


class _BlockwiseMessageSum(torch.autograd.Function):
    r""":func:`_sum_blocks` with a backward pass that recomputes each block
    on its gathered rows and adds their gradients into one buffer per input:
    neither pass holds more than one block of :math:`(\mathrm{chunk}, K)`
    temporaries. (Autograd through the blocks would save them all, and
    recomputing them under plain autograd would allocate a node-sized
    gradient per block.) :obj:`gradients` is :func:`_range_block_grads` (the
    model's closed-form gradient) or :func:`_autograd_block_grads`."""
    @staticmethod
    def forward(ctx, messages, model, gradients, num_planes, bounds, src,
                dst, ptr, *inputs):
        ctx.messages, ctx.model, ctx.gradients = messages, model, gradients
        ctx.num_planes, ctx.bounds = num_planes, bounds
        ctx.save_for_backward(src, dst, ptr, *inputs)
        return _sum_blocks(messages, num_planes, bounds, src, dst, ptr,
                           *inputs)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        src, dst, ptr, *inputs = ctx.saved_tensors
        needs = ctx.needs_input_grad[8:]
        grads = [torch.zeros_like(t) if need else None
                 for t, need in zip(inputs, needs)]
        bounds = ctx.bounds
        for first, last in zip(bounds[:-1], bounds[1:]):
            begin, end = int(ptr[first]), int(ptr[last])
            block_src, block_dst = src[begin:end], dst[begin:end]
            found = ctx.gradients(ctx, inputs, needs, begin, end, block_src,
                                  block_dst,
                                  grad_out.index_select(0, block_dst))
            for grad, (nodes, value) in zip(grads, found):
                if grad is None:
                    continue
                if nodes is None:  # per-edge: the link features
                    grad[begin:end] = value
                else:
                    for index, part in zip(nodes, value):
                        grad.index_add_(0, index, part)
        return (None, ) * 8 + tuple(grads)


# The block gradient functions return, per input (the coordinate planes, the
# sender log-weights, the link features), (row indices, parts) to add at those
# rows, or (None, block) for the per-edge link features.


def _range_block_grads(ctx, inputs, needs, begin, end, src, dst,
                       grad_messages):
    # messages m = log p(z | d) + w_src with d = |p_src - p_dst|: the model
    # gives dm/dd and dm/dz in closed form, and dd/dp_src = diff / d
    # (a range model's planes are the positions, in any dimension)
    num_planes = ctx.num_planes
    link_features = inputs[num_planes + 1][begin:end]
    deltas = [pos.index_select(0, src) - pos.index_select(0, dst)
              for pos in inputs[:num_planes]]
    distances = torch.sqrt(sum(delta * delta for delta in deltas))
    per_distance, per_range = ctx.model.distance_gradient(link_features,
                                                          distances)
    per_distance = grad_messages * per_distance
    # zero (not NaN) where paired particles coincide, as autograd's norm
    per_coordinate = torch.where(distances > 0, per_distance / distances,
                                 torch.zeros_like(distances))
    planes = []
    for delta in deltas:
        grad = per_coordinate * delta
        planes.append(((src, dst), (grad, -grad)))
    feature_grad = None
    if needs[num_planes + 1]:  # the range column; the others are not read
        feature_grad = torch.zeros_like(link_features)
        feature_grad[:, 0] = (grad_messages * per_range).sum(-1)
    return (*planes, ((src, ), (grad_messages, )), (None, feature_grad))


def _autograd_block_grads(ctx, inputs, needs, begin, end, src, dst,
                          grad_messages):
    # the block's senders and receivers as 2 * count local nodes
    num_planes = ctx.num_planes
    count = end - begin
    nodes = torch.cat([src, dst])
    local = torch.arange(2 * count, device=nodes.device)
    with torch.enable_grad():
        leaves = [t.index_select(0, nodes).requires_grad_(need)
                  for t, need in zip(inputs[:num_planes + 1], needs)]
        block_features = inputs[num_planes + 1][begin:end].detach(
        ).requires_grad_(needs[num_planes + 1])
        offsets = (inputs[num_planes + 2].index_select(0, nodes)
                  if len(inputs) > num_planes + 2 else None)
        block = ctx.messages(tuple(leaves[:num_planes]), leaves[num_planes],
                             block_features, local[:count], local[count:],
                             offsets)
        wanted = [t for t in (*leaves, block_features) if t.requires_grad]
        found = iter(torch.autograd.grad(block, wanted, grad_messages,
                                         allow_unused=True))
    needs = needs[:num_planes + 2]  # the offsets have no gradient
    grads = [next(found) if need else None for need in needs]
    grads = [torch.zeros_like(t) if g is None and need else g
             for g, t, need in zip(grads, (*leaves, block_features), needs)]
    return (*(((nodes, ), (g, )) for g in grads[:num_planes + 1]),
            (None, grads[num_planes + 1]))
