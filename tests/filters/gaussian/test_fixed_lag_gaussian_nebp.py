r"""The learned correction inside fixed-lag Gaussian BP's window: untrained
it is the recommended window; a constant weight is the window of a range
model with another noise (every message of every window step tempered); a
batch equals each graph alone; the gradient through the window's
iterations matches finite differences; checkpoints rebuild it; streaming,
save/resume, joins and leaves are in tests/filters/live/test_session.py
(live_trackers)."""
import math

import pytest
import torch
from torch_geometric.data import Batch

from tg_nebp.filters import (FixedLagGaussianBP, FixedLagGaussianNEBP,
                             GaussianNEBP, Smoothed)
from tg_nebp.models import GaussianRange
from tg_nebp.training import (gaussian_nebp_from_checkpoint,
                              gaussian_step_loss, gaussian_window_loss,
                              save_checkpoint)

from helpers import (GeneralRange, anchor_links_only,
                     assert_batch_equals_alone, embed_in_3d, gen, randomize,
                     tiny_scenario)


def _assert_same(a, b, atol):
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=atol)
    torch.testing.assert_close(a.cov, b.cov, rtol=0, atol=atol)


@pytest.mark.parametrize('lag', [1, 3])
def test_untrained_is_the_recommended_window(lag):
    # bit for bit the window of general messages, to rounding the
    # rank-one ones of the range model; filtered and smoothed, and on a
    # batch (bit for bit on every CPU path: an untrained correction's log
    # weight is sigmoid(c) - sigmoid(c) over two tensors of one shape, the
    # same kernel on the same value at every element, so exactly 0; its
    # weights are exactly 1 and its inflation adds exactly 0)
    scenario = tiny_scenario(steps=7)
    graphs = [scenario.replace(num_agents=n).generate(gen(seed))
              for n, seed in ((3, 1), (5, 2))]
    learned = FixedLagGaussianNEBP.recommended(lag=lag)
    general = FixedLagGaussianBP.recommended(lag=lag,
                                             measurement=GeneralRange())
    rank_one = FixedLagGaussianBP.recommended(lag=lag)
    for data in (graphs[0], Batch.from_data_list(graphs)):
        for wrap in (lambda t: t, Smoothed):
            out = wrap(learned)(data)
            expected = wrap(general)(data)
            assert torch.equal(out.mean, expected.mean)
            assert torch.equal(out.cov, expected.cov)
            _assert_same(out, wrap(rank_one)(data), atol=1e-9)


def test_a_constant_weight_is_a_range_of_another_noise():
    # agents that range anchors only: a message tempered by w is the
    # message of a range whose noise variance is sigma^2 / w, on every
    # step of the window at every iteration, and so are the smoothed
    # estimates; the embeddings (random) then change nothing
    data = anchor_links_only(tiny_scenario(steps=8).generate(gen(6)))
    tracker = randomize(FixedLagGaussianNEBP.recommended(lag=4), seed=2,
                        scale=0.3)
    head = tracker.correction.weight_head
    with torch.no_grad():
        head.weight.zero_()
        head.bias.fill_(-1.5)
        for layer in (tracker.correction.inflation_mlp[-1], ):
            layer.weight.zero_()
            layer.bias.zero_()
    with torch.no_grad():
        weight = float(tracker.correction.message_weights(
            torch.zeros(1, tracker.correction.hidden_dim)))
    assert 0.2 < weight < 0.8
    sigma = GaussianRange().sigma / math.sqrt(weight)
    expected = FixedLagGaussianBP.recommended(
        lag=4, measurement=GaussianRange(sigma=sigma))
    with torch.no_grad():
        for wrap in (lambda t: t, Smoothed):
            _assert_same(wrap(tracker)(data), wrap(expected)(data),
                         atol=1e-9)
        # and the tempering did act
        plain = FixedLagGaussianBP.recommended(lag=4)(data)
        assert (plain.cov - tracker(data).cov).abs().max() > 1e-3


def test_a_batch_equals_each_graph_alone_with_a_trained_correction():
    tracker = randomize(FixedLagGaussianNEBP.recommended(lag=3).double(),
                        seed=4, scale=0.3)
    # each graph stops on its own, its rows' embeddings frozen with it
    assert_batch_equals_alone(tracker, rtol=0, atol=1e-12)


def _double(data):
    data.prior_mean, data.prior_cov = (data.prior_mean.double(),
                                       data.prior_cov.double())
    data.states = data.states.double()
    return data


def _window_loss_of_step(tracker, data, state, t):
    # the window loss of time index t from the state before it
    (edge_index, edge_attr), = [pair for k, pair in enumerate(
        data.edges_by_step()) if k == t]
    step, _ = tracker.step(state, edge_index, edge_attr, data.anchor, t)
    return gaussian_window_loss(step, data)


def test_gradients_through_the_window_match_finite_differences():
    # float64, every iteration run (no early stop): the loss of every
    # step of a full window (the fifth time step, lag 3: its Gaussian
    # before the window is inflated by the learned inflation) from the
    # state before it, against central differences of the same function
    data = _double(tiny_scenario(steps=5).replace(num_agents=4).generate(
        gen(8)))
    tracker = randomize(FixedLagGaussianNEBP(
        lag=3, num_iterations=3, tolerance=None).double(), seed=5, scale=0.3)
    state = tracker.initial_state(data)
    with torch.no_grad():
        for t, (edge_index, edge_attr) in enumerate(data.edges_by_step()):
            if t == 4:
                break
            _, state = tracker.step(state, edge_index, edge_attr,
                                    data.anchor, t)
    net = tracker.correction
    parameters = [net.weight_head.bias, net.weight_head.weight,
                  net.edge_mlp[0].weight, net.node_update.weight_hh,
                  net.inflation_mlp[2].bias]
    loss = _window_loss_of_step(tracker, data, state, 4)
    grads = torch.autograd.grad(loss, parameters)
    g, h = gen(0), 1e-6
    for parameter, grad in zip(parameters, grads):
        for index in torch.randint(parameter.numel(), (2, ), generator=g):
            flat = parameter.view(-1)
            with torch.no_grad():
                flat[index] += h
                up = _window_loss_of_step(tracker, data, state, 4)
                flat[index] -= 2 * h
                down = _window_loss_of_step(tracker, data, state, 4)
                flat[index] += h
            assert float(grad.view(-1)[index]) == pytest.approx(
                float((up - down) / (2 * h)), rel=1e-5, abs=1e-7)
    # the inflation's head acted (the Gaussian before the window)
    assert float(grads[-1].abs()) > 1e-6
    # training truncates in time: through the loop with the gradient on,
    # the step's loss reaches its own iterations alone
    for step in tracker.steps(data):
        if step.t == 4:
            truncated = torch.autograd.grad(gaussian_window_loss(step, data),
                                            parameters)
    for grad, expected in zip(truncated, grads):
        torch.testing.assert_close(grad, expected, rtol=1e-9, atol=1e-12)


def test_the_window_loss_sums_the_loss_of_every_window_step():
    # against the steps' own losses: the window's estimates of steps
    # t - W + 1 .. t at time index t
    data = tiny_scenario(steps=5).generate(gen(3))
    tracker = randomize(FixedLagGaussianNEBP.recommended(lag=3), seed=1,
                        scale=0.2)
    with torch.no_grad():
        for step in tracker.steps(data):
            width = step.window_mean.size(1)
            expected = 0.0
            for k in range(width):
                time = step.t - width + 1 + k
                agents = ~data.anchor
                error = (step.window_mean[agents, k, :2] -
                         data.states[agents, time, :2]).double()
                cov = step.window_cov[agents, k, :2, :2].double()
                for e, c in zip(error, cov):
                    expected += float(0.5 * (e @ torch.linalg.solve(c, e) +
                                             torch.logdet(c)) + e @ e)
            assert float(gaussian_window_loss(step, data)) == pytest.approx(
                expected, rel=1e-10)
    # a step without a window: its own loss
    out = FixedLagGaussianNEBP.recommended(lag=1)
    first = next(iter(out.steps(data)))._replace(window_mean=None)
    assert torch.equal(gaussian_window_loss(first, data),
                       gaussian_step_loss(first, data))


def test_a_checkpoint_rebuilds_the_window(tmp_path):
    data = tiny_scenario(steps=6).generate(gen(2))
    tracker = randomize(FixedLagGaussianNEBP.recommended(lag=3, hidden_dim=8),
                        seed=3, scale=0.2)
    save_checkpoint(tmp_path / 'window.pt', tracker)
    rebuilt = gaussian_nebp_from_checkpoint(tmp_path / 'window.pt')
    assert type(rebuilt) is FixedLagGaussianNEBP and rebuilt.lag == 3
    assert rebuilt.config() == tracker.config()
    with torch.no_grad():
        a, b = Smoothed(tracker)(data), Smoothed(rebuilt)(data)
    assert torch.equal(a.mean, b.mean) and torch.equal(a.cov, b.cov)
    # what does not size the network may change at load; the rest not
    assert gaussian_nebp_from_checkpoint(tmp_path / 'window.pt',
                                         tolerance=0.1).tolerance == 0.1
    with pytest.raises(ValueError, match="'lag' is fixed"):
        gaussian_nebp_from_checkpoint(tmp_path / 'window.pt', lag=4)


def test_2d_correction_refuses_3d_positions():
    data = embed_in_3d(tiny_scenario(steps=3).generate(gen(1)))
    with pytest.raises(ValueError, match='2-D positions'):
        FixedLagGaussianNEBP.recommended(lag=2)(data)


def test_a_window_of_one_step_is_gaussian_nebp():
    # the filter's own time loop with the same correction: its embeddings
    # carried over iterations and steps, the consistency history, the
    # learned inflation before every prediction and the tempered messages
    data = tiny_scenario(steps=6).replace(num_agents=5).generate(gen(4))
    window = randomize(FixedLagGaussianNEBP(lag=1, inflation=1.0,
                                            hidden_dim=8), seed=7, scale=0.3)
    filtered = GaussianNEBP(hidden_dim=8)
    filtered.conv.load_state_dict(window.correction.state_dict())
    with torch.no_grad():
        _assert_same(window(data), filtered(data), atol=1e-12)
        # and the correction did act
        plain = FixedLagGaussianBP(1)(data)
        assert (plain.mean - window(data).mean).abs().max() > 1e-3


def test_the_consistency_history_follows_every_step():
    # the agents' history of their newest rows' consistency, an
    # exponential average over every step (GaussianNEBPConv.end_step),
    # from the second step on: the window's steps before its first slide
    # included
    data = tiny_scenario(steps=6).generate(gen(5))
    tracker = randomize(FixedLagGaussianNEBP.recommended(lag=4, hidden_dim=8),
                        seed=2, scale=0.2)
    state = tracker.initial_state(data)
    history, consistency = [], []
    with torch.no_grad():
        for t, (edge_index, edge_attr) in enumerate(data.edges_by_step()):
            _, state = tracker.step(state, edge_index, edge_attr,
                                    data.anchor, t)
            consistency.append(state.memory[:, -2])
            history.append(state.memory[:, -1])
    agents = ~data.anchor
    assert bool((history[0] == 0).all())
    for t in range(1, len(history)):
        expected = torch.lerp(history[t - 1], consistency[t - 1], 0.2)
        torch.testing.assert_close(history[t], expected, rtol=1e-6,
                                   atol=1e-7)
        assert bool((history[t][agents] > 0).all())
