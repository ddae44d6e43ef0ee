r"""The Gaussian BP tracker's time loop: each graph of a batch converges on
its own. (One iteration, the conv, is tested in
tests/nn/conv/test_gaussian_bp_conv.py with the tracker's exactness.)"""
import torch
from torch_geometric.data import Batch

from tg_nebp.filters import GaussianBP

from helpers import assert_batch_equals_alone, gen, tiny_scenario


def test_early_stop_is_per_graph_so_a_batch_equals_each_graph_alone():
    # with the tolerance the graphs of a batch stop after different numbers
    # of iterations; a stop decided over the whole batch iterated the
    # graph that had converged on (3.4 mm on the paper's network)
    assert_batch_equals_alone(GaussianBP.recommended(), rtol=0, atol=1e-12)
    scenario = tiny_scenario(steps=6)
    graphs = [scenario.replace(num_agents=n).generate(gen(seed))
              for n, seed in ((3, 11), (6, 12), (4, 13), (8, 14))]
    for tracker in (GaussianBP.recommended(),
                    GaussianBP(50, tolerance=1e-4, damping=0.3)):
        alone = [tracker(g) for g in graphs]
        batched = tracker(Batch.from_data_list(graphs))
        for field in ('mean', 'cov'):
            torch.testing.assert_close(
                getattr(batched, field),
                torch.cat([getattr(a, field) for a in alone]), rtol=0,
                atol=1e-12)
