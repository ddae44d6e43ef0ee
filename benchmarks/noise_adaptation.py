r"""The table of the results page *A model whose noise is too small*:
recommended Gaussian BP with and without the noise adaptation
(:class:`~tg_nebp.filters.NoiseAdaptation`), given each network's own
range model and the same model with a standard deviation 3 times too
small, on the same realizations of the five simulated networks: P(accept)
of the two-sided chi-square test at 0.95, RMSE, the largest error of any
agent at any step, and the seconds of the run.

From the repository root (20 realizations, seed 0: the test realizations;
seed 1 gives validation ones, where the memory was chosen):

    python benchmarks/noise_adaptation.py --realizations 20 --seed 0

It prints one Markdown row per network, model and memory as it goes (the
NLOS network's likelihood is not a Gaussian range: its row has the model
as given only).
"""
import argparse
import time

import torch

from tg_nebp.datasets import load_datasets, load_scenario
from tg_nebp.evaluation import summarize_result, track_dataset
from tg_nebp.experiments.evaluate import method_tracker
from tg_nebp.filters import GaussianBP, NoiseAdaptation
from tg_nebp.models import GaussianRange

NETWORKS = ('paper_test', 'paper_test_nlos', 'paper_test_sparse',
            'paper_test_wide_prior', 'box3d_test')


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--realizations', type=int, default=20)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--networks', nargs='+', default=list(NETWORKS))
    parser.add_argument('--memories', type=float, nargs='+', default=[0.9],
                        help='the fading memories to run (besides none)')
    parser.add_argument('--root', default='datasets')
    parser.add_argument('--threads', type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print('| network | model | memory | P(accept 0.95) | RMSE [m] | '
          'largest error [m] | s |')
    print('| --- | --- | --- | --- | --- | --- | --- |')
    for name in args.networks:
        scenario = load_scenario(name)
        dataset, = load_datasets(args.root, (scenario, args.realizations,
                                             args.seed))
        gbp, _ = method_tracker('gbp', scenario)
        models = [('as given', gbp.measurement)]
        if isinstance(gbp.measurement, GaussianRange):
            models.append(('sigma / 3', GaussianRange(
                sigma=gbp.measurement.sigma / 3,
                max_range=gbp.measurement.max_range)))
        for label, measurement in models:
            for memory in [None] + args.memories:
                adaptation = (None if memory is None else
                              NoiseAdaptation(memory=memory))
                tracker = GaussianBP.recommended(
                    motion=gbp.motion, measurement=measurement,
                    noise_adaptation=adaptation)
                start = time.perf_counter()
                entry = summarize_result(track_dataset(tracker, dataset,
                                                       seed=args.seed))
                print(f"| {name} | {label} | {memory or 'none'} | "
                      f"{entry['accept']['0.95']:.3f} | {entry['rmse']:.3f} "
                      f"| {entry['max_error']:.2f} | "
                      f"{time.perf_counter() - start:.0f} |", flush=True)


if __name__ == '__main__':
    main()
