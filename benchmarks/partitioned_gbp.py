r"""Gaussian BP with one network's agents spread over the ranks of a
torchrun job (tg_nebp.filters.PartitionedGaussianBP, gloo; with --lag L
fixed-lag Gaussian BP, PartitionedFixedLagGaussianBP): every rank
generates the paper's test network grown to --agents (the same seed),
tracks its strip and reports the seconds per step (the median of the steps
after the first), the bytes it sends per iteration and its peak resident
memory. One torch thread per rank.

    torchrun --standalone --nproc_per_node=2 benchmarks/partitioned_gbp.py \
        --agents 100000 --steps 3
    torchrun --standalone --nproc_per_node=2 benchmarks/partitioned_gbp.py \
        --agents 10000 --steps 8 --lag 5
"""
import argparse
import json
import resource
import time

import torch
import torch.distributed as dist

from tg_nebp.datasets import Scenario
from tg_nebp.filters import (PartitionedFixedLagGaussianBP,
                             PartitionedGaussianBP, partition, strips)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--agents', type=int, default=100_000)
    parser.add_argument('--steps', type=int, default=3)
    parser.add_argument('--lag', type=int, default=None,
                        help='fixed-lag Gaussian BP over L steps')
    args = parser.parse_args()
    torch.set_num_threads(1)
    dist.init_process_group('gloo')
    rank = dist.get_rank()
    scenario = Scenario.load('paper_test').grown(args.agents).replace(
        num_steps=args.steps)
    start = time.perf_counter()
    data = scenario.generate(torch.Generator().manual_seed(0))
    ranks = dist.get_world_size()
    part, plan = partition(data, strips(data, ranks), rank, ranks)
    del data
    setup = time.perf_counter() - start
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    if args.lag is None:
        tracker = PartitionedGaussianBP.recommended(plan=plan, **models)
        sent = tracker.exchanged_bytes(part.prior_mean.size(1))
    else:
        tracker = PartitionedFixedLagGaussianBP.recommended(
            plan=plan, lag=args.lag, **models)
        sent = tracker.exchanged_bytes(part.prior_mean.size(1), args.lag)
    times, start = [], time.perf_counter()
    with torch.no_grad():
        for _ in tracker.steps(part):
            now = time.perf_counter()
            times.append(now - start)
            start = now
    later = sorted(times[1:]) or times
    row = dict(rank=rank, agents=args.agents, lag=args.lag,
               owned=int(plan.owned.sum()), halo=int((~plan.owned).sum()),
               links_per_step=part.edge_index.size(1) // args.steps,
               generation_and_partition_s=round(setup, 1),
               first_step_s=round(times[0], 2),
               step_s=round(later[len(later) // 2], 2),
               sent_bytes_per_iteration=sent,
               peak_gib=round(resource.getrusage(
                   resource.RUSAGE_SELF).ru_maxrss / 2**20, 2))
    rows = [None] * dist.get_world_size()
    dist.all_gather_object(rows, row)
    if rank == 0:
        for row in rows:
            print(json.dumps(row), flush=True)
    dist.destroy_process_group()


if __name__ == '__main__':
    main()
