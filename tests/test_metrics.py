import math

import mpmath
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
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


def test_a_subnormal_covariance_is_singular_not_indefinite():
    # a float32 particle cloud collapsed onto one point (particle BP on
    # the wide-prior network): eigenvalues -1.2e-45 and 8.2e-45, rounding
    # noise of zero, made P(accept) NaN; a normal-sized indefinite
    # covariance of float32 stays NaN
    cov = torch.tensor([[[3.5e-45, 4.6e-45], [4.6e-45, 3.5e-45]],
                        [[1.0, 2.0], [2.0, 1.0]]], dtype=torch.float32)
    assert torch.linalg.eigvalsh(cov.double())[0, 0] < 0
    est = torch.tensor([[1.0, 0.0], [1.0, 0.0]])
    values = metrics.nees(est, cov, torch.zeros(2, 2))
    assert values[0] == float('inf') and torch.isnan(values[1])
    # whatever the error's direction, and zero for a zero error
    other = metrics.nees(torch.tensor([[0.0, 1.0], [0.0, 0.0]]),
                         cov[[0, 0]], torch.zeros(2, 2))
    assert other[0] == float('inf') and other[1] == 0


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

def _mp_splits(small, large, r):
    # dyadic angles from pi / 2 down to far below the scales of the peak at
    # 0 of the direction integrands below (tan theta ~ sqrt(small / large)
    # and the Gaussian width in sin theta), so that each piece is smooth on
    # its own scale for mpmath's quadrature
    scale = mpmath.sqrt(small / large)
    if r > 0 and small < large:
        scale = min(scale, 1 / (r * mpmath.sqrt(1 / small - 1 / large)))
    points = [mpmath.pi / 2]
    while points[-1] > scale / 100:
        points.append(points[-1] / 2)
    return [mpmath.mpf(0)] + points[::-1]


def _mp_dawson(y):
    # Dawson's F(y) = exp(-y^2) int_0^y exp(t^2) dt; for large y (where
    # mpmath's erfi is slow) its asymptotic series sum_k (2k - 1)!! /
    # (2 y^2)^k / (2 y), whose smallest term, about exp(-y^2), is far
    # below mpmath's precision
    if y < 12:
        return mpmath.sqrt(mpmath.pi) / 2 * mpmath.exp(-y * y) * \
            mpmath.erfi(y)
    term = total = 1 / (2 * y)
    k = 0
    while abs(term) > mpmath.eps * total:
        k += 1
        term *= (2 * k - 1) / (2 * y * y)
        total += term
    return total


def _mp_outage(eigenvalues, r):
    # P(sum_k l_k X_k^2 > r^2) at mpmath's precision, by formulas other
    # than gaussian_outage's (which conditions on the smallest variance):
    # in polar coordinates for two positive eigenvalues l1 >= l2,
    #   (2 / pi) int_0^{pi/2} exp(-r^2 a / 2) / (sqrt(l1 l2) a) dtheta,
    #   a = cos^2 theta / l1 + sin^2 theta / l2;
    # for three, l1 >= l2 >= l3, conditioning on X1 with the outage of the
    # other two in polar coordinates, whose integral over X1 is Dawson's F:
    #   erfc(r / sqrt(2 l1)) + exp(-r^2 / (2 l1)) 4 / pi^1.5 / sqrt(l2 l3)
    #   int_0^{pi/2} F(r sqrt(g / (2 l1))) / (sqrt(g) a) dtheta,
    #   a = cos^2 theta / l2 + sin^2 theta / l3, g = l1 a - 1 >= 0.
    # exp(-r^2 / (2 l1)) stays outside the integrals and the rest of the
    # factors inside, so that they are not small: mpmath's tolerance is
    # absolute
    lam = sorted((mpmath.mpf(v) for v in eigenvalues if v > 0),
                 reverse=True)
    r = mpmath.mpf(r)
    if not lam:
        return mpmath.mpf(0)
    if len(lam) == 1:
        return mpmath.erfc(r / mpmath.sqrt(2 * lam[0]))
    if len(lam) == 2:
        l1, l2 = lam
        scale = 2 / mpmath.pi / mpmath.sqrt(l1 * l2)

        def f(t):
            a = mpmath.cos(t)**2 / l1 + mpmath.sin(t)**2 / l2
            return scale * mpmath.exp(-r * r * (a - 1 / l1) / 2) / a
        return mpmath.exp(-r * r / (2 * l1)) * mpmath.quad(
            f, _mp_splits(l2, l1, r), method='gauss-legendre')
    l1, l2, l3 = lam
    scale = 4 / mpmath.pi**1.5 / mpmath.sqrt(l2 * l3)

    def f(t):
        a = mpmath.cos(t)**2 / l2 + mpmath.sin(t)**2 / l3
        g = l1 * a - 1
        if g == 0:  # the limit of F(y) / sqrt(g), F(y) ~ y
            return scale * r / mpmath.sqrt(2 * l1) / a
        return scale * _mp_dawson(r * mpmath.sqrt(g / (2 * l1))) / \
            mpmath.sqrt(g) / a
    return mpmath.erfc(r / mpmath.sqrt(2 * l1)) + mpmath.exp(
        -r * r / (2 * l1)) * mpmath.quad(f, _mp_splits(l3, l2, r),
                                         method='gauss-legendre')


def _rotation(dim, generator):
    q, _ = torch.linalg.qr(torch.randn(dim, dim, generator=generator,
                                       dtype=torch.float64))
    return q


@pytest.mark.parametrize('dim', [1, 2, 3])
def test_gaussian_outage_isotropic_is_chi_square(dim):
    variance = 0.3
    cov = variance * torch.eye(dim, dtype=torch.float64).expand(2, -1, -1)
    thresholds = [0.1, 0.5, 1.0, 2.0]
    out = metrics.gaussian_outage(cov, thresholds)
    assert out.shape == (2, 4)
    expected = [chi2.sf(r**2 / variance, dim) for r in thresholds]
    np.testing.assert_allclose(out[0].numpy(), expected, rtol=1e-9,
                               atol=1e-15)


def _diag(*values):
    return torch.diag(torch.tensor(values, dtype=torch.float64))


def test_gaussian_outage_closed_forms():
    radii = np.array([0.0, 0.05, 0.7, 1.3, 4.0, 12.0, 50.0])
    # isotropic: Rayleigh in 2-D, Maxwell in 3-D, far into the tail
    for s in (1e-3, 0.4, 30.0):
        x = radii / s
        rayleigh = np.exp(-x**2 / 2)
        maxwell = [math.erfc(v / math.sqrt(2)) + math.sqrt(2 / math.pi) *
                   v * math.exp(-v * v / 2) for v in x]
        for cov, expected in ((_diag(s * s, s * s), rayleigh),
                              (_diag(s * s, s * s, s * s), maxwell)):
            got = metrics.gaussian_outage(cov, radii)
            np.testing.assert_allclose(got.numpy(), expected, rtol=1e-12,
                                       atol=0)
    # rank one: the 1-D normal tail, however the axis lies
    variance = 2.5
    tail = [math.erfc(r / math.sqrt(2 * variance)) for r in radii]
    axis = torch.tensor([0.48, -0.6, 0.64], dtype=torch.float64)
    for cov in (_diag(variance, 0), _diag(variance, 0, 0),
                _diag(0, 0, variance), variance * torch.outer(axis, axis)):
        got = metrics.gaussian_outage(cov, radii)
        np.testing.assert_allclose(got.numpy(), tail, rtol=1e-12, atol=1e-15)
    # rank two in 3-D is the 2-D outage of its non-zero block
    np.testing.assert_allclose(
        metrics.gaussian_outage(_diag(2.0, 0.3, 0), radii).numpy(),
        metrics.gaussian_outage(_diag(2.0, 0.3), radii).numpy(), rtol=1e-13,
        atol=0)
    # a zero covariance never errs; any other errs at r = 0
    for dim in (1, 2, 3):
        assert metrics.gaussian_outage(torch.zeros(dim, dim),
                                       radii).abs().max() == 0
        assert float(metrics.gaussian_outage(1e-30 * torch.eye(dim),
                                             [0.0])) == 1


@pytest.mark.parametrize('ratio', [1e5, 1e6, 1e8, 1e12])
def test_gaussian_outage_of_elongated_covariances(ratio):
    # diag(1, 1 / ratio) at r = 1 is erfc(1 / sqrt 2) up to the small
    # axis's own effect, about 0.76 / ratio relative (the old direction
    # average gave 0.24, 2e-3 and 1e-206 for 1e5, 1e6, 1e8)
    cov = _diag(1.0, 1 / ratio)
    got = float(metrics.gaussian_outage(cov, [1.0]))
    expected = math.erfc(1 / math.sqrt(2))
    assert abs(got / expected - 1) < 1 / ratio
    with mpmath.workdps(30):
        exact = float(_mp_outage([1.0, 1 / ratio], 1.0))
    assert got == pytest.approx(exact, rel=1e-13, abs=0)


def test_gaussian_outage_of_a_ring_shaped_posterior():
    # one agent ranging to one anchor with sigma = 1 mm: variance 10 m^2
    # along the ring, 1e-6 m^2 across it; the outage at 1 m is about 0.75
    # (the old direction average gave 0.001)
    cov = _diag(10.0, 1e-6)
    got = metrics.gaussian_outage(cov, [0.5, 1.0, 3.0])
    with mpmath.workdps(30):
        exact = [float(_mp_outage([10.0, 1e-6], r)) for r in (0.5, 1, 3)]
    np.testing.assert_allclose(got.numpy(), exact, rtol=1e-13, atol=0)
    assert abs(float(got[1]) - 0.7518) < 1e-4


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


@settings(max_examples=40, deadline=None)
@given(dim=st.sampled_from([2, 3]), seed=st.integers(0, 2**32 - 1),
       log_scale=st.floats(-3, 3),
       log_spread=st.lists(st.floats(0, 12), min_size=2, max_size=2),
       axis=st.integers(0, 2),
       log_radii=st.lists(st.floats(-2, 1.6), min_size=2, max_size=2))
def test_gaussian_outage_against_mpmath(dim, seed, log_scale, log_spread,
                                        axis, log_radii):
    # a rotated covariance, condition number up to 1e12, thresholds from
    # 1/100 to 40 standard deviations of one of its axes; the reference is
    # the exact outage of the float64 matrix given (its eigenvalues to 30
    # digits). Exact eigenvalues give errors of ~1e-13 relative; the
    # absolute tolerance is for eigvalsh's rounding of a small eigenvalue
    # (~1e-16 of the largest), which moves the outage by up to ~1e-16
    # sqrt(condition number) (5e-11 at 1e12, the worst of 1800 cases)
    spread = [0.0] + log_spread[:dim - 1]
    eigenvalues = torch.tensor([10**(log_scale - v) for v in spread],
                               dtype=torch.float64)
    q = _rotation(dim, torch.Generator().manual_seed(seed))
    cov = q @ torch.diag(eigenvalues) @ q.t()
    cov = 0.5 * (cov + cov.t())
    radii = [float(eigenvalues[axis % dim].sqrt()) * 10**v for v in log_radii]
    got = metrics.gaussian_outage(cov, radii)
    with mpmath.workdps(30):
        exact = mpmath.eigsy(mpmath.matrix(cov.tolist()), eigvals_only=True)
        expected = [float(_mp_outage(list(exact), r)) for r in radii]
        condition = float(max(exact) / min(exact))
    for value, reference in zip(got.tolist(), expected):
        assert abs(value - reference) <= 1e-12 + 4e-16 * condition**0.5
        if reference > 1e-300:
            assert abs(value / reference - 1) <= 1e-10


@pytest.mark.parametrize('dim', [2, 3])
@pytest.mark.parametrize('condition', [1.0, 1e3, 1e6, 1e9, 1e12])
def test_gaussian_outage_against_monte_carlo(dim, condition):
    # 400,000 draws of a rotated covariance whose eigenvalues span
    # `condition` (log-evenly), at thresholds on the scales of its largest
    # and smallest axes; within 5 binomial standard errors
    g = torch.Generator().manual_seed(int(math.log10(condition)) + 10 * dim)
    eigenvalues = torch.logspace(0, -math.log10(condition), dim,
                                 dtype=torch.float64)
    q = _rotation(dim, g)
    count = 400_000
    errors = torch.randn(count, dim, generator=g, dtype=torch.float64) * \
        eigenvalues.sqrt() @ q.t()
    norms = errors.norm(dim=-1)
    largest, smallest = eigenvalues[0].sqrt(), eigenvalues[-1].sqrt()
    radii = [float(v) for v in (0.3 * largest, largest, 2.5 * largest,
                                smallest, 3 * smallest)]
    got = metrics.gaussian_outage(q @ torch.diag(eigenvalues) @ q.t(),
                                  radii)
    for r, value in zip(radii, got.tolist()):
        p = float((norms > r).double().mean())
        error = (max(p * (1 - p), 1 / count) / count)**0.5
        assert abs(value - p) < 5 * error, (r, value, p)


def test_gaussian_outage_refuses_what_is_no_covariance():
    eye = torch.eye(2, dtype=torch.float64)
    with pytest.raises(ValueError, match='D in 1, 2, 3'):
        metrics.gaussian_outage(torch.eye(4), [1.0])
    # eigvalsh would read one triangle: the identity
    with pytest.raises(ValueError, match=r"'cov' is not symmetric"):
        metrics.gaussian_outage(torch.tensor([[1.0, 5.0], [0.0, 1.0]]),
                                [1.0])
    skew = torch.stack([eye, eye, eye + torch.tensor([[0.0, 1e-6],
                                                      [0.0, 0.0]])])
    with pytest.raises(ValueError, match=r"'cov\[2\]' is not symmetric"):
        metrics.gaussian_outage(skew, [1.0])
    with pytest.raises(ValueError, match=r"'cov\[1, 0\]' is indefinite"):
        metrics.gaussian_outage(torch.stack([eye, _diag(1.0, -1e-3)])
                                .unsqueeze(1), [1.0])
    for cov in ([[1.0, math.inf], [math.inf, 1.0]],
                [[-math.inf, 0.0], [0.0, 1.0]]):
        with pytest.raises(ValueError, match="'cov' has a -inf variance, "
                           "or an infinite covariance"):
            metrics.gaussian_outage(torch.tensor(cov), [1.0])
    with pytest.raises(TypeError, match="'cov'"):
        metrics.gaussian_outage([[1.0, 0.0], [0.0, 1.0]], [1.0])
    # rounding: triangles 8e-10 apart are a covariance, the mean of both
    # (eigvalsh alone would read one: 4e-10 off here); so is an eigenvalue
    # of -1e-12 (one of zero)
    radii = [0.3, 1.0, 3.0]
    skewed = torch.tensor([[1.0, 0.3 + 4e-10], [0.3 - 4e-10, 0.5]],
                          dtype=torch.float64)
    torch.testing.assert_close(
        metrics.gaussian_outage(skewed, radii), metrics.gaussian_outage(
            torch.tensor([[1.0, 0.3], [0.3, 0.5]], dtype=torch.float64),
            radii), rtol=1e-13, atol=0)
    assert float(metrics.gaussian_outage(_diag(1.0, -1e-12), [1.0])) == \
        pytest.approx(math.erfc(1 / math.sqrt(2)), rel=1e-14)


def test_gaussian_outage_refuses_bad_thresholds():
    for thresholds in (['1'], '1', [None], [1.0, [2.0]],
                       torch.tensor([True])):
        with pytest.raises(TypeError, match="'thresholds'"):
            metrics.gaussian_outage(torch.eye(2), thresholds)
    for thresholds in ([-1.0], [1.0, math.nan]):
        with pytest.raises(ValueError, match="'thresholds'"):
            metrics.gaussian_outage(torch.eye(2), thresholds)


def test_gaussian_outage_of_nan_and_infinite_entries():
    # NaN in, NaN out for that covariance only; an infinite variance never
    # stays within a finite threshold; no error stays beyond r = inf
    cov = torch.stack([torch.eye(2), torch.tensor([[1.0, math.nan],
                                                   [math.nan, 1.0]]),
                       torch.tensor([[math.inf, 0.0], [0.0, 1.0]])])
    out = metrics.gaussian_outage(cov, [0.0, 1.0, math.inf])
    assert out[0].tolist() == [1.0, pytest.approx(math.exp(-0.5)), 0.0]
    assert torch.isnan(out[1]).all()
    assert out[2].tolist() == [1.0, 1.0, 0.0]


def test_gaussian_outage_keeps_the_batch_shape_in_float64():
    g = torch.Generator().manual_seed(3)
    root = torch.randn(2, 3, 2, 2, generator=g)
    cov = root @ root.transpose(-1, -2) + 0.1 * torch.eye(2)  # float32
    thresholds = torch.tensor([0.2, 0.5, 1.0, 2.0])
    out = metrics.gaussian_outage(cov, thresholds)
    assert out.shape == (2, 3, 4) and out.dtype == torch.float64
    # each the outage of its float32 matrix in float64 (the mean of both
    # triangles, which float32 rounding may set apart)
    for i in range(2):
        for j in range(3):
            single = cov[i, j].double()
            single = 0.5 * (single + single.t())
            torch.testing.assert_close(
                out[i, j], metrics.gaussian_outage(single, thresholds),
                rtol=1e-12, atol=0)
    assert metrics.gaussian_outage(cov[:0], thresholds).shape == (0, 3, 4)
    # a float32 covariance's triangles may differ by its rounding (here 2
    # units of 0.3, 6e-8)
    skewed = torch.tensor([[1.0, 0.3], [0.3, 1.0]])
    skewed[1, 0] = skewed[1, 0] + 5e-8
    assert skewed[1, 0] != skewed[0, 1]
    assert torch.isfinite(metrics.gaussian_outage(skewed, thresholds)).all()


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


def test_angle_errors_wrap_the_difference():
    import math
    from tg_nebp.metrics import angle_errors
    est = torch.tensor([3.1, -3.1, 0.5, math.pi])
    truth = torch.tensor([-3.1, 3.1, -0.5, -math.pi])
    expected = [2 * math.pi - 6.2, 2 * math.pi - 6.2, 1.0, 0.0]
    assert angle_errors(est, truth).tolist() == pytest.approx(expected,
                                                              abs=1e-6)
    assert angle_errors(est, truth).dtype == torch.float64
