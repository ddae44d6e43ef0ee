r"""An experiment, not a method of the library: can the learned correction
pay inside fixed-lag Gaussian BP's window? The correction is the edge
network of :class:`~tg_nebp.nn.conv.GaussianNEBPConv` (its invariant
features of every message edge: the normalized residual, the ends'
spreads, the message's strength, whether the source is an anchor; without
its node memory), whose weight in (0.02, 1.1) tempers every message of
every window step at every iteration (general messages: the information
and the vector scaled), and it is trained through the window's iterations:
each time step's loss is Gaussian NEBP's
(:func:`~tg_nebp.training.gaussian_step_loss`) summed over the window's
steps, one Adam step per time step, the state detached between steps.
Untrained (the head at zero) it is the recommended window exactly.

Hyper-parameters are Gaussian NEBP's shipped ones (Adam 3e-4, seed 1; 3
epochs of 16 training realizations, seed 10), fixed before the test
network was tracked; the validation realizations are seed 1's first 5 of
the training network, the test ones seed 0's of another network. Each row:
filtered and smoothed RMSE, the smoothed P(accept 0.95), and per
realization the smoothed RMSE over the smoothing bound's at the lag (mean
and standard deviation), untrained and trained; one torch thread.

    python benchmarks/window_correction.py     # paper_train -> paper_test
    python benchmarks/window_correction.py --node-memory
    python benchmarks/window_correction.py --scenario paper_train \
        paper_train_sparse --realizations 8 --test-scenario paper_test \
        paper_test_sparse --test-realizations 5

With several training networks, each gives the realizations asked (the
realizations in turn) and its own 5 validation ones; the correction's
features are invariant, so one network runs on every scenario.
"""
import argparse
import time
from types import SimpleNamespace

import torch

from tg_nebp.bounds import PosteriorCRB
from tg_nebp.datasets import Scenario
from tg_nebp.filters import FixedLagGaussianBP, Smoothed
from tg_nebp.metrics import consistency_curve, nees
from tg_nebp.nn.conv import GaussianNEBPConv
from tg_nebp.nn.conv.gaussian_bp_conv import FactorMessages, GaussianBPConv
from tg_nebp.training import gaussian_step_loss


class TemperedWindowConv(GaussianBPConv):
    # Gaussian BP's general messages of every window step, each tempered
    # by the correction's weight of its message edge; with 'node_memory'
    # the correction's node part too: an embedding of every node of every
    # window step, zero at each time step's first iteration and updated
    # at every iteration by the correction's GRU from its edges and its
    # node features (degree, anchors in reach, spread, consistency)
    def __init__(self, measurement, correction: GaussianNEBPConv,
                 node_memory: bool = False):
        super().__init__(measurement)
        self.correction = correction
        self.node_memory = node_memory
        self.memory, self.iteration = None, 0

    @property
    def rank_one(self) -> bool:
        return False  # the correction reads the general messages

    def step_messages(self, belief, edge_index, edge_attr, anchor, factors,
                      messages=None, generator=None, fresh=None):
        # GaussianNEBPConv.forward's correction over the window's rows;
        # without the node part the embeddings stay zero
        net, rows = self.correction, belief.mean.size(0)
        if self.memory is None:
            self.memory = net.initial_memory(rows)
        new, features, edge = net._corrected(
            belief, edge_index, edge_attr, anchor, self.memory, messages,
            generator, factors, self.iteration)
        if self.node_memory:
            gathered = net.propagate(factors.index, edge=edge,
                                     size=(rows, rows))
            hidden = net.node_update(torch.cat([gathered, features.node.to(
                edge)], -1), self.memory[:, :net.hidden_dim])
            self.memory = torch.cat([hidden, features.consistency.to(
                edge).view(-1, 1), self.memory[:, -1:]], -1)
            self.iteration += 1
        weight = net.message_weights(edge).to(new.eta)
        return FactorMessages(new.info * weight.view(-1, 1, 1),
                              new.eta * weight)


class CorrectedWindow(FixedLagGaussianBP):
    # the window whose conv starts every time step with a fresh memory
    def solve_step(self, *args, **kwargs):
        self.conv.memory, self.conv.iteration = None, 0
        return super().solve_step(*args, **kwargs)


def window_tracker(scenario, correction, lag, node_memory):
    tracker = CorrectedWindow.recommended(
        lag=lag, motion=scenario.motion_model,
        measurement=scenario.measurement_model)
    tracker.conv = TemperedWindowConv(scenario.measurement_model, correction,
                                      node_memory)
    return tracker


def detached(value):
    # a state with every tensor detached (training is truncated in time)
    if isinstance(value, torch.Tensor):
        return value.detach()
    if isinstance(value, tuple) and hasattr(value, '_fields'):
        return type(value)(*(detached(v) for v in value))
    if isinstance(value, (tuple, list)):
        return type(value)(detached(v) for v in value)
    return value


def window_loss(step, data):
    # Gaussian NEBP's loss of every step of the window
    width = step.window_mean.size(1)
    return sum(gaussian_step_loss(SimpleNamespace(
        mean=step.window_mean[:, k], cov=step.window_cov[:, k],
        t=step.t - width + 1 + k), data) for k in range(width))


def train(correction, realizations, epochs, lr, lag, node_memory):
    # realizations: (scenario, realization) pairs, in this order each epoch
    optimizer = torch.optim.Adam(correction.parameters(), lr=lr)
    for epoch in range(epochs):
        total = 0.0
        for scenario, data in realizations:
            tracker = window_tracker(scenario, correction, lag,
                                     node_memory)
            state = tracker.initial_state(data)
            for t, ((edge_index, edge_attr), control) in enumerate(zip(
                    data.edges_by_step(), tracker.controls_of(data))):
                step, state = tracker.step(state, edge_index, edge_attr,
                                           data.anchor, t, control=control)
                loss = window_loss(step, data)
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                total += float(loss.detach())
                state = detached(state)
        print(f'epoch {epoch}: loss {total / len(realizations):.1f}',
              flush=True)


def scores(correction, scenario, realizations, lag, node_memory):
    # filtered and smoothed RMSE, smoothed P(accept 0.95) pooled, and each
    # realization's smoothed RMSE over its smoothing bound's
    filtered = smoothed = count = 0.0
    tests, ratios = [], []
    bound = PosteriorCRB(scenario.motion_model, scenario.measurement_model,
                         lag=lag)
    with torch.no_grad():
        for data in realizations:
            agents = ~data.anchor
            truth = data.states[agents, :, :2].double()
            out = Smoothed(window_tracker(scenario, correction, lag,
                                          node_memory))(data)
            newest = window_tracker(scenario, correction, lag,
                                    node_memory)(data)
            error = (out.mean[agents, :, :2] - truth).square().sum(-1)
            smoothed += float(error.sum())
            filtered += float((newest.mean[agents, :, :2] - truth).square(
            ).sum(-1).sum())
            count += error.numel()
            tests.append(nees(out.mean[agents, :, :2].double(),
                              out.cov[agents, :, :2, :2].double(),
                              truth).flatten())
            floor = bound(data)[agents, :, :2, :2].diagonal(
                dim1=-2, dim2=-1).sum(-1).mean().sqrt()
            ratios.append(float(error.mean().sqrt() / floor))
    ratio = torch.tensor(ratios)
    accept = float(consistency_curve(torch.cat(tests), [0.95])[0])
    return (f'filtered {(filtered / count) ** 0.5:.4f} m, smoothed '
            f'{(smoothed / count) ** 0.5:.4f} m, P(accept 0.95) '
            f'{accept:.3f}, smoothed / bound {float(ratio.mean()):.3f} +- '
            f'{float(ratio.std()):.3f}')


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenario', nargs='+', default=['paper_train'])
    parser.add_argument('--test-scenario', nargs='+',
                        default=['paper_test'])
    parser.add_argument('--realizations', type=int, default=16)
    parser.add_argument('--test-realizations', type=int, default=10)
    parser.add_argument('--epochs', type=int, default=3)
    parser.add_argument('--lr', type=float, default=3e-4)
    parser.add_argument('--lag', type=int, default=5)
    parser.add_argument('--node-memory', action='store_true',
                        help="the correction's node part too (its node "
                        'features and embeddings, per time step)')
    args = parser.parse_args()
    torch.set_num_threads(1)
    scenarios = [Scenario.load(name) for name in args.scenario]
    tests = [Scenario.load(name) for name in args.test_scenario]
    torch.manual_seed(1)
    measurement = scenarios[0].measurement_model
    correction = GaussianNEBPConv(measurement)
    untrained = GaussianNEBPConv(measurement)

    def drawn(scenario, seed, count):
        generator = torch.Generator().manual_seed(seed)
        return [(scenario, scenario.generate(generator))
                for _ in range(count)]

    validation = [drawn(scenario, 1, 5) for scenario in scenarios]
    # the training networks' realizations in turn
    training = [pair for pairs in zip(*(drawn(
        scenario, 10, args.realizations) for scenario in scenarios))
        for pair in pairs]
    start = time.perf_counter()
    train(correction, training, args.epochs, args.lr, args.lag,
          args.node_memory)
    print(f'trained in {time.perf_counter() - start:.0f} s', flush=True)
    for name, groups in (
            ('validation', validation),
            ('test', [drawn(scenario, 0, args.test_realizations)
                      for scenario in tests])):
        for pairs in groups:
            where, realizations = pairs[0][0], [d for _, d in pairs]
            for label, net in (('untrained', untrained),
                               ('trained', correction)):
                row = scores(net, where, realizations, args.lag,
                             args.node_memory)
                print(f'{where.name} ({name}, {len(realizations)} '
                      f'realizations) {label}: {row}', flush=True)


if __name__ == '__main__':
    main()
