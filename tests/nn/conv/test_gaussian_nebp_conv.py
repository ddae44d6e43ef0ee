r"""The learned correction of Gaussian BP, one iteration
(GaussianNEBPConv): the identity correction is Gaussian BP bit for bit, its
maps onto the weights' and inflations' ranges, its invariant features
against plain loops, and its checks. (The tracker, GaussianNEBP, is tested
in tests/filters/gaussian/test_gaussian_nebp.py.)"""
import math

import pytest
import torch

from tg_nebp.filters import GaussianNEBP
from tg_nebp.nn.conv import GaussianBPConv, GaussianNEBPConv
from tg_nebp.nn.conv.gaussian_nebp_conv import (EDGE_FEATURES, bounded_log,
                                                position_covariance)

from helpers import embed_in_3d, first_step, gen, randomize, tiny_scenario


@pytest.mark.parametrize('three_d', [False, True])
@pytest.mark.parametrize('ends', ['both', 'receiver'])
def test_identity_correction_is_gaussian_bp_bit_for_bit(three_d, ends):
    # (bit for bit on every CPU path: an untrained correction's log
    # weight is sigmoid(c) - sigmoid(c) over two tensors of one shape, the
    # same kernel on the same value at every element, so exactly 0; its
    # weights are exactly 1 and its inflation adds exactly 0)
    data = tiny_scenario(steps=1).replace(num_agents=6).generate(gen(3))
    if three_d:
        data = embed_in_3d(data)
    scenario = tiny_scenario()
    prior, edge_index, edge_attr = first_step(data, scenario.motion_model)
    bp = GaussianBPConv(ends=ends, damping=0.2)
    corrected = GaussianNEBPConv(ends=ends, damping=0.2)
    memory = corrected.initial_memory(data.num_nodes)
    plain = belief = prior
    plain_messages = messages = None
    for iteration in range(4):
        plain, plain_messages = bp(prior, plain, edge_index, edge_attr,
                                   data.anchor, plain_messages)
        belief, messages, memory = corrected(prior, belief, edge_index,
                                             edge_attr, data.anchor, memory,
                                             messages, iteration=iteration)
        for a, b in zip((*plain, *plain_messages), (*belief, *messages)):
            assert torch.equal(a, b)
    # the embeddings learn even while the outputs are the identity
    assert memory[:, :corrected.hidden_dim].abs().sum() > 0


def test_bounded_log_maps_onto_its_range_and_is_zero_at_zero():
    raw = torch.tensor([-1e6, -3.0, 0.0, 3.0, 1e6], dtype=torch.float64)
    low, high = math.log(0.02), math.log(1.1)
    out = bounded_log(raw, low, high)
    assert out[2] == 0
    assert torch.allclose(out[[0, 4]], torch.tensor([low, high],
                                                    dtype=torch.float64))
    assert bool((out.diff() > 0).all())


def test_features_are_what_the_formulas_give():
    # a Gaussian range's normalized residual is r / sqrt(sigma^2 +
    # u^T (S_s + S_t) u) (two ranges of a pair: their mean, with half the
    # noise variance); checked with plain loops in float64
    data = tiny_scenario(steps=1).replace(num_agents=5).generate(gen(13))
    scenario = tiny_scenario()
    prior, edge_index, edge_attr = first_step(data, scenario.motion_model)
    conv = GaussianNEBPConv(scenario.measurement_model)
    bp = conv.bp
    factors = conv.factors(edge_index, data.anchor, 4)
    linearization = bp.linearize(prior, edge_index, edge_attr, factors)
    messages = bp.messages(prior, data.anchor, factors, linearization)
    features = conv.features(prior, data.anchor, factors, linearization,
                             messages, 3, conv.initial_memory(data.num_nodes))
    cov = position_covariance(prior, 2, data.anchor)
    sigma = scenario.measurement_model.sigma
    residual = EDGE_FEATURES.index('residual')
    for m, (s, t) in enumerate(factors.index.t().tolist()):
        ranges = [float(edge_attr[e, 0]) for e in range(edge_index.size(1))
                  if {int(edge_index[0, e]), int(edge_index[1, e])} == {s, t}]
        diff = prior.mean[s, :2] - prior.mean[t, :2]
        distance = float(diff.norm())
        u = diff / distance
        spread = float(u @ (cov[s] + cov[t]) @ u)
        mean_range = sum(ranges) / len(ranges)
        expected = (mean_range - distance) / math.sqrt(
            sigma**2 / len(ranges) + spread)
        assert math.sinh(float(features.edge[m, residual])) == pytest.approx(
            expected, rel=1e-9, abs=1e-12)
    assert torch.all(features.edge[:, EDGE_FEATURES.index('iteration')] ==
                     3 / conv.num_iterations)


def test_options_and_memory_are_checked():
    with pytest.raises(ValueError, match='weight_range'):
        GaussianNEBPConv(weight_range=(1.2, 2.0))
    with pytest.raises(ValueError, match='hidden_dim'):
        GaussianNEBPConv(hidden_dim=0)
    with pytest.raises(ValueError, match='position_dim'):
        GaussianNEBP(position_dim=4)
    data = tiny_scenario(steps=1).generate(gen(0))
    prior, edge_index, edge_attr = first_step(data, tiny_scenario()
                                              .motion_model)
    conv = GaussianNEBPConv()
    with pytest.raises(ValueError, match="'memory' must have shape"):
        conv(prior, prior, edge_index, edge_attr, data.anchor,
             torch.zeros(data.num_nodes, 3))
    with pytest.raises(ValueError, match="'memory' must be torch.float32"):
        conv(prior, prior, edge_index, edge_attr, data.anchor,
             conv.initial_memory(data.num_nodes).double())
    with pytest.raises(ValueError, match="'weight_range' must be"):
        GaussianNEBPConv(weight_range=(0.5, ))
    with pytest.raises(ValueError, match='built for 2-D positions'):
        GaussianNEBP()(embed_in_3d(data))


def test_the_weights_are_those_its_messages_are_tempered_by():
    # weights() at an iteration's inputs is the ratio of the tempered
    # messages that forward returns to Gaussian BP's at the same inputs
    data = tiny_scenario(steps=1).replace(num_agents=6).generate(gen(21))
    scenario = tiny_scenario()
    prior, edge_index, edge_attr = first_step(data, scenario.motion_model)
    conv = randomize(GaussianNEBPConv(), seed=4, scale=0.3)
    memory = conv.initial_memory(data.num_nodes)
    belief, messages = prior, None
    factors = conv.factors(edge_index, data.anchor, prior.mean.size(-1))
    for iteration in range(3):
        weights = conv.weights(belief, edge_index, edge_attr, data.anchor,
                               memory, messages, factors, iteration)
        plain = conv.bp.messages(
            belief, data.anchor, factors, conv.bp.linearize(
                belief, edge_index, edge_attr, factors), messages)
        belief, messages, memory = conv(prior, belief, edge_index,
                                        edge_attr, data.anchor, memory,
                                        messages, iteration=iteration)
        assert weights.shape == (factors.index.size(1), )
        assert float(weights.std()) > 0
        torch.testing.assert_close(messages.eta, plain.eta *
                                   weights.view(-1, 1), rtol=1e-12,
                                   atol=1e-12)
        torch.testing.assert_close(messages.info, plain.info *
                                   weights.view(-1, 1, 1), rtol=1e-12,
                                   atol=1e-12)
