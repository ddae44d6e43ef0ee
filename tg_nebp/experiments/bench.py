r"""Benchmarks behind :obj:`tg-nebp bench`.

For every number of agents :math:`I` (the paper's test network,
:meth:`~tg_nebp.datasets.Scenario.grown` to :math:`I` agents at the same
density) and particle count :math:`K`, on the first time step of
:obj:`--batch` realizations batched into one graph, each measurement runs in
a fresh process (so that its peak memory is its own) and reports the median
ms per call, edge-particles per second, and the peak memory beyond the
inputs:

* :obj:`bp`: :class:`~tg_nebp.nn.conv.ParticleBPConv` as the trackers call
  it (receiver-sorted edges, no messages returned), forward and forward +
  backward (gradient of a position loss w.r.t. the particles and sender
  log-weights),
* :obj:`naive`: a plain eager gather-likelihood-scatter (the baseline),
* :obj:`nebp`: :class:`~tg_nebp.nn.conv.NEBPConv`, forward and forward +
  backward (gradient of the training loss w.r.t. its parameters),
* :obj:`tracker`: :class:`~tg_nebp.filters.ParticleBP`, seconds per time
  step end to end.

A measurement whose estimated memory exceeds what the device has free is
skipped and says so."""
import ctypes
import json
import math
import multiprocessing
import queue as queue_module
import statistics
import time
from typing import Callable, Optional, Union

import torch

from tg_nebp.io import first_line
from tg_nebp.threads import ThreadGovernor
from tg_nebp.utils import free_memory_bytes

__all__ = ['add_arguments', 'run_bench', 'measure', 'BenchFailed',
           'OPERATIONS']

OPERATIONS = ('bp', 'naive', 'nebp', 'tracker')

# upper estimates of the floats per edge-particle and per node-particle that
# a measurement (its setup included) keeps alive, with margin over the peaks
# bench reports (e.g. NEBPConv forward + backward: 11 E x K floats at
# K = 50,000): beyond them the run is skipped, not killed
_FLOATS_PER_EDGE_PARTICLE = dict(naive=6.0, nebp=16.0)
_FLOATS_PER_NODE_PARTICLE = dict(bp=12.0, naive=12.0, nebp=16.0, tracker=32.0)


def add_arguments(parser):
    r"""Adds the :obj:`tg-nebp bench` options to :obj:`parser`."""
    parser.add_argument('--agents', type=int, nargs='+', default=[100],
                        help='agents I; 100 is the paper\'s test network, '
                        'others grow it at the same density (default: 100)')
    parser.add_argument('--particles', type=int, nargs='+',
                        default=[1000, 5000],
                        help='particle counts K (default: 1000 5000)')
    parser.add_argument('--ops', nargs='+', choices=OPERATIONS,
                        default=list(OPERATIONS),
                        help='what to measure (default: all)')
    parser.add_argument('--samples', type=int, nargs='+', default=[1],
                        metavar='M', help='sender particles per receiver '
                        'particle in every BP message (ops bp, nebp, '
                        'tracker; naive pairs them); rates count '
                        'edge-particle-samples E*K*M (default: 1)')
    parser.add_argument('--batch', type=int, default=1,
                        help='realizations batched into one graph '
                        '(default: 1)')
    parser.add_argument('--repeats', type=int, default=10,
                        help='timed calls per measurement (default: 10)')
    parser.add_argument('--steps', type=int, default=5,
                        help='timed tracker steps (default: 5)')
    parser.add_argument('--chunk-size', type=int, default=None,
                        help='edge chunk of ParticleBPConv (default: '
                        'automatic)')
    parser.add_argument('--forward-only', action='store_true',
                        help='skip the forward + backward measurements')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--json', action='store_true',
                        help='print one JSON object per measurement')


def _sync(device):
    if device.startswith('cuda'):
        torch.cuda.synchronize()


def _timed(fn: Callable, repeats: int, device: str,
           before: Optional[Callable] = None) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        if before is not None:  # untimed: the thread governor's reading
            before()
        _sync(device)
        start = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _proc_status_bytes(field: str) -> int:
    with open('/proc/self/status') as f:
        for line in f:
            if line.startswith(field + ':'):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f'/proc/self/status has no {field}')


class _Peak:
    r"""Peak memory beyond what is in use when it starts: the CUDA
    allocator's peak, or on the CPU the peak resident set (Linux), reset
    first through :obj:`/proc/self/clear_refs` after freed heap memory went
    back to the system, so that earlier peaks (setup) do not hide it."""
    def __init__(self, device):
        self.cuda = device.startswith('cuda')
        if self.cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            self.base = torch.cuda.memory_allocated()
        else:
            ctypes.CDLL('libc.so.6').malloc_trim(0)
            with open('/proc/self/clear_refs', 'w') as f:
                f.write('5')  # resets the peak resident set size
            self.base = _proc_status_bytes('VmRSS')

    def megabytes(self) -> float:
        if self.cuda:
            torch.cuda.synchronize()
            peak = torch.cuda.max_memory_allocated()
        else:
            peak = _proc_status_bytes('VmHWM')
        return max(peak - self.base, 0) / 2**20


def _naive(particles, log_weights, edge_index, ranges, measurement):
    # the plain eager baseline: gather [E, K, D], the model's likelihood,
    # scatter-add
    src, dst = edge_index
    log_lik = measurement.log_likelihood(ranges, particles[src],
                                         particles[dst])
    out = torch.zeros_like(log_weights).index_add_(
        0, dst, log_lik + log_weights[src])
    return log_weights + out


def network(num_agents: int, batch: int, num_steps: int, seed: int):
    r"""The benchmark graph: :obj:`batch` realizations of the paper's test
    network grown to :obj:`num_agents` agents, :obj:`num_steps` steps each
    (realization :math:`r` drawn as the dataset draws it, with seed
    :obj:`derive_seed(seed, r)`)."""
    from torch_geometric.data import Batch

    from tg_nebp.datasets import Scenario
    from tg_nebp.utils import derive_seed

    scenario = Scenario.load('paper_test')
    if num_agents != scenario.num_agents:
        scenario = scenario.grown(num_agents)
    scenario = scenario.replace(num_steps=num_steps)
    return Batch.from_data_list([
        scenario.generate(torch.Generator().manual_seed(derive_seed(seed,
                                                                    r)))
        for r in range(batch)
    ])


def measure(operation: str, num_agents: int, num_particles: int,
            device: str = 'cpu', batch: int = 1, repeats: int = 10,
            steps: int = 5, seed: int = 0, chunk_size: Optional[int] = None,
            compile: bool = False, backward: bool = True,
            num_samples: int = 1,
            threads: Union[None, int, str] = None) -> dict:
    r"""Runs one measurement in this process; returns a dict of figures.
    :obj:`threads` sets torch's intra-op threads: a count, :obj:`"auto"` (a
    :class:`~tg_nebp.threads.ThreadGovernor` updated before every timed
    call and after every tracker step) or :obj:`None` (torch's default)."""
    from torch_geometric import EdgeIndex

    from tg_nebp.filters import ParticleBP
    from tg_nebp.nn.conv import NEBPConv
    from tg_nebp.training import position_loss

    governor = None
    if threads == 'auto':
        governor = ThreadGovernor()
    elif threads is not None:
        torch.set_num_threads(threads)
    before = governor.update if governor is not None else None
    data = network(num_agents, batch, steps + 2, seed).to(device)
    edge_index, ranges = data.edges_by_step()[0]
    num_nodes, num_edges = data.num_nodes, edge_index.size(1)
    # the work: edge-particle-samples (the naive baseline pairs them)
    samples = 1 if operation == 'naive' else num_samples
    edge_particles = num_edges * num_particles * samples
    figures = dict(operation=operation, agents=num_agents, batch=batch,
                   nodes=num_nodes, edges=num_edges, particles=num_particles,
                   samples=samples, edge_particles=edge_particles,
                   device=device, compile=compile)
    need = 4 * (_FLOATS_PER_EDGE_PARTICLE.get(operation, 0.0) *
                num_edges * num_particles +
                _FLOATS_PER_NODE_PARTICLE[operation] *
                num_nodes * num_particles)
    free = free_memory_bytes(device)
    if need > 0.9 * free:
        figures['skipped'] = (f'needs about {need / 2**30:.1f} GiB, '
                              f'{free / 2**30:.1f} GiB free')
        return figures

    tracker = ParticleBP(num_particles, chunk_size=chunk_size,
                         compile=compile, num_samples=samples).to(device)
    generator = torch.Generator(device).manual_seed(seed)
    if operation == 'tracker':
        peak = _Peak(device)
        stamps = []
        with torch.no_grad():
            _sync(device)
            for _ in tracker.steps(data, generator):
                _sync(device)
                stamps.append(time.perf_counter())
                if len(stamps) > steps:
                    break
                if before is not None:  # timed: part of the step's cost
                    before()
        figures.update(
            s_per_step=statistics.median(  # the first step is a warm-up
                b - a for a, b in zip(stamps, stamps[1:])),
            peak_mb=peak.megabytes(), threads=torch.get_num_threads())
        return figures

    particles = tracker.predict(tracker.sample_prior(data, generator),
                                data.anchor, generator)
    log_weights = torch.full(particles.shape[:2], -math.log(num_particles),
                             device=device)
    sorted_edges = EdgeIndex(edge_index, sparse_size=(num_nodes, ) * 2,
                             sort_order='col')

    def loss_of(log_belief, points):
        # the training loss on the weighted mean position (the covariance
        # would add [N, K, 4] temporaries that are not the layer's)
        mean = torch.einsum('nk,nkd->nd', log_belief.softmax(-1),
                            points[..., :2])
        return position_loss(mean, data.states, 0, data.anchor)

    if operation == 'naive':

        def forward():
            return _naive(particles, log_weights, edge_index, ranges,
                          tracker.measurement)

        forward_backward = None
    elif operation == 'bp':

        def forward(points=particles, sender=log_weights):
            return tracker.conv(points, log_weights, sorted_edges, ranges,
                                sender_log_weights=sender, anchor=data.anchor,
                                validate=False, return_messages=False)[0]

        def forward_backward():
            points = particles.detach().requires_grad_()
            sender = log_weights.detach().requires_grad_()
            loss_of(forward(points, sender), points).backward()
    else:  # nebp
        torch.manual_seed(seed)
        conv = NEBPConv(num_particles, chunk_size=chunk_size,
                        compile=compile, num_samples=samples).to(device)

        def forward():
            return conv(particles, log_weights, sorted_edges, ranges,
                        data.anchor, validate=False)[0]

        def forward_backward():
            conv.zero_grad(set_to_none=True)
            loss_of(forward(), particles).backward()

    with torch.no_grad():
        if compile:
            forward()  # compiles: not part of the peak
        peak = _Peak(device)
        forward()
        figures['forward_peak_mb'] = peak.megabytes()
        seconds = _timed(forward, repeats, device, before)
    figures.update(forward_ms=seconds * 1e3,
                   forward_edge_particles_per_s=edge_particles / seconds,
                   forward_peak_in_ek_floats=figures['forward_peak_mb'] *
                   2**20 / (4 * edge_particles))
    if backward and forward_backward is not None:
        if compile:
            forward_backward()
        peak = _Peak(device)
        forward_backward()
        figures['forward_backward_peak_mb'] = peak.megabytes()
        seconds = _timed(forward_backward, repeats, device, before)
        figures.update(
            forward_backward_ms=seconds * 1e3,
            forward_backward_edge_particles_per_s=edge_particles / seconds)
    figures['threads'] = torch.get_num_threads()  # in force at the end
    return figures


def _child(queue, *args):
    # an error is a result (one line in the table), not a traceback
    try:
        figures = measure(*args)
    except Exception as e:  # noqa: BLE001 - any failure of the measurement
        figures = dict(failed=f'failed: {type(e).__name__}: {first_line(e)}')
    queue.put(figures)


def _result(queue, child) -> dict:
    # a child that dies (error, killed for memory) must not leave us waiting
    while True:
        try:
            return queue.get(timeout=1.0)
        except queue_module.Empty:
            if not child.is_alive():
                return dict(failed=f'the benchmark process exited with code '
                            f'{child.exitcode}')


def _row(f: dict) -> str:
    def num(key, fmt):
        width = int(fmt.split('.')[0])
        return format(f[key], fmt) if key in f else '-'.rjust(width)

    head = (f"{f['agents']:>7} {f['batch']:>3} {f['edges']:>8} "
            f"{f['particles']:>7} {f.get('samples', 1):>4} "
            f"{f['edge_particles']:>9.2e} {f['operation']:>8}")
    if 'skipped' in f or 'failed' in f:
        return f"{head}  {f.get('skipped') or f.get('failed')}"
    if f['operation'] == 'tracker':
        return (f"{head} {'':>10} {'':>10} {num('peak_mb', '11.1f')} "
                f"{'':>10} {'':>10} {'':>11} {num('s_per_step', '9.4f')}")
    return (f"{head} {num('forward_ms', '10.2f')} "
            f"{num('forward_edge_particles_per_s', '10.3e')} "
            f"{num('forward_peak_mb', '11.1f')} "
            f"{num('forward_backward_ms', '10.2f')} "
            f"{num('forward_backward_edge_particles_per_s', '10.3e')} "
            f"{num('forward_backward_peak_mb', '11.1f')}")


class BenchFailed(RuntimeError):
    r"""Some measurements of :func:`run_bench` failed; the command line
    exits with status 1."""


def run_bench(args) -> int:
    r"""Runs :func:`measure` for every (agents, :math:`K`, operation), each
    in a fresh process, and prints a table (or JSON lines). The options are
    checked before the first process starts (a :class:`ValueError`); a
    measurement that fails is a row of the table, and then
    :class:`BenchFailed` once all have run."""
    for name in ('agents', 'particles', 'samples'):
        if any(v < 1 for v in getattr(args, name)):
            raise ValueError(f"'--{name}' must be positive, got "
                             f"{getattr(args, name)}")
    if args.batch < 1 or args.repeats < 1 or args.steps < 1:
        raise ValueError("'--batch', '--repeats' and '--steps' must be "
                         "positive")
    if args.chunk_size is not None and args.chunk_size < 1:
        raise ValueError(f"'--chunk-size' must be positive, got "
                         f"{args.chunk_size}")
    # every option is checked here, before the first measurement process
    # starts: an M above a K would fail in each of them
    too_many = [m for m in args.samples if m > min(args.particles)]
    if too_many:
        raise ValueError(f"'--samples' {too_many} exceed the smallest "
                         f"'--particles' {min(args.particles)}: a message "
                         f"draws at most K sender particles")
    context = multiprocessing.get_context('spawn')
    if not args.json:
        print(f"{'agents':>7} {'B':>3} {'E':>8} {'K':>7} {'M':>4} "
              f"{'E*K*M':>9} {'op':>8} {'fwd ms':>10} {'fwd EKM/s':>10} "
              f"{'fwd peakMB':>11} {'f+b ms':>10} {'f+b EKM/s':>10} "
              f"{'f+b peakMB':>11} {'s/step':>9}")
    grid = [(agents, particles, samples, operation)
            for agents in args.agents for particles in args.particles
            for samples in args.samples for operation in args.ops
            # the naive baseline pairs: measured once per K
            if not (operation == 'naive' and samples != args.samples[0])]
    failed = 0
    for num_agents, num_particles, num_samples, operation in grid:
        queue = context.Queue()
        child = context.Process(
            target=_child,
            args=(queue, operation, num_agents, num_particles, args.device,
                  args.batch, args.repeats, args.steps, args.seed,
                  args.chunk_size, args.compile, not args.forward_only,
                  num_samples, args.threads))
        child.start()
        figures = _result(queue, child)
        child.join()
        figures = dict(dict(operation=operation, agents=num_agents,
                            batch=args.batch, particles=num_particles,
                            samples=num_samples, edges=0,
                            edge_particles=0.0, device=args.device),
                       **figures)
        print(json.dumps(figures) if args.json else _row(figures),
              flush=True)
        failed += 'failed' in figures
    if failed:
        raise BenchFailed(f'{failed} of {len(grid)} measurements failed '
                          f'(see the table)')
    return 0
