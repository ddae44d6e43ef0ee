r"""On CUDA the trackers pass receiver-sorted :class:`EdgeIndex` edges (the
fused, deterministic path). The same route, forced on the CPU, must give the
same tracks as plain edge tensors, and NEBP must stay differentiable."""
import torch
from torch_geometric import EdgeIndex

from tg_nebp import NEBP, ParticleBP, Scenario


def _force_edge_index(tracker):
    update = tracker.update

    def sorted_update(particles, log_weights, edge_index, edge_attr, anchor):
        n = particles.size(0)
        edges = EdgeIndex(edge_index, sparse_size=(n, n), sort_order='col')
        return update(particles, log_weights, edges, edge_attr, anchor)

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
