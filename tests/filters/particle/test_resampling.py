import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from tg_nebp.filters import (RESAMPLERS, effective_sample_size,
                             multinomial_resample, residual_resample,
                             silverman_bandwidth, stratified_resample,
                             systematic_resample)

from helpers import gen

RESAMPLER_FNS = [multinomial_resample, systematic_resample,
                 stratified_resample, residual_resample]


def random_log_weights(shape, seed):
    g = gen(seed)
    return 2.0 * torch.randn(shape, generator=g, dtype=torch.float64)


def test_registry():
    assert RESAMPLERS['multinomial'] is multinomial_resample
    assert RESAMPLERS['systematic'] is systematic_resample
    assert RESAMPLERS['stratified'] is stratified_resample
    assert RESAMPLERS['residual'] is residual_resample


@pytest.mark.parametrize('fn', RESAMPLER_FNS)
def test_shapes_dtype_and_range(fn):
    lw = random_log_weights((3, 4, 7), 0)
    idx = fn(lw, generator=gen(0))
    assert idx.shape == (3, 4, 7) and idx.dtype == torch.long
    assert bool(((idx >= 0) & (idx < 7)).all())
    idx = fn(lw, 11, generator=gen(0))
    assert idx.shape == (3, 4, 11)


def test_multinomial_counts_chi_square():
    K, M = 8, 200_000
    lw = random_log_weights((K, ), 1)
    w = torch.softmax(lw, 0).numpy()
    idx = multinomial_resample(lw, M, generator=gen(2))
    counts = np.bincount(idx.numpy(), minlength=K)
    stat = ((counts - M * w)**2 / (M * w)).sum()
    # fixed seed; the bound is the chi2(K - 1) quantile at 1 - 1e-6
    assert stat < chi2.ppf(1 - 1e-6, K - 1)


def test_multinomial_counts_binomial_per_row():
    # many rows, each an independent multinomial: check the counts of every
    # particle against its binomial mean with a 5-sigma bound
    R, K, M = 50, 5, 4000
    lw = random_log_weights((R, K), 3)
    w = torch.softmax(lw, -1).numpy()
    idx = multinomial_resample(lw, M, generator=gen(4))
    for r in range(R):
        counts = np.bincount(idx[r].numpy(), minlength=K)
        sd = np.sqrt(M * w[r] * (1 - w[r]))
        assert np.all(np.abs(counts - M * w[r]) <= 5 * sd + 1e-9)


def test_multinomial_draws_are_independent_not_systematic():
    # with equal weights multinomial counts vary (binomial variance), unlike
    # systematic resampling where every count is exactly M / K
    K, M = 10, 1000
    lw = torch.zeros(200, K, dtype=torch.float64)
    idx = multinomial_resample(lw, M, generator=gen(5))
    counts = torch.stack([torch.bincount(r, minlength=K) for r in idx])
    var = counts.double().var().item()
    expected = M * 0.1 * 0.9  # 90
    # sample variance over 2000 counts: relative std ~ sqrt(2 / 2000)
    assert abs(var - expected) < 5 * expected * math.sqrt(2 / 2000)


@pytest.mark.parametrize('seed', range(5))
@pytest.mark.parametrize('M', [7, 100, 1000])
def test_systematic_counts_are_floor_or_ceil(seed, M):
    K = 13
    lw = random_log_weights((20, K), 10 + seed)
    w = torch.softmax(lw, -1).numpy()
    idx = systematic_resample(lw, M, generator=gen(seed))
    for r in range(20):
        counts = np.bincount(idx[r].numpy(), minlength=K)
        assert counts.sum() == M
        assert np.all(counts >= np.floor(M * w[r] - 1e-9))
        assert np.all(counts <= np.ceil(M * w[r] + 1e-9))


def test_systematic_indices_sorted_and_equal_weights_exact():
    K = 16
    idx = systematic_resample(torch.zeros(3, K), generator=gen(0))
    for r in idx:
        assert torch.equal(r, torch.arange(K))  # one copy each


def test_systematic_is_unbiased():
    # E[count_k] = M w_k: average over many independent rows (offsets)
    R, K, M = 4000, 6, 10
    lw = random_log_weights((K, ), 6).expand(R, K)
    w = torch.softmax(lw[0], 0).numpy()
    idx = systematic_resample(lw, M, generator=gen(7))
    counts = np.stack([np.bincount(r, minlength=K) for r in idx.numpy()])
    mean = counts.mean(0)
    # the count is floor or ceil: variance <= 1/4, so the std of the mean
    # is at most 0.5 / sqrt(R)
    assert np.all(np.abs(mean - M * w) < 5 * 0.5 / math.sqrt(R))


@pytest.mark.parametrize('fn', RESAMPLER_FNS)
@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
def test_extremely_peaked_log_weights(fn, dtype):
    lw = torch.full((4, 50), float('-inf'), dtype=dtype)
    lw[:, 1] = -1e30
    for r, k in enumerate([0, 7, 49, 23]):
        lw[r, k] = 0.0 if r % 2 == 0 else 1e30 if dtype == torch.float64 \
            else 3e38
    idx = fn(lw, 100, generator=gen(0))
    assert idx.shape == (4, 100)
    for r, k in enumerate([0, 7, 49, 23]):
        assert bool((idx[r] == k).all())


@pytest.mark.parametrize('fn', RESAMPLER_FNS)
def test_huge_finite_log_weights(fn):
    # log-weights far from zero must not overflow
    lw = torch.tensor([[1000.0, 1000.0 + math.log(3.0)]], dtype=torch.float64)
    idx = fn(lw, 40_000, generator=gen(1))
    frac = (idx == 1).double().mean().item()
    assert abs(frac - 0.75) < 5 * math.sqrt(0.75 * 0.25 / 40_000)


@pytest.mark.parametrize('fn', RESAMPLER_FNS)
def test_zero_weight_particles_never_chosen(fn):
    lw = random_log_weights((30, 9), 8)
    lw[:, ::2] = float('-inf')
    idx = fn(lw, 500, generator=gen(2))
    assert bool((idx % 2 == 1).all())


@pytest.mark.parametrize('fn', RESAMPLER_FNS)
def test_same_seed_same_indices(fn):
    lw = random_log_weights((5, 20), 9)
    a = fn(lw, generator=gen(42))
    b = fn(lw, generator=gen(42))
    c = fn(lw, generator=gen(43))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


@pytest.mark.parametrize('fn', RESAMPLER_FNS)
def test_batched_rows_are_independent(fn):
    R, K, M = 400, 4, 1
    # identical rows: if rows shared randomness, every row would agree
    lw = torch.zeros(R, K, dtype=torch.float64)
    idx = fn(lw, M, generator=gen(3))[:, 0]
    counts = np.bincount(idx.numpy(), minlength=K)
    stat = ((counts - R / K)**2 / (R / K)).sum()
    assert stat < chi2.ppf(1 - 1e-6, K - 1)
    # consecutive rows uncorrelated: P(equal) = 1/K
    same = (idx[1:] == idx[:-1]).double().mean().item()
    p = 1 / K
    assert abs(same - p) < 5 * math.sqrt(p * (1 - p) / (R - 1))


@pytest.mark.parametrize('fn', RESAMPLER_FNS)
def test_rows_follow_their_own_weights(fn):
    # a batched call picks, for every row, only that row's valid particle
    K = 6
    lw = torch.full((K, K), float('-inf'))
    lw[torch.arange(K), torch.arange(K).flip(0)] = 0.0
    idx = fn(lw, 10, generator=gen(0))
    assert torch.equal(idx, torch.arange(K).flip(0).view(K, 1).expand(K, 10))


@pytest.mark.parametrize('fn', RESAMPLER_FNS)
def test_invalid_log_weights_raise(fn):
    with pytest.raises(ValueError, match='NaN'):
        fn(torch.tensor([0.0, float('nan')]))
    with pytest.raises(ValueError, match='K = 0'):
        fn(torch.zeros(3, 0))
    with pytest.raises(ValueError, match='-inf'):
        fn(torch.tensor([[0.0, 1.0], [float('-inf'), float('-inf')]]))
    with pytest.raises(ValueError, match=r'\+inf'):
        fn(torch.tensor([0.0, float('inf')]))
    with pytest.raises(ValueError, match='num_samples'):
        fn(torch.zeros(3), -1)


@pytest.mark.parametrize('fn', RESAMPLER_FNS)
def test_does_not_track_gradients(fn):
    lw = torch.zeros(2, 5, requires_grad=True)
    idx = fn(lw, generator=gen(0))
    assert not idx.requires_grad



@pytest.mark.parametrize('fn', [stratified_resample, residual_resample])
@pytest.mark.parametrize('M', [10, 23])
def test_stratified_and_residual_are_unbiased(fn, M):
    # E[count_k] = M w_k over many independent rows; a count's variance is
    # at most M / 4, so 5 standard errors of the mean are 5 sqrt(M/4/R)
    R, K = 4000, 6
    lw = random_log_weights((K, ), 8).expand(R, K)
    w = torch.softmax(lw[0], 0).numpy()
    idx = fn(lw, M, generator=gen(9))
    counts = np.stack([np.bincount(r, minlength=K) for r in idx.numpy()])
    assert np.all(counts.sum(1) == M)
    assert np.all(np.abs(counts.mean(0) - M * w) <
                  5 * math.sqrt(M / 4 / R))


def test_residual_keeps_the_deterministic_copies():
    lw = random_log_weights((50, 9), 10)
    M = 31
    floor = np.floor(M * torch.softmax(lw, -1).numpy())
    idx = residual_resample(lw, M, generator=gen(11)).numpy()
    counts = np.stack([np.bincount(r, minlength=9) for r in idx])
    assert np.all(counts >= floor)
    assert np.all(counts.sum(1) == M)


def test_stratified_draws_one_point_per_stratum():
    # equal weights and M = K: exactly one draw per particle
    idx = stratified_resample(torch.zeros(20, 8), generator=gen(12))
    assert torch.equal(idx, torch.arange(8).expand(20, 8))


def test_effective_sample_size_and_bandwidth():
    assert float(effective_sample_size(torch.zeros(10))) == \
        pytest.approx(10.0)
    peaked = torch.tensor([0.0, -1e9, -1e9])
    assert float(effective_sample_size(peaked)) == pytest.approx(1.0)
    w = torch.tensor([0.5, 0.25, 0.25])
    assert float(effective_sample_size(w.log())) == pytest.approx(
        1 / (0.25 + 2 * 0.0625))
    assert silverman_bandwidth(1000, 4) == pytest.approx(
        (4 / 6000)**(1 / 8))
