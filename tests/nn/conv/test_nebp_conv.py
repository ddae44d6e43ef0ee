r"""Tests of :class:`tg_nebp.nn.conv.NEBPConv` against independent references:
the classical :class:`ParticleBPConv` (when the correction is the identity,
:math:`g_s = 1`, :math:`g_v = 0`) and a float64 re-computation of the paper's
corrected message :math:`\log(g_s \boldsymbol{\phi} + g_v)` from plain loops
and the conv's own MLPs."""
import math

import pytest
import torch
from torch_geometric.data import Batch

from tg_nebp.datasets import Scenario
from tg_nebp.nn.conv import NEBPConv, ParticleBPConv
from tg_nebp.nn.conv.nebp_conv import node_embedding

from helpers import Const, Shift, gen, random_graph, tiny_scenario

# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------


def identity_correction(conv):
    r"""g_s = sigmoid(1e4) = 1 and g_v = relu(-1) = 0."""
    conv.g_s = Const(1, 1e4)
    conv.g_v = Const(conv.num_particles, -1.0)
    return conv


def reference_embedding(particles, log_weights):
    r"""Weighted mean and covariance with plain loops (float64)."""
    n, K, D = particles.shape
    x = particles.double().tolist()
    lw = log_weights.double().tolist()
    rows = []
    for i in range(n):
        top = max(lw[i])
        w = [math.exp(v - top) for v in lw[i]]
        total = sum(w)
        w = [v / total for v in w]
        mean = [sum(w[k] * x[i][k][d] for k in range(K)) for d in range(D)]
        cov = [[sum(w[k] * (x[i][k][a] - mean[a]) * (x[i][k][b] - mean[b])
                    for k in range(K)) for b in range(D)] for a in range(D)]
        rows.append(mean + [c for row in cov for c in row])
    return torch.tensor(rows, dtype=torch.float64)


def reference_nebp(conv, particles, log_weights, edge_index, edge_attr,
                   anchor, sender_log_weights=None, sigma=1.0):
    r"""One NEBP iteration recomputed in float64 from the paper's formulas,
    edge by edge: the BP message phi (plain loops), scaled to mean one over
    K; m = g_e(features, phi); corrected = log(g_s(m) * phi + g_v(m)); the
    receivers sum their corrected log-messages. Returns the new
    log-weights, the per-edge corrected log-messages, g_s, g_v and m."""
    K = particles.size(1)
    sender = log_weights if sender_log_weights is None else sender_log_weights
    pos = particles.double().tolist()
    sw = sender.double().tolist()
    h = reference_embedding(particles, log_weights)
    log_norm = math.log(math.sqrt(2 * math.pi) * sigma)
    out = log_weights.double().clone()
    corrected, gs_all, gv_all, msgs = [], [], [], []
    for e, (j, i) in enumerate(edge_index.t().tolist()):
        z = float(edge_attr[e, 0])
        log_phi = []
        for k in range(K):
            d = math.hypot(pos[j][k][0] - pos[i][k][0],
                           pos[j][k][1] - pos[i][k][1])
            log_phi.append(-0.5 * ((z - d) / sigma)**2 - log_norm + sw[j][k])
        top = max(log_phi)
        phi = [math.exp(v - top) for v in log_phi]
        scale = sum(phi) / K
        phi = torch.tensor([v / scale for v in phi], dtype=torch.float64)
        features = torch.cat([h[j, :4] - h[i, :4], h[i, 4:], h[j, 4:]]) / \
            conv.feature_scale
        with torch.no_grad():
            m = conv.g_e(torch.cat([features, phi]).view(1, -1))
            g_s = torch.sigmoid(conv.g_s(m)).view(())
            g_v = torch.relu(conv.g_v(m)).view(-1)
        if bool(anchor[j]) and not conv.correct_anchor_edges:
            log_c = phi.log()
        else:
            log_c = (g_s * phi + g_v).log()
        corrected.append(log_c)
        gs_all.append(g_s)
        gv_all.append(g_v)
        msgs.append(m.view(-1))
        if not bool(anchor[i]):
            out[i] += log_c
    return (out, torch.stack(corrected), torch.stack(gs_all),
            torch.stack(gv_all), torch.stack(msgs))


def log_softmax(x):
    return x - x.logsumexp(-1, keepdim=True)


# --------------------------------------------------------------------------
# 1. identity correction reproduces classical BP
# --------------------------------------------------------------------------

IDENTITY_CASES = [
    # seed, agents, anchors, K, correct_anchor_edges, use_sender
    (0, 5, 0, 16, False, False),
    (1, 5, 0, 16, True, True),
    (2, 5, 3, 16, False, False),
    (3, 5, 3, 16, True, False),
    (4, 6, 2, 24, False, True),
    (5, 6, 2, 24, True, True),
]


@pytest.mark.parametrize('seed,agents,anchors,K,correct_anchors,use_sender',
                         IDENTITY_CASES)
def test_identity_correction_equals_particle_bp(seed, agents, anchors, K,
                                                correct_anchors, use_sender):
    g = gen(seed)
    particles, lw, ei, ea, anchor = random_graph(g, agents, anchors, K,
                                                 into_anchor=True)
    assert ei.size(1) > 0
    if anchors:
        assert bool(anchor[ei[0]].any())  # some messages come from anchors
        assert bool(anchor[ei[1]].any())  # and some go into anchors
    sender = (torch.randn(lw.shape, generator=g, dtype=torch.float64) * 2
              if use_sender else None)
    torch.manual_seed(seed)
    conv = identity_correction(
        NEBPConv(K, message_dim=8, hidden_dim=16,
                 correct_anchor_edges=correct_anchors)).double()
    out, emb = conv(particles, lw, ei, ea, anchor,
                    sender_log_weights=sender)
    ref, _ = ParticleBPConv()(particles, lw, ei, ea,
                              sender_log_weights=sender, anchor=anchor)
    torch.testing.assert_close(log_softmax(out), log_softmax(ref),
                               atol=1e-5, rtol=0)
    # anchors keep their log-weights exactly
    assert torch.equal(out[anchor], lw[anchor])
    # the classical belief is not just the prediction (the test can fail)
    agents_mask = ~anchor
    assert not torch.allclose(log_softmax(ref)[agents_mask],
                              log_softmax(lw)[agents_mask], atol=1e-2)
    # without node update the embedding is the prediction's moments
    torch.testing.assert_close(emb, reference_embedding(particles, lw),
                               atol=1e-9, rtol=1e-9)


def test_identity_correction_float32_close_to_particle_bp():
    g = gen(10)
    particles, lw, ei, ea, anchor = random_graph(g, 6, 2, 32)
    particles, lw, ea = particles.float(), lw.float(), ea.float()
    conv = identity_correction(NEBPConv(32, message_dim=8, hidden_dim=16))
    out, _ = conv(particles, lw, ei, ea, anchor)
    ref, _ = ParticleBPConv()(particles, lw, ei, ea, anchor=anchor)
    torch.testing.assert_close(log_softmax(out), log_softmax(ref),
                               atol=1e-3, rtol=1e-5)


# --------------------------------------------------------------------------
# 2. the corrected message formula with real MLPs
# --------------------------------------------------------------------------

@pytest.mark.parametrize('correct_anchors', [False, True])
@pytest.mark.parametrize('use_sender', [False, True])
def test_corrected_messages_match_formula(correct_anchors, use_sender):
    g = gen(20 + 2 * int(correct_anchors) + int(use_sender))
    K = 16
    particles, lw, ei, ea, anchor = random_graph(g, 5, 3, K, edge_prob=0.7,
                                                 into_anchor=True)
    sender = (torch.randn(lw.shape, generator=g, dtype=torch.float64) * 2
              if use_sender else None)
    torch.manual_seed(21)
    conv = NEBPConv(K, message_dim=8, hidden_dim=16,
                    correct_anchor_edges=correct_anchors).double()
    out, emb = conv(particles, lw, ei, ea, anchor, sender_log_weights=sender)
    ref, corrected, g_s, g_v, _ = reference_nebp(conv, particles, lw, ei, ea,
                                                 anchor, sender)
    # the correction is not trivial: g_s < 1 and g_v > 0 somewhere
    assert float(g_s.max()) < 0.999
    assert bool((g_v > 0).any()) and bool((g_v == 0).any())
    torch.testing.assert_close(out, ref, atol=1e-8, rtol=1e-10)
    # anchors keep their weights, edges from anchors are uncorrected when
    # correct_anchor_edges=False
    assert torch.equal(out[anchor], lw[anchor])
    from_anchor = anchor[ei[0]]
    assert bool(from_anchor.any())
    bp_phi = reference_nebp(identity_correction(
        NEBPConv(K, message_dim=8, hidden_dim=16,
                 correct_anchor_edges=True)).double(),
                            particles, lw, ei, ea, anchor, sender)[1]
    if correct_anchors:
        assert not torch.allclose(corrected[from_anchor],
                                  bp_phi[from_anchor], atol=1e-3)
    else:
        torch.testing.assert_close(corrected[from_anchor],
                                   bp_phi[from_anchor], atol=1e-12, rtol=0)
    assert not torch.allclose(corrected[~from_anchor], bp_phi[~from_anchor],
                              atol=1e-3)


def test_single_edge_corrected_message():
    r"""One agent, one neighbour: the receiver's log-weights move by exactly
    log(g_s * phi_normalized + g_v)."""
    g = gen(30)
    K = 16
    particles = 3.0 * torch.randn(2, K, 4, generator=g, dtype=torch.float64)
    lw = torch.randn(2, K, generator=g, dtype=torch.float64)
    ei = torch.tensor([[1], [0]])
    ea = torch.tensor([[2.5]], dtype=torch.float64)
    anchor = torch.tensor([False, False])
    torch.manual_seed(31)
    conv = NEBPConv(K, message_dim=8, hidden_dim=16).double()
    out, _ = conv(particles, lw, ei, ea, anchor)
    # independent: phi from the Gaussian density, scaled to mean one
    d = (particles[1, :, :2] - particles[0, :, :2]).norm(dim=-1)
    phi = torch.exp(-0.5 * (2.5 - d)**2) / math.sqrt(2 * math.pi) * \
        lw[1].exp()
    phi = phi / phi.mean()
    h = node_embedding(particles, lw)
    features = torch.cat([h[1, :4] - h[0, :4], h[0, 4:], h[1, 4:]]) / 10.0
    with torch.no_grad():
        m = conv.g_e(torch.cat([features, phi]).view(1, -1))
        g_s = torch.sigmoid(conv.g_s(m)).view(())
        g_v = torch.relu(conv.g_v(m)).view(-1)
    expected = lw[0] + torch.log(g_s * phi + g_v)
    torch.testing.assert_close(out[0], expected, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(out[1], lw[1], atol=0, rtol=0)


def test_node_update_matches_formula():
    g = gen(40)
    K = 16
    particles, lw, ei, ea, anchor = random_graph(g, 5, 2, K, edge_prob=0.7)
    torch.manual_seed(41)
    conv = NEBPConv(K, message_dim=8, hidden_dim=16, node_update=True,
                    correct_anchor_edges=True).double()
    out, emb = conv(particles, lw, ei, ea, anchor)
    ref, _, _, _, msgs = reference_nebp(conv, particles, lw, ei, ea, anchor)
    torch.testing.assert_close(out, ref, atol=1e-8, rtol=1e-10)
    h = reference_embedding(particles, lw)
    summed = torch.zeros(lw.size(0), msgs.size(1), dtype=torch.float64)
    for e, i in enumerate(ei[1].tolist()):
        summed[i] += msgs[e]
    with torch.no_grad():
        expected = conv.g_n(torch.cat([h / conv.feature_scale, summed], -1))
    torch.testing.assert_close(emb, expected, atol=1e-10, rtol=1e-8)
    # a given embedding is used instead of the prediction's moments
    other = h + torch.randn(h.shape, generator=g, dtype=torch.float64)
    out2, _ = conv(particles, lw, ei, ea, anchor, embedding=other)
    assert not torch.allclose(out2, out, atol=1e-6)


def test_node_embedding_matches_loops():
    g = gen(50)
    particles = torch.randn(4, 9, 4, generator=g, dtype=torch.float64) * 3
    lw = torch.randn(4, 9, generator=g, dtype=torch.float64) * 2 + 5.0
    emb = node_embedding(particles, lw)  # unnormalized log-weights
    assert emb.shape == (4, 20)
    torch.testing.assert_close(emb, reference_embedding(particles, lw),
                               atol=1e-10, rtol=1e-10)


# --------------------------------------------------------------------------
# 3. gradients and numerical safety at the conv level
# --------------------------------------------------------------------------

def test_no_nan_gradient_when_g_v_is_all_zero():
    g = gen(60)
    K = 16
    particles, lw, ei, ea, anchor = random_graph(g, 5, 2, K, edge_prob=0.7)
    particles, lw, ea = particles.float(), lw.float(), ea.float()
    torch.manual_seed(61)
    conv = NEBPConv(K, message_dim=8, hidden_dim=16,
                    correct_anchor_edges=True)
    conv.g_v = Shift(conv.g_v, -1e3)  # relu(.) = 0: log g_v = -inf
    out, _ = conv(particles, lw, ei, ea, anchor)
    assert bool(torch.isfinite(out).all())
    log_softmax(out)[~anchor].exp().mul(
        torch.arange(K, dtype=torch.float32)).sum().backward()
    for name, p in conv.named_parameters():
        assert p.grad is not None, name
        assert bool(torch.isfinite(p.grad).all()), name
        if name.startswith('g_v'):
            assert bool((p.grad == 0).all()), name  # ReLU blocks it
        else:
            assert bool((p.grad != 0).any()), name


def test_no_nan_gradient_with_pruned_particle():
    g = gen(62)
    K = 16
    particles, lw, ei, ea, anchor = random_graph(g, 5, 0, K, edge_prob=0.7)
    particles, lw, ea = particles.float(), lw.float(), ea.float()
    lw[:, 1] = -math.inf  # particle 1 pruned everywhere
    torch.manual_seed(63)
    conv = NEBPConv(K, message_dim=8, hidden_dim=16)
    conv.g_v = Shift(conv.g_v, -1e3)
    out, _ = conv(particles, lw, ei, ea, anchor)
    assert not bool(torch.isnan(out).any())
    assert bool((out[:, 1] == -math.inf).all())
    finite = [k for k in range(K) if k != 1]
    out[:, finite].sum().backward()
    for name, p in conv.named_parameters():
        assert bool(torch.isfinite(p.grad).all()), name


def test_gradcheck_wrt_mlp_parameters():
    g = gen(64)
    K = 6
    particles, lw, ei, ea, anchor = random_graph(g, 3, 1, K, edge_prob=0.9)
    torch.manual_seed(65)
    conv = NEBPConv(K, message_dim=4, hidden_dim=5,
                    correct_anchor_edges=True).double()
    names = [name for name, _ in conv.named_parameters()]

    def fn(*values):
        return torch.func.functional_call(conv, dict(zip(names, values)),
                                          (particles, lw, ei, ea, anchor))[0]

    inputs = tuple(p.detach().clone().requires_grad_()
                   for p in conv.parameters())
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5,
                                    fast_mode=True)


# --------------------------------------------------------------------------
# 4. batching
# --------------------------------------------------------------------------

def snapshot_particles(data, K, generator):
    r"""Particles around the true positions of snapshot 1 (anchors: K
    copies of their position) and random log-weights."""
    n = data.num_nodes
    truth = data.states[:, 1]
    particles = truth.unsqueeze(1) + 2.0 * torch.randn(n, K, 4,
                                                       generator=generator)
    particles[data.anchor] = truth[data.anchor].unsqueeze(1).expand(-1, K, -1)
    log_weights = torch.randn(n, K, generator=generator)
    return particles, log_weights


@pytest.mark.parametrize('node_update', [False, True])
def test_batch_equals_each_graph_alone(node_update):
    K = 16
    big = Scenario.load('paper_train').replace(num_steps=3).generate(gen(0))
    small = tiny_scenario(3).generate(gen(1))
    batch = Batch.from_data_list([big, small])
    snap = batch.snapshot(1)
    g = gen(2)
    parts = [snapshot_particles(d, K, g) for d in (big, small)]
    particles = torch.cat([p for p, _ in parts])
    lw = torch.cat([w for _, w in parts])
    sender = torch.randn(lw.shape, generator=g)
    torch.manual_seed(3)
    conv = NEBPConv(K, message_dim=8, hidden_dim=16, node_update=node_update)
    out, emb = conv(particles, lw, snap.edge_index, snap.edge_attr,
                    snap.anchor, sender_log_weights=sender)
    ptr = batch.ptr.tolist()
    for b, d in enumerate((big, small)):
        part = slice(ptr[b], ptr[b + 1])
        s = d.snapshot(1)
        assert s.edge_index.size(1) > 0
        out_b, emb_b = conv(particles[part], lw[part], s.edge_index,
                            s.edge_attr, s.anchor,
                            sender_log_weights=sender[part])
        torch.testing.assert_close(out[part], out_b, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(emb[part], emb_b, atol=1e-5, rtol=1e-5)
        # and the update is not trivial
        assert not torch.allclose(out_b, lw[part], atol=1e-3)


# --------------------------------------------------------------------------
# 5. argument checks
# --------------------------------------------------------------------------

@pytest.mark.parametrize('validate', [True, False])
def test_rejects_other_number_of_particles(validate):
    g = gen(70)
    particles, lw, ei, ea, anchor = random_graph(g, 3, 1, 5)
    conv = NEBPConv(8, message_dim=4, hidden_dim=4).double()
    with pytest.raises(ValueError, match=r'K = 5') as info:
        conv(particles, lw, ei, ea, anchor, validate=validate)
    assert 'K = 8' in str(info.value)


def test_rejects_bad_constructor_arguments():
    for kwargs in (dict(num_particles=0), dict(num_particles=4, message_dim=0),
                   dict(num_particles=4, hidden_dim=0),
                   dict(num_particles=4, feature_scale=0.0)):
        with pytest.raises(ValueError):
            NEBPConv(**kwargs)


def test_g_e_and_g_v_are_sized_by_k():
    conv = NEBPConv(12, message_dim=5, hidden_dim=7, node_update=True)
    assert conv.g_e.channel_list == [36 + 12, 7, 5]
    assert conv.g_s.channel_list == [5, 7, 1]
    assert conv.g_v.channel_list == [5, 7, 12]
    assert conv.g_n.channel_list == [20 + 5, 7, 20]
    assert NEBPConv(12).g_n is None


# --------------------------------------------------------------------------
# torch.compile: no graph breaks, equal to the eager layers
# --------------------------------------------------------------------------


@pytest.mark.parametrize('grad', [False, True])
def test_layers_compile_without_graph_breaks(grad):
    g = gen(90)
    particles, lw, ei, ea, anchor = random_graph(g, 5, 2, 8)
    torch.manual_seed(90)
    nebp = NEBPConv(8, message_dim=4, hidden_dim=8).double()
    bp = ParticleBPConv()
    embedding = node_embedding(particles, lw)
    _, log_phi = bp(particles, lw, ei, ea)
    calls = [
        (nebp, (particles, lw, ei, ea, anchor), dict(validate=False)),
        (nebp.corrected_messages, (embedding, log_phi, ei, anchor, particles,
                                   lw, ea), {}),
        (bp, (particles, lw, ei, ea), dict(anchor=anchor, validate=False)),
        (bp, (particles, lw, ei, ea),
         dict(anchor=anchor, validate=False, return_messages=False)),
    ]
    with torch.set_grad_enabled(grad):
        for fn, args, kwargs in calls:
            torch._dynamo.reset()
            explanation = torch._dynamo.explain(fn)(*args, **kwargs)
            assert explanation.graph_break_count == 0, (
                fn, [b.reason for b in explanation.break_reasons])
            assert explanation.graph_count == 1


def test_compiled_nebp_conv_equals_reference_and_eager():
    g = gen(91)
    K = 16
    particles, lw, ei, ea, anchor = random_graph(g, 5, 3, K, edge_prob=0.7)
    sender = torch.randn(lw.shape, generator=g, dtype=torch.float64)
    torch.manual_seed(91)
    eager = NEBPConv(K, message_dim=8, hidden_dim=16).double()
    compiled = NEBPConv(K, message_dim=8, hidden_dim=16,
                        compile=True).double()
    compiled.load_state_dict(eager.state_dict())
    ref, _, g_s, g_v, _ = reference_nebp(eager, particles, lw, ei, ea,
                                         anchor, sender)
    assert float(g_s.max()) < 0.999 and bool((g_v > 0).any())  # not trivial
    gradients = []
    for conv in (eager, compiled):
        out, emb = conv(particles, lw, ei, ea, anchor,
                        sender_log_weights=sender)
        torch.testing.assert_close(out, ref, atol=1e-8, rtol=1e-10)
        out.log_softmax(-1).exp().mul(particles[..., 0]).sum().backward()
        gradients.append({n: p.grad for n, p in conv.named_parameters()})
    for name, grad in gradients[0].items():
        assert grad is not None and bool(grad.abs().sum() > 0), name
        torch.testing.assert_close(gradients[1][name], grad, atol=1e-10,
                                   rtol=1e-7)


@pytest.mark.parametrize('return_messages', [True, False])
def test_compiled_particle_bp_conv_equals_eager(return_messages):
    g = gen(92)
    particles, lw, ei, ea, anchor = random_graph(g, 6, 2, 8)
    sender = torch.randn(lw.shape, generator=g, dtype=torch.float64)
    outputs = [
        ParticleBPConv(chunk_size=5, compile=compile)(
            particles, lw, ei, ea, sender, anchor,
            return_messages=return_messages) for compile in (False, True)
    ]
    torch.testing.assert_close(outputs[1][0], outputs[0][0], atol=1e-9,
                               rtol=0)
    if return_messages:
        torch.testing.assert_close(outputs[1][1], outputs[0][1], atol=1e-9,
                                   rtol=0)


def test_zero_weight_row_is_rejected_not_nan():
    # the issue: an all -inf row became NaN (ParticleBPConv kept -inf)
    particles, lw, ei, ea, anchor = random_graph(gen(90), 3, 1, 8)
    conv = NEBPConv(8, message_dim=4, hidden_dim=4).double()
    lw[1] = float('-inf')
    with pytest.raises(ValueError, match=r"'log_weights\[1\]' is -inf for "
                       r"every particle"):
        conv(particles, lw, ei, ea, anchor)
    lw[1] = 0.0
    sender = lw.clone()
    sender[2] = float('-inf')
    with pytest.raises(ValueError, match=r"'sender_log_weights\[2\]'"):
        conv(particles, lw, ei, ea, anchor, sender_log_weights=sender)


def test_int32_edges_and_mixed_dtypes_match_the_reference_inputs():
    # int32 indices, and particles in another dtype than the parameters,
    # crashed inside PyG's scatter and an einsum
    particles, lw, ei, ea, anchor = random_graph(gen(91), 4, 2, 8)
    conv = NEBPConv(8, message_dim=4, hidden_dim=4, node_update=True)
    single = [t.float() for t in (particles, lw, ea)]
    expected = conv(single[0], single[1], ei, single[2], anchor)
    out = conv(single[0], single[1], ei.int(), single[2], anchor)
    assert torch.equal(out[0], expected[0])
    assert torch.equal(out[1], expected[1])
    # float64 and float16 inputs to a float32 layer: computed in float32
    wide = conv(particles, lw, ei, ea, anchor)
    assert wide[0].dtype == torch.float32
    torch.testing.assert_close(wide[0], expected[0])
    half = conv(single[0].half(), single[1], ei, single[2], anchor)
    again = conv(single[0].half().float(), single[1], ei, single[2], anchor)
    assert torch.equal(half[0], again[0])


def test_non_integer_sizes_are_type_errors():
    for kwargs in (dict(num_particles=2.5), dict(num_particles=4,
                                                   hidden_dim=True)):
        with pytest.raises(TypeError, match='must be an integer'):
            NEBPConv(**kwargs)


def test_half_parameters_and_bad_embeddings_are_named():
    particles, lw, ei, ea, anchor = random_graph(gen(92), 3, 1, 8,
                                                 dtype=torch.float32)
    with pytest.raises(TypeError, match='float32 or float64'):
        NEBPConv(8, message_dim=4, hidden_dim=4).half()(particles, lw, ei,
                                                        ea, anchor)
    conv = NEBPConv(8, message_dim=4, hidden_dim=4)
    with pytest.raises(ValueError, match=r"'embedding' must have shape "
                       r"\[4, 20\]"):
        conv(particles, lw, ei, ea, anchor, embedding=torch.zeros(4, 7))
    bad = torch.zeros(4, 20)
    bad[3, 5] = float('nan')
    with pytest.raises(ValueError, match=r"'embedding\[3\]'"):
        conv(particles, lw, ei, ea, anchor, embedding=bad)
    # float64 particles beyond float32's range: named, not NaN
    wide = particles.double()
    wide[1, :, :2] += 1e39
    with pytest.raises(ValueError, match=r"'particles\[1\]' holds a "
                       r"non-finite value"):
        conv(wide, lw, ei, ea, anchor)
