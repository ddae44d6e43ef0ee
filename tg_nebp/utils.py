r"""Small tensor helpers shared by the layers and the trackers."""
import contextlib
import os
import re
from typing import (Callable, Dict, Iterator, NamedTuple, Optional, Sequence,
                    Tuple)

import torch
import torch.distributed as dist
from torch import Tensor
from torch_geometric import EdgeIndex, Index

__all__ = [
    'inputs',
    'weighted_moments',
    'symmetrize',
    'row_jacobian',
    'row_linearization',
    'rounding_tolerance',
    'symmetric_psd_defects',
    'log_normalize',
    'logsumexp',
    'logaddexp',
    'floored_exp',
    'compute_dtype',
    'plain_tensor',
    'detached',
    'sort_by_receiver',
    'as_edge_index',
    'long_edge_index',
    'derive_seed',
    'process_group',
    'joined_process_group',
    'check_device',
    'free_memory_bytes',
    'LinkFactors',
    'link_factors',
]


def inputs(control: Optional[Tensor]) -> Dict[str, Tensor]:
    r"""The keyword arguments that hand a step's known input
    :obj:`control` to a motion model's methods: none without one, so that
    a model that takes no input keeps its signature."""
    return {} if control is None else {'control': control}


def compute_dtype(*tensors: Tensor) -> torch.dtype:
    r"""The floating dtype that the layers and trackers compute in: the
    promotion of the floating :obj:`tensors`' dtypes and float32. Half
    precision is promoted: log-weights need float32's range and
    precision."""
    dtype = torch.float32
    for tensor in tensors:
        if tensor.is_floating_point():
            dtype = torch.promote_types(dtype, tensor.dtype)
    return dtype


def weighted_moments(particles: Tensor, log_weights: Tensor):
    r"""Weighted mean :math:`\hat{\mathbf{x}}_i = \sum_k w_i^{(k)}
    \mathbf{x}_i^{(k)}` and covariance :math:`\sum_k w_i^{(k)}
    (\mathbf{x}_i^{(k)} - \hat{\mathbf{x}}_i)(\mathbf{x}_i^{(k)} -
    \hat{\mathbf{x}}_i)^\top` of particles :math:`(N, K, D)` with
    log-weights :math:`(N, K)`, normalized here
    (:func:`~tg_nebp.utils.log_normalize`), so that the weights sum to one
    whatever their scale. A row of zero weights
    gives zeros: validation rejects such rows before."""
    dtype = torch.promote_types(particles.dtype, log_weights.dtype)
    particles = particles.to(dtype)
    weights = log_normalize(log_weights.to(dtype)).exp()
    mean = torch.einsum('nk,nkd->nd', weights, particles)
    centered = particles - mean.unsqueeze(1)
    # the product's two triangles are summed in different orders by the
    # BLAS at hand: symmetric only to rounding, unless symmetrized
    return mean, symmetrize(
        (centered * weights.unsqueeze(-1)).transpose(1, 2) @ centered)


def row_jacobian(function: Callable[[Tensor], Tensor], point: Tensor,
                 create_graph: Optional[bool] = None) -> Tensor:
    r"""The Jacobian :math:`(*, O, I)` of a :obj:`function` that maps every
    row of :obj:`point` :math:`(*, I)` to its own output row :math:`(*,
    O)` (a motion model's move of each state, a measurement model's
    expectation of each link), by reverse-mode automatic differentiation
    of the function itself: one backward pass, batched over the :math:`O`
    output directions. (Forward mode would take one pass per input
    direction, and PyTorch's forward-mode products run through slow
    decompositions.) Differentiable where gradients are enabled and
    :obj:`create_graph` holds (by default: where :obj:`point` requires
    them; pass :obj:`True` where the function reads another tensor that
    does), as training through a tracker needs."""
    return row_linearization(function, (point, ), create_graph)[1][0]


def row_linearization(function: Callable[..., Tensor],
                      points: Sequence[Tensor],
                      create_graph: Optional[bool] = None
                      ) -> Tuple[Tensor, Tuple[Tensor, ...]]:
    r"""The output :math:`(*, O)` of a :obj:`function` of several
    arguments :obj:`points` (each :math:`(*, I_k)`, rows matched) and its
    Jacobian in each, :math:`(*, O, I_k)`, from one forward and one
    backward pass (as :func:`row_jacobian`, of which it is the
    several-argument form: a motion model's Jacobians in the state and in
    the input at once). The output keeps its graph where :obj:`create_graph`
    holds (by default: where a point requires gradients) and gradients are
    enabled."""
    if create_graph is None:
        create_graph = any(point.requires_grad for point in points)
    create = create_graph and torch.is_grad_enabled()
    with torch.enable_grad():
        leaves = tuple(point if create and point.requires_grad else
                       point.detach().requires_grad_() for point in points)
        out = function(*leaves)
        size = out.size(-1)
        rows = (None, ) * len(points)
        if out.numel() > 0 and out.requires_grad:
            eye = torch.eye(size, dtype=out.dtype, device=out.device)
            directions = eye.view((size, ) + (1, ) * (out.dim() - 1) +
                                  (size, )).expand((size, ) + out.shape)
            rows = torch.autograd.grad(out, leaves, directions,
                                       is_grads_batched=True,
                                       create_graph=create,
                                       allow_unused=True)
    # rows[k] holds output k's gradient: (O, *, I) to (*, O, I); an
    # output that does not depend on a point (or no row) gives zeros
    jacobians = tuple(
        out.new_zeros(out.shape + point.shape[-1:]).detach() if row is None
        else row.movedim(0, -2) for row, point in zip(rows, points))
    return (out if create else out.detach()), jacobians


def symmetrize(matrices: Tensor) -> Tensor:
    r"""The mean of both triangles, :math:`\frac{1}{2}(\mathbf{A} +
    \mathbf{A}^\top)`, of matrices :math:`(\ldots, D, D)`. Exactly
    symmetric in floating point (addition commutes), so that a covariance
    formed from rounded products is carried, saved and checked as the
    symmetric matrix it stands for, on any machine's BLAS."""
    return 0.5 * (matrices + matrices.transpose(-1, -2))


def rounding_tolerance(dtype: torch.dtype) -> float:
    r"""How far from symmetric, and how far below zero in its smallest
    eigenvalue, a computed covariance or information matrix of
    :obj:`dtype` may be, relative to its largest entry, for rounding alone
    to explain it: half the digits of the dtype, :math:`\sqrt{\epsilon}`
    (:math:`3.5 \cdot 10^{-4}` in float32, :math:`1.5 \cdot 10^{-8}` in
    float64). Products, inverses and particle sums lose far fewer digits;
    a damaged or wrong matrix is off by far more."""
    return torch.finfo(dtype).eps ** 0.5


def symmetric_psd_defects(matrices: Tensor,
                          tolerance: Optional[float] = None
                          ) -> Tuple[Tensor, Tensor, Tensor]:
    r"""Which of the matrices :math:`(\ldots, D, D)` are not
    symmetric and which not positive semi-definite, each beyond
    :obj:`tolerance` (:func:`rounding_tolerance` of their dtype by
    default) of the matrix's largest entry: two boolean masks
    :math:`(\ldots)` and the smallest eigenvalue of each matrix's
    symmetric part :math:`(\ldots)` (float64). The one check of
    covariances that the realizations' validation, a saved tracker's
    state and the metrics share, so that what one accepts no other
    refuses. A matrix with a NaN or infinite entry is neither (both masks
    true, its smallest eigenvalue NaN): no covariance holds one."""
    if tolerance is None:
        tolerance = rounding_tolerance(matrices.dtype)
    matrices = matrices.double()
    broken = ~matrices.isfinite().all(-1).all(-1)
    # eigvalsh refuses a non-finite matrix: a zero stands in for it
    matrices = matrices.masked_fill(broken[..., None, None], 0.0)
    scale = matrices.abs().amax((-1, -2))
    asymmetry = (matrices - matrices.transpose(-1, -2)).abs().amax((-1, -2))
    lowest = torch.linalg.eigvalsh(symmetrize(matrices))[..., 0]
    return ((asymmetry > tolerance * scale) | broken,
            (lowest < -tolerance * scale) | broken,
            lowest.masked_fill(broken, float('nan')))


def log_normalize(log_weights: Tensor) -> Tensor:
    r"""Normalizes log-weights over the last dimension, :math:`\log w^{(k)}
    - \log \sum_l w^{(l)}`, so that their exponentials sum to one for any
    finite input, in float32 too.

    The maximum is subtracted before the sum (:func:`torch.log_softmax`);
    :obj:`x - x.logsumexp(-1)` is not enough: around :math:`-10^{10}` the
    float32 sum :math:`\max + \log \sum` rounds back to the maximum, and
    tied particles each get weight one. A row of zero weights (all
    :math:`-\infty`) has no normalization: it stays :math:`-\infty` with a
    zero gradient, never NaN; callers that need a distribution reject it
    (:func:`~tg_nebp.data.check_particles`)."""
    zero = torch.isneginf(log_weights).all(-1, keepdim=True)
    # a finite stand-in keeps log_softmax's NaN out of both passes
    normalized = log_weights.masked_fill(zero, 0.0).log_softmax(-1)
    return normalized.masked_fill(zero, float('-inf'))


# exp() of arguments below about -87 (float32) lands in the denormal range or
# underflows, where torch's CPU exp takes a slow path (tens of times slower
# than for moderate arguments). A term this far below the largest of its sum
# is under 1e-34 of it, beneath the rounding of float32 and float64 sums.
EXP_FLOOR = -80.0


def logsumexp(values: Tensor, dim: int = 0) -> Tensor:
    r""":math:`\log \sum \exp` of :obj:`values` over :obj:`dim`, equal to
    :func:`torch.logsumexp` within rounding, several times faster on the CPU
    for terms that span hundreds of nats (likelihoods of far particles).

    The maximum is subtracted and differences below :obj:`EXP_FLOOR` are
    raised to it before the exponential: such a term is under
    :math:`10^{-34}` of the largest term, so the sum is unchanged in float32
    and float64, while the exponential never reaches the denormal range
    where it is slow. All :math:`-\infty` gives :math:`-\infty`. The
    gradient is the softmax of :obj:`values` (zero for the raised terms)."""
    top = values.detach().amax(dim, keepdim=True)
    # all -inf: a finite stand-in avoids inf - inf; the sum adds -inf back
    finite_top = top.masked_fill(torch.isneginf(top), 0.0)
    shifted = (values - finite_top).clamp_(min=EXP_FLOOR)
    # in place without autograd: no temporaries beyond the first
    terms = shifted.exp() if shifted.requires_grad else shifted.exp_()
    return terms.sum(dim).log_().add_(top.squeeze(dim))


class _LogAddExp(torch.autograd.Function):
    # one pass forward, exp(a - out) and exp(b - out) backward, every
    # exponent raised to EXP_FLOOR (torch.logaddexp's kernels take exp's
    # slow denormal path for such differences, in both passes)
    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor) -> Tensor:
        top = torch.maximum(a, b)
        # both -inf: a finite stand-in avoids inf - inf
        finite_top = top.masked_fill(torch.isneginf(top), 0.0)
        out = torch.minimum(a, b).sub_(finite_top).clamp_(
            min=EXP_FLOOR).exp_().log1p_().add_(top)
        ctx.save_for_backward(a, b, out)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        a, b, out = ctx.saved_tensors
        finite_out = out.masked_fill(torch.isneginf(out), 0.0)
        grads = []
        for value, needed in zip((a, b), ctx.needs_input_grad):
            grads.append((value - finite_out).clamp_(min=EXP_FLOOR).exp_()
                         .mul_(grad).sum_to_size(value.shape)
                         if needed else None)
        return tuple(grads)


def logaddexp(a: Tensor, b: Tensor) -> Tensor:
    r""":math:`\log(e^a + e^b)` elementwise (broadcasting), equal to
    :func:`torch.logaddexp` within rounding and several times faster on the
    CPU, forward and backward, where the two differ by more than
    :math:`-\mathrm{EXP\_FLOOR}` nats, as most corrected messages do: every
    exponent is raised to :obj:`EXP_FLOOR` (see :func:`logsumexp`), which
    changes the result and the gradient by less than :math:`10^{-34}`
    relative. Two :math:`-\infty` give :math:`-\infty` and a zero (below
    :math:`10^{-34}`) gradient, not :func:`torch.logaddexp`'s NaN."""
    return _LogAddExp.apply(a, b)


def floored_exp(values: Tensor) -> Tensor:
    r""":math:`e^x` with :math:`x` raised to :obj:`EXP_FLOOR` first, for
    log-values normalized to a maximum near zero (messages, weights): the
    result differs from :func:`torch.exp` by less than :math:`10^{-34}`
    and the exponential stays out of its slow denormal path."""
    return values.clamp_min(EXP_FLOOR).exp()


def plain_tensor(tensor: Tensor) -> Tensor:
    r""":obj:`tensor` as a plain :class:`torch.Tensor` (zero-copy): PyG's
    :class:`~torch_geometric.EdgeIndex` and :class:`~torch_geometric.Index`
    are subclasses that compiled regions should not see (their
    :obj:`as_subclass` keeps the subclass); plain tensors pass through
    untouched, which keeps :func:`torch.compile` free of graph breaks."""
    if isinstance(tensor, (EdgeIndex, Index)):
        return tensor.as_tensor()
    return tensor


def detached(value):
    r""":obj:`value` with every tensor in it detached: a tensor, or a
    (named) tuple or list of them, nested, :obj:`None` and other values
    kept (a tracker's state between the steps of a training truncated in
    time)."""
    if isinstance(value, Tensor):
        return value.detach()
    if isinstance(value, tuple) and hasattr(value, '_fields'):
        return type(value)(*(detached(item) for item in value))
    if isinstance(value, (tuple, list)):
        return type(value)(detached(item) for item in value)
    return value


def sort_by_receiver(edge_index: Tensor, num_nodes: int,
                     edge_attr: Tensor) -> Tuple[EdgeIndex, Tensor]:
    r"""The edges as an int64 :class:`~torch_geometric.EdgeIndex` sorted by
    receiver (column), and :obj:`edge_attr` in the same order: free for an
    :class:`~torch_geometric.EdgeIndex` already sorted by column (whose
    claim validation checks), else a stable sort, so each receiver's edges
    keep their order and with it the summation order of a scatter over the
    input edges. Receiver segments give deterministic sums, and let the
    convolutions sum block by block without :math:`(E, K)` tensors."""
    edge_index = as_edge_index(edge_index, num_nodes)
    if not edge_index.is_sorted_by_col:
        edge_index, perm = edge_index.sort_by('col', stable=True)
        edge_attr = edge_attr[perm]
    return edge_index, edge_attr


def as_edge_index(edge_index: Tensor, num_nodes: int) -> EdgeIndex:
    r"""The edges as an int64 :class:`~torch_geometric.EdgeIndex` of sparse
    size :obj:`(num_nodes, num_nodes)` (see :func:`long_edge_index`)."""
    edge_index = long_edge_index(edge_index, num_nodes)
    if not isinstance(edge_index, EdgeIndex):
        edge_index = EdgeIndex(edge_index, sparse_size=(num_nodes,
                                                        num_nodes))
    return edge_index


def long_edge_index(edge_index: Tensor, num_nodes: int) -> Tensor:
    r"""The edges in int64 (PyG's scatter wants it); an
    :class:`~torch_geometric.EdgeIndex` also gets the sparse size
    :obj:`(num_nodes, num_nodes)` and keeps its sort order. (PyG otherwise
    infers the size from the largest index, which silently drops the last
    nodes when they receive nothing.)"""
    if isinstance(edge_index, EdgeIndex) \
            and edge_index.sparse_size() != (num_nodes, num_nodes):
        edge_index = EdgeIndex(edge_index.as_tensor(),
                               sparse_size=(num_nodes, num_nodes),
                               sort_order=edge_index.sort_order)
    if edge_index.dtype != torch.long:
        edge_index = edge_index.to(torch.long)
    return edge_index


def derive_seed(seed: int, *parts: int) -> int:
    r"""The seed of one independent random stream, derived from a base
    :obj:`seed` and integer :obj:`parts` (a realization's index; an epoch
    and an index), the one formula for all of them: :math:`s \leftarrow (s
    \cdot 1\,000\,003 + p) \bmod (2^{63} - 1)` for every part, so
    realization :math:`r` of seed :math:`s` uses :math:`1\,000\,003 s +
    r`. Streams depend only on their own parts: a realization draws the
    same numbers in any batch, on any rank and after a resume."""
    value = int(seed)
    for part in parts:
        value = (value * 1_000_003 + int(part)) % (2**63 - 1)
    return value


def process_group() -> Tuple[int, int]:
    r"""The world size and this process's rank in the initialized
    :mod:`torch.distributed` process group (:obj:`torchrun`), or
    :obj:`(1, 0)` outside one: what training, evaluation and data
    generation use to split their work."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_world_size(), dist.get_rank()
    return 1, 0


@contextlib.contextmanager
def joined_process_group(device: str = 'cpu') -> Iterator[str]:
    r"""Joins the process group of a :obj:`torchrun` launch (WORLD_SIZE >
    1) for the duration of the block and yields this process's device:
    NCCL with one GPU per process (LOCAL_RANK) when :obj:`device` is CUDA,
    gloo on the CPU. Outside :obj:`torchrun`, or in a group already
    joined, it yields :obj:`device` and does nothing else."""
    launched = (int(os.environ.get('WORLD_SIZE', '1')) > 1
                and not dist.is_initialized())
    if launched:
        if device.startswith('cuda'):
            device = f"cuda:{int(os.environ['LOCAL_RANK'])}"
            torch.cuda.set_device(device)
        dist.init_process_group('nccl' if device.startswith('cuda')
                                else 'gloo')
    try:
        yield device
    finally:
        if launched:
            dist.destroy_process_group()


_DEVICE = re.compile(r'cpu|cuda(:\d+)?')


def check_device(device) -> str:
    r"""Returns :obj:`device` if it names a device of this machine:
    :obj:`"cpu"`, or :obj:`"cuda"` or :obj:`"cuda:N"` where CUDA has that
    GPU (a :class:`torch.device` of these too, returned as its name);
    anything else is a :class:`ValueError` naming :obj:`'device'`, before
    any work, rather than an error of torch's midway."""
    if isinstance(device, torch.device):
        device = str(device)
    if not (isinstance(device, str) and _DEVICE.fullmatch(device)):
        raise ValueError(f"'device' must be 'cpu', 'cuda' or 'cuda:N', got "
                         f"{device!r}")
    if device != 'cpu':
        if not torch.cuda.is_available():
            raise ValueError(f"'device' is '{device}', but CUDA is not "
                             f"available here")
        count = torch.cuda.device_count()
        if int(device[5:] or 0) >= count:
            raise ValueError(f"'device' is '{device}', but this machine has "
                             f"{count} CUDA device(s)")
    return device


def free_memory_bytes(device: str = 'cpu') -> int:
    r"""The memory free for new tensors on :obj:`device`, in bytes: the
    CUDA allocator's free memory on a GPU, :obj:`MemAvailable` of
    :obj:`/proc/meminfo` on the CPU (Linux; unbounded elsewhere). What
    the memory checks compare their estimates with."""
    if str(device).startswith('cuda'):
        return torch.cuda.mem_get_info(torch.device(device))[0]
    try:
        with open('/proc/meminfo') as f:
            for line in f:
                if line.startswith('MemAvailable:'):
                    return int(line.split()[1]) * 1024
    except OSError:  # pragma: no cover - not Linux
        pass
    return 2**62  # pragma: no cover - not Linux


class LinkFactors(NamedTuple):
    r"""The factors of one time step's measured links and the message
    edges that carry their messages (:func:`link_factors`): every factor's
    end nodes :obj:`ends` :math:`(P, 2)`; the factor of every link
    :obj:`factor` :math:`(E)` and whether the link runs from the factor's
    second end to its first (:obj:`swapped`); the message edges
    :obj:`index` :math:`(2, M)` (source, target), the factor of each
    (:obj:`link`), the end it informs (:obj:`end`, 0 or 1), and the message
    edge of the same factor to the other end (:obj:`reverse`, :math:`-1`
    if none)."""
    ends: Tensor
    factor: Tensor
    swapped: Tensor
    index: Tensor
    link: Tensor
    end: Tensor
    reverse: Tensor


def link_factors(edge_index: Tensor, anchor: Tensor,
                 ends: str = 'both') -> LinkFactors:
    r"""The factor graph of the measured links :obj:`edge_index` :math:`(2,
    E)` (:math:`j \to i`: agent :math:`i` measured node :math:`j`), shared
    by the message passing methods that send factor messages.

    With :obj:`ends="both"` the two measurements of a pair of nodes
    (:math:`z_{j \to i}` and :math:`z_{i \to j}`) form one factor on the
    pair :math:`(a, b)`, :math:`a < b`: two factors between the same two
    nodes would close a loop in which each counts the other's information
    again. A factor sends its message to every end that is an agent (the
    message to :math:`j` runs on the flipped edge :math:`i \to j`). With
    :obj:`ends="receiver"` (the paper's convention) every measurement is its
    own factor, whose one message goes to the agent that measured it.
    The message edges are sorted by target."""
    src, dst = edge_index
    num_nodes = anchor.numel()
    if ends == 'receiver':
        pairs = edge_index.t().contiguous()
        factor = torch.arange(src.numel(), device=src.device)
        swapped = torch.zeros_like(src, dtype=torch.bool)
    else:
        low, high = torch.minimum(src, dst), torch.maximum(src, dst)
        # one key per unordered pair (a 1-D unique is much faster than a
        # unique over rows)
        keys, factor = torch.unique(low * num_nodes + high,
                                    return_inverse=True)
        pairs = torch.stack([keys // num_nodes, keys % num_nodes], 1)
        swapped = src > dst
    count = pairs.size(0)
    numbers = torch.arange(count, device=src.device)
    to_first = (~anchor[pairs[:, 0]] if ends == 'both' else
                torch.zeros_like(numbers, dtype=torch.bool))
    second, first = numbers[~anchor[pairs[:, 1]]], numbers[to_first]
    link = torch.cat([second, first])
    end = torch.cat([torch.ones_like(second), torch.zeros_like(first)])
    # sorted by target: segment sums, deterministic on every device
    order = torch.argsort(pairs[link, end], stable=True)
    link, end = link[order], end[order]
    index = torch.stack([pairs[link, 1 - end], pairs[link, end]])
    slot = torch.full((count, 2), -1, dtype=torch.long, device=src.device)
    slot[link, end] = torch.arange(link.numel(), device=src.device)
    return LinkFactors(pairs, factor, swapped, index, link, end,
                       slot[link, 1 - end])
