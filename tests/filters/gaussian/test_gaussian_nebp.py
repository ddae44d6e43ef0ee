r"""The Gaussian NEBP tracker (GaussianNEBP): untrained it is Gaussian BP
bit for bit, a batch equals each graph alone, beliefs stay symmetric
positive definite under any weights, the estimates move with rotations,
translations and renumberings of the scene, and the gradients of the
unrolled filter match finite differences."""
import math

import pytest
import torch
from torch_geometric.data import Batch

from tg_nebp.data import Realization
from tg_nebp.filters import GaussianBP, GaussianNEBP
from tg_nebp.models import ConstantVelocity
from tg_nebp.training import gaussian_step_loss

from helpers import (GeneralRange, assert_batch_equals_alone, gen,
                     randomize, tiny_scenario)


def spd(info):
    symmetric = torch.equal(info, info.transpose(-1, -2))
    return symmetric and not bool(torch.linalg.cholesky_ex(info)[1].any())


def test_identity_tracker_is_gaussian_bp_bit_for_bit():
    # bit for bit Gaussian BP's general messages, which the correction
    # weights; to rounding the rank-one messages of plain Gaussian BP
    # (bit for bit on every CPU path: an untrained correction's log
    # weight is sigmoid(c) - sigmoid(c) over two tensors of one shape, the
    # same kernel on the same value at every element, so exactly 0; its
    # weights are exactly 1 and its inflation adds exactly 0)
    scenario = tiny_scenario(steps=6)
    graphs = [scenario.replace(num_agents=n).generate(gen(seed))
              for n, seed in ((3, 1), (6, 2), (5, 3))]
    for options in (dict(), dict(tolerance=None, num_iterations=7,
                                 damping=0.3, ends='receiver')):
        general = GaussianBP(**{'num_iterations': 20, **options},
                             measurement=GeneralRange())
        rank_one = GaussianBP(**{'num_iterations': 20, **options})
        learned = GaussianNEBP(**options)
        for data in (graphs[0], Batch.from_data_list(graphs)):
            a, b = general(data), learned(data)
            assert torch.equal(a.mean, b.mean) and torch.equal(a.cov, b.cov)
            c = rank_one(data)
            torch.testing.assert_close(c.mean, a.mean, rtol=0, atol=1e-9)
            torch.testing.assert_close(c.cov, a.cov, rtol=1e-9, atol=1e-12)


def test_a_batch_equals_each_graph_alone_with_a_trained_correction():
    tracker = GaussianNEBP().double()
    randomize(tracker, seed=4, scale=0.3)
    # each graph stops on its own and its frozen embeddings stay frozen
    assert_batch_equals_alone(tracker, rtol=0, atol=1e-12)


@pytest.mark.parametrize('seed', range(6))
def test_beliefs_stay_symmetric_positive_definite(seed):
    # random (large) weights of the whole network, ranges corrupted by up
    # to 30 m, priors from 1e-4 to 1e4 m^2, 40 steps: every belief has
    # symmetric positive definite information, weights and inflations
    # stay inside their ranges. Weights this large drive the inflation's
    # output to hundreds, where it saturates at its bounds: that the
    # bounds hold there is the point (that agents get factors of their
    # own is test_the_inflation_is_each_agents_own's)
    g = gen(100 + seed)
    scenario = tiny_scenario(steps=40).replace(num_agents=6)
    data = scenario.generate(g)
    data.edge_attr = data.edge_attr + 30 * torch.rand(
        data.edge_attr.shape, generator=g) * (torch.rand(
            data.edge_attr.shape, generator=g) < 0.3)
    scale = 10.0 ** (8 * torch.rand(data.num_nodes, generator=g) - 4)
    data.prior_cov = data.prior_cov * scale.view(-1, 1, 1)
    tracker = GaussianNEBP(num_iterations=5, tolerance=None)
    randomize(tracker, seed=seed, scale=3.0)
    conv = tracker.conv
    seen = dict(weights=[], inflations=[])
    original_beliefs = conv.bp.beliefs

    def beliefs(prior, belief, messages, factors, anchor):
        out = original_beliefs(prior, belief, messages, factors, anchor)
        assert spd(out.info[~anchor])
        return out

    original_inflation = conv.inflation

    def inflation(cov, memory, anchor):
        kappa = original_inflation(cov, memory, anchor)
        seen['inflations'].append(kappa[~anchor])
        return kappa

    conv.bp.beliefs, conv.inflation = beliefs, inflation
    with torch.no_grad():
        out = tracker(data)
    agents = ~data.anchor
    assert torch.isfinite(out.mean).all()
    covs = out.cov[agents].flatten(0, 1)
    assert spd(covs)
    kappa = torch.cat(seen['inflations'])
    low, high = conv.inflation_range
    assert bool(((kappa >= low) & (kappa <= high)).all())


def test_the_inflation_is_each_agents_own():
    # moderate weights, where the inflation is not saturated: every
    # agent's factor is a function of its own memory and covariance only
    # (each row alone gives its factor), strictly inside the range, and
    # agents that see different things get different factors; anchors 1
    g = gen(7)
    conv = randomize(GaussianNEBP().double(), seed=3, scale=0.3).conv
    num, double = 7, dict(generator=g, dtype=torch.float64)
    memory = torch.cat([torch.randn(num, conv.hidden_dim, **double),
                        torch.rand(num, 2, **double)], -1)
    root = torch.randn(num, 4, 4, **double)
    cov = root @ root.transpose(-1, -2) + 0.1 * torch.eye(
        4, dtype=torch.float64)
    anchor = torch.zeros(num, dtype=torch.bool)
    anchor[2] = True
    with torch.no_grad():
        kappa = conv.inflation(cov, memory, anchor)
        alone = torch.cat([conv.inflation(cov[[i]], memory[[i]],
                                          anchor[[i]]) for i in range(num)])
    torch.testing.assert_close(kappa, alone, rtol=1e-12, atol=0)
    low, high = conv.inflation_range
    agents = kappa[~anchor]
    assert kappa[2] == 1.0
    assert bool(((agents > low) & (agents < high)).all())
    assert float(agents.max() - agents.min()) > 1e-3 * float(agents.mean())


def rigid_motion(data, rotation, shift, order):
    r"""The realization rotated by :obj:`rotation`, shifted by
    :obj:`shift` and with its nodes renumbered: new node :obj:`k` is old
    node :obj:`order[k]`."""
    dim = rotation.size(0)
    full = torch.block_diag(rotation, rotation).to(data.prior_mean)
    offset = torch.cat([shift, torch.zeros(dim)]).to(data.prior_mean)
    new_of_old = torch.empty_like(order)
    new_of_old[order] = torch.arange(order.numel())
    return Realization(
        states=(data.states @ full.T + offset)[order],
        edge_index=new_of_old[data.edge_index], edge_attr=data.edge_attr,
        edge_time=data.edge_time, anchor=data.anchor[order],
        prior_mean=(data.prior_mean @ full.T + offset)[order],
        prior_cov=(full @ data.prior_cov @ full.T)[order],
        num_steps=int(data.num_steps), num_nodes=data.num_nodes)


@pytest.mark.parametrize('three_d', [False, True])
def test_estimates_move_with_the_scene_and_its_numbering(three_d):
    g = gen(21)
    scenario = tiny_scenario(steps=5).replace(num_agents=7)
    if three_d:
        # anchors and agents at several heights (in one plane the height
        # is a mirror ambiguity that rounding decides)
        scenario = scenario.replace(
            anchor_positions=((0.0, 0.0, 0.0), (15.0, 0.0, 6.0),
                              (7.0, 12.0, 12.0), (4.0, 5.0, 15.0)),
            agent_start_low=(3.0, 3.0, 3.0),
            agent_start_high=(10.0, 10.0, 10.0),
            prior_var=(10.0, 10.0, 10.0, 0.01, 0.01, 0.01))
    data = scenario.generate(g)
    if three_d:
        axis = torch.nn.functional.normalize(torch.randn(3, generator=g,
                                                         dtype=torch.float64),
                                             dim=0)
        skew = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]],
                             [-axis[1], axis[0], 0]], dtype=torch.float64)
        rotation = torch.linalg.matrix_exp(1.1 * skew)
        shift = torch.tensor([40.0, -7.0, 3.0], dtype=torch.float64)
    else:
        angle = 0.7
        rotation = torch.tensor([[math.cos(angle), -math.sin(angle)],
                                 [math.sin(angle), math.cos(angle)]],
                                dtype=torch.float64)
        shift = torch.tensor([40.0, -7.0], dtype=torch.float64)
    data.prior_mean, data.prior_cov = (data.prior_mean.double(),
                                       data.prior_cov.double())
    data.states = data.states.double()
    order = torch.randperm(data.num_nodes, generator=g)
    moved = rigid_motion(data, rotation, shift, order)
    # the paper's motion model drags every axis on its own (v |v| per
    # axis), so only a motion model without drag moves with a rotation
    motion = ConstantVelocity(0.05)
    tracker = GaussianNEBP(num_iterations=6, tolerance=None, motion=motion,
                           position_dim=rotation.size(0)).double()
    randomize(tracker, seed=2, scale=0.5)
    out, out_moved = tracker(data), tracker(moved)
    full = torch.block_diag(rotation, rotation)
    offset = torch.cat([shift, torch.zeros_like(shift)])
    expected_mean = (out.mean @ full.T + offset)[order]
    expected_cov = (full @ out.cov @ full.T)[order]
    agents = ~moved.anchor
    torch.testing.assert_close(out_moved.mean[agents], expected_mean[agents],
                               rtol=0, atol=1e-9)
    torch.testing.assert_close(out_moved.cov[agents], expected_cov[agents],
                               rtol=1e-9, atol=1e-10)
    # and the correction did act: it is not Gaussian BP
    plain = GaussianBP(6, tolerance=None, motion=motion)(data)
    assert (plain.mean - out.mean).abs().max() > 1e-3


def step_losses(tracker, data, steps):
    return sum(gaussian_step_loss(step, data)
               for step in tracker.steps(data) if step.t in steps)


def finite_difference(tracker, data, parameter, index, steps, h=1e-6):
    with torch.no_grad():
        flat = parameter.view(-1)
        flat[index] += h
        up = step_losses(tracker, data, steps)
        flat[index] -= 2 * h
        down = step_losses(tracker, data, steps)
        flat[index] += h
    return float((up - down) / (2 * h))


@pytest.mark.parametrize('case', ['messages', 'inflation'])
def test_gradients_of_the_unrolled_filter_match_finite_differences(case):
    # float64 throughout, every iteration run (no early stop, whose
    # iteration count jumps); 'messages': one step, every parameter that
    # the weights read; 'inflation': the loss of the second step, where
    # the inflation head acts (the first step does not read it, so the
    # truncation between steps changes nothing)
    steps = 1 if case == 'messages' else 2
    data = tiny_scenario(steps=steps).replace(num_agents=4).generate(gen(8))
    data.prior_mean, data.prior_cov = (data.prior_mean.double(),
                                       data.prior_cov.double())
    data.states = data.states.double()
    tracker = GaussianNEBP(num_iterations=4, tolerance=None).double()
    randomize(tracker, seed=5, scale=0.3)
    conv = tracker.conv
    if case == 'messages':
        parameters = [conv.weight_head.bias, conv.weight_head.weight,
                      conv.edge_mlp[0].weight, conv.node_update.weight_hh]
    else:
        parameters = [conv.inflation_mlp[2].bias, conv.inflation_mlp[0].weight]
    loss = step_losses(tracker, data, {steps - 1})
    grads = torch.autograd.grad(loss, parameters)
    g = gen(0)
    for parameter, grad in zip(parameters, grads):
        for index in torch.randint(parameter.numel(), (3, ), generator=g):
            expected = finite_difference(tracker, data, parameter,
                                         int(index), {steps - 1})
            assert float(grad.view(-1)[index]) == pytest.approx(
                expected, rel=1e-5, abs=1e-7)
    assert any(float(grad.abs().max()) > 1e-6 for grad in grads)


def test_recommended_and_settings_describe_the_correction():
    tracker = GaussianNEBP.recommended()
    assert (tracker.num_iterations, tracker.tolerance) == (20, 0.01)
    settings = tracker.settings()
    # its inflation is learned per agent, not Gaussian BP's global one
    assert 'inflation' not in settings
    assert settings['hidden_dim'] == 32 and settings['position_dim'] == 2
