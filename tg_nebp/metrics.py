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

from tg_nebp.models.layout import wrap_angle
from tg_nebp.utils import (rounding_tolerance, symmetric_psd_defects,
                           symmetrize)

__all__ = [
    'position_errors',
    'angle_errors',
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


def angle_errors(est: Tensor, truth: Tensor) -> Tensor:
    r"""The errors :math:`|\hat{\theta} - \theta|` :math:`(*)` of
    angles (a heading), the difference wrapped to :math:`(-\pi, \pi]`
    first, in float64: an estimate just across the cut at :math:`\pm \pi`
    from the truth is off by its true small angle, not by a turn."""
    _check_positions(est, truth)
    return wrap_angle((est - truth).double()).abs()


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
    counts as singular, and so does a covariance whose eigenvalues are all
    subnormal in its dtype (zero up to rounding)."""
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
    # a covariance whose largest eigenvalue is subnormal in its own dtype
    # is zero up to rounding (a float32 cloud collapsed onto one point):
    # singular, whatever the signs of its rounding noise
    tiny = torch.finfo(pos_cov.dtype).tiny if pos_cov.is_floating_point() \
        else 0.0
    subnormal = eig[..., -1].abs() < tiny
    value = torch.where(subnormal, fallback, value)
    indefinite = (eig[..., 0] < -1e-6 * eig[..., -1].abs()) & ~subnormal
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


# gaussian_outage's quadrature: Gauss-Legendre nodes per integral of its
# recursion, and the end of each integral's window in widths of its peak
# (the integrand has fallen by exp(-10^2 / 2) = 2e-22 there); their
# accuracy is tested against mpmath
_OUTAGE_NODES = 32
_OUTAGE_WINDOW = 10.0
# elements of the quadrature's largest temporary per block (its memory)
_OUTAGE_BLOCK = 1 << 18
# radii, in standard deviations of the largest axis, beyond which the
# outage underflows float64 anyway (exp(-40^2 / 2) is 0): keeps inf out
_OUTAGE_RADIUS = 40.0
# eigenvalues up to this fraction of the largest are zero: dropping one
# changes the outage by about its square root, and keeping a smaller one
# would overflow its inverse in the quadrature
_OUTAGE_ZERO = 1e-100


def gaussian_outage(cov: Tensor, thresholds: Sequence[float]) -> Tensor:
    r"""The outage :math:`\mathbb{P}(\|\mathbf{e}\| > r)` :math:`(*, R)` of
    a zero-mean Gaussian error :math:`\mathbf{e} \sim \mathcal{N}(
    \mathbf{0}, \boldsymbol{\Sigma})` for positive semi-definite
    covariances :math:`(*, D, D)`, :math:`D \leq 3`, and :math:`R`
    thresholds :math:`r \geq 0`: the outage of an efficient estimator whose
    error covariance is a bound's.

    In the eigenbasis :math:`\|\mathbf{e}\|^2 = \sum_k \lambda_k X_k^2`
    with :math:`X_k` independent standard normal and :math:`\lambda_1 \geq
    \dots \geq \lambda_D > 0` (zero eigenvalues drop out; none left is
    outage 0). Conditioning on the component of the smallest variance,
    with :math:`a = r / \sqrt{\lambda_D}`, :math:`\phi` the standard
    normal density and :math:`x = a \sin t` in :math:`\int_0^a \dots
    \mathrm{d}x` (which removes the square-root kink at :math:`x = a`),

    .. math::
        P_D(r) = \operatorname{erfc}\Big(\frac{a}{\sqrt{2}}\Big) +
        2 \int_0^{\pi / 2} \phi(a \sin t) \, a \cos t \;
        P_{D-1}(r \cos t) \, \mathrm{d}t, \qquad
        P_1(r) = \operatorname{erfc}\Big(\frac{r}{\sqrt{2 \lambda_1}}
        \Big)

    with :math:`P_{D-1}` the outage of :math:`\lambda_1, \dots,
    \lambda_{D-1}`. Up to smooth factors the integrand is
    :math:`\exp(-\frac{r^2}{2 \lambda_1} - c \sin^2 t)`, :math:`c =
    \frac{r^2}{2} (\frac{1}{\lambda_D} - \frac{1}{\lambda_1})`: a peak at
    :math:`t = 0` of width :math:`w = 1 / \sqrt{2 c} \geq 1 / a` in
    :math:`\sin t`, however elongated the covariance. Each integral is
    Gauss-Legendre with 32 nodes over :math:`\sin t \leq \min(1, 10 w)`
    (beyond, the integrand is below :math:`10^{-21}` of its peak), nested
    for :math:`D = 3`; :math:`\exp(-r^2 / (2 \lambda_1))` is taken out of
    every term (:math:`\operatorname{erfcx}`) and put back last, so that
    nothing underflows before the outage itself does.

    Against mpmath at 30 digits (an independent formula) it is within
    :math:`10^{-13}` relative for exact eigenvalues, with condition
    numbers up to :math:`10^{16}` and outages down to :math:`10^{-300}`;
    a rotated covariance adds the rounding of its eigenvalues (about
    :math:`10^{-16}` of the largest), which moves the outage by up to
    about :math:`10^{-16} \sqrt{\lambda_1 / \lambda_D}` (:math:`5 \cdot
    10^{-11}` at condition number :math:`10^{12}`). It costs 32 (2-D) and
    :math:`32^2` (3-D) evaluations of erfcx per covariance and threshold,
    in float64 whatever the input's type: :math:`10^4` covariances and 3
    thresholds take about 0.03 s (2-D) and 0.5 to 0.8 s (3-D) on one CPU
    core.

    :math:`r = 0` has outage 1 (0 for a zero covariance), :math:`r =
    \infty` outage 0. A NaN entry makes that covariance's outages NaN; an
    infinite variance (:math:`+\infty` on the diagonal, the limit of an
    ever less informative estimate) makes them 1 at every finite
    threshold. A non-symmetric covariance, a clearly indefinite one (an
    eigenvalue below zero), each beyond the rounding of its dtype relative
    to its largest entry (:func:`~tg_nebp.utils.rounding_tolerance`: a
    smaller negative eigenvalue is rounding and counts as zero) and any
    other infinite entry are a :class:`ValueError` that
    names the first such covariance; within the tolerance, the outage is
    that of the mean of both triangles."""
    if not isinstance(cov, Tensor) or cov.is_complex() or \
            cov.dtype == torch.bool:
        raise TypeError(f"'cov' must be a real tensor, got "
                        f"{_describe(cov)}")
    if cov.dim() < 2 or cov.size(-1) != cov.size(-2) or not 1 <= cov.size(
            -1) <= 3:
        raise ValueError(f"'cov' must hold D x D covariances with D in 1, "
                         f"2, 3, got shape {list(cov.shape)}")
    radii = _outage_thresholds(thresholds, cov.device)
    batch, dim = cov.shape[:-2], cov.size(-1)
    tolerance = rounding_tolerance(
        cov.dtype if cov.is_floating_point() else torch.float64)
    flat = cov.reshape(-1, dim, dim).double()
    unknown = torch.isnan(flat).flatten(1).any(1)
    diagonal = flat.diagonal(dim1=-2, dim2=-1)
    unbounded = ~unknown & (diagonal == math.inf).any(1) & \
        ~(diagonal == -math.inf).any(1)
    _refuse_first(~unknown & ~unbounded & torch.isinf(flat).flatten(1).any(
        1), batch, 'has a -inf variance, or an infinite covariance of '
        'finite variances')
    # their outage is known: a zero matrix stands in for them
    flat = flat.masked_fill((unknown | unbounded).view(-1, 1, 1), 0)
    asymmetric, indefinite, _ = symmetric_psd_defects(flat, tolerance)
    _refuse_first(asymmetric, batch, f'is not symmetric (beyond '
                  f'{tolerance:.1e} of its largest entry)')
    _refuse_first(indefinite, batch, f'is indefinite (an eigenvalue below '
                  f'-{tolerance:.1e} of its largest entry)')
    # the mean of both triangles, not the one eigvalsh reads
    eigvals = torch.linalg.eigvalsh(symmetrize(flat)).flip(-1)
    out = _centered_outage(eigvals, radii)
    out[unknown] = math.nan
    out[unbounded] = (radii < math.inf).double()
    return out.view(batch + radii.shape)


def _describe(value) -> str:
    if isinstance(value, Tensor):
        return f'a {value.dtype} tensor'
    return type(value).__name__


def _outage_thresholds(thresholds, device) -> Tensor:
    # the thresholds [R] of gaussian_outage, in float64
    if isinstance(thresholds, Tensor):
        real = not (thresholds.is_complex() or thresholds.dtype == torch.bool)
    elif isinstance(thresholds, (str, bytes)):
        real = False
    else:
        try:
            real = np.asarray(thresholds).dtype.kind in 'iuf'
        except ValueError:  # ragged
            real = False
    if not real:
        raise TypeError(f"'thresholds' must be a sequence of real numbers, "
                        f"got {thresholds!r:.60}")
    radii = torch.as_tensor(thresholds, dtype=torch.float64,
                            device=device).reshape(-1)
    if not bool((radii >= 0).all()):  # also catches NaN
        raise ValueError(f"'thresholds' must be non-negative numbers, got "
                         f"{radii.tolist()}")
    return radii


def _refuse_first(bad: Tensor, batch: torch.Size, problem: str) -> None:
    # a ValueError naming the first bad covariance [M] of a batch
    if bool(bad.any()):
        index = np.unravel_index(int(bad.nonzero()[0, 0]), tuple(batch))
        where = f"[{', '.join(str(int(i)) for i in index)}]" if index else ''
        raise ValueError(f"'cov{where}' {problem}")


def _centered_outage(eigvals: Tensor, radii: Tensor) -> Tensor:
    # the outage [M, R] of eigenvalues [M, D] in descending order, by rank
    # (a zero covariance, rank 0, keeps 0)
    out = eigvals.new_zeros(eigvals.size(0), radii.numel())
    largest = eigvals[:, 0]
    ratios = eigvals / torch.where(largest > 0, largest, 1).unsqueeze(-1)
    rank = (ratios > _OUTAGE_ZERO).sum(-1)
    nodes, weights = np.polynomial.legendre.leggauss(_OUTAGE_NODES)
    nodes = torch.as_tensor(0.5 * (nodes + 1), device=eigvals.device)
    weights = torch.as_tensor(0.5 * weights, device=eigvals.device)
    for k in range(1, eigvals.size(-1) + 1):
        rows = (rank == k).nonzero().squeeze(-1)
        size = max(1, _OUTAGE_BLOCK // max(
            1, radii.numel() * _OUTAGE_NODES**(k - 1)))
        for block in rows.split(size):
            # radii in standard deviations of the largest axis
            rho = (radii / largest[block].sqrt().unsqueeze(-1)).clamp(
                max=_OUTAGE_RADIUS)
            scaled = _scaled_outage(rho, ratios[block, :k].unsqueeze(1),
                                    nodes, weights)
            out[block] = (scaled.log() - 0.5 * rho.square()).exp()
    return out


def _scaled_outage(rho: Tensor, ratios: Tensor, nodes: Tensor,
                   weights: Tensor) -> Tensor:
    # exp(rho^2 / 2) P(sum_k ratios_k X_k^2 > rho^2) for ratios [..., k]
    # in descending order from 1, broadcast with rho [...]: gaussian_outage's
    # recursion with exp(-rho^2 / 2) taken out of every term
    if ratios.size(-1) == 1:
        return torch.special.erfcx(rho * math.sqrt(0.5))
    smallest = ratios[..., -1]
    gap = 1 / smallest - 1  # >= 0
    a = rho / smallest.sqrt()
    c = 0.5 * rho.square() * gap
    # the peak's window in sin t; 1 / 0 = inf (rho = 0, or the remaining
    # eigenvalues all equal) is the whole quarter circle
    end = torch.asin((_OUTAGE_WINDOW / (rho * gap.sqrt())).clamp(max=1))
    t = end.unsqueeze(-1) * nodes
    cos = t.cos()
    inner = _scaled_outage(rho.unsqueeze(-1) * cos,
                           ratios[..., :-1].unsqueeze(-2), nodes, weights)
    # sin^2 t from sin, not 1 - cos^2: c sin^2 t matters where t is tiny
    integrand = cos * torch.exp(-c.unsqueeze(-1) * t.sin().square()) * \
        inner
    integral = math.sqrt(2 / math.pi) * a * end * (integrand @ weights)
    return torch.special.erfcx(a * math.sqrt(0.5)) * torch.exp(-c) + integral
