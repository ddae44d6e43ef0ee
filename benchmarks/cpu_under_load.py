r"""The CPU path on a busy machine: :obj:`tg-nebp bench` of
:class:`ParticleBPConv` (forward), the naive eager baseline and, optionally,
the tracker, with 0 or more busy processes beside it (pure-Python spinners,
one core each, or :obj:`--load tracker`: the BP tracker in a loop with
torch's default threads) and every :obj:`--threads` setting of the bench
(a count, or :obj:`auto`, the thread governor).

    python benchmarks/cpu_under_load.py --busy 0 2 --threads 1 2 auto

Every cell runs :obj:`tg-nebp bench --json --threads T` in a fresh
process, with the busy processes started before and stopped after it;
the matrix is run :obj:`--rounds` times in turn and the median of the
rounds' medians is printed, in ms per call (s per step for the tracker).
Run it on an otherwise quiet machine: the spinners are the only load it
means to measure."""
import argparse
import itertools
import json
import multiprocessing
import statistics
import subprocess
import sys
import time


def spin():
    while True:
        pass


def track():
    import torch

    from tg_nebp import ParticleBP
    from tg_nebp.datasets import Scenario

    data = Scenario.load('paper_test').generate(
        torch.Generator().manual_seed(0))
    tracker = ParticleBP(1000)
    while True:
        for _ in tracker.steps(data, torch.Generator().manual_seed(0)):
            pass


def bench(threads, particles, ops, repeats, extra):
    done = subprocess.run(
        [sys.executable, '-m', 'tg_nebp', 'bench', '--ops', *ops,
         '--particles', str(particles), '--forward-only', '--json',
         '--repeats', str(repeats), '--threads', threads, *extra],
        capture_output=True, text=True, check=True)
    rows = [json.loads(line) for line in done.stdout.splitlines()
            if line.startswith('{')]
    return {row['operation']: (row['s_per_step']
                               if row['operation'] == 'tracker'
                               else row['forward_ms']) for row in rows}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--busy', type=int, nargs='+', default=[0, 2])
    parser.add_argument('--threads', nargs='+', default=['1', '2', 'auto'])
    parser.add_argument('--load', choices=['spin', 'tracker'],
                        default='spin', help='what a busy process runs')
    parser.add_argument('--ops', nargs='+', default=['bp', 'naive'])
    parser.add_argument('--particles', type=int, default=1000)
    parser.add_argument('--repeats', type=int, default=20)
    parser.add_argument('--rounds', type=int, default=3)
    parser.add_argument('--bench-args', nargs=argparse.REMAINDER,
                        default=[], help='passed on to tg-nebp bench')
    args = parser.parse_args()
    cells = list(itertools.product(args.busy, args.threads))
    results = {cell: {op: [] for op in args.ops} for cell in cells}
    for _ in range(args.rounds):
        for busy, threads in cells:
            target = spin if args.load == 'spin' else track
            spinners = [multiprocessing.Process(target=target, daemon=True)
                        for _ in range(busy)]
            for s in spinners:
                s.start()
            time.sleep(5.0 if busy else 0.0)  # the tracker's setup done
            try:
                got = bench(threads, args.particles, args.ops, args.repeats,
                            args.bench_args)
            finally:
                for s in spinners:
                    s.terminate()
                    s.join()
            for op in args.ops:
                results[(busy, threads)][op].append(got[op])
    print(f'K = {args.particles}, busy processes: {args.load}, median of '
          f'{args.rounds} rounds (each a median of {args.repeats} calls); '
          f'ms per call, s per step for the tracker')
    print('| busy processes | threads | ' + ' | '.join(args.ops) + ' |')
    print('| --- | --- | ' + ' | '.join('---' for _ in args.ops) + ' |')
    for busy, threads in cells:
        values = [statistics.median(results[(busy, threads)][op])
                  for op in args.ops]
        print(f'| {busy} | {threads} | ' + ' | '.join(
            f'{v:.4g}' for v in values) + ' |')


if __name__ == '__main__':
    main()
