import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from tg_nebp import metrics


def random_problem(shape, seed):
    g = torch.Generator().manual_seed(seed)
    est = torch.randn(shape + (2, ), generator=g, dtype=torch.float64)
    true = torch.randn(shape + (2, ), generator=g, dtype=torch.float64)
    return est, true


def test_position_errors_against_loop():
    est, true = random_problem((4, 6), 0)
    out = metrics.position_errors(est, true)
    assert out.shape == (4, 6)
    for i in range(4):
        for t in range(6):
            d = est[i, t].numpy() - true[i, t].numpy()
            assert math.isclose(float(out[i, t]), math.sqrt(d @ d),
                                rel_tol=1e-12)
    with pytest.raises(ValueError):
        metrics.position_errors(est, true[:, :3])


def test_rmse_against_numpy_loop():
    est, true = random_problem((5, 7), 1)
    total, n = 0.0, 0
    for i in range(5):
        for t in range(7):
            d = est[i, t].numpy() - true[i, t].numpy()
            total += d @ d
            n += 1
    assert math.isclose(metrics.rmse(est, true), math.sqrt(total / n),
                        rel_tol=1e-12)


def test_rmse_mask():
    est, true = random_problem((5, 7), 2)
    mask = torch.tensor([True, False, True, True, False])
    total, n = 0.0, 0
    for i in range(5):
        if not mask[i]:
            continue
        for t in range(7):
            d = est[i, t].numpy() - true[i, t].numpy()
            total += d @ d
            n += 1
    assert math.isclose(metrics.rmse(est, true, mask=mask),
                        math.sqrt(total / n), rel_tol=1e-12)
    # a mask of the full leading shape works as well
    full = mask.view(5, 1).expand(5, 7)
    assert math.isclose(metrics.rmse(est, true, mask=full),
                        math.sqrt(total / n), rel_tol=1e-12)
    # masked-out entries do not matter, however large
    est2 = est.clone()
    est2[~mask] = 1e6
    assert math.isclose(metrics.rmse(est2, true, mask=mask),
                        math.sqrt(total / n), rel_tol=1e-12)
    with pytest.raises(ValueError, match='mask'):
        metrics.rmse(est, true, mask=torch.ones(4, dtype=torch.bool))


def test_outage_against_numpy_loop():
    est, true = random_problem((6, 9), 3)
    mask = torch.arange(6) % 3 != 0
    thresholds = [0.25, 0.5, 1.0, 2.0, 4.0]
    out = metrics.outage_probability(est, true, thresholds, mask=mask)
    assert out.shape == (5, )
    for q, th in enumerate(thresholds):
        exceed, n = 0, 0
        for i in range(6):
            if not mask[i]:
                continue
            for t in range(9):
                e = np.linalg.norm(est[i, t].numpy() - true[i, t].numpy())
                exceed += e > th
                n += 1
        assert math.isclose(float(out[q]), exceed / n, rel_tol=1e-12)
    # unmasked, 2-D thresholds keep their shape
    out = metrics.outage_probability(est, true, [[0.5, 1.0], [2.0, 3.0]])
    assert out.shape == (2, 2)
    errors = np.linalg.norm((est - true).numpy(), axis=-1)
    np.testing.assert_allclose(
        out.numpy(), [[(errors > 0.5).mean(), (errors > 1.0).mean()],
                      [(errors > 2.0).mean(), (errors > 3.0).mean()]])


def test_outage_is_strict_and_monotone():
    est = torch.tensor([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0]])
    true = torch.zeros(3, 2)
    out = metrics.outage_probability(est, true, [0.0, 1.0, 2.0, 3.0])
    np.testing.assert_allclose(out.numpy(), [2 / 3, 1 / 3, 1 / 3, 0.0])


def random_spd(n, seed):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(n, 2, 2, generator=g, dtype=torch.float64)
    return a @ a.transpose(-1, -2) + 0.1 * torch.eye(2, dtype=torch.float64)


def test_nees_against_numpy_inv():
    est, true = random_problem((3, 8), 4)
    cov = random_spd(24, 5).view(3, 8, 2, 2)
    out = metrics.nees(est, cov, true)
    assert out.shape == (3, 8)
    for i in range(3):
        for t in range(8):
            e = est[i, t].numpy() - true[i, t].numpy()
            ref = e @ np.linalg.inv(cov[i, t].numpy()) @ e
            assert math.isclose(float(out[i, t]), ref, rel_tol=1e-9)


def test_nees_singular_covariance_gives_inf_not_nan():
    est = torch.tensor([[1.0, 0.0], [0.5, 0.5], [0.0, 0.0], [1.0, 2.0]])
    true = torch.zeros(4, 2)
    cov = torch.stack([
        torch.zeros(2, 2),                        # all zero
        torch.tensor([[1.0, 1.0], [1.0, 1.0]]),   # rank one
        torch.zeros(2, 2),                        # zero error
        torch.eye(2),                             # regular
    ])
    out = metrics.nees(est, cov, true)
    assert not bool(torch.isnan(out).any())
    assert math.isinf(float(out[0])) and float(out[0]) > 0
    assert math.isinf(float(out[1])) and float(out[1]) > 0
    assert float(out[2]) == 0.0
    assert math.isclose(float(out[3]), 5.0, rel_tol=1e-12)
    # inf NEES is rejected by the consistency test, never accepted
    curve = metrics.consistency_curve(out, [0.5, 0.99])
    assert bool((curve <= 0.5).all())


def consistency_reference(values, confidence, dof):
    out = []
    for c in confidence:
        alpha = 1 - c
        lo, hi = chi2.ppf(alpha / 2, dof), chi2.ppf(1 - alpha / 2, dof)
        out.append(sum(lo <= v <= hi for v in values) / len(values))
    return np.array(out)


@pytest.mark.parametrize('dof', [2, 4])
def test_consistency_curve_against_scipy_loop(dof):
    g = torch.Generator().manual_seed(6)
    values = 3 * torch.rand(500, generator=g, dtype=torch.float64) ** 2
    confidence = [0.1, 0.5, 0.9, 0.95, 0.99]
    out = metrics.consistency_curve(values, confidence, dof=dof)
    np.testing.assert_allclose(
        out.numpy(), consistency_reference(values.numpy(), confidence, dof),
        rtol=0, atol=1e-12)


def test_consistency_curve_mask():
    g = torch.Generator().manual_seed(7)
    values = 4 * torch.rand(10, 20, generator=g, dtype=torch.float64)
    mask = torch.arange(10) < 4
    values[~mask] = 1e9  # would be rejected if counted
    confidence = [0.5, 0.95]
    out = metrics.consistency_curve(values, confidence, mask=mask)
    ref = consistency_reference(values[mask].reshape(-1).numpy(),
                                confidence, 2)
    np.testing.assert_allclose(out.numpy(), ref, atol=1e-12)


@pytest.mark.parametrize('bad', [0.0, 1.0, -0.5, 1.5])
def test_consistency_curve_bad_confidence(bad):
    with pytest.raises(ValueError, match='confidence'):
        metrics.consistency_curve(torch.ones(3), [0.5, bad])


def test_consistent_gaussian_estimator_accepts_at_confidence_level():
    n = 100_000
    g = torch.Generator().manual_seed(8)
    # a different true covariance per sample
    cov = random_spd(n, 9)
    chol = torch.linalg.cholesky(cov)
    true = 10 * torch.randn(n, 2, generator=g, dtype=torch.float64)
    noise = (chol @ torch.randn(n, 2, 1, generator=g,
                                dtype=torch.float64)).squeeze(-1)
    est = true + noise
    values = metrics.nees(est, cov, true)
    confidence = [0.5, 0.9, 0.95, 0.99]
    curve = metrics.consistency_curve(values, confidence).numpy()
    for c, p in zip(confidence, curve):
        assert abs(p - c) < 5 * math.sqrt(c * (1 - c) / n)
    # an overconfident estimator (covariance 4x too small) fails
    bad = metrics.consistency_curve(metrics.nees(est, cov / 4, true),
                                    confidence).numpy()
    assert np.all(bad < np.array(confidence) - 0.1)


# --- a diverged filter never reads as a good one ---------------------------

def test_nan_estimates_give_nan_not_perfect_scores():
    est, true = random_problem((5, 3), 7)
    est[2, 1] = float('nan')  # one diverged estimate
    cov = torch.eye(2, dtype=torch.float64).expand(5, 3, 2, 2).clone()
    assert math.isnan(metrics.rmse(est, true))
    assert torch.isnan(metrics.outage_probability(est, true,
                                                  [0.5, 1.0])).all()
    values = metrics.nees(est, cov, true)
    assert torch.isnan(values[2, 1])
    assert torch.isfinite(values[0]).all()  # the others are unaffected
    assert torch.isnan(metrics.consistency_curve(values, [0.95])).all()
    # all-NaN estimates: the "outage 0, NEES 0"
    nan_est = torch.full_like(est, float('nan'))
    assert torch.isnan(metrics.outage_probability(nan_est, true, [1.0])).all()
    assert torch.isnan(metrics.nees(nan_est, cov, true)).all()


def test_nan_or_negative_definite_covariance_gives_nan_nees():
    est, true = random_problem((4, ), 8)
    cov = torch.eye(2, dtype=torch.float64).expand(4, 2, 2).clone()
    cov[1, 0, 0] = float('nan')
    cov[2] = -cov[2]
    values = metrics.nees(est, cov, true)
    assert torch.isnan(values[[1, 2]]).all()
    assert torch.isfinite(values[[0, 3]]).all()


def test_rounding_of_a_singular_covariance_is_singular_not_nan():
    # a float32 cloud collapsed onto a line: eigenvalues -2.6e-9 and 0.33,
    # and a NEES of -1.4e8 from rounding (seen in tg-nebp evaluate)
    angle = torch.tensor(1.03, dtype=torch.float64)
    rotation = torch.stack([torch.stack([angle.cos(), -angle.sin()]),
                            torch.stack([angle.sin(), angle.cos()])])
    cov = rotation @ torch.diag(torch.tensor(
        [-2.6e-9, 0.33], dtype=torch.float64)) @ rotation.t()
    err = rotation[:, 0] * 1.5  # along the collapsed direction
    value = metrics.nees(err, cov, torch.zeros(2, dtype=torch.float64))
    assert value == float('inf')


def test_masked_out_nan_does_not_count():
    est, true = random_problem((3, ), 9)
    est[0] = float('nan')
    mask = torch.tensor([False, True, True])
    assert math.isfinite(metrics.rmse(est, true, mask=mask))
    assert torch.isfinite(metrics.outage_probability(est, true, [1.0],
                                                     mask=mask)).all()


def test_empty_selection_is_an_error():
    est, true = random_problem((3, 2), 10)
    nothing = torch.zeros(3, 2, dtype=torch.bool)
    cov = torch.eye(2, dtype=torch.float64).expand(3, 2, 2, 2)
    for call in (lambda: metrics.rmse(est, true, mask=nothing),
                 lambda: metrics.outage_probability(est, true, [1.0],
                                                    mask=nothing),
                 lambda: metrics.consistency_curve(
                     metrics.nees(est, cov, true), [0.95], mask=nothing)):
        with pytest.raises(ValueError, match="'mask' selects no entry"):
            call()
    for call in (lambda: metrics.rmse_from_errors(torch.empty(0)),
                 lambda: metrics.outage_from_errors(torch.empty(0), [1.0]),
                 lambda: metrics.consistency_curve(torch.empty(0), [0.95])):
        with pytest.raises(ValueError, match='empty'):
            call()


# -- the outage of a Gaussian error (the bound's efficient estimator) --------

@pytest.mark.parametrize('dim', [1, 2, 3])
def test_gaussian_outage_isotropic_is_chi_square(dim):
    from scipy.stats import chi2
    variance = 0.3
    cov = variance * torch.eye(dim, dtype=torch.float64).expand(2, -1, -1)
    thresholds = [0.1, 0.5, 1.0, 2.0]
    out = metrics.gaussian_outage(cov, thresholds)
    assert out.shape == (2, 4)
    expected = [chi2.sf(r**2 / variance, dim) for r in thresholds]
    np.testing.assert_allclose(out[0].numpy(), expected, rtol=1e-9,
                               atol=1e-15)


@pytest.mark.parametrize('eigenvalues', [(1.0, 0.1), (1.0, 0.001),
                                         (0.05, 0.02)])
def test_gaussian_outage_2d_against_adaptive_quadrature(eigenvalues):
    # P(l1 z1^2 + l2 z2^2 > r^2) = 1 - int phi(z1) (2 Phi(...) - 1) dz1,
    # scipy's adaptive quadrature; the covariance rotated
    from scipy import integrate, stats
    l1, l2 = eigenvalues
    rotation = torch.tensor([[0.6, -0.8], [0.8, 0.6]], dtype=torch.float64)
    cov = rotation @ torch.diag(torch.tensor(eigenvalues,
                                             dtype=torch.float64)) @ \
        rotation.t()
    for r in (0.1, 0.5, 1.0, 2.0):
        edge = r / l1**0.5
        inside = integrate.quad(
            lambda z: stats.norm.pdf(z) * (2 * stats.norm.cdf(
                np.sqrt(max(r * r - l1 * z * z, 0) / l2)) - 1), -edge, edge,
            epsabs=1e-14, epsrel=1e-12, limit=200)[0]
        got = float(metrics.gaussian_outage(cov, [r]))
        assert abs(got - (1 - inside)) < 1e-9


def test_gaussian_outage_3d_against_monte_carlo():
    g = torch.Generator().manual_seed(0)
    root = torch.randn(3, 3, generator=g, dtype=torch.float64)
    cov = root @ root.t() / 3 + 0.05 * torch.eye(3, dtype=torch.float64)
    count = 1_000_000
    errors = torch.randn(count, 3, generator=g, dtype=torch.float64) @ \
        torch.linalg.cholesky(cov).t()
    norms = errors.norm(dim=-1)
    for r in (0.3, 1.0, 2.0):
        p = float((norms > r).double().mean())
        got = float(metrics.gaussian_outage(cov, [r]))
        assert abs(got - p) < 5 * max(p * (1 - p), 1e-6)**0.5 / count**0.5


def test_gaussian_outage_refuses_what_it_cannot_do():
    with pytest.raises(ValueError, match='D in 1, 2, 3'):
        metrics.gaussian_outage(torch.eye(4), [1.0])
    with pytest.raises(ValueError, match='positive definite'):
        metrics.gaussian_outage(torch.zeros(2, 2), [1.0])
    with pytest.raises(ValueError, match='non-negative'):
        metrics.gaussian_outage(torch.eye(2), [-1.0])


def test_nees_of_three_dimensional_errors_has_three_degrees_of_freedom():
    # an efficient 3-D Gaussian estimator with the right covariance passes
    # the two-sided chi-square test with 3 degrees of freedom, not with 2
    g = torch.Generator().manual_seed(7)
    count = 20_000
    root = torch.randn(count, 3, 3, generator=g, dtype=torch.float64)
    cov = root @ root.transpose(1, 2) + 0.1 * torch.eye(3,
                                                        dtype=torch.float64)
    errors = (torch.linalg.cholesky(cov) @ torch.randn(
        count, 3, 1, generator=g, dtype=torch.float64)).squeeze(-1)
    truth = torch.zeros(count, 3, dtype=torch.float64)
    values = metrics.nees(errors, cov, truth)
    three = metrics.consistency_curve(values, [0.5, 0.95], dof=3)
    two = metrics.consistency_curve(values, [0.5, 0.95], dof=2)
    # binomial standard errors of fractions of 20,000: 0.0035 at the 0.5
    # level, 0.0015 at 0.95; the 2-dof test is off by 7 and 9 of them
    assert abs(float(three[0]) - 0.5) < 0.01
    assert abs(float(three[1]) - 0.95) < 0.005
    assert abs(float(two[0]) - 0.5) > 0.015
    assert abs(float(two[1]) - 0.95) > 0.008
