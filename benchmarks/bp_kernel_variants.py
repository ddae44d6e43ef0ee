r"""Compares formulations of the BP factor kernel (one ParticleBPConv
iteration) on one time step of the paper's test network, B realizations
batched: the library's eager chunked path, torch.compile of the message
computation (+ eager scatter), torch.compile of message + scatter, and a
compiled dense-neighbour reduction (deterministic, no atomics).

    python benchmarks/bp_kernel_variants.py --device cuda --particles 50000
"""
import argparse
import math
import statistics
import time

import torch
from torch_geometric.loader import DataLoader

from tg_nebp import CooperativeLocalizationDataset, ParticleBP


def timed(fn, repeats, device):
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        if device == 'cuda':
            torch.cuda.synchronize()
        start = time.perf_counter()
        fn()
        if device == 'cuda':
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def messages(px, py, lw, ranges, src, dst, inv_two_var: float,
             log_norm: float):
    dx = px[src] - px[dst]
    dy = py[src] - py[dst]
    d = torch.sqrt(dx * dx + dy * dy)
    r = ranges - d
    return lw[src] - inv_two_var * r * r - log_norm


def fused(px, py, lw, ranges, src, dst, inv_two_var: float, log_norm: float):
    m = messages(px, py, lw, ranges, src, dst, inv_two_var, log_norm)
    return torch.zeros_like(lw).index_add_(0, dst, m)


def dense(px, py, lw, nbr, nbr_range, valid, inv_two_var: float,
          log_norm: float):
    # nbr [N, D] sender of the d-th incoming edge of node i (0 if padding)
    dx = px[nbr] - px.unsqueeze(1)
    dy = py[nbr] - py.unsqueeze(1)
    d = torch.sqrt(dx * dx + dy * dy)
    r = nbr_range.unsqueeze(-1) - d
    m = lw[nbr] - inv_two_var * r * r - log_norm
    return torch.where(valid.unsqueeze(-1), m, 0.0).sum(1)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument('--device', default='cpu')
    parser.add_argument('--particles', type=int, nargs='+', default=[1000])
    parser.add_argument('--batch', type=int, default=1)
    parser.add_argument('--repeats', type=int, default=20)
    parser.add_argument('--root', default='datasets')
    parser.add_argument('--compile', action='store_true')
    args = parser.parse_args()
    dev = args.device
    ds = CooperativeLocalizationDataset(args.root, 'paper_test', args.batch,
                                        0, log=False)
    data = next(iter(DataLoader(ds, batch_size=args.batch))).to(dev)
    ei, ranges = data.edges_by_step()[0]
    src, dst = ei
    n = data.num_nodes
    deg = torch.bincount(dst, minlength=n)
    max_deg = int(deg.max())
    ptr = torch.cat([deg.new_zeros(1), deg.cumsum(0)])
    slot = torch.arange(ei.size(1), device=dev) - ptr[dst]
    nbr = torch.zeros(n, max_deg, dtype=torch.long, device=dev)
    nbr_range = torch.zeros(n, max_deg, device=dev)
    valid = torch.zeros(n, max_deg, dtype=torch.bool, device=dev)
    nbr[dst, slot] = src
    nbr_range[dst, slot] = ranges[:, 0]
    valid[dst, slot] = True
    sigma = 1.0
    c = (0.5 / sigma**2, math.log(math.sqrt(2 * math.pi) * sigma))
    print(f'device {dev} ({torch.cuda.get_device_name() if dev == "cuda" else "cpu"}), '
          f'batch {args.batch}, N {n}, E {ei.size(1)}, max in-degree {max_deg}')
    for k in args.particles:
        tracker = ParticleBP(k).to(dev)
        g = torch.Generator(dev).manual_seed(0)
        parts = tracker.sample_prior(data, g)
        lw = torch.full((n, k), -math.log(k), device=dev)
        px, py = parts[..., 0].contiguous(), parts[..., 1].contiguous()
        ek = ei.size(1) * k
        ref, _ = tracker.conv(parts, lw, ei, ranges, validate=False)
        rows = {}
        with torch.no_grad():
            rows['library eager'] = timed(
                lambda: tracker.conv(parts, lw, ei, ranges, validate=False),
                args.repeats, dev)
            rows['naive eager'] = timed(
                lambda: fused(px, py, lw, ranges, src, dst, *c),
                args.repeats, dev)
            if args.compile:
                cm = torch.compile(messages, dynamic=False)
                rows['compiled msgs + scatter'] = timed(
                    lambda: torch.zeros_like(lw).index_add_(
                        0, dst, cm(px, py, lw, ranges, src, dst, *c)),
                    args.repeats, dev)
                cf = torch.compile(fused, dynamic=False)
                out = cf(px, py, lw, ranges, src, dst, *c)
                err_f = float((out + lw - ref).abs().max())
                rows['compiled fused'] = timed(
                    lambda: cf(px, py, lw, ranges, src, dst, *c),
                    args.repeats, dev)
                cd = torch.compile(dense, dynamic=False)
                out = cd(px, py, lw, nbr, nbr_range, valid, *c)
                err_d = float((out + lw - ref).abs().max())
                a = cd(px, py, lw, nbr, nbr_range, valid, *c)
                b = cd(px, py, lw, nbr, nbr_range, valid, *c)
                rows['compiled dense'] = timed(
                    lambda: cd(px, py, lw, nbr, nbr_range, valid, *c),
                    args.repeats, dev)
                print(f'  K={k}: max |fused - library| {err_f:.2e}, '
                      f'|dense - library| {err_d:.2e}, dense repeatable '
                      f'{bool(torch.equal(a, b))}')
        for name, sec in rows.items():
            print(f'  K={k:>6} {name:<26} {sec * 1e3:9.3f} ms '
                  f'{ek / sec:10.3e} edge-particles/s')


if __name__ == '__main__':
    main()
