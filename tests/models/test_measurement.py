import math

import numpy as np
import pytest
import torch
from scipy.stats import norm

from tg_nebp.models import (GaussianRange, NLOSRange, StudentTRange,
                            model_from_config)

from helpers import gen


@pytest.mark.parametrize('sigma', [1.0, 0.3, 2.5])
def test_log_likelihood_matches_scipy(sigma):
    g = torch.Generator().manual_seed(0)
    E, K = 6, 9
    ranges = 20 * torch.rand(E, 1, generator=g, dtype=torch.float64)
    # states [p, v]: the likelihood reads the positions
    sender = 30 * torch.rand(E, K, 4, generator=g, dtype=torch.float64)
    receiver = 30 * torch.rand(E, K, 4, generator=g, dtype=torch.float64)
    model = GaussianRange(sigma=sigma)
    out = model.log_likelihood(ranges, sender, receiver)
    assert out.shape == (E, K)
    ref = np.empty((E, K))
    for e in range(E):
        for k in range(K):
            dist = np.linalg.norm(sender[e, k, :2].numpy() -
                                  receiver[e, k, :2].numpy())
            ref[e, k] = norm.logpdf(float(ranges[e, 0]), loc=dist, scale=sigma)
    np.testing.assert_allclose(out.numpy(), ref, rtol=1e-12, atol=1e-12)


def test_log_likelihood_of_distance_matches_scipy():
    model = GaussianRange(sigma=0.7)
    ranges = torch.tensor([[3.0], [10.0]], dtype=torch.float64)
    dist = torch.tensor([[3.0, 4.5, 0.0], [9.0, 20.0, 10.0]],
                        dtype=torch.float64)
    out = model.log_likelihood_of_distance(ranges, dist)
    ref = norm.logpdf(ranges.numpy(), loc=dist.numpy(), scale=0.7)
    np.testing.assert_allclose(out.numpy(), ref, rtol=1e-12)


@pytest.mark.parametrize('sigma', [1.0, 0.5])
def test_sample_noise_statistics_far_away(sigma):
    n = 100_000
    distances = torch.linspace(15.0, 60.0, n, dtype=torch.float64)
    model = GaussianRange(sigma=sigma)
    ranges = model.sample_ranges(
        distances, generator=torch.Generator().manual_seed(1)).view(-1)
    noise = (ranges - distances).numpy()
    # >= 15 sigma from zero: the redraw never triggers, noise is N(0, sigma^2)
    assert abs(noise.mean()) < 5 * sigma / math.sqrt(n)
    assert abs(noise.std() - sigma) < 5 * sigma / math.sqrt(2 * n)


def test_sample_never_negative_for_tiny_distances():
    n = 50_000
    distances = torch.full((n, ), 1e-3, dtype=torch.float64)
    distances[::2] = 0.0
    ranges = GaussianRange(sigma=1.0).sample_ranges(
        distances, generator=torch.Generator().manual_seed(2)).view(-1)
    assert ranges.shape == distances.shape
    assert bool((ranges >= 0).all())
    assert bool(torch.isfinite(ranges).all())
    # redrawing below zero gives the half-normal: mean sigma * sqrt(2/pi)
    half = ranges[::2].numpy()
    expected = math.sqrt(2 / math.pi)
    sd = math.sqrt(1 - 2 / math.pi)
    assert abs(half.mean() - expected) < 5 * sd / math.sqrt(half.size)


def test_sample_is_reproducible():
    model = GaussianRange()
    d = torch.linspace(0.0, 5.0, 100)
    a = model.sample_ranges(d, generator=torch.Generator().manual_seed(5))
    b = model.sample_ranges(d, generator=torch.Generator().manual_seed(5))
    c = model.sample_ranges(d, generator=torch.Generator().manual_seed(6))
    assert torch.equal(a, b) and not torch.equal(a, c)


def connect_reference(pos, receiver, max_range):
    pos = pos.numpy()
    pairs = set()
    for i in range(len(pos)):
        if not receiver[i]:
            continue
        for j in range(len(pos)):
            if j == i:
                continue
            d = pos[j] - pos[i]
            if math.sqrt(d[0] * d[0] + d[1] * d[1]) <= max_range:
                pairs.add((j, i))
    return pairs


@pytest.mark.parametrize('block_size', [2048, 7, 1])
@pytest.mark.parametrize('max_range', [20.0, 7.5])
def test_connect_matches_double_loop(max_range, block_size):
    g = torch.Generator().manual_seed(3)
    n = 60  # more than 25 nodes: cdist would take its matmul shortcut
    pos = 80 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    receiver = torch.rand(n, generator=g) < 0.7
    edges = GaussianRange(max_range=max_range).connect(pos, receiver,
                                                       block_size=block_size)
    assert edges.shape[0] == 2 and edges.dtype == torch.long
    got = list(map(tuple, edges.t().tolist()))
    assert len(got) == len(set(got))  # no duplicates
    assert got == sorted(got)  # ordered by sender, then receiver
    ref = connect_reference(pos, receiver, max_range)
    assert len(ref) > 0
    assert set(got) == ref


def dense_connect(pos, receiver, max_range):
    # every pair's distance as cdist computes it without its matmul
    # shortcut, in one dense matrix: the search the cell list replaced
    within = torch.cdist(pos, pos, compute_mode='donot_use_mm_for_euclid_dist'
                         ) <= max_range
    within &= receiver.view(1, -1)
    within.fill_diagonal_(False)
    return torch.stack(within.nonzero(as_tuple=True))


@pytest.mark.parametrize('seed', range(8))
def test_cell_search_gives_the_dense_search_exactly(seed):
    # 2-D and 3-D, float32 and float64, a quarter of the nodes on a lattice
    # of spacing max_range (pairs exactly at the boundary), any block size:
    # the same links in the same order, bit for bit
    g = torch.Generator().manual_seed(seed)
    dim, dtype = 2 + seed % 2, (torch.float32, torch.float64)[seed // 2 % 2]
    n = int(torch.randint(30, 300, (1, ), generator=g))
    max_range = float(1 + 29 * torch.rand(1, generator=g))
    pos = 200 * torch.rand(n, dim, generator=g, dtype=torch.float64) - 50
    lattice = n // 4
    pos[:lattice] = max_range * torch.randint(0, 5, (lattice, dim),
                                              generator=g)
    pos = pos.to(dtype)
    receiver = torch.rand(n, generator=g) < 0.8
    block = int(torch.randint(1, 64, (1, ), generator=g))
    edges = GaussianRange(max_range=max_range).connect(pos, receiver, block)
    expected = dense_connect(pos, receiver, max_range)
    assert expected.size(1) > 0 and torch.equal(edges, expected)


def test_connect_includes_pairs_exactly_at_max_range():
    # a chain with spacing exactly max_range along the x axis (exactly
    # representable differences) plus random clutter: > 25 nodes
    xs = 0.1 + 20.0 * torch.arange(30, dtype=torch.float64)
    chain = torch.stack([xs, torch.full_like(xs, 7.3)], dim=1)
    diffs = chain[1:, 0] - chain[:-1, 0]
    g = torch.Generator().manual_seed(4)
    clutter = torch.rand(10, 2, generator=g, dtype=torch.float64) * 600
    clutter[:, 1] += 100.0  # far from the chain
    pos = torch.cat([chain, clutter])
    receiver = torch.ones(len(pos), dtype=torch.bool)
    edges = GaussianRange(max_range=20.0).connect(pos, receiver)
    got = set(map(tuple, edges.t().tolist()))
    assert got == connect_reference(pos, receiver, 20.0)
    for k in range(29):
        if float(diffs[k]) <= 20.0:
            assert (k, k + 1) in got and (k + 1, k) in got
        else:
            assert (k, k + 1) not in got


def test_connect_never_ends_at_non_receivers():
    pos = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    receiver = torch.tensor([True, False, False])
    edges = GaussianRange().connect(pos, receiver)
    assert set(map(tuple, edges.t().tolist())) == {(1, 0), (2, 0)}


@pytest.mark.parametrize('name,kwargs', [
    ('sigma', dict(sigma=0.0)),
    ('sigma', dict(sigma=-1.0)),
    ('sigma', dict(sigma=float('nan'))),
    ('sigma', dict(sigma=float('inf'))),
    ('sigma', dict(sigma=1e-20)),  # 1 / (2 sigma^2) overflows float32
    ('max_range', dict(max_range=0.0)),
    ('max_range', dict(max_range=-5.0)),
    ('max_range', dict(max_range=float('nan'))),
])
def test_bad_parameters_raise(name, kwargs):
    with pytest.raises(ValueError, match=f"'{name}'"):
        GaussianRange(**kwargs)


def test_smallest_sigma_gives_no_nan():
    # zero residuals times the largest accepted factor stay finite, huge
    # ones overflow to -inf (never 0 * inf = NaN), in both code paths; a
    # smaller sigma is refused
    model = GaussianRange(sigma=1e-6)
    ranges = torch.tensor([[3.0], [3.0]])
    distances = torch.tensor([[3.0, 3.5], [3.0, 1e14]])
    for likelihood in (model.log_likelihood_of_distance,
                       model.log_likelihood_of_distance_):
        out = likelihood(ranges, distances.clone())
        assert not torch.isnan(out).any()
        assert torch.isfinite(out[:, 0]).all() and torch.isneginf(out[1, 1])
    with pytest.raises(ValueError, match="'sigma' must be at least 1e-06"):
        GaussianRange(sigma=1e-19)


# ---- Student-t and NLOS ranges ---------------------------------------------

def residual_grid():
    z = torch.tensor([[4.0], [10.0], [0.5]], dtype=torch.float64)
    d = torch.tensor([[4.0, 3.0, 9.0, 0.0],
                      [2.0, 10.5, 30.0, 7.0],
                      [0.0, 0.4, 12.0, 1.5]], dtype=torch.float64)
    return z, d


@pytest.mark.parametrize('sigma,nu', [(1.0, 3.0), (0.5, 1.0), (2.0, 30.0)])
def test_student_t_matches_scipy(sigma, nu):
    from scipy.stats import t as student_t
    z, d = residual_grid()
    out = StudentTRange(sigma, nu).log_likelihood_of_distance(z, d)
    for e in range(3):
        for k in range(4):
            expected = student_t.logpdf(float(z[e, 0] - d[e, k]), nu,
                                        scale=sigma)
            assert math.isclose(float(out[e, k]), expected, rel_tol=1e-10,
                                abs_tol=1e-12)


@pytest.mark.parametrize('p_nlos,bias_mean', [(0.2, 3.0), (0.5, 0.7),
                                              (1.0, 2.0), (0.0, 1.0)])
def test_nlos_mixture_matches_numerical_integration(p_nlos, bias_mean):
    from scipy.integrate import quad
    from scipy.stats import norm as gauss
    sigma = 0.8
    z, d = residual_grid()
    out = NLOSRange(sigma, p_nlos, bias_mean).log_likelihood_of_distance(z, d)
    rate = 1 / bias_mean
    for e in range(3):
        for k in range(4):
            x = float(z[e, 0] - d[e, k])
            nlos, _ = quad(lambda b: rate * math.exp(-rate * b) *
                           gauss.pdf(x - b, scale=sigma), 0, math.inf,
                           epsabs=1e-300, limit=200)
            expected = (1 - p_nlos) * gauss.pdf(x, scale=sigma) + \
                p_nlos * nlos
            assert math.isclose(float(out[e, k]), math.log(expected),
                                rel_tol=1e-7, abs_tol=1e-9)


def test_nlos_far_residuals_are_finite_with_finite_gradients():
    model = NLOSRange(0.5, 0.2, 3.0)
    z = torch.tensor([[1000.0], [0.0]], dtype=torch.float64)
    d = torch.tensor([[0.0, 1e3, 2e3], [900.0, 0.0, 1e4]],
                     dtype=torch.float64, requires_grad=True)
    out = model.log_likelihood_of_distance(z, d)
    assert torch.isfinite(out).all()
    out.sum().backward()
    assert torch.isfinite(d.grad).all()


def test_nlos_oracle_reads_the_flag():
    model = NLOSRange(0.8, 0.3, 2.0, oracle=True)
    assert model.features == ('range', 'nlos')
    z, d = residual_grid()
    los, nlos = NLOSRange(0.8, 0.0, 2.0), NLOSRange(0.8, 1.0, 2.0)
    flagged = torch.cat([z, torch.tensor([[1.0], [0.0], [1.0]],
                                         dtype=torch.float64)], 1)
    out = model.log_likelihood_of_distance(flagged, d)
    torch.testing.assert_close(out[[0, 2]], nlos.log_likelihood_of_distance(
        z, d)[[0, 2]])
    torch.testing.assert_close(out[1], los.log_likelihood_of_distance(z,
                                                                      d)[1])


def test_nlos_generation_statistics():
    # one realization of many nodes: the pairs' NLOS flags are symmetric,
    # a fraction p of pairs, and NLOS ranges read long by the bias mean
    n, p_nlos, bias_mean, sigma = 400, 0.2, 3.0, 0.5
    model = NLOSRange(sigma, p_nlos, bias_mean)
    links = model.sample_links(n, gen(4))
    assert torch.equal(links, links.t()) and not links.diagonal().any()
    pairs = n * (n - 1) / 2
    fraction = float(links.triu(1).sum()) / pairs
    assert abs(fraction - p_nlos) < 5 * math.sqrt(p_nlos * (1 - p_nlos) /
                                                  pairs)
    edges = torch.triu_indices(n, n, 1)
    distances = torch.full((edges.size(1), ), 50.0, dtype=torch.float64)
    features = model.sample_ranges(distances, links, edges, gen(5))
    flag = features[:, 1].bool()
    assert torch.equal(flag, links[edges[0], edges[1]])
    excess = features[:, 0] - distances
    m = int(flag.sum())
    assert abs(float(excess[flag].mean()) - bias_mean) < 5 * math.sqrt(
        bias_mean**2 + sigma**2) / math.sqrt(m)
    assert abs(float(excess[~flag].mean())) < 5 * sigma / math.sqrt(
        int((~flag).sum()))


def test_student_t_samples_follow_the_distribution():
    from scipy.stats import kstest
    model = StudentTRange(0.7, 3.0)
    distances = torch.full((20_000, ), 500.0, dtype=torch.float64)
    excess = (model.sample_ranges(distances, generator=gen(6)).view(-1) -
              distances) / 0.7
    assert kstest(excess.numpy(), 't', args=(3.0, )).pvalue > 1e-3


def test_nlos_links_switch_as_a_markov_chain():
    # redrawn with probability s per step: stationary fraction p, and a
    # pair keeps its state from one step to the next with probability
    # 1 - s + s (p^2 + (1 - p)^2)
    n, p_nlos, s = 300, 0.2, 0.1
    model = NLOSRange(p_nlos=p_nlos, switch_prob=s)
    g = gen(7)
    links = model.sample_links(n, g)
    kept, fractions = [], []
    upper = torch.triu_indices(n, n, 1)
    for _ in range(20):
        following = model.step_links(links, g)
        assert torch.equal(following, following.t())
        kept.append(float((following == links)[upper[0], upper[1]].float()
                          .mean()))
        fractions.append(float(following[upper[0], upper[1]].float().mean()))
        links = following
    pairs = upper.size(1)
    expected_kept = 1 - s + s * (p_nlos**2 + (1 - p_nlos)**2)
    assert abs(sum(kept) / 20 - expected_kept) < 5 * math.sqrt(
        expected_kept * (1 - expected_kept) / (20 * pairs))
    assert abs(sum(fractions) / 20 - p_nlos) < 0.01
    # without switching nothing is drawn: the generator is untouched
    fixed = NLOSRange(p_nlos=p_nlos)
    g1, g2 = gen(8), gen(8)
    assert fixed.step_links(links, g1) is links
    assert torch.equal(torch.rand(3, generator=g1), torch.rand(3,
                                                               generator=g2))


# -- what the Gaussian methods and the bound take from a range model --------

def _draw_ranges(model, distance, count, generator):
    # the ranges of one link, drawn here as the model's docstring describes
    # its noise (independently of its sampler); NLOS links i.i.d. with
    # probability p_nlos
    noise = torch.randn(count, generator=generator, dtype=torch.float64)
    if isinstance(model, StudentTRange):
        chi2 = torch.distributions.Chi2(torch.tensor(model.nu,
                                                     dtype=torch.float64))
        torch.manual_seed(int(torch.randint(1 << 30, (1, ),
                                            generator=generator)))
        noise = noise / (chi2.sample((count, )) / model.nu).sqrt()
    z = distance + model.sigma * noise
    if isinstance(model, NLOSRange):
        nlos = torch.rand(count, generator=generator,
                          dtype=torch.float64) < model.p_nlos
        bias = torch.empty(count, dtype=torch.float64).exponential_(
            1 / model.bias_mean, generator=generator)
        z = z + nlos * bias
    return z.view(-1, 1)


@pytest.mark.parametrize('model', [
    GaussianRange(0.5), GaussianRange(2.0), StudentTRange(1.0, 3.0),
    StudentTRange(0.3, 1.5), NLOSRange(), NLOSRange(0.5, 0.4, 0.3),
    NLOSRange(1.0, 0.2, 30.0)])
def test_range_information_is_the_squared_score(model):
    # E[(d log p / d d)^2] by Monte Carlo over ranges drawn as the model
    # says, scored by the model's own likelihood, within 5 standard errors
    g = torch.Generator().manual_seed(0)
    count = 200_000
    z = _draw_ranges(model, 10.0, count, g)
    distances = torch.full((count, 1), 10.0, dtype=torch.float64)
    squared = model.distance_score(z, distances).square().view(-1)
    estimate, error = squared.mean(), squared.std() / count**0.5
    info = model.range_information(z[:1], torch.tensor([10.0],
                                                       dtype=torch.float64))
    assert abs(float(info) - float(estimate)) < 5 * float(error), (
        float(info), float(estimate), float(error))


def test_nlos_oracle_information_follows_the_flag():
    model = NLOSRange(oracle=True)
    z = torch.tensor([[10.0, 0.0], [10.0, 1.0]], dtype=torch.float64)
    info = model.range_information(z, torch.full((2, ), 10.0,
                                                 dtype=torch.float64))
    assert float(info[0]) == pytest.approx(1 / model.sigma**2, rel=1e-6)
    # the exponentially modified Gaussian is flatter: less information
    assert float(info[1]) < float(info[0])


def test_generic_range_information_is_a_monte_carlo_of_the_score():
    # a user's Laplace model has no closed form in the library; its score
    # is +-1/b, so every draw's squared score is exactly 1 / b^2
    from tg_nebp.models import RangeModel

    class Laplace(RangeModel, name='test-laplace-information'):
        def params(self):
            return dict(max_range=self.max_range)

        def log_likelihood_of_distance(self, z, distances):
            return -(z[:, :1] - distances).abs() / 0.8 - math.log(1.6)

        def sample_ranges(self, distances, link_state=None,
                          edge_index=None, generator=None):
            uniform = torch.rand(distances.shape, generator=generator,
                                 dtype=distances.dtype) - 0.5
            return (distances - 0.8 * uniform.sign() *
                    torch.log1p(-2 * uniform.abs())).view(-1, 1)

    model = Laplace()
    distances = torch.tensor([3.0, 12.0], dtype=torch.float64)
    info = model.range_information(distances.view(-1, 1), distances,
                                   torch.Generator().manual_seed(0))
    torch.testing.assert_close(info, torch.full_like(info, 1 / 0.8**2))


def test_robust_weights():
    z = torch.tensor([[10.0], [12.0], [7.5], [10.0]], dtype=torch.float64)
    distances = torch.full((4, 1), 10.0, dtype=torch.float64)
    residual = z - distances
    score, weights = GaussianRange(0.5).robust_weights(z, distances)
    torch.testing.assert_close(score, residual / 0.25)
    torch.testing.assert_close(weights, torch.full_like(weights, 4.0))
    nu, sigma = 3.0, 0.7
    score, weights = StudentTRange(sigma, nu).robust_weights(z, distances)
    torch.testing.assert_close(weights, (nu + 1) / (nu * sigma**2 +
                                                    residual.square()))
    torch.testing.assert_close(score, weights * residual)


def test_nlos_robust_weights_fall_back_to_the_curvature():
    # the mixture's mode is not at a zero residual: where its score points
    # away from zero (and at zero), the weight is the observed information
    # (clamped at 0); elsewhere score / residual
    # (and a user's two-mode likelihood, a peak at a zero residual and one
    # at +4 m: beyond the dip between them the score points away from zero
    # and the log-likelihood is convex there, a negative curvature that is
    # dropped)
    from tg_nebp.models import RangeModel

    class TwoModes(RangeModel, name='test-two-modes'):
        def params(self):
            return dict(max_range=self.max_range)

        def log_likelihood_of_distance(self, z, distances):
            residual = z[:, :1] - distances
            return torch.logaddexp(-0.5 * (residual / 0.5)**2,
                                   -0.5 * ((residual - 4.0) / 0.5)**2)

    for model in (NLOSRange(1.0, 0.4, 1.0), TwoModes()):
        z = torch.linspace(6.0, 16.0, 201, dtype=torch.float64).view(-1, 1)
        distances = torch.full_like(z, 10.0)
        score, weights = model.robust_weights(z, distances)
        residual = z - distances
        step = 1e-4
        log_lik = [model.log_likelihood_of_distance(z, distances + h)
                   for h in (-step, 0.0, step)]
        curvature = -(log_lik[0] - 2 * log_lik[1] + log_lik[2]) / step**2
        toward = score * residual > 0
        assert bool(toward.any()) and bool((~toward).any())
        torch.testing.assert_close(weights[toward],
                                   (score / residual)[toward])
        torch.testing.assert_close(weights[~toward],
                                   curvature[~toward].clamp_min(0),
                                   rtol=1e-5, atol=1e-6)
    assert bool((curvature[~toward] < 0).any())  # the dip's


def test_range_linearization_is_the_likelihood_gradient():
    g = torch.Generator().manual_seed(3)
    sender = 5 * torch.randn(6, 4, generator=g, dtype=torch.float64)
    receiver = 5 * torch.randn(6, 4, generator=g, dtype=torch.float64)
    z = (sender[:, :2] - receiver[:, :2]).norm(dim=-1, keepdim=True) + 0.4
    model = StudentTRange(0.8, 4.0)
    assert model.scope(4) == (0, 1) and model.scope(6) == (0, 1, 2)
    grad, curvature = model.linearize(z, sender, receiver)
    ends = [x.clone().requires_grad_() for x in (sender, receiver)]
    model.log_likelihood(z, ends[0].unsqueeze(1),
                         ends[1].unsqueeze(1)).sum().backward()
    # on the positions of both ends (the velocities' gradient is zero)
    full = torch.cat([e.grad for e in ends], -1)
    torch.testing.assert_close(grad, full[:, [0, 1, 4, 5]])
    assert full[:, [2, 3, 6, 7]].abs().max() == 0
    # rank one along the gradient of the distance, scaled by the weight
    _, weights = model.robust_weights(z, (sender[:, :2] - receiver[:, :2])
                                      .norm(dim=-1, keepdim=True))
    unit = torch.cat([sender[:, :2] - receiver[:, :2],
                      receiver[:, :2] - sender[:, :2]], -1).double()
    unit = unit / unit.norm(dim=-1, keepdim=True) * 2**0.5
    expected = weights.view(-1, 1, 1) * unit.unsqueeze(-1) * unit.unsqueeze(
        -2)
    torch.testing.assert_close(curvature, expected)


def test_generic_fisher_information_matches_the_range_blocks():
    # a measurement model that is no RangeModel (GaussianRange's formula
    # behind the generic interface) gets the Monte Carlo of its squared
    # score over the full states: the range model's closed-form blocks
    from tg_nebp.models import MeasurementModel

    class Wrapped(MeasurementModel, name='test-wrapped-gaussian'):
        fisher_samples = 20_000
        inner = GaussianRange(0.5)

        def params(self):
            return {}

        def log_likelihood(self, z, sender, receiver):
            return self.inner.log_likelihood(z, sender, receiver)

        def sample_features(self, states_j, states_i, link_state,
                            edge_index, generator=None):
            return self.inner.sample_features(states_j, states_i, None,
                                              None, generator)

    g = torch.Generator().manual_seed(1)
    receiver = 8 * torch.rand(3, 4, generator=g, dtype=torch.float64)
    # at least 8 sigma apart: sampling never redraws a negative range
    sender = receiver + torch.tensor([[4.0, 3.0, 0.0, 0.0], [-5.0, 1.0, 0.0,
                                                              0.0],
                                      [0.5, -6.0, 0.0, 0.0]],
                                     dtype=torch.float64)
    z = torch.zeros(3, 1, dtype=torch.float64)
    sampled = Wrapped().fisher_information(z, sender, receiver, g)
    exact = GaussianRange(0.5).fisher_information(z, sender, receiver)
    # 4 / sigma^2 scale; 20,000 draws: about 1 % of it
    torch.testing.assert_close(sampled, exact, rtol=0, atol=0.1)
    grad, curvature = Wrapped().linearize(z, sender, receiver, g)
    assert grad.shape == (3, 8)
    torch.testing.assert_close(curvature, exact, rtol=0, atol=0.1)


def test_closed_form_weights_equal_the_generic_ones():
    # a subclass that restates the likelihood loses the closed forms
    # (Model.provides): its weights come from automatic differentiation
    class PlainGaussian(GaussianRange, name='test-plain-gaussian-weights'):
        def log_likelihood_of_distance(self, z, distances):
            return super().log_likelihood_of_distance(z, distances)

    class PlainStudentT(StudentTRange, name='test-plain-student-weights'):
        def log_likelihood_of_distance(self, z, distances):
            return super().log_likelihood_of_distance(z, distances)

    z = torch.linspace(4.0, 16.0, 97, dtype=torch.float64).view(-1, 1)
    distances = torch.full_like(z, 10.0)
    for closed, generic in ((GaussianRange(0.6), PlainGaussian(0.6)),
                            (StudentTRange(0.7, 2.5),
                             PlainStudentT(0.7, 2.5))):
        assert closed.provides('distance_weights')
        assert not generic.provides('distance_weights')
        for a, b in zip(closed.robust_weights(z, distances),
                        generic.robust_weights(z, distances)):
            torch.testing.assert_close(a, b)


def test_range_by_sensor_is_each_links_own_sensor_model():
    # every piece (likelihood, robust weights, Fisher information) is the
    # named sensor's StudentTRange's, link by link, written as a plain loop
    from tg_nebp.models import StudentTRangeBySensor
    sigma, nu = [0.1, 0.02, 0.3], [3.0, 32.0, 8.0]
    model = StudentTRangeBySensor(sigma, nu, max_range=40.0)
    generator = torch.Generator().manual_seed(0)
    sensor = torch.randint(0, 3, (50, ), generator=generator).double()
    z = torch.stack([5 + torch.rand(50, generator=generator,
                                    dtype=torch.float64), sensor], 1)
    distances = 5 + torch.rand(50, 4, generator=generator,
                               dtype=torch.float64)
    log_lik = model.log_likelihood_of_distance(z, distances)
    score, weights = model.robust_weights(z, distances)
    information = model.range_information(z, distances[:, 0])
    for e in range(50):
        own = StudentTRange(sigma[int(sensor[e])], nu[int(sensor[e])])
        torch.testing.assert_close(log_lik[e], own.log_likelihood_of_distance(
            z[e:e + 1], distances[e:e + 1])[0])
        s, w = own.robust_weights(z[e:e + 1], distances[e:e + 1])
        torch.testing.assert_close((score[e], weights[e]), (s[0], w[0]))
        torch.testing.assert_close(information[e], own.range_information(
            z[e:e + 1], distances[e:e + 1, 0])[0])
    assert model_from_config(model.config(), 'measurement') == model
    with pytest.raises(ValueError, match='link 0 names sensor 3.0; the '
                       'model has sensors 0 to 2'):
        model.log_likelihood_of_distance(torch.tensor([[1.0, 3.0]]),
                                         torch.ones(1, 1))
    with pytest.raises(ValueError, match="lists of one entry per sensor"):
        StudentTRangeBySensor([0.1, 0.2], [3.0])
