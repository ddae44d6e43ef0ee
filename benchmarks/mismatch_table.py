r"""BP under range-model mismatch: the paper's test network with NLOS links
(``paper_test_nlos``) and without (``paper_test``), tracked with the
Gaussian, the Student-t and the NLOS-mixture likelihood. The likelihoods
keep the scenario's sigma and max_range (``tg-nebp evaluate --measurement``);
the Student-t's nu = 3 and the NLOS mixture's p_nlos = 0.2 and bias mean 3 m
are the models' defaults, fixed before any test realization was tracked.

One markdown row per (scenario, K, likelihood): the means over realizations
of P_out(0.5/1/2 m) and P(accept at 0.95), the particles drawn as in
``tg-nebp evaluate`` (so the means equal its figures),
and the standard error of the mean (std across realizations / sqrt(R)).

    python benchmarks/mismatch_table.py --realizations 20 --particles 1000 5000
"""
import argparse
import math
import time

import torch

from tg_nebp import CooperativeLocalizationDataset, ParticleBP
from tg_nebp.evaluation import summarize, track_dataset
from tg_nebp.models import model_like


def per_realization(tracker, dataset, seed):
    # every realization has the same agents and steps: its entries are one
    # contiguous block of the flat errors and NEES
    result = track_dataset(tracker, dataset, seed=seed)
    rows = []
    for errors, nees in zip(result['errors'].view(len(dataset), -1),
                            result['nees'].view(len(dataset), -1)):
        s = summarize(errors, nees)
        rows.append([s['outage']['0.5'], s['outage']['1.0'],
                     s['outage']['2.0'], s['accept']['0.95']])
    return torch.tensor(rows, dtype=torch.float64)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument('--scenarios', nargs='+',
                        default=['paper_test_nlos', 'paper_test'])
    parser.add_argument('--particles', type=int, nargs='+',
                        default=[1000, 5000])
    parser.add_argument('--measurements', nargs='+',
                        default=['gaussian', 'student-t', 'nlos'])
    parser.add_argument('--realizations', type=int, default=20)
    parser.add_argument('--root', default='datasets')
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args()
    print('| scenario | K | likelihood | P_out 0.5 / 1 / 2 m | '
          'P(accept 0.95) | s.e. P_out(1 m) / P(accept) | s |')
    print('| --- | --- | --- | --- | --- | --- | --- |')
    for name in args.scenarios:
        dataset = CooperativeLocalizationDataset(
            args.root, name, args.realizations, args.seed, log=False)
        scenario = dataset.scenario
        for particles in args.particles:
            for measurement in args.measurements:
                model = model_like(measurement, 'measurement',
                                   scenario.measurement_model)
                tracker = ParticleBP(particles,
                                     motion=scenario.motion_model,
                                     measurement=model)
                start = time.perf_counter()
                table = per_realization(tracker, dataset, args.seed)
                seconds = time.perf_counter() - start
                mean = table.mean(0)
                error = table.std(0) / math.sqrt(len(table))
                print(f'| {name} | {particles:,} | {measurement} | '
                      f'{mean[0]:.3f} / {mean[1]:.3f} / {mean[2]:.3f} | '
                      f'{mean[3]:.3f} | {error[1]:.3f} / {error[3]:.3f} | '
                      f'{seconds:.0f} |', flush=True)


if __name__ == '__main__':
    main()
