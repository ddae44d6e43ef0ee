import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import norm
from torch_geometric import EdgeIndex
from torch_geometric.data import Batch
from torch_geometric.loader import DataLoader

from tg_nebp import metrics
from tg_nebp.data import Realization
from tg_nebp.datasets import Scenario
from tg_nebp.filters import ParticleBP, weighted_moments
from tg_nebp.filters.particle.resampling import RESAMPLERS
from tg_nebp.models import ConstantVelocityDrag, GaussianRange

from helpers import gen, tiny_scenario

PRIOR_VAR = torch.tensor([10.0, 10.0, 0.01, 0.01])


def custom_realization(states, anchor, edges_per_step, seed=0, sigma=1.0):
    r"""A realization over true :obj:`states` [N, T, 4] with the given
    edges (list of lists of (j, i)) and ranges drawn from the model."""
    n, steps, _ = states.shape
    g = gen(seed)
    edge_index, edge_time = [], []
    for t, edges in enumerate(edges_per_step):
        for j, i in edges:
            edge_index.append((j, i))
            edge_time.append(t)
    edge_index = torch.tensor(edge_index, dtype=torch.long).view(-1, 2).t()
    edge_time = torch.tensor(edge_time, dtype=torch.long)
    pos = states[..., :2]
    dist = (pos[edge_index[0], edge_time] - pos[edge_index[1], edge_time]
            ).norm(dim=-1)
    ranges = GaussianRange(sigma).sample_ranges(dist.double(),
                                                generator=g).float()
    prior_mean = states[:, 0].clone()
    prior_cov = torch.diag(PRIOR_VAR).repeat(n, 1, 1)
    prior_mean[anchor, 2:] = 0
    prior_cov[anchor] = 0
    return Realization(states=states, edge_index=edge_index,
                       edge_attr=ranges.view(-1, 1), edge_time=edge_time,
                       anchor=anchor, prior_mean=prior_mean,
                       prior_cov=prior_cov, num_steps=steps, num_nodes=n)


def small_realization(seed=0, steps=5):
    scenario = Scenario.load('paper_train').replace(num_steps=steps)
    return scenario.generate(gen(seed))


# ---- accuracy ---------------------------------------------------------------

def test_one_agent_three_anchors_localizes():
    # three anchors at 120 degrees around the agent's start region; with the
    # paper's sigma_r = 1 m a filter cannot get below ~0.63 m (linearized
    # Kalman bound for this geometry), so this test uses sigma_r = 0.5 m
    # (bound ~0.36 m)
    anchors = tuple((30 + 10 * math.cos(a), 30 + 10 * math.sin(a))
                    for a in (math.pi / 2, math.pi * 7 / 6, math.pi * 11 / 6))
    scenario = Scenario(name='one', num_agents=1, anchor_positions=anchors,
                        agent_start_low=28.0, agent_start_high=32.0,
                        num_steps=20,
                        measurement=GaussianRange(sigma=0.5))
    data = [scenario.generate(gen(seed)) for seed in range(4)]
    for d in data:  # every anchor measured at every step
        assert d.num_edges == 3 * 20
    batch = next(iter(DataLoader(data, batch_size=4)))
    tracker = ParticleBP(num_particles=2000, motion=scenario.motion_model,
                         measurement=scenario.measurement_model)
    out = tracker(batch, generator=gen(10))
    agents = ~batch.anchor
    est, true = out.mean[agents, 9:20, :2], batch.states[agents, 9:20, :2]
    rmse = metrics.rmse(est, true)
    assert rmse < 0.5
    # the prior alone (std sqrt(10) per axis) would be ~4.5 m off
    prior_err = metrics.rmse(batch.prior_mean[agents, :2],
                             batch.states[agents, 0, :2])
    assert prior_err > 2.0


# ---- the update against a loop reference ------------------------------------

def reference_update(particles, edges, ranges, num_iterations, sigma):
    r"""Particle BP in plain numpy: uniform prediction weights, messages
    log p(z | x_j^(k), x_i^(k)) + log w~_j^(k), beliefs normalized after
    every iteration, anchors untouched."""
    n, k = particles.shape[:2]
    base = np.full((n, k), -math.log(k))
    sender = base.copy()
    for _ in range(num_iterations):
        belief = base.copy()
        for (j, i), z in zip(edges, ranges):
            d = np.linalg.norm(particles[j, :, :2] - particles[i, :, :2],
                               axis=-1)
            belief[i] += norm.logpdf(z, loc=d, scale=sigma) + sender[j]
        m = belief.max(-1, keepdims=True)
        sender = belief - (m + np.log(np.exp(belief - m).sum(-1,
                                                             keepdims=True)))
    return sender


@pytest.mark.parametrize('num_iterations', [1, 2])
def test_first_step_weights_match_loop_reference(num_iterations):
    data = tiny_scenario(steps=2).generate(gen(1))
    tracker = ParticleBP(num_particles=64, num_iterations=num_iterations)
    steps = list(tracker.steps(data, generator=gen(2)))
    assert [s.t for s in steps] == [0, 1]
    for t, step in enumerate(steps):
        mask = data.edge_time == t
        edges = data.edge_index[:, mask].t().tolist()
        ranges = data.edge_attr[mask, 0].double().numpy()
        assert len(edges) > 0
        ref = reference_update(step.particles.double().numpy(), edges,
                               ranges, num_iterations, 1.0)
        np.testing.assert_allclose(step.log_weights.double().numpy(), ref,
                                   rtol=1e-4, atol=1e-4)
        # the estimate is the weighted mean / covariance of the particles
        w = np.exp(ref)
        p = step.particles.double().numpy()
        mean = np.einsum('nk,nkd->nd', w, p)
        np.testing.assert_allclose(step.mean.numpy(), mean, rtol=1e-4,
                                   atol=1e-4)
        for i in range(data.num_nodes):
            c = p[i] - mean[i]
            cov = (w[i, :, None] * c).T @ c
            np.testing.assert_allclose(step.cov[i].numpy(), cov, rtol=1e-3,
                                       atol=1e-4)


def test_weighted_moments_against_numpy():
    g = gen(0)
    particles = torch.randn(3, 50, 4, generator=g, dtype=torch.float64)
    lw = torch.randn(3, 50, generator=g, dtype=torch.float64)
    lw = lw - lw.logsumexp(-1, keepdim=True)
    mean, cov = weighted_moments(particles, lw)
    for i in range(3):
        w = lw[i].exp().numpy()
        p = particles[i].numpy()
        m = (w[:, None] * p).sum(0)
        np.testing.assert_allclose(mean[i].numpy(), m, rtol=1e-12)
        np.testing.assert_allclose(cov[i].numpy(),
                                   np.cov(p.T, aweights=w, bias=True),
                                   rtol=1e-10, atol=1e-12)


def test_sample_prior_statistics():
    data = small_realization()
    K = 20_000
    particles = ParticleBP(num_particles=K).sample_prior(data, gen(0))
    assert particles.shape == (30, K, 4)
    agents = ~data.anchor
    p = particles[agents].double()
    mean = p.mean(1)
    sd = PRIOR_VAR.double().sqrt()
    assert bool(((mean - data.prior_mean[agents].double()).abs()
                 < 5 * sd / math.sqrt(K)).all())
    var = p.var(1)
    assert bool(((var / PRIOR_VAR.double() - 1).abs()
                 < 5 * math.sqrt(2 / K)).all())
    anchors = particles[data.anchor]
    assert torch.equal(anchors, data.prior_mean[data.anchor].unsqueeze(1)
                       .expand_as(anchors))


# ---- determinism ------------------------------------------------------------

@pytest.mark.parametrize('resampler', ['multinomial', 'systematic'])
def test_same_seed_same_output(resampler):
    data = small_realization(seed=3)
    tracker = ParticleBP(num_particles=100, resampler=resampler)
    a = tracker(data, generator=gen(5))
    b = tracker(data, generator=gen(5))
    c = tracker(data, generator=gen(6))
    assert torch.equal(a.mean, b.mean) and torch.equal(a.cov, b.cov)
    agents = ~data.anchor
    assert not torch.equal(a.mean[agents], c.mean[agents])
    # the difference is Monte Carlo noise, not a different answer
    assert metrics.rmse(a.mean[agents, :, :2], c.mean[agents, :, :2]) < 3.0


# ---- missing measurements ---------------------------------------------

def two_agents_three_anchors(steps):
    anchor_pos = torch.tensor([[0.0, 0.0], [20.0, 0.0], [10.0, 17.0]])
    agent = torch.tensor([[10.0, 6.0, 0.1, -0.05], [40.0, 40.0, 0.0, 0.1]])
    motion = ConstantVelocityDrag()
    traj, state = [], agent.double()
    g = gen(7)
    for _ in range(steps):
        state = motion.sample(state, g)
        traj.append(state)
    agents = torch.stack(traj, 1).float()
    anchors = torch.cat([anchor_pos, torch.zeros(3, 2)], 1)
    states = torch.cat([agents, anchors.unsqueeze(1).expand(3, steps, 4)])
    anchor = torch.tensor([False, False, True, True, True])
    # agent 0 hears the anchors except at t = 2; agent 1 never hears anyone
    edges = [[] if t == 2 else [(2, 0), (3, 0), (4, 0)] for t in range(steps)]
    data = custom_realization(states, anchor, edges, seed=8)
    # the prior of step 0 is centered at the true initial state
    data.prior_mean[:2] = agent
    return data


def test_agent_without_edges_keeps_its_prediction():
    steps, K = 5, 4000
    data = two_agents_three_anchors(steps)
    tracker = ParticleBP(num_particles=K)
    outs = list(tracker.steps(data, generator=gen(9)))
    motion = ConstantVelocityDrag()
    for step in outs:
        assert bool(torch.isfinite(step.mean).all())
        assert bool(torch.isfinite(step.cov).all())
        assert bool(torch.isfinite(step.log_weights).all())
        # normalized beliefs
        torch.testing.assert_close(step.log_weights.logsumexp(-1),
                                   torch.zeros(5), atol=1e-4, rtol=0)
    # agent 0 at t = 2, agent 1 always: uniform weights, estimate = plain
    # mean of the predicted particles
    for t, i in [(2, 0)] + [(t, 1) for t in range(steps)]:
        step = outs[t]
        torch.testing.assert_close(step.log_weights[i],
                                   torch.full((K, ), -math.log(K)))
        torch.testing.assert_close(step.mean[i],
                                   step.particles[i].mean(0), atol=1e-4,
                                   rtol=1e-5)
    # the prediction of agent 0 at t = 2 is the propagated estimate of t = 1
    prev, cur = outs[1], outs[2]
    expected = motion.propagate(prev.mean[0].double(),
                                torch.zeros(2, dtype=torch.float64))
    sd = torch.diagonal(cur.cov[0]).double().sqrt()
    # multinomial resampling and motion noise: MC std about sd * sqrt(2/K)
    assert bool(((cur.mean[0].double() - expected).abs()
                 < 5 * sd * math.sqrt(2 / K)).all())
    # agent 1 (never measured) keeps the prior propagated by the motion
    # model: mean and position variance of the prediction
    mean = data.prior_mean[1].double()
    pos_var = 10.0
    for t in range(steps):
        mean = motion.propagate(mean, torch.zeros(2, dtype=torch.float64))
        # x_t = x_0 + (t + 1) v_0 + noise: var 10 + (t + 1)^2 0.01 + small
        pos_var = 10.0 + (t + 1)**2 * 0.01
        est = outs[t].mean[1].double()
        mc_sd = math.sqrt(pos_var * (t + 2) / K)
        assert bool(((est[:2] - mean[:2]).abs() < 5 * mc_sd).all())
        var = torch.diagonal(outs[t].cov[1])[:2].double()
        assert bool(((var / pos_var - 1).abs()
                     < 5 * math.sqrt(2 * (t + 2) / K) + 0.01).all())


def test_agent_without_edges_in_tracker_output():
    data = two_agents_three_anchors(4)
    out = ParticleBP(num_particles=500)(data, generator=gen(1))
    assert bool(torch.isfinite(out.mean).all())
    assert bool(torch.isfinite(out.cov).all())
    # agent 0 is localized, agent 1 stays as uncertain as its prior
    assert float(out.cov[0, -1, 0, 0]) < 2.0
    assert float(out.cov[1, -1, 0, 0]) > 5.0


# ---- batches ----------------------------------------------------------

def test_batch_of_two_realizations():
    T = 5
    a = small_realization(seed=4, steps=T)
    b = tiny_scenario(steps=T).generate(gen(5))
    batch = next(iter(DataLoader([a, b], batch_size=2)))
    N = a.num_nodes + b.num_nodes
    out = ParticleBP(num_particles=300)(batch, generator=gen(0))
    assert out.mean.shape == (N, T, 4)
    assert out.cov.shape == (N, T, 4, 4)
    assert bool(torch.isfinite(out.mean).all())
    assert bool(torch.isfinite(out.cov).all())
    # covariances symmetric positive semi-definite
    torch.testing.assert_close(out.cov, out.cov.transpose(-1, -2))
    cov = out.cov.double()
    eig = torch.linalg.eigvalsh(cov)
    scale = cov.abs().amax((-1, -2), keepdim=False).unsqueeze(-1)
    assert bool((eig >= -1e-5 * scale.clamp_min(1.0)).all())
    # anchors: their known position, zero velocity, zero covariance
    known = batch.prior_mean[batch.anchor].unsqueeze(1).expand(-1, T, 4)
    torch.testing.assert_close(out.mean[batch.anchor], known, atol=1e-4,
                               rtol=1e-5)
    assert float(out.cov[batch.anchor].abs().max()) < 1e-6
    # the agents of both graphs are tracked to within a few metres
    agents = ~batch.anchor
    err = metrics.position_errors(out.mean[agents, :, :2],
                                  batch.states[agents, :, :2])
    assert float(err[:, -1].median()) < 3.0


@pytest.mark.parametrize('resampler', ['multinomial', 'systematic'])
def test_per_graph_generators_make_a_batch_track_as_each_graph_alone(
        resampler):
    T, K = 4, 32
    a = small_realization(seed=6, steps=T)  # 30 nodes
    b = tiny_scenario(steps=T).generate(gen(7))  # 6 nodes
    batch = Batch.from_data_list([a, b])
    tracker = ParticleBP(num_particles=K, resampler=resampler)
    together = list(tracker.steps(batch, [gen(10), gen(11)]))
    alone = [list(tracker.steps(a, gen(10))), list(tracker.steps(b, gen(11)))]
    ptr = batch.ptr.tolist()
    for t in range(T):
        for g in range(2):
            part = slice(ptr[g], ptr[g + 1])
            one = alone[g][t]
            # the same particles (prior, prediction and resampling draws)
            torch.testing.assert_close(together[t].particles[part],
                                       one.particles, rtol=0, atol=1e-4)
            torch.testing.assert_close(together[t].mean[part], one.mean,
                                       rtol=0, atol=1e-4)
            torch.testing.assert_close(together[t].cov[part], one.cov,
                                       rtol=1e-4, atol=1e-4)
    # one generator for the whole batch draws other numbers for graph b
    shared = tracker(batch, gen(11))
    assert not torch.allclose(shared.mean[ptr[1]:, -1],
                              alone[1][-1].mean, atol=1e-2)


def test_one_generator_in_a_list_equals_the_generator():
    data = small_realization(seed=8, steps=3)
    tracker = ParticleBP(num_particles=16)
    a = tracker(data, [gen(3)])
    b = tracker(data, gen(3))
    assert torch.equal(a.mean, b.mean) and torch.equal(a.cov, b.cov)


def test_wrong_number_of_generators():
    data = small_realization(seed=9, steps=2)
    batch = Batch.from_data_list([data, data])
    tracker = ParticleBP(num_particles=8)
    for generators, graphs, count in (([gen(0)], batch, 1),
                                      ([gen(0)] * 3, batch, 3),
                                      ([gen(0), gen(1)], data, 2),
                                      ([], data, 0)):
        with pytest.raises(ValueError) as info:
            tracker(graphs, generators)
        message = str(info.value)
        assert "'generator'" in message and f'{count} generators' in message
        assert f'{2 if graphs is batch else 1} graphs' in message


def test_invalid_arguments():
    with pytest.raises(ValueError, match='num_particles'):
        ParticleBP(num_particles=0)
    with pytest.raises(ValueError, match='num_iterations'):
        ParticleBP(num_iterations=0)
    with pytest.raises(ValueError, match='resampler'):
        ParticleBP(resampler='stratified-ish')


def test_custom_resampler_is_used():
    calls = []

    def keep_first(log_weights, num_samples, generator):
        calls.append(log_weights.shape)
        return torch.zeros(log_weights.shape[:-1] + (num_samples, ),
                           dtype=torch.long)

    data = small_realization(steps=3)
    tracker = ParticleBP(num_particles=20, resampler=keep_first)
    outs = list(tracker.steps(data, generator=gen(0)))
    # before every step's prediction but the first (none after the last)
    assert calls == [(30, 20)] * 2
    # after keeping particle 0 only, the spread at the next step is the
    # motion noise alone: tiny compared with the prior
    assert float(outs[1].cov[:25, 0, 0].max()) < 0.01


# ---- extreme inputs: weights stay normalized, never NaN ---------------------

def static_network(num_agents, num_anchors, steps, seed):
    r"""Agents and anchors at rest in [0, 20]^2, every node measured by every
    agent at every step, ranges drawn from the model."""
    g = gen(seed)
    n = num_agents + num_anchors
    pos = 20 * torch.rand(n, 2, generator=g)
    states = torch.cat([pos, torch.zeros(n, 2)], 1).unsqueeze(1).repeat(
        1, steps, 1)
    anchor = torch.arange(n) >= num_agents
    edges = [(j, i) for i in range(num_agents) for j in range(n) if i != j]
    return custom_realization(states, anchor, [edges] * steps, seed=seed)


def assert_normalized(step, dtype):
    weights = step.log_weights.double().exp()
    assert not torch.isnan(step.log_weights).any()
    assert torch.isfinite(step.mean).all() and torch.isfinite(step.cov).all()
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert torch.allclose(weights.sum(-1), torch.ones_like(weights[:, 0]),
                          atol=tol, rtol=0)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(st.data())
def test_property_extreme_inputs_keep_weights_normalized(data):
    dtype = data.draw(st.sampled_from([torch.float32, torch.float64]))
    num_agents = data.draw(st.integers(1, 4))
    net = static_network(num_agents, data.draw(st.integers(1, 3)), 2,
                         data.draw(st.integers(0, 1000)))
    # an agent believed far from where its ranges put it ...
    agent = data.draw(st.integers(0, num_agents - 1))
    offset = data.draw(st.floats(-1e6, 1e6))
    net.prior_mean[agent, data.draw(st.integers(0, 1))] += offset
    # ... ranges anywhere between 0 and 1e6 m, and peaked likelihoods
    for e in data.draw(st.lists(st.integers(0, net.edge_attr.size(0) - 1),
                                max_size=3)):
        net.edge_attr[e, 0] = data.draw(st.floats(0.0, 1e6))
    sigma = data.draw(st.floats(1e-3, 10.0))
    net.prior_mean, net.edge_attr = net.prior_mean.to(dtype), \
        net.edge_attr.to(dtype)
    bp = ParticleBP(num_particles=16, measurement=GaussianRange(sigma),
                    resampler=data.draw(st.sampled_from(['multinomial',
                                                         'systematic'])))
    for step in bp.steps(net, gen(0)):
        assert step.log_weights.dtype == dtype
        assert_normalized(step, dtype)


def test_far_prior_neighbours_estimates_match_float64():
    # the issue's case: an agent believed 1e5 m away made its neighbours'
    # float32 weights sum to 2 or 3 and doubled their estimates
    net = static_network(3, 3, 2, seed=3)
    net.prior_mean[0, 0] += 1e6
    bp = ParticleBP(num_particles=64)
    step = next(bp.steps(net, gen(1)))
    assert_normalized(step, torch.float32)
    # the same particles updated in float64
    edge_index, edge_attr = net.edges_by_step()[0]
    uniform = torch.full((6, 64), -math.log(64), dtype=torch.float64)
    log_weights = bp.update(step.particles.double(), uniform, edge_index,
                            edge_attr.double(), net.anchor)
    mean, _ = weighted_moments(step.particles.double(), log_weights)
    # the neighbours (agent 0's own float32 log-weights, around -5e11, are
    # resolved to 6e4 only)
    assert torch.allclose(step.mean[1:].double(), mean[1:], atol=1e-3)


def test_int32_edges_track_as_int64():
    net = static_network(2, 3, 3, seed=4)
    expected = ParticleBP(num_particles=16)(net, gen(2))
    net.edge_index = net.edge_index.int()
    net.edge_time = net.edge_time.int()
    for tracker in (ParticleBP(num_particles=16),
                    ParticleBP(num_particles=16, num_iterations=2)):
        out = tracker(net, gen(2))
        reference = expected if tracker.num_iterations == 1 else tracker(
            static_network(2, 3, 3, seed=4), gen(2))
        assert torch.equal(out.mean, reference.mean)


def test_half_precision_prior_is_tracked_in_float32():
    net = static_network(2, 3, 2, seed=5)
    net.prior_mean = net.prior_mean.half()
    net.prior_cov = net.prior_cov.half()
    out = ParticleBP(num_particles=16)(net, gen(3))
    assert out.mean.dtype == torch.float32
    net.prior_mean = net.prior_mean.float()  # the same values in float32
    net.prior_cov = net.prior_cov.float()
    assert torch.equal(out.mean, ParticleBP(num_particles=16)(net,
                                                               gen(3)).mean)


def test_zero_belief_names_the_node_and_its_ranges():
    # the smallest accepted sigma (1e-6 m) and residuals of about 1e14 m:
    # every scaled squared residual overflows float32 to -inf
    net = static_network(1, 3, 2, seed=6)
    net.prior_mean[0, :2] += 1e14
    bp = ParticleBP(num_particles=8, measurement=GaussianRange(1e-6))
    with pytest.raises(ValueError, match=r"node 0 at time index 0: its "
                       r"measurements \('edge_attr\[0\]' = .*, "
                       r"'edge_attr\[1\]' = .*\) give every one of its "
                       r"particles zero likelihood in torch.float32"):
        bp(net, gen(0))


@pytest.mark.parametrize('value', [2.5, '16', True])
def test_non_integer_particle_count_is_a_type_error(value):
    with pytest.raises(TypeError, match="'num_particles' must be an integer"):
        ParticleBP(num_particles=value)


def test_update_validates_its_inputs():
    # update is public: an out-of-range receiver corrupted the heap
    particles, log_weights = torch.randn(3, 8, 4), torch.zeros(3, 8)
    anchor = torch.zeros(3, dtype=torch.bool)
    bp = ParticleBP(8)
    with pytest.raises(ValueError, match=r"'edge_index\[1, 0\]' = 9 is out "
                       r"of range for 3 nodes"):
        bp.update(particles, log_weights, torch.tensor([[0], [9]]),
                  torch.tensor([[1.0]]), anchor)
    with pytest.raises(ValueError, match=r"'log_weights\[0\]' holds a finite "
                       r"value beyond"):
        bp.update(particles, torch.full_like(log_weights, 3e38),
                  torch.tensor([[0], [1]]), torch.tensor([[1.0]]), anchor)


def test_edge_index_without_sparse_size_counts_every_node():
    # PyG infers the size from the largest receiver: node 2, which receives
    # nothing, got node 0's row
    g = gen(12)
    particles, log_weights = torch.randn(3, 8, 4, generator=g), \
        torch.randn(3, 8, generator=g)
    anchor = torch.zeros(3, dtype=torch.bool)
    edges, ranges = torch.tensor([[1, 2], [0, 0]]), torch.tensor([[1.], [2.]])
    bp = ParticleBP(8)
    expected = bp.update(particles, log_weights, edges, ranges, anchor)
    for claim in (EdgeIndex(edges, sort_order='col'), EdgeIndex(edges)):
        out = bp.update(particles, log_weights, claim, ranges, anchor)
        assert torch.equal(out, expected)
    assert torch.allclose(expected[2], log_weights[2].log_softmax(-1))


@pytest.mark.parametrize('dtype', [torch.int8, torch.uint8, torch.int16,
                                   torch.int32])
def test_narrow_edge_time_keeps_every_step(dtype):
    # edge_time * num_nodes overflowed int8: ranges went to other steps
    data = tiny_scenario(30).generate(gen(2))
    narrow = data.clone()
    narrow.edge_time = data.edge_time.to(dtype)
    for (ei, ea), (ni, na) in zip(data.edges_by_step(),
                                  narrow.edges_by_step()):
        assert torch.equal(ei, ni) and torch.equal(ea, na)


def test_diverging_motion_is_named_not_nan():
    # the explicit quadratic drag is unstable beyond |v| = 2 / (drag dt)
    data = static_network(2, 3, 8, seed=7)
    data.prior_mean[:2, 2] = 100.0
    bp = ParticleBP(16, motion=ConstantVelocityDrag(sigma_a=0.0))
    with pytest.raises(ValueError, match=r"node 0 at time index \d: the "
                       r"motion model .* predicted states beyond"):
        for step in bp.steps(data, gen(0)):
            assert not torch.isnan(step.log_weights).any()


@pytest.mark.parametrize('generator', [[1, 2], 'abc', 5])
def test_generator_of_wrong_type(generator):
    with pytest.raises(TypeError, match="'generator' must be a "
                       "torch.Generator"):
        ParticleBP(8)(static_network(2, 3, 2, seed=8), generator)


def test_resampler_of_wrong_type():
    with pytest.raises(TypeError, match="'resampler' must be a name or a "
                       "callable"):
        ParticleBP(8, resampler=5)


def test_motion_model_of_another_state_dimension():
    class Planar(ConstantVelocityDrag):  # states [p_x, p_y, v_x, v_y, z]
        state_dim = 5

    with pytest.raises(ValueError, match=r"'prior_mean' holds states of size "
                       r"4 but the motion model .* has state dimension 5"):
        ParticleBP(8, motion=Planar())(static_network(1, 3, 2, seed=9),
                                       gen(0))


@pytest.mark.parametrize('model', ['gaussian', 'motion'])
def test_models_of_the_wrong_role(model):
    kwargs = ({'measurement': ConstantVelocityDrag()} if model == 'gaussian'
              else {'motion': GaussianRange()})
    with pytest.raises(TypeError, match="must be a (MeasurementModel|"
                       "MotionModel)"):
        ParticleBP(8, **kwargs)


# ---- M-sample messages in the tracker --------------------------------------

def test_one_sample_tracks_exactly_as_the_paired_filter():
    net = static_network(3, 3, 3, seed=10)
    paired = ParticleBP(32)(net, gen(4))
    one = ParticleBP(32, num_samples=1)(net, gen(4))
    assert torch.equal(paired.mean, one.mean)
    assert torch.equal(paired.cov, one.cov)


@pytest.mark.parametrize('num_samples', [4, 'all'])
def test_sampled_tracker_batch_equals_each_graph_alone(num_samples):
    graphs = [static_network(2, 3, 3, seed=s) for s in (11, 12)]
    tracker = ParticleBP(16, num_samples=num_samples)
    alone = [tracker(g, [gen(20 + i)]).mean for i, g in enumerate(graphs)]
    batched = tracker(Batch.from_data_list(graphs), [gen(20), gen(21)]).mean
    torch.testing.assert_close(batched, torch.cat(alone), atol=1e-5,
                               rtol=1e-5)
    again = tracker(Batch.from_data_list(graphs), [gen(20), gen(21)]).mean
    assert torch.equal(batched, again)  # same seed, same result


def test_more_samples_make_a_better_filter():
    # the exact message beats the pairing on the same realizations (means
    # over 4 realizations, a margin far beyond their spread at K = 64)
    nets = [static_network(3, 3, 5, seed=s) for s in range(30, 34)]
    def rmse(tracker):
        errors = []
        for i, net in enumerate(nets):
            mean = tracker(net, gen(i)).mean
            agents = ~net.anchor
            errors.append((mean[agents, :, :2] -
                           net.states[agents, :, :2]).norm(dim=-1))
        return float(torch.cat(errors).square().mean().sqrt())
    assert rmse(ParticleBP(64, num_samples='all')) < rmse(ParticleBP(64))


# ---- regularized and ESS-adaptive resampling --------------------------------

def test_regularized_jitter_has_the_stated_covariance():
    # one node whose particles coincide: after resampling the spread is the
    # jitter alone, covariance h^2 cov (5 standard errors, K = 20,000)
    K, h = 20_000, 0.3
    cov = torch.tensor([[2.0, 0.6, 0.0, 0.0], [0.6, 1.0, 0.0, 0.0],
                        [0.0, 0.0, 0.04, 0.01], [0.0, 0.0, 0.01, 0.02]],
                       dtype=torch.float64)
    particles = torch.ones(2, K, 4, dtype=torch.float64)
    log_weights = torch.zeros(2, K, dtype=torch.float64)
    covs = torch.stack([cov, torch.zeros(4, 4, dtype=torch.float64)])
    tracker = ParticleBP(K, regularize=h)
    moved, carried = tracker.resample_step(particles, log_weights, covs,
                                           gen(13))
    jitter = moved[0] - 1.0
    sample = jitter.t() @ jitter / K
    expected = h**2 * cov
    scale = (expected.diagonal().unsqueeze(0) *
             expected.diagonal().unsqueeze(1)).sqrt()
    assert bool(((sample - expected).abs() <=
                 5 * math.sqrt(2 / K) * scale + 1e-12).all())
    assert torch.equal(moved[1], particles[1])  # zero covariance: no jitter
    assert torch.allclose(carried.exp().sum(-1), torch.ones(2,
                                                            dtype=torch.float64))
    silverman = ParticleBP(K, regularize='silverman')
    assert silverman.regularize == 'silverman'


def test_ess_adaptive_resampling_keeps_high_ess_nodes():
    K = 64
    particles = torch.randn(2, K, 4, generator=gen(14), dtype=torch.float64)
    flat = torch.full((K, ), -math.log(K), dtype=torch.float64)
    peaked = torch.full((K, ), -50.0, dtype=torch.float64)
    peaked[3] = 0.0
    log_weights = torch.stack([flat - 0.01 * torch.arange(K), peaked])
    log_weights = log_weights.log_softmax(-1)
    cov = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
    tracker = ParticleBP(K, ess_threshold=0.5)
    moved, carried = tracker.resample_step(particles, log_weights, cov,
                                           gen(15))
    # node 0 (ESS near K) keeps its particles and weights, node 1 (ESS 1)
    # is resampled onto its one particle with uniform weights
    assert torch.equal(moved[0], particles[0])
    assert torch.equal(carried[0], log_weights[0])
    assert bool((moved[1] == particles[1, 3]).all())
    assert torch.allclose(carried[1], torch.full((K, ), -math.log(K),
                                                 dtype=torch.float64))


def test_estimate_is_unchanged_by_a_step_without_information():
    # static agent, no motion noise, no measurements at step 1: without
    # resampling the estimate stays; resampling every step moves it
    states = torch.tensor([[[5.0, 5.0, 0.0, 0.0]] * 3, [[0.0, 0.0, 0, 0]] * 3,
                           [[10.0, 0.0, 0, 0]] * 3, [[0.0, 10.0, 0, 0]] * 3])
    anchor = torch.tensor([False, True, True, True])
    edges = [[(1, 0), (2, 0), (3, 0)], [], [(1, 0), (2, 0), (3, 0)]]
    net = custom_realization(states, anchor, edges, seed=16)
    net.prior_cov[0, 2:, 2:] = 0.0  # no velocity uncertainty
    motion = ConstantVelocityDrag(sigma_a=0.0)
    adaptive = [s.mean for s in ParticleBP(
        256, motion=motion, ess_threshold=1e-9).steps(net, gen(17))]
    assert torch.equal(adaptive[1], adaptive[0])
    always = [s.mean for s in ParticleBP(256, motion=motion).steps(
        net, gen(17))]
    assert not torch.equal(always[1], always[0])


@pytest.mark.parametrize('kwargs,error', [
    (dict(ess_threshold=1.5), ValueError), (dict(ess_threshold=0.0),
                                            ValueError),
    (dict(regularize='scott'), TypeError), (dict(regularize=-1.0),
                                            ValueError)])
def test_resampling_options_are_checked(kwargs, error):
    with pytest.raises(error):
        ParticleBP(8, **kwargs)


def test_recommended_configuration_and_overrides():
    tracker = ParticleBP.recommended()
    assert (tracker.num_particles, tracker.num_samples,
            tracker.regularize) == (500, 32, 'silverman')
    assert tracker.bp_conv.num_samples == 32
    assert tracker.resampler is RESAMPLERS['multinomial']
    measurement = GaussianRange(0.5)
    other = ParticleBP.recommended(num_particles=64, measurement=measurement)
    assert (other.num_particles, other.num_samples) == (64, 32)
    assert other.measurement is measurement and other.bp_conv.measurement \
        is measurement
    # the constructor's default stays the paper's configuration
    paper = ParticleBP()
    assert (paper.num_particles, paper.num_samples, paper.regularize) == (
        1000, 1, None)


# -- both ends, extrinsic messages ------------------------------------------

def two_agents_step(seed=0, count=60):
    r"""Two agents that measure each other (one factor of two ranges) and
    each one anchor: particles spread around their truth, uniform weights,
    exact messages possible at this K."""
    g = gen(seed)
    truth = torch.tensor([[2.0, 3.0], [9.0, 4.0], [0.0, 0.0], [12.0, 0.0]],
                         dtype=torch.float64)
    particles = torch.zeros(4, count, 4, dtype=torch.float64)
    particles[:, :, :2] = truth.unsqueeze(1)
    particles[:2, :, :2] += 2 * torch.randn(2, count, 2, generator=g,
                                            dtype=torch.float64)
    edge_index = torch.tensor([[1, 0, 2, 3], [0, 1, 0, 1]])
    ranges = ((truth[edge_index[0]] - truth[edge_index[1]]).norm(dim=-1) +
              0.5 * torch.randn(4, generator=g, dtype=torch.float64))
    log_weights = torch.full((4, count), -math.log(count),
                             dtype=torch.float64)
    anchor = torch.tensor([False, False, True, True])
    return particles, log_weights, edge_index, ranges.view(-1, 1), anchor


def test_both_ends_count_each_range_once_and_iterations_do_not_overcount():
    # the exact posterior marginal of agent i at its particles, by a plain
    # loop: its anchor's range, and the sum over j's particles of j's
    # anchor range times BOTH ranges of the link, each once
    particles, lw, edge_index, ranges, anchor = two_agents_step()
    sigma = 1.0
    tracker = ParticleBP(60, 1, num_samples='all', ends='both')
    one = tracker.update(particles, lw, edge_index, ranges, anchor)
    x = particles[:, :, :2].numpy()
    z = ranges.view(-1).numpy()

    def lik(value, a, b):
        return norm.logpdf(value, loc=np.linalg.norm(a - b, axis=-1),
                           scale=sigma)

    for i, j in ((0, 1), (1, 0)):
        expected = np.empty(60)
        for k in range(60):
            # over j's particles: its anchor's range and the link's two
            terms = (lik(z[2 + j], x[j], x[2 + j, 0]) +
                     lik(z[0], x[j], x[i, k]) + lik(z[1], x[j], x[i, k]))
            top = terms.max()
            expected[k] = (lik(z[2 + i], x[i, k], x[2 + i, 0]) + top +
                           np.log(np.exp(terms - top).sum()))
        expected -= expected.max() + np.log(np.exp(
            expected - expected.max()).sum())
        # one iteration: j's extrinsic belief is its prior, and i's message
        # holds j's anchor only after two; so compare the converged ones
        converged = ParticleBP(60, 2, num_samples='all', ends='both').update(
            particles, lw, edge_index, ranges, anchor)
        np.testing.assert_allclose(converged[i].numpy(), expected,
                                   rtol=1e-9, atol=1e-9)
        ten = ParticleBP(60, 10, num_samples='all', ends='both').update(
            particles, lw, edge_index, ranges, anchor)
        np.testing.assert_allclose(ten[i].numpy(), converged[i].numpy(),
                                   rtol=1e-9, atol=1e-9)
    assert not torch.allclose(one, converged)


def test_receiver_iterations_warn_and_both_ends_needs_a_range_model():
    with pytest.warns(UserWarning, match="counts it again"):
        ParticleBP(10, 2)
    from tg_nebp.models import MeasurementModel

    class Bearing(MeasurementModel, name='test-bearing-ends'):
        def params(self):
            return {}

    with pytest.raises(TypeError, match='symmetric in the two ends'):
        ParticleBP(10, 1, measurement=Bearing(), ends='both')
    with pytest.raises(ValueError, match="'ends'"):
        ParticleBP(10, ends='sender')


def test_both_ends_batch_equals_each_graph_alone():
    scenario = tiny_scenario(steps=3)
    small = scenario.generate(gen(1))
    large = scenario.replace(num_agents=5).generate(gen(2))
    tracker = ParticleBP(32, 3, num_samples=4, ends='both')
    alone = [tracker(d, [gen(10 + g)]) for g, d in enumerate((small,
                                                              large))]
    batched = tracker(Batch.from_data_list([small, large]),
                      [gen(10), gen(11)])
    torch.testing.assert_close(batched.mean, torch.cat([a.mean
                                                        for a in alone]),
                               rtol=1e-4, atol=1e-4)


# -- positions of any dimension ---------------------------------------------

# BP's means of realization seed 3 of paper_test (4 steps, K = 200, seed 1,
# one thread), as the code before positions of any dimension gave them: the
# sum over the first 100 nodes and node 5's state at the last step. Float32
# sums round by the CPU's kernels, and resampling turns a last-bit
# difference of a weight into another particle drawn: from there on the run
# is another Monte Carlo draw, not the stored one to rounding (the
# regularized run under ATEN_CPU_CAPABILITY=default: the sum moved by
# 2.5e-5 relative, node 5's x by 19.5 mm, 1.1 of the standard errors
# below; the sums moved by up to 1.2e-5 relative and node 5's state by up
# to 8 mm on an AVX-512 CPU). So each is compared to 5 standard errors of
# the difference of two such draws, sqrt(2 var / K) with the run's own
# posterior variances (their sum over the 100 nodes for the sum): 0.9 to
# 1.9e-4 relative and 1.5 to 9 cm here. A change of the 2-D path's
# arithmetic is such a draw too; what the test catches is a change of its
# answer: the kernel bound of issue 37 moved the sum by 8 standard errors,
# and a wrong dimension moves a state by metres
BEFORE_3D = {
    'paired': (39058.96476991568, [24.40610122680664, 59.562530517578125,
                                   0.09814085066318512,
                                   0.13850262761116028]),
    # regularized: since the kernel is bounded by the step's prediction
    # (issue 37; before it 39066.8 and [25.20, 57.49, 0.081, 0.175])
    'marginalized': (39078.32702835748, [25.251041412353516,
                                        57.524452209472656,
                                        0.10601877421140671,
                                        0.1815936267375946]),
}


@pytest.mark.parametrize('name', list(BEFORE_3D))
def test_two_dimensional_results_are_unchanged(name):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        data = Scenario.load('paper_test').replace(num_steps=4).generate(
            gen(3))
        options = ({} if name == 'paired' else
                   dict(num_samples=8, regularize='silverman'))
        out = ParticleBP(200, **options)(data, gen(1))
    finally:
        torch.set_num_threads(threads)
    total, state = BEFORE_3D[name]
    variances = out.cov.double().diagonal(dim1=-2, dim2=-1)
    assert abs(float(out.mean[:100].double().sum()) - total) <= 5 * math.sqrt(
        2 * float(variances[:100].sum()) / 200)
    np.testing.assert_array_less(
        np.abs(np.array(out.mean[5, 3].tolist()) - state),
        5 * (2 * variances[5, 3] / 200).sqrt().numpy())


def three_d_scenario(steps=3, agents=4):
    return Scenario(name='cube', num_agents=agents,
                    anchor_positions=((0.0, 0.0, 0.0), (15.0, 0.0, 10.0),
                                      (0.0, 15.0, 10.0), (15.0, 15.0, 0.0)),
                    agent_start_low=(3.0, 3.0, 2.0),
                    agent_start_high=(12.0, 12.0, 8.0), num_steps=steps,
                    prior_var=(4.0, 4.0, 4.0, 0.01, 0.01, 0.01))


@pytest.mark.parametrize('options', [{}, dict(num_samples=4,
                                              regularize='silverman'),
                                     dict(ends='both')])
def test_three_dimensional_tracking_batches_and_localizes(options):
    scenario = three_d_scenario()
    small, large = (scenario.generate(gen(1)),
                    scenario.replace(num_agents=6).generate(gen(2)))
    tracker = ParticleBP(300, **options)
    alone = [tracker(d, [gen(10 + g)]) for g, d in enumerate((small,
                                                              large))]
    batched = tracker(Batch.from_data_list([small, large]),
                      [gen(10), gen(11)])
    assert batched.mean.shape == (4 + 6 + 2 * 4, 3, 6)  # agents, anchors
    torch.testing.assert_close(batched.mean, torch.cat([a.mean
                                                        for a in alone]),
                               rtol=1e-4, atol=1e-4)
    errors = (alone[1].mean[..., :3] - large.states[..., :3]).norm(dim=-1)
    assert float(errors[~large.anchor, -1].mean()) < 2.0


def test_particles_that_cannot_fit_are_refused_before_any_work():
    bp = ParticleBP(1000)
    needed = 113 * 1000 * (3 * 4 + 2) * 4
    bp.check_memory(113, 4, torch.float32, free=needed)
    with pytest.raises(ValueError, match="1000 particles on 113 nodes need "
                       "at least"):
        bp.check_memory(113, 4, torch.float32, free=needed - 1)
    # float64 doubles it
    with pytest.raises(ValueError):
        bp.check_memory(113, 4, torch.float64, free=needed)


def test_settings_name_the_resampler():
    # metrics.json entries of runs with other resamplers must differ
    from tg_nebp.filters import systematic_resample

    def own(log_weights, count, generator):
        return systematic_resample(log_weights, count, generator)

    assert ParticleBP(8).settings()['resampler'] == 'multinomial'
    assert ParticleBP(8, resampler='systematic').settings()[
        'resampler'] == 'systematic'
    assert ParticleBP(8, resampler=own).settings()['resampler'] == 'own'


def test_regularized_resampling_never_moves_an_anchor():
    # the kernel jitter of an anchor's one-point cloud grew its
    # rounding-level spread geometrically (to 1e18 m on a real sequence):
    # an anchor's particles stay its known position, bit for bit
    data = tiny_scenario(steps=30).generate(gen(2))
    # 100 particles: 1/100 is inexact, so the one-point cloud's mean rounds
    tracker = ParticleBP.recommended(num_particles=100)
    anchors = data.anchor.nonzero().view(-1)
    for step in tracker.steps(data, gen(3)):
        known = data.prior_mean[anchors].unsqueeze(1).expand(-1, 100, -1)
        assert torch.equal(step.particles[anchors], known.to(
            step.particles.dtype))


def test_the_reported_covariance_is_the_cloud_inflated_to_its_prediction():
    # the recommended tracker reports its weighted particle covariance
    # inflated by report_inflation, no further than the predicted cloud's;
    # the particles, weights and means are those of the same draws
    # reported as they are
    from tg_nebp.filters.particle.particle_bp import RECOMMENDED
    from helpers import bounded_inflation_by_loops
    data = tiny_scenario(steps=4).generate(gen(5))
    reporting = ParticleBP.recommended(num_particles=64)
    assert reporting.report_inflation == RECOMMENDED['report_inflation'] > 1
    plain = ParticleBP.recommended(num_particles=64, report_inflation=1.0)
    state = plain.initial_state(data, gen(9))
    mine = gen(9)
    inflated_any = False
    for t, (step, (edges, _)) in enumerate(zip(
            reporting.steps(data, gen(9)),
            zip(data.edges_by_step(), plain.controls_of(data)))):
        if t == 0:  # the same stream: the prior's draws first
            plain.initial_state(data, mine)
        own, state = plain.step(state, *edges, data.anchor, t, mine)
        # bit for bit on every CPU path: the same draws and operations on
        # the same inputs, the report touches the covariance only
        assert torch.equal(step.mean, own.mean)
        assert torch.equal(step.log_weights, own.log_weights)
        # float32 clouds: to float32's resolution of the whitening
        expected = bounded_inflation_by_loops(
            own.cov, state.predicted, reporting.report_inflation)
        torch.testing.assert_close(step.cov.double(), expected,
                                   rtol=1e-3, atol=1e-6)
        inflated_any |= bool((step.cov.diagonal(dim1=-2, dim2=-1) >
                              own.cov.diagonal(dim1=-2, dim2=-1) * 1.5)
                             .any())
    assert inflated_any
