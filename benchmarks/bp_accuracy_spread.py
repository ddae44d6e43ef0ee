r"""BP accuracy on the paper's test network per realization: the mean and
the spread across realizations of P_out(0.5/1/2 m) and P(accept at 0.95),
the spread of an R-realization mean, and the best and worst realization, so
that results from few realizations (e.g. the authors' code run on 1 or 2)
can be compared with stated uncertainty.

    python benchmarks/bp_accuracy_spread.py --particles 1000 --realizations 20
"""
import argparse
import math

import torch

from tg_nebp import CooperativeLocalizationDataset, ParticleBP
from tg_nebp.evaluation import summarize, track_dataset


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument('--particles', type=int, default=1000)
    parser.add_argument('--realizations', type=int, default=20)
    parser.add_argument('--iterations', type=int, default=1)
    parser.add_argument('--resampler', default='multinomial')
    parser.add_argument('--device', default='cpu')
    parser.add_argument('--root', default='datasets')
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args()
    dataset = CooperativeLocalizationDataset(args.root, 'paper_test',
                                             args.realizations, args.seed,
                                             log=False)
    tracker = ParticleBP(args.particles, args.iterations,
                         resampler=args.resampler).to(args.device)
    rows = []
    # every realization has the same agents and steps: its entries are one
    # contiguous block of the flat errors and NEES
    result = track_dataset(tracker, dataset, device=args.device,
                           seed=args.seed)
    for errors, nees in zip(result['errors'].view(len(dataset), -1),
                            result['nees'].view(len(dataset), -1)):
        s = summarize(errors, nees)
        rows.append([s['outage']['0.5'], s['outage']['1.0'],
                     s['outage']['2.0'], s['accept']['0.95']])
    table = torch.tensor(rows, dtype=torch.float64)
    names = ['P_out(0.5)', 'P_out(1)', 'P_out(2)', 'P_acc(0.95)']
    print(f'K={args.particles} T={args.iterations} {args.resampler} '
          f'R={len(dataset)} device={args.device}')
    for c, name in enumerate(names):
        col = table[:, c]
        print(f'  {name:<12} mean {col.mean():.3f}  std/realization '
              f'{col.std():.3f}  std of a 2-realization mean '
              f'{col.std() / math.sqrt(2):.3f}  min {col.min():.3f} max '
              f'{col.max():.3f}')


if __name__ == '__main__':
    main()
