r"""GPU checks (skipped without CUDA): the conv and the tracker on CUDA agree
with the CPU, and the tracker is deterministic on one device."""
import math

import pytest
import torch

from tg_nebp import ParticleBP, Scenario

cuda = pytest.mark.skipif(not torch.cuda.is_available(),
                          reason='needs a CUDA device')


def _data():
    scenario = Scenario.load('paper_test').replace(num_steps=6)
    return scenario.generate(torch.Generator().manual_seed(3))


@cuda
def test_conv_cuda_equals_cpu():
    data = _data()
    tracker = ParticleBP(4000)
    particles = tracker.sample_prior(data, torch.Generator().manual_seed(0))
    log_weights = torch.randn(particles.shape[:2],
                              generator=torch.Generator().manual_seed(1))
    edge_index, ranges = data.edges_by_step()[0]
    cpu, cpu_msg = tracker.conv(particles, log_weights, edge_index, ranges,
                                anchor=data.anchor)
    gpu, gpu_msg = tracker.conv.cuda()(particles.cuda(), log_weights.cuda(),
                                       edge_index.cuda(), ranges.cuda(),
                                       anchor=data.anchor.cuda())
    # float32 sums of up to ~30 terms of size ~1e2: a few 1e-5 relative
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-5, atol=1e-3)
    torch.testing.assert_close(gpu_msg.cpu(), cpu_msg, rtol=1e-5, atol=1e-3)


@cuda
def test_tracker_cuda_deterministic():
    data = _data().to('cuda')
    tracker = ParticleBP(2000).cuda()
    first = tracker(data, torch.Generator('cuda').manual_seed(0))
    second = tracker(data, torch.Generator('cuda').manual_seed(0))
    assert torch.equal(first.mean, second.mean)
    assert torch.equal(first.cov, second.cov)
    other = tracker(data, torch.Generator('cuda').manual_seed(1))
    assert not torch.equal(first.mean, other.mean)
    agents = ~data.anchor
    error = (first.mean[agents, :, :2] - data.states[agents, :, :2]).norm(
        dim=-1)
    assert bool(torch.isfinite(first.cov).all())
    # the same filter statistics as on the CPU: errors of a few metres at
    # most after the prior's ~4.5 m
    assert float(error[:, -1].mean()) < 2.0 * math.sqrt(2)


@cuda
def test_fused_path_equals_messages_path_on_cuda():
    from torch_geometric import EdgeIndex
    data = _data().to('cuda')
    tracker = ParticleBP(3000).cuda()
    particles = tracker.sample_prior(data,
                                     torch.Generator('cuda').manual_seed(0))
    log_weights = torch.randn(particles.shape[:2], device='cuda',
                              generator=torch.Generator('cuda').manual_seed(1))
    edge_index, ranges = data.edges_by_step()[0]
    sorted_edges = EdgeIndex(edge_index, sparse_size=(data.num_nodes, ) * 2,
                             sort_order='col')
    reference, _ = tracker.conv(particles, log_weights, edge_index, ranges,
                                anchor=data.anchor)
    fused, messages = tracker.conv(particles, log_weights, sorted_edges,
                                   ranges, anchor=data.anchor,
                                   return_messages=False)
    assert messages is None
    torch.testing.assert_close(fused, reference, rtol=1e-5, atol=1e-3)
    again, _ = tracker.conv(particles, log_weights, sorted_edges, ranges,
                            anchor=data.anchor, return_messages=False)
    assert torch.equal(fused, again)


@cuda
def test_compiled_nebp_conv_equals_eager_and_is_deterministic_on_cuda():
    from torch_geometric import EdgeIndex

    from tg_nebp.nn.conv import NEBPConv

    data = _data().to('cuda')
    num_particles = 512
    particles = ParticleBP(num_particles).sample_prior(
        data, torch.Generator('cuda').manual_seed(0))
    log_weights = torch.full(particles.shape[:2], -math.log(num_particles),
                             device='cuda')
    edge_index, ranges = data.edges_by_step()[0]
    n = data.num_nodes
    edges = EdgeIndex(edge_index, sparse_size=(n, n), sort_order='col')
    torch.manual_seed(0)
    eager = NEBPConv(num_particles).cuda()
    compiled = NEBPConv(num_particles, compile=True).cuda()
    compiled.load_state_dict(eager.state_dict())
    beliefs = [
        conv(particles, log_weights, edges, ranges, data.anchor)[0]
        .log_softmax(-1) for conv in (eager, compiled, compiled)
    ]
    torch.testing.assert_close(beliefs[1].exp(), beliefs[0].exp(), atol=1e-5,
                               rtol=0)
    assert torch.equal(beliefs[1], beliefs[2])
