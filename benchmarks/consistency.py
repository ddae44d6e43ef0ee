r"""The consistency table of the results page (*Consistency in every
regime*): every recommended method on the same realizations of the five
simulated networks, P(accept) of the two-sided chi-square test at 0.95 and
0.99, the mean NEES, the RMSE and the largest error, beside the bound of those realizations;
Gaussian BP, hybrid BP and particle BP also as they report their beliefs
(``report_inflation`` 1), from the same runs' estimates.

From the repository root (20 realizations, seed 0: the test realizations
that ``tg-nebp compare`` tracks; seed 1 gives validation ones):

    python benchmarks/consistency.py --realizations 20 --seed 0

It prints one Markdown row per method and network as it goes.
"""
import argparse
import time

import torch

from tg_nebp.datasets import load_datasets, load_scenario
from tg_nebp.evaluation import bound_dataset, summarize_result, track_dataset
from tg_nebp.experiments.evaluate import method_tracker
from tg_nebp.filters import ParticleBP

NETWORKS = ('paper_test', 'paper_test_nlos', 'paper_test_sparse',
            'paper_test_wide_prior', 'box3d_test')


def _trackers(scenario):
    # (row, tracker): the recommended methods with the scenario's own
    # models, and the same configurations reporting their beliefs
    gbp, _ = method_tracker('gbp', scenario)
    models = dict(motion=gbp.motion, measurement=gbp.measurement)
    return [
        ('centralized IEKF', method_tracker('iekf', scenario)[0]),
        ('Gaussian BP', gbp),
        ('Gaussian BP, belief',
         method_tracker('gbp', scenario, report_inflation=1.0)[0]),
        ('hybrid BP', method_tracker('hybrid', scenario)[0]),
        ('hybrid BP, belief',
         method_tracker('hybrid', scenario, report_inflation=1.0)[0]),
        ('particle BP, recommended', ParticleBP.recommended(**models)),
        ('particle BP, belief',
         ParticleBP.recommended(report_inflation=1.0, **models)),
    ]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--realizations', type=int, default=20)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--networks', nargs='+', default=list(NETWORKS))
    parser.add_argument('--root', default='datasets')
    parser.add_argument('--threads', type=int, default=1)
    parser.add_argument('--methods', nargs='+', default=None,
                        help='the rows whose name starts with one of these '
                        '(default: every row, the bound first)')
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print('| network | method | P(accept 0.95 / 0.99) | mean NEES | '
          'RMSE [m] | largest error [m] | s |')
    print('| --- | --- | --- | --- | --- | --- | --- |')
    for name in args.networks:
        scenario = load_scenario(name)
        dataset, = load_datasets(args.root, (scenario, args.realizations,
                                             args.seed))
        start = time.perf_counter()
        if args.methods is None:
            bound = summarize_result(bound_dataset(
                method_tracker('pcrb', scenario)[0], dataset,
                seed=args.seed))
            print(f"| {name} | the bound | | | {bound['rmse']:.3f} | | "
                  f"{time.perf_counter() - start:.0f} |", flush=True)
        for row, tracker in _trackers(scenario):
            if args.methods is not None and not row.startswith(
                    tuple(args.methods)):
                continue
            start = time.perf_counter()
            result = track_dataset(tracker, dataset, seed=args.seed)
            entry = summarize_result(result)
            accept = entry['accept']
            print(f"| {name} | {row} | {accept['0.95']:.3f} / "
                  f"{accept['0.99']:.3f} | "
                  f"{float(result['nees'].double().mean()):.3g} | "
                  f"{entry['rmse']:.3f} | {entry['max_error']:.2f} | "
                  f"{time.perf_counter() - start:.0f} |", flush=True)


if __name__ == '__main__':
    main()
