r"""Tests of the :math:`M`-sample (marginalized) messages of
:class:`tg_nebp.nn.conv.ParticleBPConv` against a float64 loop over all
particle pairs, and of the estimator's unbiasedness."""
import math

import pytest
import torch

from tg_nebp.models import GaussianRange
from tg_nebp.nn.conv import ParticleBPConv

from helpers import gen, random_graph


def exact_reference(particles, log_weights, sender, edge_index, ranges,
                    anchor, sigma):
    r"""log w_i^(k) + sum_(j -> i) log sum_l w_j^(l) N(z; |p_j^l - p_i^k|,
    sigma^2), with plain loops in float64 (anchors unchanged)."""
    n, K = log_weights.shape
    out = log_weights.double().clone()
    x = particles.double().tolist()
    lw = sender.double().tolist()
    for e in range(edge_index.size(1)):
        j, i = int(edge_index[0, e]), int(edge_index[1, e])
        if bool(anchor[i]):
            continue
        z = float(ranges[e, 0])
        for k in range(K):
            terms = []
            for l in range(K):
                d = math.hypot(x[j][l][0] - x[i][k][0],
                               x[j][l][1] - x[i][k][1])
                terms.append(lw[j][l] - 0.5 * ((z - d) / sigma)**2 -
                             math.log(math.sqrt(2 * math.pi) * sigma))
            top = max(terms)
            out[i, k] += top + math.log(sum(math.exp(t - top)
                                            for t in terms))
    return out


@pytest.mark.parametrize('return_messages,chunk', [(True, None), (False, 3),
                                                   (False, None)])
def test_all_samples_equal_the_exact_message(return_messages, chunk):
    particles, lw, ei, ea, anchor = random_graph(gen(40), 4, 2, 6)
    sender = torch.randn(lw.shape, generator=gen(41), dtype=torch.float64)
    conv = ParticleBPConv(GaussianRange(0.8), chunk_size=chunk,
                          num_samples='all')
    out, _ = conv(particles, lw, ei, ea, sender, anchor,
                  return_messages=return_messages)
    expected = exact_reference(particles, lw, sender, ei, ea, anchor, 0.8)
    torch.testing.assert_close(out, expected, atol=1e-9, rtol=1e-9)
    # M = K given as a number is the same
    same, _ = ParticleBPConv(GaussianRange(0.8), num_samples=6)(
        particles, lw, ei, ea, sender, anchor)
    torch.testing.assert_close(same, expected, atol=1e-9, rtol=1e-9)


def test_one_sample_is_the_paired_message_bit_for_bit():
    particles, lw, ei, ea, anchor = random_graph(gen(42), 5, 2, 7)
    paired = ParticleBPConv()(particles, lw, ei, ea, anchor=anchor)
    one = ParticleBPConv(num_samples=1)(particles, lw, ei, ea, anchor=anchor,
                                        generator=gen(0))
    assert torch.equal(paired[0], one[0]) and torch.equal(paired[1], one[1])


def test_sampled_message_is_unbiased():
    # the mean of (K / M) sum_m w^(l_m) p(l_m) over shift draws equals the
    # exact sum_l w^(l) p(l); 4000 draws, 5 standard errors
    particles, lw, ei, ea, anchor = random_graph(gen(43), 2, 1, 8,
                                                 edge_prob=1.0)
    sender = torch.randn(lw.shape, generator=gen(44),
                         dtype=torch.float64).log_softmax(-1)
    K, M = 8, 3
    conv = ParticleBPConv(num_samples=M)
    g = gen(45)
    draws = torch.stack([
        conv(particles, lw, ei, ea, sender, anchor, generator=g)[1].exp()
        * K / M for _ in range(4000)])
    exact_messages = ParticleBPConv(num_samples='all')(
        particles, lw, ei, ea, sender, anchor)[1].exp()
    mean, error = draws.mean(0), draws.std(0) / math.sqrt(len(draws))
    assert bool(((mean - exact_messages).abs() <= 5 * error + 1e-12).all())
    assert bool((error > 0).any())  # the test has power


def test_sample_gradients_equal_autograd_of_materialized_messages():
    particles, lw, ei, ea, anchor = random_graph(gen(46), 5, 2, 6,
                                                 edge_prob=0.8)
    sender = torch.randn(lw.shape, generator=gen(47), dtype=torch.float64)
    conv = ParticleBPConv(num_samples=3, chunk_size=2)
    offsets = conv.draw_offsets(7, 6, generator=gen(48))
    grads = []
    for return_messages in (True, False):
        inputs = [particles.clone().requires_grad_(),
                  sender.clone().requires_grad_(), ea.clone().requires_grad_()]
        out, _ = conv(inputs[0], lw, ei, inputs[2], inputs[1], anchor,
                      return_messages=return_messages,
                      sample_offsets=offsets)
        out.sin().sum().backward()
        grads.append([t.grad for t in inputs])
    for blockwise, materialized in zip(grads[1], grads[0]):
        torch.testing.assert_close(blockwise, materialized, atol=1e-10,
                                   rtol=1e-9)


def test_draw_offsets_and_their_validation():
    conv = ParticleBPConv(num_samples=4)
    offsets = conv.draw_offsets(2000, 10, generator=gen(49))
    assert offsets.shape == (2000, ) and offsets.dtype == torch.long
    # uniform on {0, ..., K - 1}: a chi-square test at 9 degrees of freedom
    # (the 0.999 quantile is 27.9)
    counts = torch.bincount(offsets, minlength=10).double()
    assert counts.numel() == 10
    assert float(((counts - 200)**2 / 200).sum()) < 27.9
    assert ParticleBPConv(num_samples='all').draw_offsets(5, 10).eq(0).all()
    assert ParticleBPConv().draw_offsets(5, 10) is None
    particles, lw, ei, ea, anchor = random_graph(gen(50), 3, 1, 10)
    with pytest.raises(ValueError, match="'sample_offsets' must be an "
                       "integer tensor of shape \\[4\\]"):
        conv(particles, lw, ei, ea, anchor=anchor,
             sample_offsets=offsets[:3])
    with pytest.raises(TypeError, match="'sample_offsets' must be an "
                       "integer tensor of shape \\[4\\], got a list"):
        conv(particles, lw, ei, ea, anchor=anchor,
             sample_offsets=[0, 1, 2, 3])
    with pytest.raises(ValueError, match=r"'sample_offsets\[2\]' = 10 must "
                       r"lie in \[0, 10\)"):
        conv(particles, lw, ei, ea, anchor=anchor,
             sample_offsets=torch.tensor([0, 1, 10, 3]))
    with pytest.raises(ValueError, match="num_samples = 1 pairs"):
        ParticleBPConv()(particles, lw, ei, ea, anchor=anchor,
                         sample_offsets=offsets[:4])
    with pytest.raises(ValueError, match="'num_samples' = 4 exceeds the "
                       "K = 3 particles"):
        conv(particles[:, :3], lw[:, :3], ei, ea, anchor=anchor)
    with pytest.raises(TypeError, match="'num_samples' must be an integer"):
        ParticleBPConv(num_samples=2.5)


@pytest.mark.parametrize('samples,chunk', [('all', None), ('all', 2),
                                           (1, None)])
def test_per_edge_sender_weights(samples, chunk):
    # extrinsic beliefs: every edge's own sender log-weights, against the
    # float64 loop with that edge's weights (all samples), and for M = 1
    # against the paired message of a sender that has those weights
    particles, lw, ei, ea, anchor = random_graph(gen(45), 4, 2, 5)
    per_edge = torch.randn(ei.size(1), 5, generator=gen(46),
                           dtype=torch.float64)
    conv = ParticleBPConv(GaussianRange(0.8), chunk_size=chunk,
                          num_samples=samples)
    out, messages = conv(particles, lw, ei, ea, anchor=anchor,
                         edge_sender_log_weights=per_edge)
    assert messages.shape == (ei.size(1), 5)
    for e in range(ei.size(1)):
        j, i = int(ei[0, e]), int(ei[1, e])
        sender = lw.clone()
        sender[j] = per_edge[e]
        one = ei[:, e:e + 1]
        if samples == 'all':
            expected = exact_reference(particles, lw, sender, one,
                                       ea[e:e + 1], anchor, 0.8)[i] - lw[i]
        else:
            _, expected = ParticleBPConv(GaussianRange(0.8))(
                particles, lw, one, ea[e:e + 1], sender, anchor)
            expected = expected[0]
        torch.testing.assert_close(messages[e], expected, atol=1e-9,
                                   rtol=1e-9)
    with pytest.raises(ValueError, match="'edge_sender_log_weights' must "
                       "have shape"):
        conv(particles, lw, ei, ea, anchor=anchor,
             edge_sender_log_weights=per_edge[:-1])


def three_d_graph(seed, agents=4, anchors=2, count=6):
    # random 3-D particles (states [p, v] of 6 entries), edges into agents
    g = gen(seed)
    n = agents + anchors
    truth = 12 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    particles = torch.zeros(n, count, 6, dtype=torch.float64)
    particles[..., :3] = truth.unsqueeze(1)
    particles[:agents, :, :3] += 2 * torch.randn(agents, count, 3,
                                                 generator=g,
                                                 dtype=torch.float64)
    particles[..., 3:] = torch.randn(n, count, 3, generator=g,
                                     dtype=torch.float64)
    anchor = torch.arange(n) >= agents
    pairs = [(j, i) for i in range(agents) for j in range(n) if i != j]
    edge_index = torch.tensor(pairs).t().contiguous()
    ranges = ((truth[edge_index[0]] - truth[edge_index[1]]).norm(dim=-1) +
              0.5 * torch.randn(len(pairs), generator=g,
                                dtype=torch.float64)).abs().view(-1, 1)
    log_weights = torch.randn(n, count, generator=g, dtype=torch.float64)
    return particles, log_weights, edge_index, ranges, anchor


@pytest.mark.parametrize('samples,chunk', [('all', None), ('all', 3),
                                           (1, None), (1, 2)])
def test_three_dimensional_messages_against_a_loop(samples, chunk):
    # log w_i^k + sum_j log sum_l w_j^l N(z; |p_j^l - p_i^k|_3, sigma^2)
    # (all samples) or its paired term (l = k), in plain float64 loops
    particles, lw, ei, ea, anchor = three_d_graph(47)
    sigma, K = 0.8, lw.size(1)
    conv = ParticleBPConv(GaussianRange(sigma), chunk_size=chunk,
                          num_samples=samples)
    for return_messages in (True, False):
        out, _ = conv(particles, lw, ei, ea, anchor=anchor,
                      return_messages=return_messages)
        expected = lw.clone()
        x = particles[..., :3].tolist()
        for e in range(ei.size(1)):
            j, i = int(ei[0, e]), int(ei[1, e])
            for k in range(K):
                terms = [float(lw[j, l]) - 0.5 * ((float(ea[e, 0]) - math.dist(
                    x[j][l], x[i][k])) / sigma)**2 - math.log(
                        math.sqrt(2 * math.pi) * sigma)
                         for l in (range(K) if samples == 'all' else [k])]
                top = max(terms)
                expected[i, k] += top + math.log(sum(math.exp(t - top)
                                                     for t in terms))
        torch.testing.assert_close(out, expected, atol=1e-9, rtol=1e-9)


def test_three_dimensional_gradients_equal_autograd_of_the_formula():
    # the closed-form blockwise backward (paired) and the autograd one
    # (M samples) against autograd through the materialized messages
    particles, lw, ei, ea, anchor = three_d_graph(48)
    for samples in (1, 3):
        grads = []
        for return_messages in (True, False):
            p = particles.clone().requires_grad_()
            conv = ParticleBPConv(GaussianRange(0.8), chunk_size=2,
                                  num_samples=samples)
            out, _ = conv(p, lw, ei, ea, anchor=anchor,
                          return_messages=return_messages,
                          sample_offsets=None if samples == 1 else
                          torch.tensor([0, 2, 1, 5, 4, 3]))
            out.logsumexp(-1).sum().backward()
            grads.append(p.grad)
        torch.testing.assert_close(grads[0], grads[1], atol=1e-10,
                                   rtol=1e-10)
        assert grads[0][..., :3].abs().amax() > 0


def test_a_plane_in_three_dimensions_gives_the_two_dimensional_messages():
    # 2-D particles embedded in 3-D at height zero: the same beliefs
    particles, lw, ei, ea, anchor = random_graph(gen(49), 4, 2, 6)
    flat = torch.zeros(particles.shape[:2] + (6, ), dtype=torch.float64)
    flat[..., :2] = particles[..., :2]
    flat[..., 3:5] = particles[..., 2:]
    for samples in (1, 'all'):
        conv = ParticleBPConv(GaussianRange(0.8), num_samples=samples)
        two, _ = conv(particles, lw, ei, ea, anchor=anchor)
        three, _ = conv(flat, lw, ei, ea, anchor=anchor)
        torch.testing.assert_close(three, two, atol=1e-12, rtol=1e-12)
