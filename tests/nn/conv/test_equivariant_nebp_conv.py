r"""Tests of :class:`tg_nebp.nn.conv.EquivariantNEBPConv`: a float64
re-computation with plain loops, equivariance to a permutation of each
node's particles, one set of weights at any K (duplicated particles give the
same beliefs), the identity correction equals BP, batching, and finite
gradients with -inf log-messages."""
import math

import pytest
import torch
from torch_geometric.data import Batch, Data

import tg_nebp.nn.conv.equivariant_nebp_conv as module
from tg_nebp.nn.conv import EquivariantNEBPConv, ParticleBPConv
from tg_nebp.nn.conv.nebp_conv import node_embedding

from helpers import Const, gen, random_graph


def make_conv(seed=0, **kwargs):
    torch.manual_seed(seed)
    options = dict(message_dim=6, hidden_dim=12, particle_dim=8,
                   num_samples='all')
    options.update(kwargs)
    return EquivariantNEBPConv(**options).double()


def loop_moments(points, log_weights):
    # weighted mean and covariance of 2-D points with plain loops
    top = max(log_weights)
    w = [math.exp(v - top) for v in log_weights]
    total = sum(w)
    w = [v / total for v in w]
    mean = [sum(wk * p[d] for wk, p in zip(w, points)) for d in range(2)]
    cov = [[sum(wk * (p[a] - mean[a]) * (p[b] - mean[b])
                for wk, p in zip(w, points)) for b in range(2)]
           for a in range(2)]
    return mean, cov


def reference(conv, particles, log_weights, edge_index, edge_attr, anchor,
              sigma=1.0):
    r"""The layer's formula edge by edge and particle by particle in
    float64: the exact BP message, its mean-one scaling, the whitened
    positions (2x2 Cholesky by hand), the message summaries, g_e, g_s and
    the per-particle g_v from the conv's own weights."""
    n, K, _ = particles.shape
    pos = particles[..., :2].double().tolist()
    lw = log_weights.double().tolist()
    emb = node_embedding(particles.double(), log_weights.double())
    moments = [loop_moments(pos[i], lw[i]) for i in range(n)]
    out = log_weights.double().clone()
    for e in range(edge_index.size(1)):
        j, i = int(edge_index[0, e]), int(edge_index[1, e])
        z = float(edge_attr[e, 0])
        log_phi = []
        for k in range(K):
            terms = [lw[j][l] - 0.5 * ((z - math.dist(pos[j][l], pos[i][k]))
                                       / sigma)**2
                     for l in range(K)]
            top = max(terms)
            log_phi.append(top + math.log(sum(math.exp(t - top)
                                              for t in terms)))
        top = max(log_phi)
        total = math.log(sum(math.exp(v - top) for v in log_phi)) + top
        log_phi = [v - total + math.log(K) for v in log_phi]
        (mx, my), cov = moments[i]
        jitter = (cov[0][0] + cov[1][1]) / 2 * 1e-6 + 1e-12
        a = math.sqrt(cov[0][0] + jitter)
        b = cov[1][0] / a
        c = math.sqrt(cov[1][1] + jitter - b * b)
        u = []
        for k in range(K):
            u0 = (pos[i][k][0] - mx) / a
            u.append((u0, (pos[i][k][1] - my - b * u0) / c))
        top = max(lw[i][k] + log_phi[k] for k in range(K))
        pi = [math.exp(lw[i][k] + log_phi[k] - top) for k in range(K)]
        total = sum(pi)
        pi = [p / total for p in pi]
        first = [sum(p * v[d] for p, v in zip(pi, u)) for d in range(2)]
        second = [sum(p * v[0] * v[0] for p, v in zip(pi, u)),
                  sum(p * v[0] * v[1] for p, v in zip(pi, u)),
                  sum(p * v[1] * v[1] for p, v in zip(pi, u))]
        ess = 1 / (K * sum(p * p for p in pi))
        h_i, h_j = emb[i], emb[j]
        features = torch.cat([h_j[:4] - h_i[:4], h_i[4:], h_j[4:]]) / 10.0
        summaries = torch.tensor(first + second + [ess], dtype=torch.float64)
        with torch.no_grad():
            m = conv.g_e(torch.cat([features, summaries]).view(1, -1))
            g_s = torch.sigmoid(conv.g_s(m)).item()
            edge_part = conv.g_v_edge(m)[0]
        (sx, sy), scov = moments[j]
        spread = math.sqrt(0.5 * (scov[0][0] + scov[1][1]) + 1.0)
        top = max(log_phi)
        for k in range(K):
            below = max(log_phi[k] - top, -30.0) / 10.0
            residual = (z - math.dist(pos[i][k], (sx, sy))) / spread
            f = torch.tensor([u[k][0], u[k][1], below, residual],
                             dtype=torch.float64)
            with torch.no_grad():
                hidden = torch.nn.functional.leaky_relu(
                    edge_part + conv.g_v_particle(f))
                g_v = math.exp(conv.g_v_out(hidden).item())
            corrected = g_s * math.exp(log_phi[k]) + g_v
            if bool(anchor[j]) and not conv.correct_anchor_edges:
                corrected = math.exp(log_phi[k])
            out[i, k] += math.log(corrected)
    out[anchor] = log_weights.double()[anchor]
    return out


@pytest.mark.parametrize('correct_anchors', [False, True])
def test_matches_a_float64_loop_reference(correct_anchors):
    particles, lw, ei, ea, anchor = random_graph(gen(60), 4, 2, 5,
                                                 edge_prob=0.8)
    lw = torch.randn(lw.shape, generator=gen(61), dtype=torch.float64)
    conv = make_conv(correct_anchor_edges=correct_anchors)
    out, _ = conv(particles, lw, ei, ea, anchor)
    expected = reference(conv, particles, lw, ei, ea, anchor)
    torch.testing.assert_close(out, expected, rtol=1e-9, atol=1e-9)


def permute_each_node(g, *tensors):
    # an independent permutation of every node's particles
    n, K = tensors[0].shape[:2]
    perms = torch.stack([torch.randperm(K, generator=g) for _ in range(n)])
    rows = torch.arange(n).view(-1, 1)
    return perms, [t[rows, perms] for t in tensors]


def test_equivariant_to_a_permutation_of_each_nodes_particles():
    particles, lw, ei, ea, anchor = random_graph(gen(62), 6, 3, 9,
                                                 edge_prob=0.6)
    lw = torch.randn(lw.shape, generator=gen(63), dtype=torch.float64)
    sender = torch.randn(lw.shape, generator=gen(64), dtype=torch.float64)
    conv = make_conv(node_update=True)
    out, emb = conv(particles, lw, ei, ea, anchor, sender_log_weights=sender)
    perms, (p2, lw2, s2) = permute_each_node(gen(65), particles, lw, sender)
    out2, emb2 = conv(p2, lw2, ei, ea, anchor, sender_log_weights=s2)
    rows = torch.arange(out.size(0)).view(-1, 1)
    torch.testing.assert_close(out2, out[rows, perms], rtol=1e-10,
                               atol=1e-10)
    torch.testing.assert_close(emb2, emb, rtol=1e-10, atol=1e-10)


def test_paper_layer_is_not_equivariant():
    # the motivation, measured: NEBPConv's g_v ties offset k to index k
    from tg_nebp.nn.conv import NEBPConv
    particles, lw, ei, ea, anchor = random_graph(gen(66), 6, 3, 9,
                                                 edge_prob=0.6)
    torch.manual_seed(0)
    conv = NEBPConv(9, message_dim=6, hidden_dim=12,
                    num_samples='all').double()
    out, _ = conv(particles, lw, ei, ea, anchor)
    perms, (p2, lw2) = permute_each_node(gen(67), particles, lw)
    out2, _ = conv(p2, lw2, ei, ea, anchor)
    rows = torch.arange(out.size(0)).view(-1, 1)
    assert (out2 - out[rows, perms]).abs().max() > 1e-3


def test_same_weights_at_any_k_and_duplicated_particles_agree():
    conv = make_conv()
    for K in (100, 1000):
        particles, lw, ei, ea, anchor = random_graph(gen(68), 4, 2, K,
                                                     edge_prob=0.7)
        out, _ = conv(particles, lw, ei, ea, anchor)
        assert out.shape == (6, K) and bool(torch.isfinite(out).all())
    # every particle twice, each copy with half the weight: the same
    # distribution, so the same normalized beliefs per copy
    particles, lw, ei, ea, anchor = random_graph(gen(69), 4, 2, 7,
                                                 edge_prob=0.7)
    lw = torch.randn(lw.shape, generator=gen(70),
                     dtype=torch.float64).log_softmax(-1)
    out, _ = conv(particles, lw, ei, ea, anchor)
    twice, _ = conv(particles.repeat(1, 2, 1), lw.repeat(1, 2) - math.log(2),
                    ei, ea, anchor)
    torch.testing.assert_close(twice.log_softmax(-1),
                               out.repeat(1, 2).log_softmax(-1),
                               rtol=1e-9, atol=1e-9)


def test_identity_correction_equals_particle_bp():
    particles, lw, ei, ea, anchor = random_graph(gen(71), 5, 3, 8,
                                                 edge_prob=0.7)
    sender = torch.randn(lw.shape, generator=gen(72), dtype=torch.float64)
    conv = make_conv(num_samples=1)
    conv.g_s = Const(1, 1e4)  # sigmoid = 1
    torch.nn.init.zeros_(conv.g_v_out.weight)
    torch.nn.init.constant_(conv.g_v_out.bias, -1e4)  # exp = 0
    out, _ = conv(particles, lw, ei, ea, anchor, sender_log_weights=sender)
    bp, _ = ParticleBPConv()(particles, lw, ei, ea, sender, anchor)
    # equal up to a per-node constant (the mean-one scaling of messages)
    torch.testing.assert_close(out.log_softmax(-1), bp.log_softmax(-1),
                               rtol=1e-10, atol=1e-10)


def test_batch_equals_each_graph_alone():
    conv = make_conv(num_samples=1)
    graphs = []
    for seed in (73, 74):
        particles, lw, ei, ea, anchor = random_graph(gen(seed), 4, 2, 6,
                                                     edge_prob=0.7)
        graphs.append(Data(particles=particles, lw=lw, edge_index=ei,
                           edge_attr=ea, anchor=anchor, num_nodes=6))
    batch = Batch.from_data_list(graphs)
    out, _ = conv(batch.particles, batch.lw, batch.edge_index,
                  batch.edge_attr, batch.anchor)
    alone = torch.cat([conv(g.particles, g.lw, g.edge_index, g.edge_attr,
                            g.anchor)[0] for g in graphs])
    torch.testing.assert_close(out, alone, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('chunk', [1, 40, 1 << 20])
def test_per_particle_mlp_in_chunks_equals_the_plain_formula(monkeypatch,
                                                            chunk):
    # g_v over chunks of edges with a closed-form backward: the same values
    # and gradients as the formula written with autograd, for chunks of one
    # edge, of a few, and all edges at once
    monkeypatch.setattr(module, 'HIDDEN_CHUNK', chunk)
    g = gen(78)
    inputs = [torch.randn(shape, generator=g, dtype=torch.float64,
                          requires_grad=True)
              for shape in ((5, 6), (5, 7, 4), (6, 4), (1, 6), (1, ))]
    edge_part, features, weight_p, weight_o, bias_o = inputs
    plain = (torch.nn.functional.leaky_relu(
        edge_part.unsqueeze(1) + features @ weight_p.t()) @ weight_o.t()
    ).squeeze(-1) + bias_o
    out = module._ParticleMLP.apply(*inputs)
    torch.testing.assert_close(out, plain, rtol=1e-14, atol=1e-14)
    weights = torch.randn(5, 7, generator=g, dtype=torch.float64)
    for got, want in zip(torch.autograd.grad((out * weights).sum(), inputs),
                         torch.autograd.grad((plain * weights).sum(),
                                             inputs)):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradcheck(module._ParticleMLP.apply, inputs)


def test_offsets_never_die():
    # a ReLU head pushed below zero at every particle (as training left
    # one) gives zero offsets, BP's beliefs and no gradient ever again;
    # the log-domain head keeps a positive offset with a gradient
    particles, lw, ei, ea, anchor = random_graph(gen(77), 5, 2, 8,
                                                 edge_prob=0.8)
    conv = make_conv(num_samples=1)
    torch.nn.init.constant_(conv.g_v_out.bias, -8.0)
    seen = []
    combine = conv.combine

    def spy(message, log_phi, log_offset, edge_index, anchor):
        seen.append(log_offset)
        return combine(message, log_phi, log_offset, edge_index, anchor)

    conv.combine = spy
    out, _ = conv(particles, lw, ei, ea, anchor)
    assert bool(torch.isfinite(seen[0]).all())
    out.log_softmax(-1)[~anchor].square().sum().backward()
    assert bool(conv.g_v_out.bias.grad.abs() > 0)
    assert bool(conv.g_v_particle.weight.grad.abs().sum() > 0)
    bp, _ = ParticleBPConv()(particles, lw, ei, ea, None, anchor)
    assert not torch.allclose(out.log_softmax(-1)[~anchor],
                              bp.log_softmax(-1)[~anchor], atol=1e-6)


def test_gradients_reach_every_parameter_and_are_finite_with_neg_inf():
    particles, lw, ei, ea, anchor = random_graph(gen(75), 5, 2, 8,
                                                 edge_prob=0.8)
    # paired messages with -inf sender weights: -inf log-messages, and one
    # agent whose every message is -inf at some particles
    sender = torch.randn(lw.shape, generator=gen(76), dtype=torch.float64)
    sender[:5, :3] = -math.inf
    # and -inf prediction weights (the offsets keep every corrected message
    # finite, so these are what stays -inf)
    lw[0, :2] = -math.inf
    conv = make_conv(num_samples=1, node_update=True,
                     correct_anchor_edges=True)
    out, emb = conv(particles, lw, ei, ea, anchor, sender_log_weights=sender)
    assert bool(torch.isneginf(out).any())
    finite = torch.isfinite(out)
    (out[finite].sin().sum() + emb.sum()).backward()
    for name, parameter in conv.named_parameters():
        assert parameter.grad is not None, name
        assert bool(torch.isfinite(parameter.grad).all()), name
        assert bool(parameter.grad.abs().sum() > 0), name


def test_bad_sizes_are_named():
    with pytest.raises(TypeError, match="'particle_dim' must be an integer"):
        EquivariantNEBPConv(particle_dim=2.5)
    with pytest.raises(ValueError, match="'message_dim'"):
        EquivariantNEBPConv(message_dim=0)
