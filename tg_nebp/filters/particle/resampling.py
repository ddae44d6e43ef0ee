r"""Resamplers: pure functions from log-weights :math:`(*, K)` to ancestor
indices :math:`(*, M)`, as in filterpy. They never touch the particles, so
any tracker (or user) applies them with :func:`torch.gather`."""
from typing import Optional

import torch
from torch import Tensor

from tg_nebp.data.validation import is_integer

__all__ = ['multinomial_resample', 'systematic_resample',
           'stratified_resample', 'residual_resample', 'RESAMPLERS',
           'effective_sample_size', 'silverman_bandwidth']


def _probabilities(log_weights: Tensor) -> Tensor:
    if log_weights.dim() == 0:
        raise ValueError("'log_weights' must have a particle dimension "
                         "(*, K), got a scalar")
    if log_weights.size(-1) == 0:
        raise ValueError("'log_weights' holds K = 0 particles")
    for bad, what in ((torch.isnan(log_weights), 'holds NaN'),
                      (log_weights == float('inf'), 'holds +inf'),
                      (torch.isneginf(log_weights).all(-1, keepdim=True),
                       'is a row of zero weights (all -inf): nothing to '
                       'resample from')):
        rows = bad.any(-1)
        if bool(rows.any()):
            row = ''.join(f'[{i}]' for i in rows.nonzero()[0].tolist())
            raise ValueError(f"'log_weights{row}' {what}")
    # softmax subtracts the maximum: finite for any finite log-weights
    return torch.softmax(log_weights.detach().double(), dim=-1)


def multinomial_resample(log_weights: Tensor,
                         num_samples: Optional[int] = None,
                         generator: Optional[torch.Generator] = None
                         ) -> Tensor:
    r"""Multinomial resampling (the paper's): :math:`M` independent draws
    with probabilities :math:`w^{(k)} \propto \exp(\log w^{(k)})`.

    Args:
        log_weights (torch.Tensor): Unnormalized log-weights :math:`(*, K)`.
        num_samples (int, optional): :math:`M`. (default: :obj:`K`)
        generator (torch.Generator, optional): Source of randomness.
            (default: :obj:`None`)

    Shapes:
        - **input:** :math:`(*, K)`
        - **output:** :math:`(*, M)` indices in :math:`[0, K)`
    """
    probs = _probabilities(log_weights)
    num_samples = _num_samples(num_samples, probs)
    # inverse CDF at i.i.d. uniforms: exact multinomial draws, batched over
    # all rows in one searchsorted (torch.multinomial loops over rows)
    return _inverse_cdf(probs, _uniform(probs, num_samples, generator))


def systematic_resample(log_weights: Tensor,
                        num_samples: Optional[int] = None,
                        generator: Optional[torch.Generator] = None
                        ) -> Tensor:
    r"""Systematic resampling: one uniform offset :math:`u \sim U[0, 1)`
    per row and the points :math:`(m + u) / M`, :math:`m = 0, \dots, M-1`;
    lower variance than multinomial resampling.

    Args:
        log_weights (torch.Tensor): Unnormalized log-weights :math:`(*, K)`.
        num_samples (int, optional): :math:`M`. (default: :obj:`K`)
        generator (torch.Generator, optional): Source of randomness.
            (default: :obj:`None`)

    Shapes:
        - **input:** :math:`(*, K)`
        - **output:** :math:`(*, M)` indices in :math:`[0, K)`
    """
    probs = _probabilities(log_weights)
    num_samples = _num_samples(num_samples, probs)
    return _inverse_cdf(probs, _strata(num_samples,
                                       _uniform(probs, 1, generator)))


def stratified_resample(log_weights: Tensor,
                        num_samples: Optional[int] = None,
                        generator: Optional[torch.Generator] = None
                        ) -> Tensor:
    r"""Stratified resampling: one uniform :math:`u_m \sim U[0, 1)` per
    stratum and the points :math:`(m + u_m) / M`; unbiased offspring counts
    with lower variance than multinomial resampling.

    Args:
        log_weights (torch.Tensor): Unnormalized log-weights :math:`(*, K)`.
        num_samples (int, optional): :math:`M`. (default: :obj:`K`)
        generator (torch.Generator, optional): Source of randomness.
            (default: :obj:`None`)

    Shapes:
        - **input:** :math:`(*, K)`
        - **output:** :math:`(*, M)` indices in :math:`[0, K)`
    """
    probs = _probabilities(log_weights)
    num_samples = _num_samples(num_samples, probs)
    return _inverse_cdf(probs, _strata(num_samples, _uniform(
        probs, num_samples, generator)))


def residual_resample(log_weights: Tensor,
                      num_samples: Optional[int] = None,
                      generator: Optional[torch.Generator] = None
                      ) -> Tensor:
    r"""Residual resampling: particle :math:`k` gets :math:`\lfloor M w^{(k)}
    \rfloor` copies deterministically, and the remaining :math:`R = M -
    \sum_k \lfloor M w^{(k)} \rfloor` are drawn multinomially with
    probabilities proportional to the residuals :math:`M w^{(k)} - \lfloor M
    w^{(k)} \rfloor`; unbiased offspring counts.

    Args:
        log_weights (torch.Tensor): Unnormalized log-weights :math:`(*, K)`.
        num_samples (int, optional): :math:`M`. (default: :obj:`K`)
        generator (torch.Generator, optional): Source of randomness.
            (default: :obj:`None`)

    Shapes:
        - **input:** :math:`(*, K)`
        - **output:** :math:`(*, M)` indices in :math:`[0, K)` (the
          deterministic copies first, in index order)
    """
    probs = _probabilities(log_weights)
    num_samples = _num_samples(num_samples, probs)
    expected = probs * num_samples
    copies = expected.floor()
    residual = expected - copies
    kept = copies.sum(-1, keepdim=True)
    # positions [0, kept) take the copies in index order, the others draw
    # from the residuals (whose sum, M - kept, is positive whenever a
    # position is left)
    position = torch.arange(num_samples, dtype=probs.dtype,
                            device=probs.device).expand(
                                probs.shape[:-1] + (num_samples, ))
    deterministic = torch.searchsorted(copies.cumsum(-1),
                                       position.contiguous(), right=True)
    left = residual.sum(-1, keepdim=True)
    drawn = _inverse_cdf(torch.where(left > 0, residual, probs),
                         _uniform(probs, num_samples, generator))
    index = torch.where(position < kept, deterministic, drawn)
    return index.clamp_(max=probs.size(-1) - 1)


def _uniform(probs: Tensor, count: int,
             generator: Optional[torch.Generator]) -> Tensor:
    # count uniforms in [0, 1) per row of probs
    return torch.rand(probs.shape[:-1] + (count, ), dtype=probs.dtype,
                      device=probs.device, generator=generator)


def _strata(num_samples: int, offsets: Tensor) -> Tensor:
    # the points (m + u_m) / M, one per stratum m (a shared offset u for
    # systematic resampling, one per stratum for stratified resampling)
    grid = torch.arange(num_samples, dtype=offsets.dtype,
                        device=offsets.device)
    return (grid + offsets) / num_samples


def _num_samples(num_samples: Optional[int], probs: Tensor) -> int:
    if num_samples is None:
        return probs.size(-1)
    if not is_integer(num_samples):
        raise TypeError(f"'num_samples' must be an integer, got "
                        f"{num_samples!r}")
    if num_samples < 0:
        raise ValueError(f"'num_samples' must be non-negative, got "
                         f"{num_samples}")
    return int(num_samples)


def _inverse_cdf(probs: Tensor, points: Tensor) -> Tensor:
    cdf = probs.cumsum(-1)
    cdf = cdf / cdf[..., -1:]  # the last bin ends exactly at 1
    index = torch.searchsorted(cdf, points.contiguous(), right=True)
    return index.clamp_(max=probs.size(-1) - 1)


#: The resamplers by name (:obj:`--resampler` of the CLI, the
#: :obj:`resampler` argument of the trackers).
RESAMPLERS = {
    'multinomial': multinomial_resample,
    'systematic': systematic_resample,
    'stratified': stratified_resample,
    'residual': residual_resample,
}


def effective_sample_size(log_weights: Tensor) -> Tensor:
    r"""The effective sample size :math:`1 / \sum_k (w^{(k)})^2` of
    (unnormalized) log-weights :math:`(*, K)`: :math:`K` for equal weights,
    1 for a single surviving particle."""
    return 1.0 / torch.softmax(log_weights.double(), dim=-1).square().sum(-1)


def silverman_bandwidth(num_particles: int, state_dim: int) -> float:
    r"""Silverman's rule of thumb for a Gaussian kernel in :math:`d`
    dimensions, :math:`h = (4 / (K (d + 2)))^{1 / (d + 4)}`, the scale of
    regularized resampling's jitter relative to the particle spread."""
    return (4.0 / (num_particles * (state_dim + 2)))**(1.0 / (state_dim + 4))
