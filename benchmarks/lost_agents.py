r"""Lost agents before and after the relocation with hindsight (issue 64).

Each method on the same realizations of a scenario (those of ``tg-nebp
evaluate --scenario S --realizations R --seed K``), one torch thread:
Gaussian BP, hybrid BP, and the window of ``--lag`` steps (fixed-lag
Gaussian BP, hybrid BP over it) without and with the relocation with
hindsight (:class:`~tg_nebp.filters.TrajectorySearch`), filtered and, for
the windows, smoothed (each step's estimate as it leaves the window).
Printed per method: RMSE, P_out(1 m), the largest error, the number of
agents more than 5 m off at the last step of each realization (and their
total) and the seconds per realization; the bound of the same
realizations is ``tg-nebp evaluate --method pcrb`` (``--lag L`` for the
smoothing bound).

    python benchmarks/lost_agents.py --scenario paper_test_sparse \
        --realizations 20 --seed 0 --lag 10
"""
import argparse
import time

import torch

from tg_nebp.datasets import load_datasets
from tg_nebp.experiments.evaluate import scenario_of
from tg_nebp.filters import (HYBRID_RECOMMENDED, FixedLagGaussianBP,
                             GaussianBP, HybridBP, LinkSearch, Smoothed,
                             TrajectorySearch)

#: An agent farther than this from the truth at the last step is lost.
LOST = 5.0


def methods(models: dict, lag: int) -> dict:
    # name: (tracker, whether it smooths)
    def window(relocation):
        return FixedLagGaussianBP.recommended(lag=lag, relocation=relocation,
                                              **models)
    return {
        'gbp': (GaussianBP.recommended(**models), False),
        'hybrid': (HybridBP.recommended(**models), False),
        f'gbp-lag{lag}': (window(None), True),
        f'gbp-lag{lag} + LinkSearch': (window(LinkSearch()), True),
        f'gbp-lag{lag} + TrajectorySearch': (window(TrajectorySearch()),
                                             True),
        f'hybrid-lag{lag} + TrajectorySearch': (HybridBP(
            window(TrajectorySearch()), **HYBRID_RECOMMENDED), False),
    }


def scored(out, data):
    # every agent's position error (A, T) and the agents lost at the end
    dim = data.states.size(-1) // 2
    agents = ~data.anchor
    error = (out.mean[agents, :, :dim] -
             data.states[agents, :, :dim].double()).norm(dim=-1)
    return error, int((error[:, -1] > LOST).sum())


def line(name, errors, lost, seconds):
    error = torch.cat([e.flatten() for e in errors])
    return (f"{name}: RMSE {float(error.square().mean().sqrt()):.3f} m, "
            f"P_out(1 m) {float((error > 1).double().mean()):.4f}, max "
            f"{float(error.max()):.1f} m, beyond {LOST:g} m at the last step "
            f"{sum(lost)} {lost}, {seconds:.1f} s per realization")


def report(key, method, dataset, before=None):
    r"""Runs :obj:`method` on every realization of :obj:`dataset` (a
    generator seeded 0 each; :obj:`before`, where given, called with the
    realization first) and prints its :func:`line` as :obj:`key`."""
    errors, lost, start = [], [], time.perf_counter()
    for data in dataset:
        if before is not None:
            before(data)
        with torch.no_grad():
            out = method(data, generator=torch.Generator().manual_seed(0))
        error, count = scored(out, data)
        errors.append(error)
        lost.append(count)
    seconds = (time.perf_counter() - start) / len(dataset)
    print(line(key, errors, lost, seconds), flush=True)


def realizations(parser: argparse.ArgumentParser):
    r"""The run's arguments (a scenario, its test realizations and the
    window's lag, with those :obj:`parser` adds), its realizations and the
    scenario's models, one torch thread."""
    parser.add_argument('--scenario', default='paper_test_sparse')
    parser.add_argument('--realizations', type=int, default=20)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--lag', type=int, default=10)
    parser.add_argument('--root', default='datasets')
    args = parser.parse_args()
    torch.set_num_threads(1)
    scenario = scenario_of(args.scenario)
    dataset, = load_datasets(args.root, (scenario, args.realizations,
                                         args.seed))
    return args, dataset, dict(motion=scenario.motion_model,
                               measurement=scenario.measurement_model)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--only', nargs='*', default=None,
                        help='the methods to run (by name), all by default')
    args, dataset, models = realizations(parser)
    for name, (tracker, smooths) in methods(models, args.lag).items():
        if args.only and name not in args.only:
            continue
        runs = [(name, tracker)]
        if smooths:
            runs.append((name + ', smoothed', Smoothed(tracker)))
        for key, method in runs:
            report(key, method, dataset)


if __name__ == '__main__':
    main()
