r"""A smoother's filtered and smoothed estimates on a scenario's test
realizations (seed 0), with the largest position error beside the RMSE and
the two-sided P(accept 0.95): the figures that ``tg-nebp compare`` gives
without the largest error. One pass of the smoother's steps; the smoothed
estimates are read as :class:`tg_nebp.filters.Smoothed` reads them (each
step's as it leaves the window, the rest from the last window; the
incremental smoother's from its last step). Methods: ``incremental``
(:class:`~tg_nebp.filters.IncrementalSmoother`), ``batch``
(:class:`~tg_nebp.filters.CentralizedSmoother` over the whole sequence: its
steps are already smoothed), ``batch-lagL`` (the centralized smoother over
a window of L steps) and ``gbp-lagL`` (fixed-lag Gaussian BP,
recommended), each with the scenario's likelihood.

    python benchmarks/smoother_errors.py --scenario mrclam-6-range \
        --root ../shared/data/mrclam --method incremental
    python benchmarks/smoother_errors.py --scenario paper_test \
        --realizations 5 --method batch
"""
import argparse

import torch

from tg_nebp.datasets import load_datasets
from tg_nebp.experiments.evaluate import scenario_of
from tg_nebp.filters import (CentralizedSmoother, FixedLagGaussianBP,
                             IncrementalSmoother)
from tg_nebp.metrics import consistency_curve, nees


def tracker_of(method: str, scenario):
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    if method == 'incremental':
        return IncrementalSmoother(**models)
    if method == 'batch':
        return CentralizedSmoother(None, **models)
    if method.startswith('batch-lag'):
        return CentralizedSmoother(int(method[9:]), **models)
    if method.startswith('gbp-lag'):
        return FixedLagGaussianBP.recommended(lag=int(method[7:]), **models)
    raise SystemExit(f'unknown method {method!r}')


def filtered_and_smoothed(tracker, data):
    # each step's newest estimate, and each step's smoothed one (None for
    # a tracker without windows)
    filtered, smoothed, last = [], {}, None
    lag = tracker.lag
    for step in tracker.steps(data):
        filtered.append((step.mean, step.cov))
        last = step
        if step.window_mean is not None and step.window_mean.size(1) == lag:
            smoothed[step.t - lag + 1] = (step.window_mean[:, 0],
                                          step.window_cov[:, 0])
    if last.window_mean is not None:
        width = last.window_mean.size(1)
        for k in range(width):
            smoothed.setdefault(last.t - width + 1 + k,
                                (last.window_mean[:, k],
                                 last.window_cov[:, k]))
    smoothed = [smoothed[t] for t in sorted(smoothed)] or None
    return filtered, smoothed


def summary(realizations, estimates) -> str:
    errors, scores = [], []
    for data, steps in zip(realizations, estimates):
        agents = ~data.anchor
        truth = data.states[agents, :, :2].double()
        mean = torch.stack([m for m, _ in steps], 1)[agents, :, :2].double()
        cov = torch.stack([c for _, c in steps], 1)[agents, :, :2,
                                                    :2].double()
        errors.append((mean - truth).norm(dim=-1).flatten())
        scores.append(nees(mean, cov, truth).flatten())
    error = torch.cat(errors)
    accept = consistency_curve(torch.cat(scores), [0.95])
    return (f'RMSE {float(error.square().mean().sqrt()):.3f} m, max '
            f'{float(error.max()):.2f} m, P(accept 0.95) '
            f'{float(accept[0]):.3f}')


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenario', required=True)
    parser.add_argument('--root', default='datasets')
    parser.add_argument('--realizations', type=int, default=None)
    parser.add_argument('--method', required=True)
    args = parser.parse_args()
    scenario = scenario_of(args.scenario)
    dataset, = load_datasets(args.root, (scenario, args.realizations, 0))
    realizations = [dataset[i] for i in range(len(dataset))]
    runs = []
    with torch.no_grad():
        for data in realizations:
            runs.append(filtered_and_smoothed(
                tracker_of(args.method, scenario), data))
    print(f'{args.scenario} {args.method} filtered (the batch smoother: '
          f'smoothed): {summary(realizations, [f for f, _ in runs])}')
    if runs[0][1] is not None:
        print(f'{args.scenario} {args.method} smoothed: '
              f'{summary(realizations, [s for _, s in runs])}')


if __name__ == '__main__':
    main()
