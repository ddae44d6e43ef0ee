r"""Seconds per realization of Gaussian BP (recommended) on the paper's test
network: one realization alone and 20 batched into one graph, the median of
3 timed runs after a warm-up run, one torch thread; eager, or with the
rank-one messages compiled (``--compile``). The figures of the docs' page
on Gaussian BP. An earlier tree is measured the same way from its checkout:

    python benchmarks/gbp_paper_speed.py
    python benchmarks/gbp_paper_speed.py --compile
    PYTHONPATH=/path/to/old/checkout python benchmarks/gbp_paper_speed.py
"""
import argparse
import json
import statistics
import time

import torch
from torch_geometric.data import Batch

import tg_nebp
from tg_nebp.datasets import Scenario
from tg_nebp.filters import GaussianBP


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--compile', action='store_true')
    parser.add_argument('--batch', type=int, default=20)
    parser.add_argument('--repeats', type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    scenario = Scenario.load('paper_test')
    generator = torch.Generator().manual_seed(0)
    data = [scenario.generate(generator) for _ in range(args.batch)]
    batch = Batch.from_data_list(data)
    # (an earlier tree has no 'compile': asked only when given)
    options = dict(compile=True) if args.compile else {}
    tracker = GaussianBP.recommended(motion=scenario.motion_model,
                                     measurement=scenario.measurement_model,
                                     **options)
    alone, batched = [], []
    with torch.no_grad():
        tracker(batch)  # a warm-up (and the compilation)
        for k in range(args.repeats):
            start = time.perf_counter()
            tracker(data[k])
            alone.append(time.perf_counter() - start)
            start = time.perf_counter()
            tracker(batch)
            batched.append((time.perf_counter() - start) / args.batch)
    print(json.dumps(dict(
        package=tg_nebp.__file__, compile=args.compile,
        alone_s=round(statistics.median(alone), 4),
        batched_per_realization_s=round(statistics.median(batched), 4))))


if __name__ == '__main__':
    main()
