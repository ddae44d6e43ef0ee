r"""HybridBPConv: the message at the receiver's particles is the link's
likelihood with the source's extrinsic Gaussian integrated out (a closed
form for a Gaussian range and a linear Gaussian model, a float64 quadrature
for a nonlinear heavy-tailed one), an anchor source sends the likelihood
itself, the sources are extrinsic, and the closed form of the range models
equals the general messages."""
import math

import pytest
import torch

from tg_nebp.filters import GaussianBP
from tg_nebp.models import GaussianRange, NLOSRange, StudentTRange
from tg_nebp.nn.conv import GaussianBPConv, HybridBPConv, SourceBeliefs

from helpers import gen, linear_offset_model, tiny_scenario

DOUBLE = dict(dtype=torch.float64)


def two_nodes(ranges, source_anchor=False, size=4):
    r"""Node 0 an agent, node 1 the source; 'ranges' (j, i, z): node i
    measured node j at z. The factors of Gaussian BP with both ends."""
    edge_index = torch.tensor([[j, i] for j, i, _ in ranges]).t()
    edge_attr = torch.tensor([[z] for _, _, z in ranges], **DOUBLE)
    order = torch.argsort(edge_index[1], stable=True)
    edge_index, edge_attr = edge_index[:, order], edge_attr[order]
    anchor = torch.tensor([False, source_anchor])
    factors = GaussianBPConv(ends='both').factors(edge_index, anchor, size)
    return edge_index, edge_attr, anchor, factors


def sources_at(factors, states, covs, anchor, width=2):
    r"""SourceBeliefs of every message edge from given source states and
    scope covariances (zero for an anchor)."""
    source = factors.index[0]
    cov = covs[source].clone()
    known = anchor[source]
    eye = torch.eye(width, **DOUBLE)
    info = torch.where(known.view(-1, 1, 1), eye,
                       torch.linalg.inv(torch.where(known.view(-1, 1, 1),
                                                    eye, cov)))
    return SourceBeliefs(states[source], info,
                         cov.masked_fill(known.view(-1, 1, 1), 0.0), known)


def into_agent(factors):
    # the message edge that ends at node 0
    return int((factors.index[1] == 0).nonzero()[0, 0])


@pytest.mark.parametrize('both', [False, True])
def test_a_gaussian_range_message_adds_the_source_variance(both):
    # one range (or both of a pair): N(z; d, sigma^2 + u^T Sigma u) per
    # range, the pair's two correlated through the shared source
    sigma = 0.7
    model = GaussianRange(sigma=sigma)
    ranges = [(1, 0, 5.3)] + ([(0, 1, 4.6)] if both else [])
    edge_index, edge_attr, anchor, factors = two_nodes(ranges)
    source = torch.tensor([4.0, 1.0, 0.3, -0.2], **DOUBLE)
    cov = torch.tensor([[0.8, 0.3], [0.3, 0.5]], **DOUBLE)
    states = torch.stack([torch.zeros(4, **DOUBLE), source])
    covs = torch.stack([torch.eye(2, **DOUBLE), cov])
    sources = sources_at(factors, states, covs, anchor)
    g = gen(3)
    particles = torch.cat([3 * torch.randn(1, 9, 2, generator=g, **DOUBLE),
                           torch.zeros(1, 9, 2, **DOUBLE)], -1)
    particles = torch.cat([particles, source.expand(1, 9, 4)])
    out = HybridBPConv(model).log_messages(particles, sources, factors,
                                           edge_index, edge_attr)
    m = into_agent(factors)
    for k in range(9):
        offset = source[:2] - particles[0, k, :2]
        d = float(offset.norm())
        u = offset / d
        v = float(u @ cov @ u)
        z = edge_attr[:, 0]
        joint = sigma**2 * torch.eye(len(ranges), **DOUBLE) + v
        resid = z - d
        expected = (-0.5 * resid @ torch.linalg.solve(joint, resid) -
                    0.5 * torch.logdet(2 * math.pi * joint))
        assert float(out[m, k]) == pytest.approx(float(expected), abs=1e-10)


def test_a_linear_gaussian_message_is_exact_through_the_general_path():
    # the linear offset model (no closed form of its own in the conv):
    # integral of N(z; x_s - x_t + o, s^2 I) N(x_s; mu, Sigma) is
    # N(z; mu - x_t + o, s^2 I + Sigma)
    model = linear_offset_model()(0.4)
    edge_index = torch.tensor([[1], [0]])
    z = torch.tensor([[1003.0, 998.5]], **DOUBLE)
    anchor = torch.tensor([False, False])
    factors = GaussianBPConv(model, ends='both').factors(edge_index, anchor,
                                                          4)
    mu = torch.tensor([2.5, -1.0, 0.0, 0.0], **DOUBLE)
    cov = torch.tensor([[0.6, -0.2], [-0.2, 0.3]], **DOUBLE)
    states = torch.stack([torch.zeros(4, **DOUBLE), mu])
    sources = sources_at(factors, states,
                         torch.stack([torch.eye(2, **DOUBLE), cov]), anchor)
    particles = torch.randn(2, 6, 4, generator=gen(4), **DOUBLE)
    out = HybridBPConv(model).log_messages(particles, sources, factors,
                                           edge_index, z)
    m = into_agent(factors)
    total = 0.16 * torch.eye(2, **DOUBLE) + cov
    for k in range(6):
        resid = z[0] - model.OFFSET - (mu[:2] - particles[0, k, :2])
        expected = (-0.5 * resid @ torch.linalg.solve(total, resid) -
                    0.5 * torch.logdet(2 * math.pi * total))
        assert float(out[m, k]) == pytest.approx(float(expected), abs=1e-9)


def test_a_heavy_tailed_message_matches_a_quadrature_of_the_source():
    # Student-t range, a sharp source (0.05 m^2), residuals of 0 to 2
    # sigma: the second-order expansion on the source's side against a
    # float64 grid integral of p(z | x_s, x_t) N(x_s) over +-6 sd. The
    # expansion takes the model's robust (IRLS) weight for the curvature,
    # which the Student-t's true curvature undercuts off the mode: within
    # 0.1 nats (0.08 seen at 2 sigma; 0.01 for the Gaussian range, whose
    # error is the distance's own curvature across the link)
    model = StudentTRange(sigma=0.5, nu=3.0)
    edge_index, edge_attr, anchor, factors = two_nodes([(1, 0, 6.1)])
    mu = torch.tensor([5.0, 2.0, 0.0, 0.0], **DOUBLE)
    cov = torch.tensor([[0.05, 0.01], [0.01, 0.04]], **DOUBLE)
    states = torch.stack([torch.zeros(4, **DOUBLE), mu])
    sources = sources_at(factors, states,
                         torch.stack([torch.eye(2, **DOUBLE), cov]), anchor)
    targets = torch.tensor([[0.0, 0.0], [0.5, -0.4], [-1.0, 1.5]], **DOUBLE)
    particles = torch.zeros(2, 3, 4, **DOUBLE)
    particles[0, :, :2] = targets
    particles[1] = mu
    out = HybridBPConv(model).log_messages(particles, sources, factors,
                                           edge_index, edge_attr)
    m = into_agent(factors)
    axis = torch.linspace(-6, 6, 401, **DOUBLE)
    lower = torch.linalg.cholesky(cov)
    grid = torch.stack(torch.meshgrid(axis, axis, indexing='ij'), -1).view(
        -1, 2)
    points = mu[:2] + grid @ lower.T
    density = torch.exp(-0.5 * grid.square().sum(-1)) / (
        2 * math.pi * torch.det(lower))
    cell = float((axis[1] - axis[0])**2 * torch.det(lower))
    for k in range(3):
        distance = (points - targets[k]).norm(dim=-1).view(1, -1)
        likelihood = model.log_likelihood_of_distance(edge_attr,
                                                      distance).exp()
        expected = math.log(float((likelihood * density).sum()) * cell)
        assert float(out[m, k]) == pytest.approx(expected, abs=0.1)


def test_an_anchor_source_sends_the_likelihood_itself():
    model = NLOSRange()
    edge_index, edge_attr, anchor, factors = two_nodes(
        [(1, 0, 7.2)], source_anchor=True)
    known = torch.tensor([3.0, 4.0, 0.0, 0.0], **DOUBLE)
    states = torch.stack([torch.zeros(4, **DOUBLE), known])
    sources = sources_at(factors, states, torch.zeros(2, 2, 2, **DOUBLE),
                         anchor)
    particles = torch.randn(2, 5, 4, generator=gen(5), **DOUBLE)
    out = HybridBPConv(model).log_messages(particles, sources, factors,
                                           edge_index, edge_attr)
    expected = model.log_likelihood(edge_attr, known.expand(1, 5, 4),
                                    particles[:1])
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-12)


def test_the_sources_are_the_beliefs_without_the_factors_message():
    # Gaussian BP's final beliefs and messages of a step: each message
    # edge's source information is its belief's marginal on the scope
    # minus what this factor sent it (every agent's belief is its prior
    # plus its messages: the extrinsic part is the rest)
    data = tiny_scenario(steps=2).generate(gen(3))
    tracker = GaussianBP(num_iterations=30, tolerance=None)
    state = tracker.initial_state(data)
    edge_index, edge_attr = next(iter(data.edges_by_step()))
    solved = tracker.solve_step(state, edge_index, edge_attr, data.anchor,
                                0)
    conv = HybridBPConv()
    sources = conv.sources(solved.belief, solved.factors, solved.messages,
                           data.anchor)
    messages = solved.messages.factor_messages()
    source, target = solved.factors.index
    for m in range(source.numel()):
        s = int(source[m])
        if bool(data.anchor[s]):
            assert bool(sources.known[m])
            assert torch.equal(sources.state[m], solved.belief.mean[s])
            continue
        info = torch.linalg.inv(torch.linalg.inv(solved.belief.info[s])[
            :2, :2])
        back = int(solved.factors.reverse[m])
        expected = info - (messages.info[back] if back >= 0 else 0.0)
        torch.testing.assert_close(sources.info[m], expected, rtol=1e-9,
                                   atol=1e-9)
        torch.testing.assert_close(sources.cov[m], torch.linalg.inv(
            expected), rtol=1e-9, atol=1e-9)


def _general(model):
    # the same range model through a linearize of its own: the general
    # path of the messages
    class General(type(model)):
        def linearize(self, *args, **kwargs):
            return super().linearize(*args, **kwargs)

    return General(**model.params())


def _step_messages(model, particles_per_node):
    # the arguments of the messages on the first step of a tiny network
    # solved by Gaussian BP: particles about its posterior, the sources'
    # extrinsic beliefs, its factors and links
    data = tiny_scenario(steps=2).generate(gen(7))
    tracker = GaussianBP(measurement=model)
    edge_index, edge_attr = next(iter(data.edges_by_step()))
    solved = tracker.solve_step(tracker.initial_state(data), edge_index,
                                edge_attr.double(), data.anchor, 0)
    sources = HybridBPConv(model).sources(solved.belief, solved.factors,
                                          solved.messages, data.anchor)
    particles = solved.output.mean.unsqueeze(1) + 0.7 * torch.randn(
        data.num_nodes, particles_per_node, 4, generator=gen(8), **DOUBLE)
    return (particles, sources, solved.factors, edge_index.long(),
            edge_attr.double())


@pytest.mark.parametrize('model', [GaussianRange(), StudentTRange(),
                                   NLOSRange()])
def test_the_range_closed_form_equals_the_general_messages(model):
    # the rank-one arithmetic of a range model against the general path
    # (the same model through a linearize of its own): messages and the
    # target side's linearization, to rounding
    general = _general(model)
    conv = HybridBPConv(model)
    args = _step_messages(model, 8)
    assert conv.rank_one and not HybridBPConv(general).rank_one
    torch.testing.assert_close(conv.log_messages(*args),
                               HybridBPConv(general).log_messages(*args),
                               rtol=0, atol=1e-10)
    for ours, theirs in zip(conv.target_linearization(*args),
                            HybridBPConv(general).target_linearization(
                                *args)):
        torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-10)
    # in blocks of message edges (a block's edge between a factor's two
    # ranges, one edge per block, more than all): the same, both paths
    for measurement in (model, general):
        whole = HybridBPConv(measurement, chunk_size=None)
        expected = (whole.log_messages(*args),
                    *whole.target_linearization(*args))
        for size in (1, 3, 7, 10_000):
            blocks = HybridBPConv(measurement, chunk_size=size)
            for ours, theirs in zip((blocks.log_messages(*args),
                                     *blocks.target_linearization(*args)),
                                    expected):
                torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-12)


def test_the_belief_is_the_prior_plus_the_messages_normalized():
    data = tiny_scenario(steps=2).generate(gen(9))
    tracker = GaussianBP()
    edge_index, edge_attr = next(iter(data.edges_by_step()))
    solved = tracker.solve_step(tracker.initial_state(data), edge_index,
                                edge_attr, data.anchor, 0)
    conv = HybridBPConv()
    sources = conv.sources(solved.belief, solved.factors, solved.messages,
                           data.anchor)
    particles = solved.output.mean.unsqueeze(1) + torch.randn(
        data.num_nodes, 5, 4, generator=gen(1), **DOUBLE)
    prior = torch.randn(data.num_nodes, 5, generator=gen(2), **DOUBLE)
    belief, messages = conv(particles, prior, sources, solved.factors,
                            edge_index.long(), edge_attr.double())
    expected = prior.clone()
    for m, t in enumerate(solved.factors.index[1].tolist()):
        expected[t] += messages[m]
    torch.testing.assert_close(belief, expected.log_softmax(-1), rtol=0,
                               atol=1e-12)
    with pytest.raises(ValueError, match="'chunk_size'"):
        HybridBPConv(chunk_size=0)
    with pytest.raises(TypeError, match="'measurement'"):
        HybridBPConv(measurement='gaussian')


@pytest.mark.parametrize('general', [False, True])
def test_tempered_messages_are_each_edges_power(general):
    # a message edge's log-message, gradient and curvature multiplied by
    # its power: against the sum over the message edges one at a time
    model = _general(GaussianRange()) if general else GaussianRange()
    conv = HybridBPConv(model, chunk_size=3)
    args = _step_messages(model, 6)
    particles, sources, factors, edge_index, edge_attr = args
    count = factors.index.size(1)
    power = torch.rand(count, generator=gen(9), **DOUBLE) * 2
    prior = torch.zeros(particles.shape[:2], **DOUBLE)
    _, messages = conv(*args[:1], prior, *args[1:], tempering=power)
    torch.testing.assert_close(messages, conv.log_messages(*args) *
                               power.view(-1, 1), rtol=0, atol=1e-12)
    grad, curv = conv.target_linearization(*args, tempering=power)
    expected_grad, expected_curv = torch.zeros_like(grad), torch.zeros_like(
        curv)
    for m in range(count):
        one = factors._replace(index=factors.index[:, [m]],
                               link=factors.link[[m]], end=factors.end[[m]],
                               reverse=factors.reverse[[m]])
        g, w = conv.target_linearization(
            particles, SourceBeliefs(*(part[[m]] for part in sources)), one,
            edge_index, edge_attr)
        expected_grad += power[m] * g
        expected_curv += power[m] * w
    torch.testing.assert_close(grad, expected_grad, rtol=0, atol=1e-10)
    torch.testing.assert_close(curv, expected_curv, rtol=0, atol=1e-10)
