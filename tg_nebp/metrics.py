r"""Accuracy and consistency metrics of position estimates, as in the
`"Neural Enhanced Belief Propagation for Cooperative Localization"
<https://arxiv.org/abs/2105.12903>`_ paper. Every function takes estimates
and truths of any leading shape :math:`(*, D)` (e.g. :math:`(N, T, 2)`;
positions of any dimension :math:`D`) and
an optional boolean :obj:`mask` :math:`(*)` selecting the entries to count
(e.g. the agents, not the anchors).

A diverged filter never reads as a good one: a NaN estimate, error or
covariance makes the result NaN (RMSE, outage, NEES, consistency), and an
empty selection is a :class:`ValueError`."""
import math
from typing import Optional, Sequence

import numpy as np
import torch
from scipy.stats import chi2
from torch import Tensor

__all__ = [
    'position_errors',
    'rmse',
    'rmse_from_errors',
    'outage_probability',
    'outage_from_errors',
    'nees',
    'consistency_curve',
    'gaussian_outage',
]


def _select(values: Tensor, mask: Optional[Tensor]) -> Tensor:
    if mask is None:
        return _non_empty(values.reshape(-1))
    if mask.shape != values.shape[:mask.dim()]:
        raise ValueError(f"'mask' of shape {list(mask.shape)} does not "
                         f"match the leading shape {list(values.shape)}")
    mask = mask.bool()
    if not bool(mask.any()):
        raise ValueError("'mask' selects no entry")
    return values[mask].reshape(-1)


def _non_empty(values: Tensor, name: str = 'errors') -> Tensor:
    if values.numel() == 0:
        raise ValueError(f"'{name}' is empty: a metric of no entry is "
                         f"undefined")
    return values


def position_errors(est_pos: Tensor, true_pos: Tensor) -> Tensor:
    r"""Euclidean errors :math:`\|\hat{\mathbf{p}} - \mathbf{p}\|`
    :math:`(*)`."""
    _check_positions(est_pos, true_pos)
    return torch.linalg.vector_norm((est_pos - true_pos).double(), dim=-1)


def _check_positions(est_pos: Tensor, true_pos: Tensor) -> None:
    for name, pos in (('est_pos', est_pos), ('true_pos', true_pos)):
        if not isinstance(pos, Tensor):
            raise TypeError(f"'{name}' must be a tensor, got "
                            f"{type(pos).__name__}")
    if est_pos.shape != true_pos.shape:
        raise ValueError(f"'est_pos' {list(est_pos.shape)} and 'true_pos' "
                         f"{list(true_pos.shape)} differ in shape")


def rmse(est_pos: Tensor, true_pos: Tensor,
         mask: Optional[Tensor] = None) -> float:
    r"""Root mean squared position error :math:`\sqrt{\mathbb{E}\|\hat{
    \mathbf{p}} - \mathbf{p}\|^2}` over the selected entries."""
    return rmse_from_errors(_select(position_errors(est_pos, true_pos), mask))


def rmse_from_errors(errors: Tensor) -> float:
    r"""RMSE of precomputed position errors :math:`(*)`."""
    return float(_non_empty(errors).double().square().mean().sqrt())


def outage_probability(est_pos: Tensor, true_pos: Tensor,
                       thresholds: Sequence[float],
                       mask: Optional[Tensor] = None) -> Tensor:
    r"""Outage probability :math:`P_{\mathrm{out}}(e_{\mathrm{th}}) =
    \mathbb{P}(\|\hat{\mathbf{p}} - \mathbf{p}\| > e_{\mathrm{th}})` for
    every threshold, as a tensor of the thresholds' shape."""
    return outage_from_errors(
        _select(position_errors(est_pos, true_pos), mask), thresholds)


def outage_from_errors(errors: Tensor, thresholds: Sequence[float]) -> Tensor:
    r"""Outage probabilities of precomputed position errors :math:`(*)`;
    NaN if any error is NaN (a comparison with NaN would count it as no
    outage)."""
    errors = _non_empty(errors.reshape(-1).double())
    thresholds = torch.as_tensor(thresholds, dtype=torch.float64,
                                 device=errors.device)
    if not bool((thresholds >= 0).all()):  # also catches NaN
        raise ValueError(f"'thresholds' must be non-negative numbers, got "
                         f"{thresholds.tolist()}")
    outage = (errors.unsqueeze(-1) > thresholds.reshape(-1)).double().mean(0)
    if bool(torch.isnan(errors).any()):
        outage = torch.full_like(outage, float('nan'))
    return outage.view(thresholds.shape)


def nees(est_pos: Tensor, pos_cov: Tensor, true_pos: Tensor) -> Tensor:
    r"""Position normalized estimation error squared
    :math:`e = (\hat{\mathbf{p}} - \mathbf{p})^\top
    \hat{\boldsymbol{\Sigma}}_{\mathbf{p}}^{-1} (\hat{\mathbf{p}} -
    \mathbf{p})` for covariances :math:`(*, D, D)`. A singular covariance
    gives :math:`+\infty` (or :math:`0` for a zero error); a NaN estimate,
    truth or covariance, or a clearly indefinite covariance, gives NaN; a
    negative value from rounding of a numerically singular covariance
    counts as singular."""
    _check_positions(est_pos, true_pos)
    dim = est_pos.size(-1)
    if pos_cov.shape != est_pos.shape + (dim, ):
        raise ValueError(f"'pos_cov' must have shape "
                         f"{list(est_pos.shape) + [dim]}, got "
                         f"{list(pos_cov.shape)}")
    err = (est_pos - true_pos).double().unsqueeze(-1)
    cov = pos_cov.double()
    solution, info = torch.linalg.solve_ex(cov, err)
    value = (err * solution).sum((-1, -2))
    singular = (info != 0) | ~torch.isfinite(value)
    fallback = torch.where(err.abs().sum((-1, -2)) > 0, float('inf'), 0.0)
    # a negative value from a numerically singular PSD covariance (a
    # collapsed particle cloud in float32) is rounding: singular as well
    value = torch.where(singular | (value < 0), fallback, value)
    nan_cov = torch.isnan(cov).flatten(-2).any(-1)
    eig = torch.linalg.eigvalsh(torch.where(
        nan_cov.unsqueeze(-1).unsqueeze(-1), torch.eye(dim, dtype=cov.dtype,
                                                       device=cov.device),
        cov))
    # NaN in, or a covariance that is no covariance (clearly indefinite):
    # NaN out
    indefinite = eig[..., 0] < -1e-6 * eig[..., -1].abs()
    unknown = torch.isnan(err).any(-1).any(-1) | nan_cov | indefinite
    return value.masked_fill(unknown, float('nan'))


def consistency_curve(nees_values: Tensor, confidence: Sequence[float],
                      dof: int = 2, mask: Optional[Tensor] = None) -> Tensor:
    r"""Two-sided chi-square consistency test: for each confidence level
    :math:`1 - \alpha`, the fraction of NEES values in :math:`[r_1, r_2]`
    with :math:`F_{\chi^2_d}(r_1) = \alpha / 2` and
    :math:`F_{\chi^2_d}(r_2) = 1 - \alpha / 2`, i.e.
    :math:`\mathbb{P}(\text{accept } H_0)`. A consistent estimator gives the
    confidence level itself."""
    values = _select(nees_values, mask).double()
    confidence = torch.as_tensor(confidence, dtype=torch.float64)
    if not bool(((confidence > 0) & (confidence < 1)).all()):  # NaN too
        raise ValueError("'confidence' levels must lie in (0, 1)")
    if isinstance(dof, bool) or not isinstance(dof, int) or dof < 1:
        raise ValueError(f"'dof' must be a positive integer, got {dof!r}")
    alpha = (1 - confidence.reshape(-1)).numpy()
    low = torch.as_tensor(chi2.ppf(alpha / 2, dof), device=values.device)
    high = torch.as_tensor(chi2.ppf(1 - alpha / 2, dof), device=values.device)
    inside = (values.unsqueeze(-1) >= low) & (values.unsqueeze(-1) <= high)
    accept = inside.double().mean(0)
    if bool(torch.isnan(values).any()):  # NaN would count as rejected
        accept = torch.full_like(accept, float('nan'))
    return accept.view(confidence.shape).cpu()


# quadrature of the direction average in gaussian_outage: midpoint nodes
# of a quarter circle (2-D) and of an octant's azimuth, Gauss-Legendre
# nodes of its cos(polar angle) (3-D); their accuracy is tested
OUTAGE_NODES_2D = 256
OUTAGE_NODES_3D = (48, 64)
# covariances per block of the quadrature (its memory)
_OUTAGE_BLOCK = 4096


def _directions(dim: int, dtype, device):
    # unit vectors u and weights w, sum w = 1, of the average over the
    # sphere of a function even in every coordinate (one quadrant or octant
    # stands for all)
    if dim == 2:
        angle = (torch.arange(OUTAGE_NODES_2D, dtype=torch.float64) +
                 0.5) * (math.pi / 2 / OUTAGE_NODES_2D)
        units = torch.stack([angle.cos(), angle.sin()], -1)
        weights = torch.full((OUTAGE_NODES_2D, ), 1 / OUTAGE_NODES_2D,
                             dtype=torch.float64)
    else:
        polar, azimuth = OUTAGE_NODES_3D
        nodes, gauss = np.polynomial.legendre.leggauss(polar)
        cosine = torch.from_numpy(0.5 * (nodes + 1))  # on [0, 1]
        angle = (torch.arange(azimuth, dtype=torch.float64) + 0.5) * (
            math.pi / 2 / azimuth)
        sine = (1 - cosine.square()).sqrt().view(-1, 1)
        units = torch.stack([(sine * angle.cos()).flatten(),
                             (sine * angle.sin()).flatten(),
                             cosine.view(-1, 1).expand(-1, azimuth).flatten()],
                            -1)
        weights = (torch.from_numpy(0.5 * gauss).view(-1, 1) / azimuth
                   ).expand(-1, azimuth).flatten()
    return units.to(dtype=dtype, device=device), weights.to(dtype=dtype,
                                                            device=device)


def gaussian_outage(cov: Tensor, thresholds: Sequence[float]) -> Tensor:
    r"""The outage :math:`\mathbb{P}(\|\mathbf{e}\| > e_{\mathrm{th}})`
    :math:`(*, R)` of a zero-mean Gaussian error :math:`\mathbf{e} \sim
    \mathcal{N}(\mathbf{0}, \boldsymbol{\Sigma})` for positive definite
    covariances :math:`(*, D, D)`, :math:`D \leq 3`, and :math:`R`
    thresholds: the outage of an efficient estimator whose error
    covariance is a bound's.

    In polar coordinates the radial integral is an incomplete gamma
    function, which leaves an average over directions :math:`\mathbf{u}`
    of the unit sphere (in the eigenbasis, eigenvalues
    :math:`\lambda_k`, :math:`a(\mathbf{u}) = \sum_k u_k^2 / \lambda_k`):

    .. math::
        \mathbb{P}(\|\mathbf{e}\| > r) = \mathbb{E}_{\mathbf{u}} \left[
        \frac{Q\big(\frac{D}{2}, \frac{r^2 a(\mathbf{u})}{2}\big)}
        {\sqrt{\textstyle\prod_k \lambda_k} \; a(\mathbf{u})^{D/2}}
        \right]

    with :math:`Q` the regularized upper incomplete gamma function. For
    :math:`D = 1` it is :math:`\operatorname{erfc}(r / \sqrt{2
    \lambda})`; for :math:`D = 2` the direction average is the midpoint
    rule over a quarter circle (:obj:`OUTAGE_NODES_2D` nodes, spectrally
    accurate for this smooth periodic integrand); for :math:`D = 3`
    Gauss-Legendre in the cosine of the polar angle times the midpoint
    rule in the azimuth over an octant (:obj:`OUTAGE_NODES_3D`). Computed
    in float64: within :math:`10^{-9}` of the exact value for condition
    numbers up to :math:`10^3` (tested against adaptive quadrature)."""
    if cov.dim() < 2 or cov.size(-1) != cov.size(-2) or not 1 <= cov.size(
            -1) <= 3:
        raise ValueError(f"'cov' must hold D x D covariances with D in 1, "
                         f"2, 3, got shape {list(cov.shape)}")
    radii = torch.as_tensor(thresholds, dtype=torch.float64,
                            device=cov.device).reshape(-1)
    if not bool((radii >= 0).all()):
        raise ValueError(f"'thresholds' must be non-negative numbers, got "
                         f"{radii.tolist()}")
    dim = cov.size(-1)
    eigvals = torch.linalg.eigvalsh(cov.double().reshape(-1, dim, dim))
    if not bool((eigvals[:, 0] > 0).all()):
        raise ValueError("'cov' must be positive definite")
    if dim == 1:
        out = torch.special.erfc(radii / (2 * eigvals).sqrt())
        return out.view(cov.shape[:-2] + radii.shape)
    units, weights = _directions(dim, torch.float64, cov.device)
    parts = []
    for block in eigvals.split(_OUTAGE_BLOCK):
        # a [B, U]: the quadratic form of every direction, in the eigenbasis
        a = (units.square() / block.unsqueeze(1)).sum(-1)
        scale = block.prod(-1).sqrt().unsqueeze(1) * a.pow(dim / 2)
        tail = torch.special.gammaincc(
            torch.full_like(a, dim / 2).unsqueeze(-1),
            0.5 * a.unsqueeze(-1) * radii.square())
        parts.append(torch.einsum('bur,u->br', tail / scale.unsqueeze(-1),
                                  weights))
    return torch.cat(parts).view(cov.shape[:-2] + radii.shape)
