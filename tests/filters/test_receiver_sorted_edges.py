r"""On CUDA the trackers pass receiver-sorted :class:`EdgeIndex` edges (the
fused, deterministic path). The same route, forced on the CPU, must give the
same tracks as plain edge tensors, and NEBP must stay differentiable."""
import torch
from torch_geometric import EdgeIndex

from tg_nebp import NEBP, ParticleBP, Scenario


def _force_edge_index(tracker):
    update = tracker.update

    def sorted_update(particles, log_weights, edge_index, edge_attr, anchor,
                      **options):
        n = particles.size(0)
        edges = EdgeIndex(edge_index, sparse_size=(n, n), sort_order='col')
        return update(particles, log_weights, edges, edge_attr, anchor,
                      **options)

    tracker.update = sorted_update


def _data():
    return Scenario.load('paper_train').replace(num_steps=3).generate(
        torch.Generator().manual_seed(0))


def test_bp_tracker_same_with_receiver_sorted_edges():
    data = _data()
    tracker = ParticleBP(128)
    plain = tracker(data, torch.Generator().manual_seed(0))
    _force_edge_index(tracker)
    routed = tracker(data, torch.Generator().manual_seed(0))
    torch.testing.assert_close(routed.mean, plain.mean, rtol=0, atol=1e-4)


def test_nebp_tracker_same_with_receiver_sorted_edges():
    data = _data()
    torch.manual_seed(0)
    tracker = NEBP(64)
    plain = tracker(data, torch.Generator().manual_seed(0))
    _force_edge_index(tracker)
    routed = tracker(data, torch.Generator().manual_seed(0))
    torch.testing.assert_close(routed.mean, plain.mean, rtol=0, atol=1e-4)
    routed.mean[~data.anchor].square().sum().backward()
    for name, param in tracker.named_parameters():
        assert param.grad is not None and bool(
            torch.isfinite(param.grad).all()), name


def test_update_sorts_edges_given_in_any_order():
    data = _data()
    tracker = ParticleBP(64)
    particles = tracker.sample_prior(data, torch.Generator().manual_seed(1))
    log_weights = torch.full(particles.shape[:2], -6.0)
    edge_index, ranges = data.edges_by_step()[0]
    shuffle = torch.randperm(edge_index.size(1),
                             generator=torch.Generator().manual_seed(2))
    in_order = tracker.update(particles, log_weights, edge_index, ranges,
                              data.anchor)
    shuffled = tracker.update(particles, log_weights, edge_index[:, shuffle],
                              ranges[shuffle], data.anchor)
    # only the summation order differs (log-weights of order 10-100)
    torch.testing.assert_close(shuffled, in_order, rtol=1e-4, atol=1e-4)
    # ranges must travel with their edges: pairing them wrongly changes it
    wrong = tracker.update(particles, log_weights, edge_index[:, shuffle],
                           ranges, data.anchor)
    assert float((wrong - in_order).abs().max()) > 1.0
