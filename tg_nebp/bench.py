r"""Benchmarks behind :obj:`tg-nebp bench`: :class:`ParticleBPConv` on one
time step of the paper's test network (:obj:`--batch` realizations as one
graph): ms per iteration as the tracker calls it (no messages returned),
edge-particles per second and peak memory beyond the inputs, the same with
the edge messages returned, a naive eager gather-likelihood-scatter, and the
whole :class:`ParticleBP` tracker (seconds per time step, peak memory). Each particle count runs in a fresh
process so that peak memory is its own."""
import json
import math
import multiprocessing
import queue as queue_module
import resource
import statistics
import time

import torch

__all__ = ['add_arguments', 'run_bench', 'measure']


def add_arguments(parser):
    r"""Adds the :obj:`tg-nebp bench` options to :obj:`parser`."""
    parser.add_argument('--particles', type=int, nargs='+',
                        default=[1000, 5000],
                        help='particle counts K (default: 1000 5000)')
    parser.add_argument('--repeats', type=int, default=10,
                        help='timed iterations per K (default: 10)')
    parser.add_argument('--steps', type=int, default=5,
                        help='tracker time steps per K (default: 5)')
    parser.add_argument('--batch', type=int, default=1,
                        help='test realizations batched into one graph '
                        '(default: 1)')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--json', action='store_true',
                        help='print one JSON object per K')


def _sync(device):
    if device.startswith('cuda'):
        torch.cuda.synchronize()


def _timed(fn, repeats, device):
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _rss_peak_bytes():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _naive(particles, log_weights, edge_index, ranges, sigma):
    # the plain eager baseline: gather [E, K, 2], likelihood, scatter-add
    src, dst = edge_index
    dist = (particles[src, :, :2] - particles[dst, :, :2]).norm(dim=-1)
    log_lik = -0.5 * ((ranges - dist) / sigma)**2 - math.log(
        math.sqrt(2 * math.pi) * sigma)
    out = torch.zeros_like(log_weights).index_add_(
        0, dst, log_lik + log_weights[src])
    return log_weights + out


def measure(num_particles, device='cpu', repeats=10, steps=5, seed=0,
            root='datasets', batch=1):
    r"""Measures one particle count :math:`K` in this process; returns a
    dict of figures."""
    from torch_geometric import EdgeIndex
    from torch_geometric.data import Batch

    from tg_nebp.datasets import CooperativeLocalizationDataset
    from tg_nebp.filters import ParticleBP

    dataset = CooperativeLocalizationDataset(root, 'paper_test', batch, seed,
                                             log=False)
    data = Batch.from_data_list(list(dataset)).to(device)
    tracker = ParticleBP(num_particles).to(device)
    generator = torch.Generator(device).manual_seed(seed)
    particles = tracker.sample_prior(data, generator)
    log_weights = torch.full(particles.shape[:2], -math.log(num_particles),
                             device=device)
    edge_index, ranges = data.edges_by_step()[0]
    num_edges = edge_index.size(1)
    conv = tracker.conv
    # as the tracker calls it: no messages returned; on CUDA receiver-sorted
    # edges take the fused kernel
    tracker_edges = EdgeIndex(edge_index, sparse_size=(data.num_nodes, ) * 2,
                              sort_order='col') if device.startswith(
                                  'cuda') else edge_index

    def conv_step():
        return conv(particles, log_weights, tracker_edges, ranges,
                    anchor=data.anchor, validate=False, return_messages=False)

    def conv_with_messages():
        return conv(particles, log_weights, edge_index, ranges,
                    anchor=data.anchor, validate=False)

    figures = dict(particles=num_particles, edges=num_edges, device=device,
                   batch=batch)
    with torch.no_grad():
        # peak memory of one iteration beyond its inputs
        if device.startswith('cuda'):
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            base = torch.cuda.memory_allocated()
            conv_step()
            torch.cuda.synchronize()
            peak = torch.cuda.max_memory_allocated() - base
        else:
            base = _rss_peak_bytes()
            conv_step()
            peak = max(_rss_peak_bytes() - base, 0)
        seconds = _timed(conv_step, repeats, device)
        with_messages = _timed(conv_with_messages, repeats, device)
        naive = _timed(
            lambda: _naive(particles, log_weights, edge_index, ranges,
                           tracker.measurement.sigma), repeats, device)
        edge_particles = num_edges * num_particles
        figures.update(
            ms_per_iteration=seconds * 1e3,
            edge_particles_per_s=edge_particles / seconds,
            with_messages_ms_per_iteration=with_messages * 1e3,
            naive_ms_per_iteration=naive * 1e3,
            speedup_vs_naive=naive / seconds,
            peak_mb=peak / 2**20,
            peak_in_ek_floats=peak / (4 * edge_particles),
        )

        # the whole tracker: seconds per time step (first step is warm-up)
        if device.startswith('cuda'):
            torch.cuda.reset_peak_memory_stats()
        stamps = []
        _sync(device)
        for step in tracker.steps(data, generator):
            _sync(device)
            stamps.append(time.perf_counter())
            if len(stamps) > steps:
                break
        per_step = [b - a for a, b in zip(stamps, stamps[1:])]
        figures['tracker_s_per_step'] = statistics.median(per_step)
        figures['tracker_peak_mb'] = (
            torch.cuda.max_memory_allocated() / 2**20 if device.startswith(
                'cuda') else _rss_peak_bytes() / 2**20)
    return figures


def _child(queue, *args):
    queue.put(measure(*args))


def _result(queue, child):
    # a child that dies (error, out of memory) must not leave us waiting
    while True:
        try:
            return queue.get(timeout=1.0)
        except queue_module.Empty:
            if not child.is_alive():
                raise RuntimeError(f'the benchmark process failed (exit '
                                   f'code {child.exitcode})') from None


def run_bench(args) -> int:
    r"""Runs :func:`measure` for every :math:`K` of :obj:`args.particles`,
    each in a fresh process, and prints a table (or JSON lines)."""
    context = multiprocessing.get_context('spawn')
    # generate the test network once, before the children read it
    from tg_nebp.datasets import CooperativeLocalizationDataset
    CooperativeLocalizationDataset(args.root, 'paper_test', args.batch,
                                   args.seed, log=False)
    if not args.json:
        print(f"{'K':>7} {'E':>6} {'ms/iter':>9} {'edge-part/s':>12} "
              f"{'+msgs ms':>9} {'naive ms':>9} {'speedup':>8} {'peak MB':>9} "
              f"{'peak/EK':>8} {'s/step':>8} {'tracker MB':>11}")
    for num_particles in args.particles:
        queue = context.Queue()
        child = context.Process(
            target=_child, args=(queue, num_particles, args.device,
                                 args.repeats, args.steps, args.seed,
                                 args.root, args.batch))
        child.start()
        figures = _result(queue, child)
        if args.json:
            print(json.dumps(figures))
        else:
            f = figures
            print(f"{f['particles']:>7} {f['edges']:>6} "
                  f"{f['ms_per_iteration']:>9.2f} "
                  f"{f['edge_particles_per_s']:>12.3e} "
                  f"{f['with_messages_ms_per_iteration']:>9.2f} "
                  f"{f['naive_ms_per_iteration']:>9.2f} "
                  f"{f['speedup_vs_naive']:>8.2f} {f['peak_mb']:>9.1f} "
                  f"{f['peak_in_ek_floats']:>8.2f} "
                  f"{f['tracker_s_per_step']:>8.4f} "
                  f"{f['tracker_peak_mb']:>11.1f}", flush=True)
    return 0
