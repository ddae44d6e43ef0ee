import math

import numpy as np
import pytest
import torch
from scipy.stats import norm

from tg_nebp.models import GaussianRange, NLOSRange, StudentTRange

from helpers import gen


@pytest.mark.parametrize('sigma', [1.0, 0.3, 2.5])
def test_log_likelihood_matches_scipy(sigma):
    g = torch.Generator().manual_seed(0)
    E, K = 6, 9
    ranges = 20 * torch.rand(E, 1, generator=g, dtype=torch.float64)
    sender = 30 * torch.rand(E, K, 2, generator=g, dtype=torch.float64)
    receiver = 30 * torch.rand(E, K, 2, generator=g, dtype=torch.float64)
    model = GaussianRange(sigma=sigma)
    out = model.log_likelihood(ranges, sender, receiver)
    assert out.shape == (E, K)
    ref = np.empty((E, K))
    for e in range(E):
        for k in range(K):
            dist = np.linalg.norm(sender[e, k].numpy() -
                                  receiver[e, k].numpy())
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
    # zero residuals times the largest accepted factor stay finite, large
    # ones overflow to -inf (never 0 * inf = NaN), in both code paths
    model = GaussianRange(sigma=1e-19)
    ranges = torch.tensor([[3.0], [3.0]])
    distances = torch.tensor([[3.0, 3.5], [3.0, 1e3]])
    for likelihood in (model.log_likelihood_of_distance,
                       model.log_likelihood_of_distance_):
        out = likelihood(ranges, distances.clone())
        assert not torch.isnan(out).any()
        assert torch.isfinite(out[:, 0]).all() and torch.isneginf(out[1, 1])


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
