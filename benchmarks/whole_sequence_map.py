r"""The whole sequence's smoothers and MAP of each realization, the
references of issue 64: the centralized full smoother (``tg-nebp evaluate
--method iekf --lag all``, the scenario's own models) started from its
filter (as it runs by default), from the incremental smoother's last step
(``start=Smoothed(IncrementalSmoother())``, ``--escape`` without the
search), from there with the search of better basins
(:class:`~tg_nebp.filters.ParticleTrajectorySearch`, drawing from a
generator seeded with the realization's index), and, by
:meth:`CentralizedSmoother.smoothed_from
<tg_nebp.filters.CentralizedSmoother.smoothed_from>`, started from the
true states (the optimum of the truth's basin, the best the data allow;
the truth only starts the solver) and from a method's smoothed estimates
(fixed-lag Gaussian BP of ``--lag`` steps with the relocation with
hindsight, :class:`~tg_nebp.filters.TrajectorySearch`). On the test
realizations of ``tg-nebp evaluate --scenario S --realizations R --seed
K``, one torch thread. Printed: each realization's RMSE and agents more
than 5 m off at the last step and the whole sequence's cost (negative
log-posterior, up to a constant) of each, then the pooled RMSE,
P_out(1 m), largest error, lost agents and seconds per realization (the
search's include the incremental smoother's and its start's).

    python benchmarks/whole_sequence_map.py --scenario paper_test_sparse \
        --realizations 20 --seed 0 --lag 10
"""
import argparse
import time

import torch

from lost_agents import line, realizations, scored  # beside this one
from tg_nebp.filters import (CentralizedSmoother, FixedLagGaussianBP,
                             IncrementalSmoother, ParticleTrajectorySearch,
                             Smoothed, TrackOutput, TrajectorySearch)

FILTER = 'full smoother from its filter'
INCREMENTAL = 'incremental smoother, last step'
FROM_INCREMENTAL = "full smoother from the incremental smoother's"
SEARCH = f'{FROM_INCREMENTAL} + ParticleTrajectorySearch'
TRUTH = 'MAP from the truth'


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--only', nargs='+', default=None,
                        help='the rows to run (default: all)')
    args, dataset, models = realizations(parser)
    smoother = CentralizedSmoother(None, **models)
    searching = CentralizedSmoother(None, search=ParticleTrajectorySearch(),
                                    **models)
    window = Smoothed(FixedLagGaussianBP.recommended(
        lag=args.lag, relocation=TrajectorySearch(), **models))
    name = f'gbp-lag{args.lag} + TrajectorySearch, smoothed'
    names = [FILTER, INCREMENTAL, FROM_INCREMENTAL, SEARCH, TRUTH, name,
             f'MAP from {name}']
    rows = names if args.only is None else args.only
    unknown = sorted(set(rows) - set(names))
    if unknown:
        parser.error(f'unknown rows {unknown}; the rows are {names}')
    pooled = {key: ([], [], 0.0) for key in names if key in rows}

    def run(key, data, method, extra=0.0):
        began = time.perf_counter()
        with torch.no_grad():
            out = method()
        seconds = time.perf_counter() - began + extra
        if key not in pooled:  # only the start of another row
            return out, seconds
        error, lost = scored(out, data)
        errors, losts, total = pooled[key]
        pooled[key] = (errors + [error], losts + [lost], total + seconds)
        text.append(f"{key}: RMSE {float(error.square().mean().sqrt()):.3f}"
                    f" m, lost {lost}, cost "
                    f"{float(smoother.sequence_cost(data, out.mean)):.1f}")
        return out, seconds

    for index, data in enumerate(dataset):
        text = []
        if FILTER in rows:
            run(FILTER, data, lambda: smoother(data))
        if {INCREMENTAL, FROM_INCREMENTAL, SEARCH} & set(rows):
            began = time.perf_counter()
            *_, last = IncrementalSmoother(**models).steps(data)
            spent = time.perf_counter() - began
            if INCREMENTAL in rows:
                run(INCREMENTAL, data, lambda: TrackOutput(
                    last.window_mean, last.window_cov), spent)
            start, more = run(FROM_INCREMENTAL, data,
                              lambda: smoother.smoothed_from(
                                  data, last.window_mean), spent)
            if SEARCH in rows:
                # from the incremental start's optimum: what
                # start='incremental' with the search runs
                run(SEARCH, data, lambda: searching.smoothed_from(
                    data, start.mean, torch.Generator().manual_seed(index)),
                    more)
        if TRUTH in rows:
            run(TRUTH, data, lambda: smoother.smoothed_from(data,
                                                            data.states))
        if name in rows or f'MAP from {name}' in rows:
            smoothed, _ = run(name, data, lambda: window(data))
            if f'MAP from {name}' in rows:
                run(f'MAP from {name}', data, lambda: smoother.smoothed_from(
                    data, smoothed.mean))
        print(f"realization {index}: " + '; '.join(text), flush=True)
    for key, (errors, losts, total) in pooled.items():
        print(line(key, errors, losts, total / len(dataset)))


if __name__ == '__main__':
    main()
