r"""The whole sequence's smoothers and MAP of each realization, the
references of issue 64: the centralized full smoother (``tg-nebp evaluate
--method iekf --lag all``, the scenario's own models) started from its
filter (as it runs by default), from the incremental smoother's last step
(``start=Smoothed(IncrementalSmoother())``), from a method's smoothed
estimates (fixed-lag Gaussian BP of ``--lag`` steps with the relocation
with hindsight, :class:`~tg_nebp.filters.TrajectorySearch`), from the
better of those two optima by the whole sequence's cost (what a
``start`` of both keeps), from there with the search of better basins
(:class:`~tg_nebp.filters.ParticleTrajectorySearch`, drawing from a
generator seeded with the realization's index), with groups of agents
exchanged between the two optima
(:class:`~tg_nebp.filters.GroupExchange`), with the exchange and then
the search, with the exchange and then groups flipped across their
outside neighbours' line (:class:`~tg_nebp.filters.GroupFlip`), with the
exchange, the flip and the search (what ``--escape`` runs, with
``--lag`` 10), and started
from the true states (the optimum of the truth's basin, the best the
data allow; the truth only starts the solver), each by
:meth:`CentralizedSmoother.smoothed_from
<tg_nebp.filters.CentralizedSmoother.smoothed_from>`. On the test
realizations of ``tg-nebp evaluate --scenario S --realizations R --seed
K``, one torch thread. Printed: each realization's RMSE and agents more
than 5 m off at the last step and the whole sequence's cost (negative
log-posterior, up to a constant) of each, then the pooled RMSE,
P_out(1 m), largest error, lost agents and seconds per realization (a
row that starts from others' includes their seconds). ``--indices`` runs
some of the realizations only (each keeps its index, and so its search's
seed), to split a run over processes.

    python benchmarks/whole_sequence_map.py --scenario paper_test_sparse \
        --realizations 20 --seed 0 --lag 10
"""
import argparse
import time

import torch

from lost_agents import line, realizations, scored  # beside this one
from tg_nebp.filters import (CentralizedSmoother, FixedLagGaussianBP,
                             GroupExchange, GroupFlip, IncrementalSmoother,
                             ParticleTrajectorySearch,
                             Smoothed, TrackOutput, TrajectorySearch)

FILTER = 'full smoother from its filter'
INCREMENTAL = 'incremental smoother, last step'
FROM_INCREMENTAL = "full smoother from the incremental smoother's"
BEST = 'full smoother from the better of both starts'
SEARCH = f'{BEST} + ParticleTrajectorySearch'
EXCHANGE = f'{BEST}, groups exchanged'
EXCHANGE_SEARCH = f'{EXCHANGE} + ParticleTrajectorySearch'
FLIP = f'{EXCHANGE}, groups flipped'
ESCAPE = f'{FLIP} + ParticleTrajectorySearch'
TRUTH = 'MAP from the truth'


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--only', nargs='+', default=None,
                        help='the rows to run (default: all)')
    parser.add_argument('--indices', nargs='+', type=int, default=None,
                        help='the realizations to run (default: all)')
    args, dataset, models = realizations(parser)
    smoother = CentralizedSmoother(None, **models)
    searching = CentralizedSmoother(None, search=ParticleTrajectorySearch(),
                                    **models)
    exchanging = CentralizedSmoother(None, exchange=GroupExchange(),
                                     **models)
    flipping = CentralizedSmoother(None, flip=GroupFlip(), **models)
    window = Smoothed(FixedLagGaussianBP.recommended(
        lag=args.lag, relocation=TrajectorySearch(), **models))
    name = f'gbp-lag{args.lag} + TrajectorySearch, smoothed'
    from_window = f'MAP from {name}'
    names = [FILTER, INCREMENTAL, FROM_INCREMENTAL, name, from_window, BEST,
             SEARCH, EXCHANGE, EXCHANGE_SEARCH, FLIP, ESCAPE, TRUTH]
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

    outside = sorted(set(args.indices or ()) - set(range(len(dataset))))
    if outside:
        parser.error(f'--indices {outside} are not realizations 0 to '
                     f'{len(dataset) - 1}')
    run_indices = [index for index in range(len(dataset))
                   if args.indices is None or index in args.indices]
    for index in run_indices:
        data = dataset[index]
        text = []
        if FILTER in rows:
            run(FILTER, data, lambda: smoother(data))
        both = {BEST, SEARCH, EXCHANGE, EXCHANGE_SEARCH, FLIP,
                ESCAPE} & set(rows)
        starts = []  # (optimum, seconds) of each start
        if both or {INCREMENTAL, FROM_INCREMENTAL} & set(rows):
            began = time.perf_counter()
            *_, last = IncrementalSmoother(**models).steps(data)
            spent = time.perf_counter() - began
            if INCREMENTAL in rows:
                run(INCREMENTAL, data, lambda: TrackOutput(
                    last.window_mean, last.window_cov), spent)
            starts.append(run(FROM_INCREMENTAL, data,
                              lambda: smoother.smoothed_from(
                                  data, last.window_mean), spent))
        if both or {name, from_window} & set(rows):
            smoothed, spent = run(name, data, lambda: window(data))
            starts.append(run(from_window, data,
                              lambda: smoother.smoothed_from(
                                  data, smoothed.mean), spent))
        if both:
            # the lower cost's optimum (the first of equal ones), as a
            # start of both keeps it
            costs = [float(smoother.sequence_cost(data, out.mean))
                     for out, _ in starts]
            kept = starts[costs.index(min(costs))][0]
            spent = sum(seconds for _, seconds in starts)
            run(BEST, data, lambda: kept, spent)
            if SEARCH in rows:
                run(SEARCH, data, lambda: searching.smoothed_from(
                    data, kept.mean, torch.Generator().manual_seed(index)),
                    spent)
            if {EXCHANGE, EXCHANGE_SEARCH, FLIP, ESCAPE} & set(rows):
                exchanged, spent = run(EXCHANGE, data, lambda: (
                    exchanging.smoothed_from(data, [
                        out.mean for out, _ in starts])), spent)
            # the search after the others, as a smoother with them all
            # runs it (the exchange and the flip draw nothing)
            if EXCHANGE_SEARCH in rows:
                run(EXCHANGE_SEARCH, data, lambda: searching.smoothed_from(
                    data, exchanged.mean,
                    torch.Generator().manual_seed(index)), spent)
            if {FLIP, ESCAPE} & set(rows):
                flipped, spent = run(FLIP, data, lambda: (
                    flipping.smoothed_from(data, exchanged.mean)), spent)
            if ESCAPE in rows:
                run(ESCAPE, data, lambda: searching.smoothed_from(
                    data, flipped.mean,
                    torch.Generator().manual_seed(index)), spent)
        if TRUTH in rows:
            run(TRUTH, data, lambda: smoother.smoothed_from(data,
                                                            data.states))
        print(f"realization {index}: " + '; '.join(text), flush=True)
    for key, (errors, losts, total) in pooled.items():
        print(line(key, errors, losts, total / len(run_indices)))


if __name__ == '__main__':
    main()
