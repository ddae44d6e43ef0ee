import math

import numpy as np
import pytest
import torch

from tg_nebp.data import Realization
from tg_nebp.filters import GaussianBP
from tg_nebp.models import (ConstantVelocity, GaussianRange, NLOSRange,
                            StudentTRange)
from tg_nebp.nn.conv import (FactorMessages, GaussianBelief, GaussianBPConv,
                             RangeMessages)

from helpers import (NonNegativeRange, assert_batch_equals_alone, gen,
                     linear_kalman_filter, linear_offset_model,
                     linear_scenario, tiny_scenario)


def one_step(pairs, anchors, seed=0, sigma=0.5, count=None):
    r"""One time step of linear-offset measurements: 'count' agents 0..A-1
    (by default all but the anchors of the nodes that 'pairs' names), then
    the anchors at the given positions; every (j, i) of 'pairs' is a
    measurement of j by agent i."""
    g = gen(seed)
    if count is None:
        count = 1 + max(max(p) for p in pairs) - len(anchors)
    positions = torch.cat([10 * torch.rand(count, 2, generator=g,
                                           dtype=torch.float64),
                           torch.tensor(anchors, dtype=torch.float64)])
    states = torch.cat([positions, torch.zeros_like(positions)], 1)
    model = linear_offset_model()(sigma)
    motion = ConstantVelocity(0.2)
    moved = states.clone()
    moved[:count] = motion.mean(states[:count])
    edge_index = torch.tensor(pairs).t()
    noise = sigma * torch.randn(len(pairs), 2, generator=g,
                                dtype=torch.float64)
    edge_attr = (moved[edge_index[0], :2] - moved[edge_index[1], :2] +
                 model.OFFSET + noise)
    anchor = torch.arange(len(states)) >= count
    prior_cov = torch.diag_embed(torch.tensor(
        [4.0, 4.0, 0.1, 0.1], dtype=torch.float64).expand(len(states), -1))
    prior_cov = prior_cov * (~anchor).view(-1, 1, 1)
    prior_mean = states + torch.cat([
        2 * torch.randn(count, 4, generator=g, dtype=torch.float64) *
        torch.tensor([1.0, 1.0, 0.1, 0.1], dtype=torch.float64),
        torch.zeros(len(anchors), 4, dtype=torch.float64)])
    data = Realization(states=moved.unsqueeze(1), edge_index=edge_index,
                       edge_attr=edge_attr,
                       edge_time=torch.zeros(len(pairs), dtype=torch.long),
                       anchor=anchor, prior_mean=prior_mean,
                       prior_cov=prior_cov, num_steps=1,
                       num_nodes=len(states))
    return data, motion, model


def exact_and_gbp(data, motion, model, iterations, ends='both'):
    means, covs, agents = linear_kalman_filter(data, motion, model)
    out = GaussianBP(iterations, motion=motion, measurement=model,
                     ends=ends, tolerance=None)(data)
    return (means[:, 0], covs[:, 0], out.mean[agents, 0].numpy(),
            out.cov[agents, 0].numpy())


def test_tree_beliefs_are_the_exact_marginals():
    # a chain anchor - 0 - 1 - 2 with both directions of every agent link
    # measured: a tree of factors (a link's two ranges are one factor);
    # after as many iterations as its diameter, the exact marginals
    pairs = [(3, 0), (1, 0), (0, 1), (2, 1), (1, 2)]
    data, motion, model = one_step(pairs, anchors=[(0.0, 0.0)])
    means, covs, mean, cov = exact_and_gbp(data, motion, model, 4)
    np.testing.assert_allclose(mean, means, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(cov, covs, rtol=1e-10, atol=1e-12)


def test_loopy_means_converge_to_the_exact_means():
    # a ring of five agents and two anchors (walk-summable: converges);
    # the means are exact, the variances only approximately so
    pairs = [(i, (i + 1) % 5) for i in range(5)] + [((i + 1) % 5, i)
                                                    for i in range(5)]
    pairs += [(5, 0), (6, 2), (5, 3)]
    data, motion, model = one_step(pairs, anchors=[(0.0, 0.0),
                                                   (10.0, 5.0)])
    means, covs, mean, cov = exact_and_gbp(data, motion, model, 200)
    np.testing.assert_allclose(mean, means, rtol=1e-8, atol=1e-8)
    # loopy BP's variances: close, and not larger than the exact ones
    variances = np.diagonal(cov, axis1=-2, axis2=-1)
    exact = np.diagonal(covs, axis1=-2, axis2=-1)
    assert np.all(variances <= exact * (1 + 1e-9))
    np.testing.assert_allclose(variances, exact, rtol=0.5)


def test_iterations_do_not_count_a_measurement_twice():
    # two agents that measure each other: after one iteration their exact
    # posterior, and the same after ten, since every message marginalizes
    # the other end's extrinsic belief (without its own message back)
    for pairs, exact_after in (([(1, 0), (0, 1)], 1),
                               ([(1, 0), (0, 1), (2, 0), (3, 1)], 2)):
        # (an anchor that nobody measures where the pair has none)
        anchors = [(0.0, 0.0), (10.0, 0.0)] if len(pairs) > 2 else [
            (50.0, 50.0)]
        data, motion, model = one_step(pairs, anchors=anchors, count=2)
        means, covs, mean, cov = exact_and_gbp(data, motion, model,
                                               exact_after)
        np.testing.assert_allclose(mean, means, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(cov, covs, rtol=1e-10, atol=1e-12)
        _, _, mean10, cov10 = exact_and_gbp(data, motion, model, 10)
        np.testing.assert_allclose(mean10, mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(cov10, cov, rtol=1e-12, atol=1e-14)


def test_both_measurements_of_a_link_count_once_each():
    # two agents, no anchors in reach of agent 1: its position is known
    # only through the two ranges of the link; the exact posterior uses
    # both, once each; the receiver convention gives each agent one
    pairs = [(1, 0), (0, 1), (2, 0)]
    data, motion, model = one_step(pairs, anchors=[(0.0, 0.0)])
    means, covs, mean, cov = exact_and_gbp(data, motion, model, 5)
    np.testing.assert_allclose(mean, means, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(cov, covs, rtol=1e-10, atol=1e-12)
    _, _, _, receiver = exact_and_gbp(data, motion, model, 5,
                                      ends='receiver')
    assert receiver[1, 0, 0] > cov[1, 0, 0] * 1.1


def test_factors_and_message_edges():
    # links 2->0 (anchor 2), 1->0, 0->1: two factors {0, 1} (both ranges of
    # the pair) and {0, 2}; messages to 0 and 1 from {0, 1}, to 0 from {0, 2}
    conv = GaussianBPConv()
    edge_index = torch.tensor([[2, 1, 0], [0, 0, 1]])
    anchor = torch.tensor([False, False, True])
    f = conv.factors(edge_index, anchor, 4, slots=True)
    assert f.ends.tolist() == [[0, 1], [0, 2]]
    # a range model's factors are rank one: no slots unless asked for
    assert conv.rank_one and conv.factors(edge_index, anchor,
                                          4).curvature_slots is None
    # every link's 4 x 4 linearization (positions of [x_j; x_i]) placed in
    # its factor's [x_a; x_b], against a plain loop
    values = torch.arange(3 * 16, dtype=torch.float64).view(3, 4, 4)
    placed = torch.zeros(2 * 16, dtype=torch.float64).index_add_(
        0, f.curvature_slots, values.reshape(-1)).view(2, 4, 4)
    expected = torch.zeros(2, 4, 4, dtype=torch.float64)
    for e, (j, i) in enumerate(edge_index.t().tolist()):
        factor = f.ends.tolist().index(sorted([j, i]))
        order = [0, 1, 2, 3] if j < i else [2, 3, 0, 1]
        for r in range(4):
            for c in range(4):
                expected[factor, order[r], order[c]] += values[e, r, c]
    torch.testing.assert_close(placed, expected)
    # every message edge reads its factor with its target's half second,
    # and its reverse is the message of the same factor to the other end
    read = placed.view(-1)[f.message_slots].view(-1, 4, 4)
    sources, targets = f.index.tolist()
    assert sorted(zip(sources, targets)) == [(0, 1), (1, 0), (2, 0)]
    for m, (s_, t) in enumerate(zip(sources, targets)):
        factor = f.ends.tolist().index(sorted([s_, t]))
        order = [0, 1, 2, 3] if s_ < t else [2, 3, 0, 1]
        torch.testing.assert_close(read[m], placed[factor][order][:, order])
        if f.reverse[m] >= 0:
            r = int(f.reverse[m])
            assert (sources[r], targets[r]) == (t, s_)
        else:
            assert anchor[s_]
    receiver = GaussianBPConv(ends='receiver').factors(edge_index, anchor,
                                                       4)
    assert receiver.index.tolist() == edge_index.tolist()
    assert (receiver.reverse == -1).all()


def test_batch_equals_each_graph_alone():
    assert_batch_equals_alone(GaussianBP(3))


def test_linear_tracker_over_steps_keeps_marginals_only():
    # on a tree (two agents, anchors), Gaussian BP at every step gives the
    # exact marginals of the step, so over the steps it is the centralized
    # filter that drops the cross-agent covariances between steps
    from tg_nebp.filters import CentralizedIEKF
    scenario = linear_scenario(steps=4, num_agents=2)
    data = scenario.generate(gen(6))
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    gbp = GaussianBP(3, tolerance=None, **models)(data)
    ideal = CentralizedIEKF(marginal=True, **models)(data)
    torch.testing.assert_close(gbp.mean, ideal.mean, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(gbp.cov, ideal.cov, rtol=1e-9, atol=1e-12)


def test_inflation_and_tolerance():
    # one agent between two anchors: a tree, so Gaussian BP is the Kalman
    # filter whose covariance is inflated before every later prediction
    scenario = linear_scenario(steps=4, num_agents=1)
    data = scenario.generate(gen(8))
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    means, covs, agents = linear_kalman_filter(data, inflation=1.7,
                                               **models)
    out = GaussianBP(2, tolerance=None, inflation=1.7, **models)(data)
    np.testing.assert_allclose(out.mean[agents].numpy(), means, rtol=1e-10,
                               atol=1e-10)
    np.testing.assert_allclose(out.cov[agents].numpy(), covs, rtol=1e-10,
                               atol=1e-12)
    # a tolerance no iteration can miss stops after the first
    data = tiny_scenario(steps=3).generate(gen(9))
    one = GaussianBP(1, tolerance=None)(data)
    stopped = GaussianBP(30, tolerance=1e9)(data)
    torch.testing.assert_close(stopped.mean, one.mean, rtol=0, atol=0)
    assert not torch.allclose(GaussianBP(30, tolerance=None)(data).mean,
                              one.mean)


def test_options_are_checked():
    with pytest.raises(ValueError, match="'ends'"):
        GaussianBPConv(ends='sender')
    with pytest.raises(ValueError, match="'damping'"):
        GaussianBPConv(damping=1.0)
    assert GaussianBP(2, damping=0.5).settings()['damping'] == 0.5
    with pytest.raises(ValueError, match="'inflation'"):
        GaussianBP(inflation=0.9)
    recommended = GaussianBP.recommended(ends='receiver').settings()
    assert (recommended['inflation'], recommended['iterations'],
            recommended['tolerance'], recommended['ends']) == (
                1.5, 20, 0.01, 'receiver')


def test_a_plane_in_three_dimensions_gives_the_two_dimensional_beliefs():
    # every node at height zero: no range says anything about heights, and
    # the horizontal beliefs are the 2-D ones (Gaussian BP, the IEKF and
    # the bound alike)
    from helpers import embed_in_3d
    from tg_nebp.bounds import PosteriorCRB
    from tg_nebp.filters import CentralizedIEKF
    data = tiny_scenario(steps=3).generate(gen(4))
    flat = embed_in_3d(data)
    plane = [0, 1, 3, 4]
    for method in (GaussianBP(5), CentralizedIEKF()):
        two, three = method(data), method(flat)
        torch.testing.assert_close(three.mean[..., plane], two.mean,
                                   rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(
            three.cov[..., plane, :][..., plane], two.cov, rtol=1e-9,
            atol=1e-12)
    two, three = PosteriorCRB()(data), PosteriorCRB()(flat)
    torch.testing.assert_close(three[..., plane, :][..., plane], two,
                               rtol=1e-9, atol=1e-12)


# -- the inputs are checked as the particle conv checks them ----------------

def snapshot(seed=31, dtype=torch.float64):
    r"""A random snapshot for both convs: particles, and Gaussian beliefs
    of the same nodes (the particles' moments; anchors known)."""
    from helpers import random_graph
    from tg_nebp.filters import weighted_moments
    particles, log_weights, edge_index, edge_attr, anchor = random_graph(
        gen(seed), 4, 3, 16, dtype=dtype)
    mean, cov = weighted_moments(particles, log_weights)
    cov = cov + 0.1 * torch.eye(4, dtype=dtype)
    info = torch.where(anchor.view(-1, 1, 1), torch.zeros_like(cov),
                       torch.linalg.inv(cov))
    belief = GaussianBelief(mean, info)
    return particles, log_weights, edge_index, edge_attr, anchor, belief


def corrupt(name, edge_index, edge_attr, anchor):
    edge_index, edge_attr = edge_index.clone(), edge_attr.clone()
    if name in ('nan', 'inf', 'negative'):
        edge_attr[3, 0] = dict(nan=math.nan, inf=math.inf,
                               negative=-0.5)[name]
    elif name == 'self-loop':
        edge_index[0, 2] = edge_index[1, 2]
    elif name == 'out of range':
        edge_index[0, 1] = anchor.numel() + 2
    elif name == 'flat ranges':
        edge_attr = edge_attr.view(-1)
    elif name == 'short ranges':
        edge_attr = edge_attr[1:]
    elif name == 'float anchor':
        anchor = anchor.double()
    elif name == 'short anchor':
        anchor = anchor[1:]
    return edge_index, edge_attr, anchor


BAD_LINKS = {
    'nan': r"'edge_attr\[3\]' = nan is not finite",
    'inf': r"'edge_attr\[3\]' = inf is not finite",
    'negative': r"'edge_attr\[3\]' = -0.5 is a negative range",
    'self-loop': r"'edge_index\[:, 2\]' is a self-loop",
    'out of range': r"'edge_index\[0, 1\]' = 9 is out of range for 7 nodes",
    'flat ranges': r"'edge_attr' must have shape \[\d+, F\]",
    'short ranges': r"'edge_attr' must have shape \[\d+, F\]",
    'float anchor': r"'anchor' must be a bool tensor of shape \[7\]",
    'short anchor': r"'anchor' must be a bool tensor of shape \[7\]",
}


@pytest.mark.parametrize('name', sorted(BAD_LINKS))
def test_both_convs_refuse_the_same_bad_links(name):
    from tg_nebp.nn.conv import ParticleBPConv
    particles, log_weights, edge_index, edge_attr, anchor, belief = (
        snapshot())
    edge_index, edge_attr, anchor = corrupt(name, edge_index, edge_attr,
                                            anchor)
    # a likelihood that needs ranges of at least zero (the library's take
    # negative ones)
    with pytest.raises(ValueError, match=BAD_LINKS[name]):
        ParticleBPConv(NonNegativeRange())(particles, log_weights,
                                           edge_index, edge_attr,
                                           anchor=anchor)
    with pytest.raises(ValueError, match=BAD_LINKS[name]):
        GaussianBPConv(NonNegativeRange())(belief, belief, edge_index,
                                           edge_attr, anchor)


def test_bad_beliefs_and_messages_are_named():
    *_, edge_index, edge_attr, anchor, belief = snapshot()
    conv = GaussianBPConv()
    mean, info = belief

    def refused(prior, current, message, messages=None):
        with pytest.raises(ValueError, match=message):
            conv(prior, current, edge_index, edge_attr, anchor, messages)

    bad = mean.clone()
    bad[2, 1] = math.nan
    refused(belief, GaussianBelief(bad, info), r"'belief.mean\[2\]' holds "
            r"a non-finite value")
    skew = info.clone()
    skew[1, 0, 1] += 1.0
    refused(GaussianBelief(mean, skew), belief,
            r"'prior.info\[1\]' is not symmetric")
    refused(GaussianBelief(mean, -info), belief,
            r"'prior.info\[0\]' is not positive semi-definite")
    refused(belief, GaussianBelief(mean[1:], info[1:]),
            r"'belief.mean' holds 6 nodes but the graph has 7")
    refused(belief, GaussianBelief(mean, info[..., :2]),
            r"'belief.info' must have shape \[7, 4, 4\]")
    _, rank_one = conv(belief, belief, edge_index, edge_attr, anchor)
    refused(belief, belief, r"'messages.direction' must have shape",
            rank_one._replace(direction=rank_one.direction[:, :1]))
    messages = rank_one.factor_messages()
    refused(belief, belief, r"'messages.info' must have shape",
            FactorMessages(messages.info[1:], messages.eta))
    nan = messages.eta.clone()
    nan[4, 0] = math.nan
    refused(belief, belief, r"'messages.eta\[4\]' holds a non-finite",
            FactorMessages(messages.info, nan))
    # no prior information and no message: a state nothing determines
    flat = GaussianBelief(mean, torch.zeros_like(info))
    lonely = edge_index[:, edge_index[1] != 0]
    with pytest.raises(ValueError, match='the belief of node 0 has singular '
                       'information'):
        conv(flat, belief, lonely, edge_attr[edge_index[1] != 0], anchor)


def test_half_precision_is_computed_in_float32():
    *_, edge_index, edge_attr, anchor, belief = snapshot()
    conv = GaussianBPConv()
    half = GaussianBelief(*(t.half() for t in belief))
    single = GaussianBelief(*(t.half().float() for t in belief))
    got, _ = conv(half, half, edge_index, edge_attr.half(), anchor)
    want, _ = conv(single, single, edge_index, edge_attr.half().float(),
                   anchor)
    assert got.mean.dtype == torch.float32
    torch.testing.assert_close(got.mean, want.mean, rtol=0, atol=0)
    torch.testing.assert_close(got.info, want.info, rtol=0, atol=0)


def in_general_form(model):
    # the same model through the general (matrix) messages: a range model
    # with a linearize of its own is not sent rank-one messages
    class General(type(model)):
        def linearize(self, *args):
            return super().linearize(*args)
    return General(**model.params())


def random_beliefs(dim, seed, agents=10, anchors=3):
    # agents and anchors in a box, beliefs near the truth with random SPD
    # information, links within 7 m in both directions except a few in one
    # only (factors of one and of two ranges)
    g = gen(seed)
    n, size = agents + anchors, 2 * dim
    truth = 10 * torch.rand(n, dim, generator=g, dtype=torch.float64)
    anchor = torch.arange(n) >= agents
    mean = torch.cat([truth, torch.randn(n, dim, generator=g,
                                         dtype=torch.float64)], -1)
    mean[:agents, :dim] += torch.randn(agents, dim, generator=g,
                                       dtype=torch.float64)
    root = torch.randn(n, size, size, generator=g, dtype=torch.float64)
    info = root @ root.transpose(-1, -2) / size + 0.2 * torch.eye(size)
    info = torch.where(anchor.view(-1, 1, 1), torch.zeros_like(info), info)
    src, dst = torch.meshgrid(torch.arange(n), torch.arange(n),
                              indexing='ij')
    near = (torch.cdist(truth, truth) < 7) & (src != dst) & ~anchor[dst]
    near &= torch.rand(n, n, generator=g) < 0.9
    edge_index = torch.stack([src[near], dst[near]])
    distance = (truth[edge_index[0]] - truth[edge_index[1]]).norm(dim=-1)
    # some ranges far off (NLOS), where the robust weights matter
    edge_attr = (distance + 0.3 * torch.randn(distance.shape, generator=g,
                                              dtype=torch.float64) +
                 4 * (torch.rand(distance.shape, generator=g) < 0.15)
                 ).clamp_min(0).view(-1, 1)
    return GaussianBelief(mean, info), edge_index, edge_attr, anchor


@pytest.mark.parametrize('dim', [2, 3])
@pytest.mark.parametrize('ends', ['both', 'receiver'])
@pytest.mark.parametrize('model', [GaussianRange(0.3), StudentTRange(0.3, 3),
                                   NLOSRange(0.3, 0.2, 3.0)],
                         ids=['gaussian', 'student-t', 'nlos'])
def test_rank_one_messages_equal_the_general_messages(dim, ends, model):
    # the closed-form scalar messages of range factors against the general
    # Schur complements of their matrices, over iterations that remove
    # the previous messages, with anchors, in 2-D and 3-D
    prior, edge_index, edge_attr, anchor = random_beliefs(dim, seed=dim)
    fast = GaussianBPConv(model, ends)
    general = GaussianBPConv(in_general_form(model), ends)
    assert fast.rank_one and not general.rank_one
    beliefs, messages = [prior, prior], [None, None]
    for iteration in range(6):
        for k, conv in enumerate((fast, general)):
            beliefs[k], messages[k] = conv(prior, beliefs[k], edge_index,
                                           edge_attr, anchor, messages[k])
        assert isinstance(messages[0], RangeMessages)
        for got, expected in zip(messages[0].factor_messages(),
                                 messages[1]):
            torch.testing.assert_close(got, expected, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(beliefs[0].mean, beliefs[1].mean,
                                   rtol=0, atol=1e-9)
        torch.testing.assert_close(beliefs[0].info, beliefs[1].info,
                                   rtol=1e-9, atol=1e-9)
    # the iterations moved the beliefs: the test is not of a fixed point
    assert float((beliefs[0].mean - prior.mean).abs().max()) > 0.1


@pytest.mark.parametrize('ends', ['both', 'receiver'])
@pytest.mark.parametrize('slots', [False, True])
def test_restricted_factors_are_the_factors_of_the_kept_links(ends, slots):
    # three graphs of a batch, the middle one dropped: the factors of the
    # other two, renumbered, without sorting again
    graphs = [random_beliefs(2, seed, agents=5 + seed) for seed in (4, 5, 6)]
    offsets = [0, 12, 25]  # 9, 10 and 11 agents and 3 anchors
    edge_index = torch.cat([g[1] + o for g, o in zip(graphs, offsets)], 1)
    anchor = torch.cat([g[3] for g in graphs])
    keep = torch.ones_like(anchor)
    keep[offsets[1]:offsets[2]] = False
    conv = GaussianBPConv(ends=ends)
    full = conv.factors(edge_index, anchor, 4, slots=slots)
    number = torch.cumsum(keep, 0) - 1
    links = keep[edge_index[1]]
    expected = conv.factors(number[edge_index[:, links]], anchor[keep], 4,
                            slots=slots)
    got = conv.restricted_factors(full, keep, 4)
    for field, value in got._asdict().items():
        other = getattr(expected, field)
        assert (value is None and other is None) or torch.equal(
            value, other), field
    assert got.index.size(1) < full.index.size(1)


def test_compiled_rank_one_messages_equal_the_eager_ones():
    # the torch.compile-fused messages, first and later iterations (two
    # compiled graphs), in 2-D and 3-D (dynamic sizes), to rounding
    eager, compiled = GaussianBPConv(), GaussianBPConv(compile=True)
    for dim in (2, 3):
        prior, edge_index, edge_attr, anchor = random_beliefs(dim, seed=dim)
        beliefs, messages = [prior, prior], [None, None]
        for iteration in range(3):
            for k, conv in enumerate((eager, compiled)):
                beliefs[k], messages[k] = conv(prior, beliefs[k], edge_index,
                                               edge_attr, anchor, messages[k])
            for got, expected in zip(messages[1], messages[0]):
                torch.testing.assert_close(got, expected, rtol=1e-12,
                                           atol=1e-12)
            torch.testing.assert_close(beliefs[1].mean, beliefs[0].mean,
                                       rtol=0, atol=1e-12)


def test_a_step_without_links_keeps_the_prior():
    # no link: no message, in both forms, and the checks of the previous
    # (empty) messages hold
    prior, _, _, anchor = random_beliefs(2, seed=7)
    edge_index = torch.zeros(2, 0, dtype=torch.long)
    edge_attr = torch.zeros(0, 1, dtype=torch.float64)
    for conv in (GaussianBPConv(), GaussianBPConv(damping=0.2)):
        belief, messages = conv(prior, prior, edge_index, edge_attr, anchor)
        belief, messages = conv(prior, belief, edge_index, edge_attr, anchor,
                                messages)
        torch.testing.assert_close(belief.mean, prior.mean, rtol=0,
                                   atol=1e-12)
        assert all(t.size(0) == 0 for t in messages)


def test_a_singular_belief_keeps_its_prior_and_the_step_goes_on():
    # messages that cancel an agent's prior information (what rounding
    # does to messages that outweigh a very wide prior by many orders):
    # that agent keeps its prior, with a warning naming it; the others'
    # beliefs are the usual sums
    *_, edge_index, edge_attr, anchor, belief = snapshot()
    conv = GaussianBPConv(ends='both')
    factors = conv.factors(edge_index, anchor, belief.mean.size(-1))
    _, rank_one = conv(belief, belief, edge_index, edge_attr, anchor)
    messages = rank_one.factor_messages()
    agent = int((~anchor).nonzero()[0, 0])
    into = (factors.index[1] == agent).nonzero().view(-1)
    info = messages.info.clone()
    width = messages.eta.size(-1)
    # the agent's prior without position-velocity correlation: a message
    # of minus its position information leaves the position undetermined
    regular_info = belief.info.clone()
    regular_info[agent, :width, width:] = 0
    regular_info[agent, width:, :width] = 0
    regular = GaussianBelief(belief.mean, regular_info)
    info[into] = 0
    info[into[0]] = -regular_info[agent, :width, :width]
    with pytest.warns(RuntimeWarning, match=rf"node\(s\) \[{agent}\] became "
                      r"singular"):
        got = conv.beliefs(regular, belief, FactorMessages(
            info, messages.eta), factors, anchor)
    torch.testing.assert_close(got.info[agent], regular_info[agent])
    torch.testing.assert_close(got.mean[agent], belief.mean[agent])
    # a prior without velocity information cannot stand in for itself
    prior_info = regular_info.clone()
    prior_info[agent, width:, width:] = 0
    prior = GaussianBelief(belief.mean, prior_info)
    others = ~anchor
    others[agent] = False
    want = conv.beliefs(regular, belief, messages, factors, anchor)
    torch.testing.assert_close(got.info[others], want.info[others])
    # a prior that cannot stand in: refused by name
    with pytest.raises(ValueError, match=rf"the belief of node {agent} has "
                       r"singular information"):
        conv.beliefs(prior, belief, FactorMessages(
            torch.zeros_like(info), messages.eta), factors, anchor)
