import math
from typing import Optional

import torch
from torch import Tensor

from tg_nebp.data.validation import check_number

__all__ = ['GaussianRange']


class GaussianRange:
    r"""Range measurements with additive Gaussian noise, from the `"Neural
    Enhanced Belief Propagation for Cooperative Localization"
    <https://arxiv.org/abs/2105.12903>`_ paper

    .. math::
        z_{j \to i} = \| \mathbf{p}_j - \mathbf{p}_i \| + r_{j \to i}, \quad
        r_{j \to i} \sim \mathcal{N}(0, \sigma_r^2),

    measured by agent :math:`i` for every node :math:`j` within
    :obj:`max_range`, with log-likelihood

    .. math::
        \log p(z_{j \to i} | \mathbf{x}_j, \mathbf{x}_i) =
        -\frac{(z_{j \to i} - \| \mathbf{p}_j - \mathbf{p}_i \|)^2}
        {2 \sigma_r^2} - \log (\sqrt{2 \pi} \sigma_r).

    A range sensor never reports a negative distance, so :meth:`sample`
    redraws the noise of the rare measurements that would fall below zero
    (pairs closer than a few :math:`\sigma_r`); the likelihood keeps the
    paper's Gaussian form.

    Args:
        sigma (float, optional): Noise standard deviation :math:`\sigma_r` in
            metres. (default: :obj:`1.0`)
        max_range (float, optional): Communication range in metres: pairs
            farther apart do not measure. (default: :obj:`20.0`)

    Shapes:
        - **input:** ranges :math:`(E, 1)`, distances :math:`(E, K)`
        - **output:** log-likelihoods :math:`(E, K)`
    """
    def __init__(self, sigma: float = 1.0, max_range: float = 20.0):
        sigma = check_number(sigma, 'sigma')
        max_range = check_number(max_range, 'max_range')
        # the likelihood scales squared residuals by 1 / (2 sigma^2): an
        # infinite factor would turn a zero residual into NaN
        if not sigma**2 * torch.finfo(torch.float32).max >= 0.5:
            raise ValueError(f"'sigma' = {sigma} is too small: 1 / (2 "
                             f"sigma^2) overflows float32")
        self.sigma = sigma
        self.max_range = max_range

    def log_likelihood_of_distance(self, ranges: Tensor, distances: Tensor,
                                   inplace: bool = False) -> Tensor:
        r"""The log-likelihood of the measured :obj:`ranges` :math:`(E, 1)`
        given the particle distances :math:`(E, K)`; :obj:`inplace`
        overwrites :obj:`distances` (no autograd through it)."""
        log_norm = math.log(math.sqrt(2 * math.pi) * self.sigma)
        if inplace:
            return distances.sub_(ranges).square_().mul_(
                -0.5 / self.sigma**2).sub_(log_norm)
        scaled = (ranges - distances) / self.sigma
        return -0.5 * scaled * scaled - log_norm

    def log_likelihood(self, ranges: Tensor, sender_pos: Tensor,
                       receiver_pos: Tensor) -> Tensor:
        r"""The log-likelihood of the measured :obj:`ranges` :math:`(E, 1)`
        given sender and receiver positions :math:`(E, K, 2)`."""
        return self.log_likelihood_of_distance(
            ranges, torch.linalg.vector_norm(sender_pos - receiver_pos,
                                             dim=-1))

    def sample(self, distances: Tensor,
               generator: Optional[torch.Generator] = None) -> Tensor:
        r"""Draws measured ranges for the true :obj:`distances`, redrawing
        the noise wherever a range would be negative."""
        ranges = torch.empty_like(distances)
        todo = torch.ones_like(distances, dtype=torch.bool)
        while bool(todo.any()):
            noise = torch.randn(distances.shape, dtype=distances.dtype,
                                device=distances.device, generator=generator)
            ranges = torch.where(todo, distances + self.sigma * noise, ranges)
            todo = ranges < 0
        return ranges

    def connect(self, pos: Tensor, receiver: Tensor,
                block_size: int = 2048) -> Tensor:
        r"""Returns the measurement edges :obj:`[2, E]` (:math:`j \to i`)
        from every node :math:`j` to every :obj:`receiver` node :math:`i \neq
        j` within :obj:`max_range` of it, for positions :obj:`pos`
        :math:`(N, 2)`, ordered by sender, then receiver. Senders are handled
        :obj:`block_size` at a time, so memory stays :math:`O(N)` per
        block."""
        num_nodes = pos.size(0)
        blocks = []
        for start in range(0, num_nodes, block_size):
            senders = pos[start:start + block_size]
            # the matrix-multiplication shortcut of cdist cancels
            # catastrophically: pairs at the boundary would flip, so compute
            # every difference explicitly
            within = torch.cdist(
                senders, pos, compute_mode='donot_use_mm_for_euclid_dist'
            ) <= self.max_range
            within &= receiver.view(1, -1)  # column i receives
            rows = torch.arange(senders.size(0), device=pos.device)
            within[rows, rows + start] = False  # no self-edges
            src, dst = within.nonzero(as_tuple=True)
            blocks.append(torch.stack([src + start, dst]))
        if not blocks:
            return torch.empty(2, 0, dtype=torch.long, device=pos.device)
        return torch.cat(blocks, dim=1)

    def __repr__(self) -> str:
        return (f'{self.__class__.__name__}(sigma={self.sigma}, '
                f'max_range={self.max_range})')
