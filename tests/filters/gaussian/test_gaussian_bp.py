r"""The Gaussian BP tracker's time loop: each graph of a batch converges on
its own. (One iteration, the conv, is tested in
tests/nn/conv/test_gaussian_bp_conv.py with the tracker's exactness.)"""
import torch
from torch_geometric.data import Batch

from tg_nebp.filters import GBP_RECOMMENDED, GaussianBP

from helpers import (assert_batch_equals_alone, bounded_inflation_by_loops,
                     gen, tiny_scenario)


class Counting(GaussianBP):
    # Gaussian BP that counts the nodes of every iteration it runs
    def __init__(self, **options):
        super().__init__(**options)
        self.nodes = []

    def iterate(self, prior, *args):
        self.nodes.append(prior.mean.size(0))
        return super().iterate(prior, *args)


def test_early_stop_is_per_graph_so_a_batch_equals_each_graph_alone():
    # with the tolerance the graphs of a batch stop after different numbers
    # of iterations; a stop decided over the whole batch iterated the
    # graph that had converged on (3.4 mm on the paper's network). The
    # converged graphs leave the iterations: bit for bit each graph alone
    assert_batch_equals_alone(GaussianBP.recommended(), rtol=0, atol=0)
    scenario = tiny_scenario(steps=6)
    graphs = [scenario.replace(num_agents=n).generate(gen(seed))
              for n, seed in ((3, 11), (6, 12), (4, 13), (8, 14))]
    for options in (GBP_RECOMMENDED, dict(num_iterations=50, tolerance=1e-4,
                                          damping=0.3)):
        tracker = Counting(**options)
        alone = [tracker(g) for g in graphs]
        tracker.nodes = []
        batched = tracker(Batch.from_data_list(graphs))
        # bit for bit on every CPU path: see assert_batch_equals_alone
        for field in ('mean', 'cov'):
            assert torch.equal(getattr(batched, field), torch.cat(
                [getattr(a, field) for a in alone]))
        # some iterations ran on fewer than all the nodes
        assert min(tracker.nodes) < max(tracker.nodes)


def test_the_reported_covariance_is_the_belief_inflated_to_the_prediction():
    # the recommended tracker reports its belief's covariance inflated by
    # report_inflation, no further than the step's prediction in any
    # direction; the means, and all it carries to later steps, are those
    # of the same tracker reporting its beliefs as they are
    data = tiny_scenario(steps=5).generate(gen(3))
    reporting = GaussianBP.recommended()
    assert reporting.report_inflation == GBP_RECOMMENDED[
        'report_inflation'] > 1
    plain = GaussianBP.recommended(report_inflation=1.0)
    state = plain.initial_state(data)
    inflated_any = False
    for t, (step, (edges, control)) in enumerate(zip(
            reporting.steps(data), zip(data.edges_by_step(),
                                       plain.controls_of(data)))):
        own, state = plain.step(state, *edges, data.anchor, t,
                                control=control)
        # bit for bit on every CPU path: both run the same operations on
        # the same inputs, the report touches the covariance only
        assert torch.equal(step.mean, own.mean)
        expected = bounded_inflation_by_loops(own.cov, state.predicted,
                                      reporting.report_inflation)
        torch.testing.assert_close(step.cov, expected, rtol=1e-9,
                                   atol=1e-12)
        inflated_any |= bool((step.cov.diagonal(dim1=-2, dim2=-1) >
                              own.cov.diagonal(dim1=-2, dim2=-1) * 1.5)
                             .any())
        # never beyond the prediction
        gap = state.predicted - step.cov
        assert float(torch.linalg.eigvalsh(gap).min()) > -1e-9
    assert inflated_any
