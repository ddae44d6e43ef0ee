r"""A fused Triton kernel for a range model's BP factor summed over each
receiver's incoming edges, for edges sorted by receiver (CSC):

.. math::
    s_i^{(k)} = \sum_{e = \mathrm{ptr}_i}^{\mathrm{ptr}_{i+1} - 1}
    \log p\big(z_e \,\big|\, \|\mathbf{p}_{j_e}^{(k)} -
    \mathbf{p}_i^{(k)}\|\big) + \log \tilde{w}_{j_e}^{(k)}.

The kernel holds no likelihood of its own: it compiles the model's
:obj:`fused_log_pdf(range, distance, c0, c1)` (an arithmetic function, see
:class:`~tg_nebp.models.GaussianRange`) with the model's two constants.

One program owns one receiver and a block of particles and walks its
incoming edges in order: no per-edge tensor is written, no atomics are used,
so the result is deterministic and the memory traffic is about three reads
per edge-particle (sender coordinates and log-weight) plus one write per
node-particle."""
import types
from typing import Any, Callable, Dict, Tuple

import torch
from torch import Tensor

__all__ = ['fused_bp_available', 'fused_bp_segment_sum']

try:  # Triton ships with CUDA builds of PyTorch only
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - CPU-only installs
    triton = None


def fused_bp_available(tensor: Tensor) -> bool:
    r"""Whether the fused kernel can run on :obj:`tensor`'s device."""
    return triton is not None and tensor.is_cuda


if triton is not None:

    @triton.jit
    def _bp_csc_kernel(pos_x, pos_y, log_w, ranges, src, ptr, out,
                       num_particles, c0, c1, log_pdf: tl.constexpr,
                       BLOCK: tl.constexpr):
        node = tl.program_id(0).to(tl.int64)
        offs = tl.program_id(1) * BLOCK + tl.arange(0, BLOCK)
        mask = offs < num_particles
        row = node * num_particles
        x_i = tl.load(pos_x + row + offs, mask=mask, other=0.0)
        y_i = tl.load(pos_y + row + offs, mask=mask, other=0.0)
        acc = tl.zeros([BLOCK], dtype=tl.float32)
        start = tl.load(ptr + node)
        end = tl.load(ptr + node + 1)
        for e in range(start, end):
            sender = tl.load(src + e).to(tl.int64) * num_particles
            z = tl.load(ranges + e)
            dx = tl.load(pos_x + sender + offs, mask=mask, other=0.0) - x_i
            dy = tl.load(pos_y + sender + offs, mask=mask, other=0.0) - y_i
            acc += tl.load(log_w + sender + offs, mask=mask, other=0.0) \
                + log_pdf(z, tl.sqrt(dx * dx + dy * dy), c0, c1)
        tl.store(out + row + offs, acc, mask=mask)


_COMPILED: Dict[Callable, Any] = {}  # one Triton function per formula


def fused_bp_segment_sum(pos_x: Tensor, pos_y: Tensor,
                         sender_log_weights: Tensor, ranges: Tensor,
                         src: Tensor, ptr: Tensor, log_pdf: Callable,
                         constants: Tuple[float, float],
                         block: int = 1024) -> Tensor:
    r"""The summed log-messages :math:`(N, K)` of edges sorted by receiver.

    Args:
        pos_x (torch.Tensor): Particle x-coordinates :math:`(N, K)`.
        pos_y (torch.Tensor): Particle y-coordinates :math:`(N, K)`.
        sender_log_weights (torch.Tensor): :math:`(N, K)`.
        ranges (torch.Tensor): Measured ranges :math:`(E)` or :math:`(E, 1)`.
        src (torch.Tensor): Sender of every edge :math:`(E)`.
        ptr (torch.Tensor): Receiver pointer :math:`(N + 1)`.
        log_pdf (callable): The model's arithmetic
            :obj:`fused_log_pdf(range, distance, c0, c1)`.
        constants (tuple): Its constants :obj:`(c0, c1)`.
        block (int, optional): Particles per program. (default: :obj:`1024`)
    """
    if triton is None:
        raise RuntimeError('the fused BP kernel needs Triton')
    if pos_x.dtype != torch.float32:
        raise ValueError(f"the fused BP kernel works in float32, got "
                         f"{pos_x.dtype}")
    num_nodes, num_particles = pos_x.shape
    pos_x, pos_y = pos_x.contiguous(), pos_y.contiguous()
    log_w = sender_log_weights.contiguous()
    out = torch.empty_like(pos_x)
    if log_pdf not in _COMPILED:
        # the model's own function, seeing triton.language as Triton
        # requires (its module does not import Triton)
        visible = types.FunctionType(log_pdf.__code__,
                                     {**log_pdf.__globals__, 'tl': tl},
                                     log_pdf.__name__)
        _COMPILED[log_pdf] = triton.jit(visible)
    grid = (num_nodes, triton.cdiv(num_particles, block))
    _bp_csc_kernel[grid](pos_x, pos_y, log_w, ranges.reshape(-1).contiguous(),
                         src.contiguous(), ptr.contiguous(), out,
                         num_particles, *map(float, constants),
                         log_pdf=_COMPILED[log_pdf], BLOCK=block)
    return out
