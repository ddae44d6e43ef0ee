r"""Small tensor helpers shared by the layers and the trackers."""
import torch
from torch import Tensor
from torch_geometric import EdgeIndex, Index

__all__ = ['weighted_moments', 'plain_tensor']


def weighted_moments(particles: Tensor, log_weights: Tensor):
    r"""Weighted mean :math:`\hat{\mathbf{x}}_i = \sum_k w_i^{(k)}
    \mathbf{x}_i^{(k)}` and covariance :math:`\sum_k w_i^{(k)}
    (\mathbf{x}_i^{(k)} - \hat{\mathbf{x}}_i)(\mathbf{x}_i^{(k)} -
    \hat{\mathbf{x}}_i)^\top` of particles :math:`(N, K, D)` with normalized
    log-weights :math:`(N, K)`."""
    weights = log_weights.exp()
    mean = torch.einsum('nk,nkd->nd', weights, particles)
    centered = particles - mean.unsqueeze(1)
    cov = (centered * weights.unsqueeze(-1)).transpose(1, 2) @ centered
    return mean, cov


def plain_tensor(tensor: Tensor) -> Tensor:
    r""":obj:`tensor` as a plain :class:`torch.Tensor` (zero-copy): PyG's
    :class:`~torch_geometric.EdgeIndex` and :class:`~torch_geometric.Index`
    are subclasses that compiled regions should not see (their
    :obj:`as_subclass` keeps the subclass); plain tensors pass through
    untouched, which keeps :func:`torch.compile` free of graph breaks."""
    if isinstance(tensor, (EdgeIndex, Index)):
        return tensor.as_tensor()
    return tensor
