r"""Tests of :class:`tg_nebp.nn.conv.ParticleBPConv` against a slow, plain
Python reference of one particle BP iteration (loops over edges and
particles, :func:`math.hypot` and :func:`math.log` only)."""
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch_geometric import EdgeIndex
from torch_geometric.data import Batch, Data

import tg_nebp.nn.conv.particle_bp_conv as conv_module
from tg_nebp.filters import ParticleBP
from tg_nebp.models import GaussianRange
from tg_nebp.nn.conv import ParticleBPConv

from helpers import gen, random_graph

# --------------------------------------------------------------------------
# reference and random graphs
# --------------------------------------------------------------------------


def as_lists(particles, log_weights, edge_index, edge_attr,
             sender_log_weights, anchor):
    # the inputs of one BP iteration as float64 Python lists
    pos = particles.double().tolist()
    lw = log_weights.double().tolist()
    sender = lw if sender_log_weights is None else \
        sender_log_weights.double().tolist()
    edges = edge_index.tolist()
    ranges = edge_attr.double().view(-1).tolist()
    is_anchor = [False] * len(lw) if anchor is None else anchor.tolist()
    return pos, lw, sender, edges, ranges, is_anchor


def reference(particles, log_weights, edge_index, edge_attr, sigma=1.0,
              sender_log_weights=None, anchor=None):
    r"""One BP iteration with plain Python loops, in float64."""
    pos, lw, sender, edges, ranges, is_anchor = as_lists(
        particles, log_weights, edge_index, edge_attr, sender_log_weights,
        anchor)
    log_norm = math.log(math.sqrt(2.0 * math.pi) * sigma)
    out = [list(row) for row in lw]
    messages = []
    for e, (j, i) in enumerate(zip(edges[0], edges[1])):
        row = []
        for k in range(len(lw[0])):
            d = math.hypot(pos[j][k][0] - pos[i][k][0],
                           pos[j][k][1] - pos[i][k][1])
            m = -0.5 * ((ranges[e] - d) / sigma)**2 - log_norm + sender[j][k]
            row.append(m)
            if not is_anchor[i]:
                out[i][k] += m
        messages.append(row)
    num_particles = len(lw[0])
    return (torch.tensor(out, dtype=torch.float64),
            torch.tensor(messages, dtype=torch.float64).view(-1,
                                                             num_particles))


def float32_error_bound(particles, log_weights, edge_index, edge_attr,
                        sigma=1.0, sender_log_weights=None, anchor=None):
    r"""Bounds, in plain loops, on the float32 rounding error of
    :func:`reference`'s messages and beliefs. A range residual
    :math:`z - d` loses :math:`u(|z| + d)` to cancellation, which the
    quadratic scales by :math:`|z - d| / \sigma^2`; each float32 sum of
    n terms loses at most :math:`n u` times their absolute sum, with
    :math:`u = 2^{-24}`. With a small sigma and a large residual this is
    far above any fixed tolerance: a 5 m residual at sigma = 1 cm puts a
    single rounding of d at about 0.3 nats."""
    u = 2.0**-24
    pos, lw, sender, edges, ranges, is_anchor = as_lists(
        particles, log_weights, edge_index, edge_attr, sender_log_weights,
        anchor)
    log_norm = abs(math.log(math.sqrt(2.0 * math.pi) * sigma))
    cancellation = [[0.0] * len(row) for row in lw]
    magnitude = [[abs(x) for x in row] for row in lw]
    terms = [1] * len(lw)
    messages = []
    for e, (j, i) in enumerate(zip(edges[0], edges[1])):
        row = []
        terms[i] += 0 if is_anchor[i] else 1
        for k in range(len(lw[0])):
            d = math.hypot(pos[j][k][0] - pos[i][k][0],
                           pos[j][k][1] - pos[i][k][1])
            z = ranges[e]
            lost = 4 * u * (abs(z) + d + 1.0) * abs(z - d) / sigma**2
            size = 0.5 * ((z - d) / sigma)**2 + log_norm + abs(sender[j][k])
            row.append(lost + 4 * u * size)
            if not is_anchor[i]:
                cancellation[i][k] += lost
                magnitude[i][k] += size
        messages.append(row)
    out = [[c + (n + 2) * u * m for c, m in zip(crow, mrow)]
           for crow, mrow, n in zip(cancellation, magnitude, terms)]
    num_particles = len(lw[0])
    return (torch.tensor(out, dtype=torch.float64),
            torch.tensor(messages, dtype=torch.float64).view(-1,
                                                             num_particles))


def assert_within(actual, expected, bound, atol):
    r"""Every element within its own bound plus ``atol``."""
    excess = (actual.double() - expected).abs() - bound - atol
    worst = int(excess.argmax()) if excess.numel() else 0
    assert excess.numel() == 0 or excess.max() <= 0, (
        f'element {worst}: {actual.view(-1)[worst].item()} vs '
        f'{expected.view(-1)[worst].item()}, allowed '
        f'{bound.view(-1)[worst].item() + atol}')


# --------------------------------------------------------------------------
# 1. equality with the reference
# --------------------------------------------------------------------------

CASES = [
    # seed, agents, anchors, K, sigma, chunk_size, explicit sender, anchor
    (0, 4, 0, 5, 1.0, None, False, False),
    (1, 5, 2, 7, 1.0, None, True, True),
    (2, 6, 3, 4, 0.5, None, True, True),
    (3, 6, 3, 4, 0.5, 1, True, True),
    (4, 7, 2, 6, 1.0, 3, False, True),
    (5, 3, 4, 9, 0.5, 3, True, False),
    (6, 8, 1, 3, 2.0, 2, True, True),
]


@pytest.mark.parametrize(
    'seed,agents,anchors,K,sigma,chunk,use_sender,use_anchor', CASES)
def test_matches_reference(seed, agents, anchors, K, sigma, chunk,
                           use_sender, use_anchor):
    g = gen(seed)
    particles, lw, ei, ea, anchor = random_graph(g, agents, anchors, K,
                                                 sigma=sigma)
    assert ei.size(1) > 0
    sender = (torch.randn(lw.shape, generator=g, dtype=lw.dtype) * 3
              if use_sender else None)
    anchor = anchor if use_anchor else None
    conv = ParticleBPConv(GaussianRange(sigma=sigma), chunk_size=chunk)
    out, msg = conv(particles, lw, ei, ea, sender_log_weights=sender,
                    anchor=anchor)
    ref_out, ref_msg = reference(particles, lw, ei, ea, sigma, sender, anchor)
    assert out.shape == lw.shape and msg.shape == (ei.size(1), K)
    torch.testing.assert_close(out, ref_out, atol=1e-5, rtol=0)
    torch.testing.assert_close(msg, ref_msg, atol=1e-5, rtol=0)
    if use_anchor:  # anchors' rows unchanged, bit for bit
        assert torch.equal(out[anchor], lw[anchor])


def test_chunk_sizes_agree_float32():
    g = gen(10)
    particles, lw, ei, ea, anchor = random_graph(g, 9, 3, 11,
                                                 dtype=torch.float32)
    sender = torch.randn(lw.shape, generator=g)
    outs = [
        ParticleBPConv(chunk_size=c)(particles, lw, ei, ea, sender, anchor)
        for c in (None, 1, 3, ei.size(1) - 1, ei.size(1), 10 * ei.size(1))
    ]
    ref_out, ref_msg = reference(particles, lw, ei, ea, 1.0, sender, anchor)
    for out, msg in outs:
        assert out.dtype == torch.float32 and msg.dtype == torch.float32
        torch.testing.assert_close(out.double(), ref_out, atol=1e-4,
                                   rtol=1e-5)
        torch.testing.assert_close(msg.double(), ref_msg, atol=1e-4,
                                   rtol=1e-5)
        # the chunked path computes the same numbers as the one-shot path
        torch.testing.assert_close(out, outs[0][0], atol=1e-6, rtol=1e-6)


def test_non_positive_chunk_size_rejected():
    with pytest.raises(ValueError, match="'chunk_size' must be positive"):
        ParticleBPConv(chunk_size=0)


def test_edges_into_anchor_are_ignored():
    g = gen(11)
    particles, lw, ei, ea, anchor = random_graph(g, 4, 3, 5,
                                                 into_anchor=True,
                                                 edge_prob=0.8)
    assert bool(anchor[ei[1]].any())
    out, msg = ParticleBPConv()(particles, lw, ei, ea, anchor=anchor)
    ref_out, ref_msg = reference(particles, lw, ei, ea, anchor=anchor)
    assert torch.equal(out[anchor], lw[anchor])
    torch.testing.assert_close(out, ref_out, atol=1e-5, rtol=0)
    # the messages on those edges are still computed
    torch.testing.assert_close(msg, ref_msg, atol=1e-5, rtol=0)


# --------------------------------------------------------------------------
# 2. batching
# --------------------------------------------------------------------------


def test_batch_equals_separate_graphs():
    g = gen(20)
    data_list = []
    for agents, anchors in ((3, 2), (7, 3), (25, 4)):
        particles, lw, ei, ea, anchor = random_graph(g, agents, anchors, 6,
                                                     edge_prob=0.3,
                                                     area=30.0)
        sender = torch.randn(lw.shape, generator=g, dtype=lw.dtype)
        data_list.append(Data(particles=particles, log_weights=lw,
                              sender=sender, edge_index=ei, edge_attr=ea,
                              anchor=anchor, num_nodes=agents + anchors))
    batch = Batch.from_data_list(data_list)
    conv = ParticleBPConv(chunk_size=7)
    out, msg = conv(batch.particles, batch.log_weights, batch.edge_index,
                    batch.edge_attr, batch.sender, batch.anchor)
    edge_ptr = torch.tensor([0] + [d.edge_index.size(1) for d in data_list])
    edge_ptr = edge_ptr.cumsum(0)
    for b, d in enumerate(data_list):
        alone_out, alone_msg = conv(d.particles, d.log_weights, d.edge_index,
                                    d.edge_attr, d.sender, d.anchor)
        nodes = slice(int(batch.ptr[b]), int(batch.ptr[b + 1]))
        edges = slice(int(edge_ptr[b]), int(edge_ptr[b + 1]))
        torch.testing.assert_close(out[nodes], alone_out, atol=1e-10, rtol=0)
        torch.testing.assert_close(msg[edges], alone_msg, atol=1e-10, rtol=0)
        # and each graph agrees with the reference
        ref_out, _ = reference(d.particles, d.log_weights, d.edge_index,
                               d.edge_attr, 1.0, d.sender, d.anchor)
        torch.testing.assert_close(alone_out, ref_out, atol=1e-5, rtol=0)


# --------------------------------------------------------------------------
# 3. permutation equivariance
# --------------------------------------------------------------------------


@pytest.mark.parametrize('chunk', [None, 2])
def test_node_permutation_equivariance(chunk):
    g = gen(30)
    particles, lw, ei, ea, anchor = random_graph(g, 8, 3, 5, edge_prob=0.6)
    sender = torch.randn(lw.shape, generator=g, dtype=lw.dtype)
    n = lw.size(0)
    perm = torch.randperm(n, generator=g)  # new node a is old node perm[a]
    inv = torch.empty_like(perm)
    inv[perm] = torch.arange(n)
    conv = ParticleBPConv(chunk_size=chunk)
    out, msg = conv(particles, lw, ei, ea, sender, anchor)
    out_p, msg_p = conv(particles[perm], lw[perm], inv[ei], ea, sender[perm],
                        anchor[perm])
    torch.testing.assert_close(out_p, out[perm], atol=1e-12, rtol=0)
    torch.testing.assert_close(msg_p, msg, atol=1e-12, rtol=0)
    # edge order does not matter either
    eperm = torch.randperm(ei.size(1), generator=g)
    out_e, msg_e = conv(particles, lw, ei[:, eperm], ea[eperm], sender,
                        anchor)
    torch.testing.assert_close(out_e, out, atol=1e-10, rtol=0)
    torch.testing.assert_close(msg_e, msg[eperm], atol=1e-12, rtol=0)


# --------------------------------------------------------------------------
# 4. numerical safety
# --------------------------------------------------------------------------


def _hub_graph(dtype):
    r"""Agent 0 hears 60 neighbours (45 agents, 15 anchors) with ranges
    far from most particle distances; agent 1 hears nobody."""
    g = gen(40)
    K = 64
    num_agents, num_anchors = 47, 15
    n = num_agents + num_anchors
    particles = 20.0 * torch.randn(n, K, 4, generator=g,
                                   dtype=torch.float64)
    particles[num_agents:] = particles[num_agents:, :1]  # K copies
    anchor = torch.arange(n) >= num_agents
    src = torch.tensor([j for j in range(n) if j not in (0, 1)])
    ei = torch.stack([src, torch.zeros_like(src)])
    ea = 100.0 + 50.0 * torch.rand(src.numel(), 1, generator=g,
                                   dtype=torch.float64)
    lw = torch.full((n, K), -math.log(K), dtype=torch.float64)
    lw[1] = torch.randn(K, generator=g, dtype=torch.float64)
    return particles.to(dtype), lw.to(dtype), ei, ea.to(dtype), anchor


@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
def test_many_neighbours_peaked_likelihood_is_finite(dtype):
    particles, lw, ei, ea, anchor = _hub_graph(dtype)
    assert ei.size(1) == 60
    sigma = 1e-3
    conv = ParticleBPConv(GaussianRange(sigma=sigma))
    out, msg = conv(particles, lw, ei, ea, anchor=anchor)
    assert bool(torch.isfinite(out).all()) and bool(torch.isfinite(msg).all())
    # the likelihoods are astronomically small but do not underflow
    assert float(out[0].max()) < -1e6
    normalized = out[0] - out[0].logsumexp(-1)
    assert abs(float(normalized.double().exp().sum()) - 1.0) < 1e-5
    ref_out, _ = reference(particles, lw, ei, ea, sigma, anchor=anchor)
    torch.testing.assert_close(out.double(), ref_out, rtol=1e-5, atol=1e-5)
    assert int(out[0].argmax()) == int(ref_out[0].argmax())
    # no incoming edge: log-weights kept exactly
    assert torch.equal(out[1], lw[1])
    assert torch.equal(out[2:], lw[2:])


@pytest.mark.parametrize('num_iterations', [1, 2])
def test_particle_bp_update_is_normalized_and_finite(num_iterations):
    particles, lw, ei, ea, anchor = _hub_graph(torch.float32)
    K = lw.size(1)
    bp = ParticleBP(num_particles=K, num_iterations=num_iterations,
                    measurement=GaussianRange(sigma=1e-3))
    new = bp.update(particles, lw, ei, ea, anchor)
    assert new.shape == lw.shape
    assert bool(torch.isfinite(new).all())
    sums = new.double().exp().sum(-1)
    torch.testing.assert_close(sums, torch.ones_like(sums), atol=1e-5, rtol=0)
    # one iteration is the reference belief, normalized
    ref_out, _ = reference(particles, lw, ei, ea, 1e-3, anchor=anchor)
    ref = ref_out - ref_out.logsumexp(-1, keepdim=True)
    if num_iterations == 1:
        torch.testing.assert_close(new.double(), ref, atol=1e-4, rtol=1e-5)
    # agents without measurements just normalize their prediction
    torch.testing.assert_close(new[1].double(), ref[1], atol=1e-5, rtol=0)


def test_particle_bp_update_two_iterations_matches_reference():
    g = gen(41)
    particles, lw, ei, ea, anchor = random_graph(g, 6, 2, 5, edge_prob=0.6)
    bp = ParticleBP(num_particles=5, num_iterations=2)
    new = bp.update(particles, lw, ei, ea, anchor)
    out1, _ = reference(particles, lw, ei, ea, anchor=anchor)
    sender = out1 - out1.logsumexp(-1, keepdim=True)
    out2, _ = reference(particles, lw, ei, ea, sender_log_weights=sender,
                        anchor=anchor)
    torch.testing.assert_close(new, out2 - out2.logsumexp(-1, keepdim=True),
                               atol=1e-5, rtol=0)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.data())
def test_property_no_nan_for_wide_log_weights(data):
    num_agents = data.draw(st.integers(1, 5), label='agents')
    num_anchors = data.draw(st.integers(0, 3), label='anchors')
    K = data.draw(st.integers(1, 4), label='K')
    n = num_agents + num_anchors
    coord = st.floats(-100.0, 100.0, allow_nan=False, width=32)
    pos = data.draw(st.lists(st.lists(coord, min_size=2, max_size=2),
                             min_size=n * K, max_size=n * K), label='pos')
    particles = torch.zeros(n, K, 4)
    particles[..., :2] = torch.tensor(pos).view(n, K, 2)
    particles[num_agents:] = particles[num_agents:, :1]
    pairs = [(j, i) for i in range(num_agents) for j in range(n) if i != j]
    chosen = data.draw(st.lists(st.sampled_from(pairs), max_size=12)
                       if pairs else st.just([]), label='edges')
    ei = torch.tensor(chosen, dtype=torch.long).view(-1, 2).t().contiguous()
    ea = torch.tensor(data.draw(st.lists(
        st.floats(0.0, 300.0, width=32), min_size=len(chosen),
        max_size=len(chosen)), label='ranges')).view(-1, 1)
    wide = st.floats(-1e4, 1e4, allow_nan=False, width=32)
    lw = torch.tensor(data.draw(st.lists(wide, min_size=n * K,
                                         max_size=n * K),
                                label='log_weights')).view(n, K)
    sender = None
    if data.draw(st.booleans(), label='explicit sender'):
        sender = torch.tensor(data.draw(st.lists(
            wide, min_size=n * K, max_size=n * K))).view(n, K)
    sigma = data.draw(st.sampled_from([1e-2, 1.0, 5.0]), label='sigma')
    anchor = torch.arange(n) >= num_agents
    conv = ParticleBPConv(GaussianRange(sigma=sigma),
                          chunk_size=data.draw(st.sampled_from([None, 1, 2])))
    out, msg = conv(particles, lw, ei, ea, sender, anchor)
    assert not bool(torch.isnan(out).any())
    assert not bool(torch.isnan(msg).any())
    assert bool(torch.isfinite(out).all())
    ref_out, ref_msg = reference(particles, lw, ei, ea, sigma, sender, anchor)
    out_bound, msg_bound = float32_error_bound(particles, lw, ei, ea, sigma,
                                               sender, anchor)
    assert_within(out, ref_out, out_bound, atol=1e-4)
    assert_within(msg, ref_msg, msg_bound, atol=1e-4)
    normalized = out.double() - out.double().logsumexp(-1, keepdim=True)
    sums = normalized.exp().sum(-1)
    torch.testing.assert_close(sums, torch.ones_like(sums), atol=1e-6,
                               rtol=0)


def test_minus_inf_log_weight_stays_minus_inf_without_nan():
    g = gen(42)
    particles, lw, ei, ea, anchor = random_graph(g, 4, 1, 3, edge_prob=1.0)
    lw[:, 1] = -math.inf  # particle 1 pruned everywhere
    out, msg = ParticleBPConv()(particles, lw, ei, ea, anchor=anchor)
    assert not bool(torch.isnan(out).any())
    assert bool((out[:, 1] == -math.inf).all())
    assert bool(torch.isfinite(out[:, [0, 2]]).all())


# --------------------------------------------------------------------------
# 5. anchors only
# --------------------------------------------------------------------------


def test_agent_hearing_only_anchors_uses_them():
    g = gen(50)
    K = 8
    anchors_xy = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]],
                              dtype=torch.float64)
    truth = torch.tensor([3.0, 4.0], dtype=torch.float64)
    n = 4  # node 0 the agent, nodes 1..3 anchors
    particles = torch.zeros(n, K, 4, dtype=torch.float64)
    particles[0, :, :2] = truth + 3.0 * torch.randn(K, 2, generator=g,
                                                   dtype=torch.float64)
    particles[0, 0, :2] = truth  # one particle exactly at the truth
    particles[1:, :, :2] = anchors_xy.unsqueeze(1)
    anchor = torch.tensor([False, True, True, True])
    ei = torch.tensor([[1, 2, 3], [0, 0, 0]])
    ea = (anchors_xy - truth).norm(dim=-1).view(-1, 1)  # noiseless ranges
    lw = torch.full((n, K), -math.log(K), dtype=torch.float64)
    out, msg = ParticleBPConv()(particles, lw, ei, ea, anchor=anchor)
    assert not torch.allclose(out[0], lw[0])
    ref_out, ref_msg = reference(particles, lw, ei, ea, anchor=anchor)
    torch.testing.assert_close(out, ref_out, atol=1e-5, rtol=0)
    torch.testing.assert_close(msg, ref_msg, atol=1e-5, rtol=0)
    assert torch.equal(out[1:], lw[1:])
    # the particle at the true position explains the ranges best
    assert int(out[0].argmax()) == 0


# --------------------------------------------------------------------------
# 6. deterministic aggregation through a receiver-sorted EdgeIndex
# --------------------------------------------------------------------------


@pytest.mark.parametrize('chunk', [None, 2])
def test_sorted_edge_index_uses_segment_sum(monkeypatch, chunk):
    g = gen(60)
    particles, lw, ei, ea, anchor = random_graph(g, 9, 3, 6, edge_prob=0.5,
                                                 dtype=torch.float32)
    sender = torch.randn(lw.shape, generator=g)
    n = lw.size(0)
    order = torch.argsort(ei[1] * n + ei[0])
    ei_sorted, ea_sorted = ei[:, order], ea[order]
    conv = ParticleBPConv(chunk_size=chunk)
    plain_out, plain_msg = conv(particles, lw, ei_sorted, ea_sorted, sender,
                                anchor)

    calls = []
    original = conv_module.segment

    def spy(src, ptr, reduce='sum'):
        calls.append(ptr.clone())
        return original(src, ptr, reduce=reduce)

    monkeypatch.setattr(conv_module, 'segment', spy)
    edge_index = EdgeIndex(ei_sorted, sparse_size=(n, n), sort_order='col')
    out, msg = conv(particles, lw, edge_index, ea_sorted, sender, anchor)
    out2, _ = conv(particles, lw, edge_index, ea_sorted, sender, anchor)
    # the segment sum was used, with the CSC pointer of the receivers
    assert len(calls) == 2
    expected_ptr = torch.zeros(n + 1, dtype=torch.long)
    expected_ptr[1:] = torch.bincount(ei_sorted[1], minlength=n).cumsum(0)
    assert torch.equal(calls[0].long(), expected_ptr)
    # the sums run in another order (to rounding); the messages are the
    # same operations on the same edges before either sum: bit for bit
    torch.testing.assert_close(out, plain_out, atol=1e-5, rtol=1e-6)
    torch.testing.assert_close(msg, plain_msg, atol=0, rtol=0)
    assert torch.equal(out, out2)  # deterministic
    ref_out, _ = reference(particles, lw, ei, ea, 1.0, sender, anchor)
    torch.testing.assert_close(out.double(), ref_out, atol=1e-4, rtol=1e-5)
    assert out.shape == (n, lw.size(1))


# --------------------------------------------------------------------------
# 7. gradients
# --------------------------------------------------------------------------


@pytest.mark.parametrize('chunk', [None, 1])
def test_gradcheck(chunk):
    g = gen(70)
    particles, lw, ei, ea, anchor = random_graph(g, 3, 1, 3, edge_prob=0.8)
    sender = torch.randn(lw.shape, generator=g, dtype=torch.float64)
    conv = ParticleBPConv(GaussianRange(sigma=0.7), chunk_size=chunk)

    def fn(p, w, s):
        out, msg = conv(p, w, ei, ea, s, anchor, validate=False)
        return out, msg

    inputs = (particles.clone().requires_grad_(),
              lw.clone().requires_grad_(), sender.clone().requires_grad_())
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5)


def test_gradients_match_reference_formula():
    r"""d out_i^k / d p_i^k from the closed form of the Gaussian range
    likelihood, and d out_i^k / d sender_j^k = number of edges j -> i."""
    g = gen(71)
    particles, lw, ei, ea, anchor = random_graph(g, 4, 2, 3, edge_prob=0.7)
    sender = torch.randn(lw.shape, generator=g, dtype=torch.float64)
    sigma = 0.8
    p = particles.clone().requires_grad_()
    s = sender.clone().requires_grad_()
    out, _ = ParticleBPConv(GaussianRange(sigma=sigma))(p, lw, ei, ea, s,
                                                         anchor)
    out.sum().backward()
    # reference gradients with plain loops
    n, K = lw.shape
    pos = particles.tolist()
    gp = [[[0.0] * 4 for _ in range(K)] for _ in range(n)]
    gs = [[0.0] * K for _ in range(n)]
    for e, (j, i) in enumerate(zip(ei[0].tolist(), ei[1].tolist())):
        if bool(anchor[i]):
            continue
        z = float(ea[e, 0])
        for k in range(K):
            dx = pos[j][k][0] - pos[i][k][0]
            dy = pos[j][k][1] - pos[i][k][1]
            d = math.hypot(dx, dy)
            dld = (z - d) / sigma**2  # d log N / d distance
            gp[j][k][0] += dld * dx / d
            gp[j][k][1] += dld * dy / d
            gp[i][k][0] -= dld * dx / d
            gp[i][k][1] -= dld * dy / d
            gs[j][k] += 1.0
    torch.testing.assert_close(p.grad, torch.tensor(gp, dtype=torch.float64),
                               atol=1e-8, rtol=1e-6)
    torch.testing.assert_close(s.grad, torch.tensor(gs, dtype=torch.float64),
                               atol=0, rtol=0)


def test_gradient_finite_when_paired_particles_coincide():
    particles = torch.zeros(2, 2, 4, dtype=torch.float64)
    particles[0, 1, :2] = torch.tensor([1.0, 2.0])  # particle 0 coincides
    particles.requires_grad_()
    lw = torch.zeros(2, 2, dtype=torch.float64)
    ei = torch.tensor([[1], [0]])
    ea = torch.tensor([[0.5]], dtype=torch.float64)
    out, _ = ParticleBPConv()(particles, lw, ei, ea)
    out.sum().backward()
    assert bool(torch.isfinite(particles.grad).all())


def test_sorted_edge_index_without_messages_equals_plain_path():
    gen = torch.Generator().manual_seed(11)
    num_nodes, num_particles = 12, 64
    particles = 10 * torch.randn(num_nodes, num_particles, 4, generator=gen)
    log_weights = torch.randn(num_nodes, num_particles, generator=gen)
    src = torch.randint(0, num_nodes, (40, ), generator=gen)
    dst = (src + torch.randint(1, num_nodes, (40, ), generator=gen)) % num_nodes
    order = torch.argsort(dst, stable=True)
    edge_index = torch.stack([src[order], dst[order]])
    ranges = 10 * torch.rand(40, 1, generator=gen)
    conv = ParticleBPConv()
    reference, reference_messages = conv(particles, log_weights, edge_index,
                                         ranges)
    sorted_edges = EdgeIndex(edge_index, sparse_size=(num_nodes, num_nodes),
                             sort_order='col')
    out, messages = conv(particles, log_weights, sorted_edges, ranges,
                         return_messages=False)
    assert messages is None
    torch.testing.assert_close(out, reference, rtol=1e-6, atol=1e-4)
    out, messages = conv(particles, log_weights, sorted_edges, ranges)
    torch.testing.assert_close(out, reference, rtol=1e-6, atol=1e-4)
    torch.testing.assert_close(messages, reference_messages)


# --------------------------------------------------------------------------
# 8. summing without materializing the messages (bounded memory)
# --------------------------------------------------------------------------


@pytest.mark.parametrize('chunk', [None, 1, 3, 10_000])
@pytest.mark.parametrize('as_edge_index', [False, True])
def test_without_messages_matches_reference(chunk, as_edge_index):
    g = gen(80)
    particles, lw, ei, ea, anchor = random_graph(g, 9, 3, 5, edge_prob=0.6)
    sender = torch.randn(lw.shape, generator=g, dtype=torch.float64)
    n = lw.size(0)
    if as_edge_index:  # sorted by receiver, as the trackers pass them
        order = torch.argsort(ei[1], stable=True)
        ei, ea = ei[:, order], ea[order]
        edges = EdgeIndex(ei, sparse_size=(n, n), sort_order='col')
    else:  # random order: the conv sorts them itself
        order = torch.randperm(ei.size(1), generator=g)
        ei, ea = ei[:, order], ea[order]
        edges = ei
    conv = ParticleBPConv(GaussianRange(sigma=0.8), chunk_size=chunk)
    out, messages = conv(particles, lw, edges, ea, sender, anchor,
                         return_messages=False)
    ref_out, _ = reference(particles, lw, ei, ea, 0.8, sender, anchor)
    assert messages is None
    torch.testing.assert_close(out, ref_out, atol=1e-9, rtol=0)


def test_without_messages_works_block_by_block(monkeypatch):
    # every edge is computed exactly once, in blocks of whole receivers that
    # hold at most chunk + (edges of the block's first receiver) edges
    g = gen(81)
    particles, lw, ei, ea, anchor = random_graph(g, 14, 3, 4, edge_prob=0.7)
    chunk = 5
    blocks = []
    original = ParticleBPConv._log_messages

    def spy(self, planes, sender, link_features, src, dst, shifts=None):
        blocks.append((src.clone(), dst.clone()))
        return original(self, planes, sender, link_features, src, dst,
                        shifts)

    monkeypatch.setattr(ParticleBPConv, '_log_messages', spy)
    conv = ParticleBPConv(chunk_size=chunk)
    out, _ = conv(particles, lw, ei, ea, anchor=anchor, return_messages=False)
    assert len(blocks) > 3
    degree = torch.bincount(ei[1], minlength=lw.size(0))
    seen = torch.cat([torch.stack(b) for b in blocks], dim=1)
    order = torch.argsort(ei[1], stable=True)
    assert torch.equal(seen, ei[:, order])  # each edge once, none left out
    receivers_so_far = set()
    for _, dst in blocks:
        receivers = set(dst.tolist())
        assert not receivers & receivers_so_far  # whole receivers per block
        receivers_so_far |= receivers
        first = int(dst.min())
        assert dst.numel() <= chunk + int(degree[first])
    ref_out, _ = reference(particles, lw, ei, ea, anchor=anchor)
    torch.testing.assert_close(out, ref_out, atol=1e-9, rtol=0)


@given(degrees=st.lists(st.integers(0, 12), min_size=1, max_size=40),
       chunk=st.integers(1, 30))
@settings(max_examples=200, deadline=None)
def test_property_receiver_blocks_partition_the_nodes(degrees, chunk):
    ptr = torch.tensor([0] + degrees).cumsum(0)
    bounds = ParticleBPConv._receiver_blocks(ptr, chunk)
    assert bounds[0] == 0 and bounds[-1] == len(degrees)
    assert all(a < b for a, b in zip(bounds, bounds[1:]))
    for first, last in zip(bounds[:-1], bounds[1:]):
        edges = int(ptr[last] - ptr[first])
        # a block holds about one chunk: at most the edges of its first
        # receiver beyond it
        assert edges <= chunk + degrees[first]


@pytest.mark.parametrize('chunk', [None, 2])
def test_gradcheck_without_messages(chunk):
    # several blocks are recomputed in the backward pass (checkpointing)
    g = gen(82)
    particles, lw, ei, ea, anchor = random_graph(g, 5, 2, 3, edge_prob=0.8)
    sender = torch.randn(lw.shape, generator=g, dtype=torch.float64)
    conv = ParticleBPConv(GaussianRange(sigma=0.7), chunk_size=chunk)

    def fn(p, s, r):
        out, _ = conv(p, lw, ei, r, s, anchor, validate=False,
                      return_messages=False)
        return out

    inputs = (particles.clone().requires_grad_(),
              sender.clone().requires_grad_(), ea.clone().requires_grad_())
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5)
    # and the gradients equal those of the materialized path
    grads = []
    for return_messages in (True, False):
        p, s = particles.clone().requires_grad_(), sender.clone(
        ).requires_grad_()
        out, _ = conv(p, lw, ei, ea, s, anchor,
                      return_messages=return_messages)
        out.square().sum().backward()
        grads.append((p.grad, s.grad))
    torch.testing.assert_close(grads[0], grads[1], atol=1e-9, rtol=1e-9)


class LogCoshRange(GaussianRange):
    r"""A heavier-tailed range likelihood: it overrides the Gaussian formula
    only, so the Gaussian's fast pieces (closed-form gradient, in-place,
    fused) are closed to it and autograd differentiates it."""
    def log_likelihood_of_distance(self, z, distances):
        return -torch.log(torch.cosh((z[:, :1] - distances) / self.sigma))


@pytest.mark.parametrize('measurement', [GaussianRange(sigma=0.7),
                                         LogCoshRange(sigma=0.7)])
def test_blockwise_gradients_equal_autograd_of_materialized_messages(
        measurement):
    g = gen(83)
    particles, lw, ei, ea, anchor = random_graph(g, 6, 2, 4, edge_prob=0.8)
    sender = torch.randn(lw.shape, generator=g, dtype=torch.float64)
    # one pair of coinciding particles: a zero, not NaN, gradient
    particles[1, 0, :2] = particles[0, 0, :2]
    grads = []
    for chunk, return_messages in ((None, True), (2, False)):
        conv = ParticleBPConv(measurement, chunk_size=chunk)
        inputs = [particles.clone().requires_grad_(),
                  sender.clone().requires_grad_(), ea.clone().requires_grad_()]
        out, _ = conv(inputs[0], lw, ei, inputs[2], inputs[1], anchor,
                      return_messages=return_messages)
        out.sin().sum().backward()
        grads.append([t.grad for t in inputs])
    for blockwise, materialized in zip(grads[1], grads[0]):
        assert bool(torch.isfinite(blockwise).all())
        torch.testing.assert_close(blockwise, materialized, atol=1e-10,
                                   rtol=1e-9)


# ---- index and floating dtypes that validation accepts ---------------------

@pytest.mark.parametrize('return_messages', [True, False])
def test_int32_edge_index_equals_int64(return_messages):
    # int32 passed check_graph, then PyG's scatter wanted int64
    particles, lw, ei, ea, anchor = random_graph(gen(80), 4, 2, 6)
    conv = ParticleBPConv()
    expected = conv(particles, lw, ei, ea, anchor=anchor,
                    return_messages=return_messages)
    for edges in (ei.int(), EdgeIndex(ei.int(), sparse_size=(6, 6))):
        out = conv(particles, lw, edges, ea, anchor=anchor,
                   return_messages=return_messages)
        assert torch.equal(out[0], expected[0])
        if return_messages:
            assert torch.equal(out[1], expected[1])


def test_half_precision_inputs_compute_in_float32():
    particles, lw, ei, ea, anchor = random_graph(gen(81), 4, 2, 6,
                                                 dtype=torch.float32)
    conv = ParticleBPConv()
    half = conv(particles.half(), lw, ei, ea, anchor=anchor)
    same = conv(particles.half().float(), lw, ei, ea, anchor=anchor)
    assert half[0].dtype == torch.float32
    assert torch.equal(half[0], same[0]) and torch.equal(half[1], same[1])
    # ranges and weights in bfloat16: float32 too
    out, _ = conv(particles, lw.bfloat16(), ei, ea.bfloat16(), anchor=anchor)
    assert out.dtype == torch.float32 and torch.isfinite(out).all()


def test_false_sort_claim_is_rejected_not_believed():
    # the issue: an unsorted EdgeIndex claiming sort_order='col' passed and
    # gave log-weights off by up to 58
    particles, lw, ei, ea, anchor = random_graph(gen(82), 5, 2, 4)
    ei, ea = ei.flip(1), ea.flip(0)  # random_graph sorts by receiver
    claimed = EdgeIndex(ei, sparse_size=(7, 7), sort_order='col')
    with pytest.raises(ValueError, match=r"'edge_index' claims "
                       r"sort_order='col' but 'edge_index\[1, \d+\]'"):
        ParticleBPConv()(particles, lw, claimed, ea, anchor=anchor,
                         return_messages=False)
