r"""The latency of one live step on the paper's test network (100 agents,
13 anchors): a recorded realization (seed 0, realization 0) replayed line
by line through a :class:`~tg_nebp.filters.TrackingSession`, every line
read, stepped and its estimate line formatted; the median, 90th
percentile and largest of the 49 steps after the first (which joins every
node), and the median of the session's update alone (no JSON), one torch
thread, with the objects made before the replay frozen out of the garbage
collector's passes as ``tg-nebp track`` does (``gc.freeze``). The methods are
those of ``tg-nebp track`` at their defaults (particle BP and the Gaussian
NEBP as named below). The figures of the docs' page "Tracking live":

    python benchmarks/track_latency.py
    python benchmarks/track_latency.py --methods gbp iekf --threads 2

Another scenario's first realization (a real sequence's: ``--scenario
mrclam-6 --root DIR``), with the options of ``tg-nebp track``: the
incremental smoother and fixed-lag Gaussian BP on sequence 6's stream
(odometry as the lines' inputs),

    python benchmarks/track_latency.py --scenario mrclam-6 --root DIR \
        --methods iekf --lag all --incremental --measurement student-t-range-bearing
    python benchmarks/track_latency.py --scenario mrclam-6 --root DIR \
        --methods gbp --lag 5 --measurement student-t-range-bearing

and with a smoother's line holding the final step of its window alone
(``--window final``, as ``tg-nebp track --window final``).
"""
import argparse
import gc
import json
import statistics
import time

import torch

from tg_nebp.datasets import Scenario, load_datasets
from tg_nebp.experiments.evaluate import method_tracker, scenario_of
from tg_nebp.filters import TrackingSession
from tg_nebp.live import (WINDOW_LINES, estimate_line, parse_step,
                          realization_lines)

# the options of every method (tg-nebp track's defaults otherwise)
OPTIONS = {'bp': dict(), 'gnebp': dict(checkpoint='paper')}


def replay(tracker, lines, window='all'):
    # every line's seconds: read, step, write (the estimate line, with the
    # smoother's window as --window writes it), and the step's (the
    # session's update) alone
    session = TrackingSession(tracker)
    seconds, updates = [], []
    with torch.no_grad():
        for line in lines:
            start = time.perf_counter()
            step = parse_step(line)
            stepping = time.perf_counter()
            output = session.update(step.links, step.ranges, step.dt,
                                    step.time, step.join, step.leave,
                                    step.control)
            updates.append(time.perf_counter() - stepping)
            estimate_line(session, output, window)
            seconds.append(time.perf_counter() - start)
    return seconds, updates


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--methods', nargs='+',
                        default=['gbp', 'iekf', 'gnebp', 'bp'])
    parser.add_argument('--threads', type=int, default=1)
    parser.add_argument('--scenario', default='paper_test')
    parser.add_argument('--root', default=None,
                        help="a real sequence's folder (mrclam-N)")
    parser.add_argument('--lag', default=None,
                        help="as tg-nebp track's (a number, or 'all')")
    parser.add_argument('--incremental', action='store_true')
    parser.add_argument('--measurement', default=None)
    parser.add_argument('--window', choices=list(WINDOW_LINES),
                        default='all', help="as tg-nebp track's")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scenario = scenario_of(args.scenario)
    if isinstance(scenario, Scenario):
        data = scenario.generate(torch.Generator().manual_seed(0))
        dt = float(scenario.motion_model.params().get('dt', 1.0))
    else:  # a real sequence: its first window
        data = load_datasets(args.root, (scenario, None, 0))[0][0]
        dt = scenario.dt
    lag = None if args.lag is None else \
        args.lag if args.lag == 'all' else int(args.lag)
    given = dict(lag=lag, incremental=args.incremental,
                 measurement=args.measurement)
    for method in args.methods:
        tracker, _ = method_tracker(method, scenario,
                                    **OPTIONS.get(method, {}), **given)
        lines = list(realization_lines(
            data, len(tracker.measurement.features), dt))
        replay(tracker, lines[:3])  # warm-up
        # as tg-nebp track does: the objects made so far leave the
        # collector's full passes
        gc.freeze()
        seconds, updates = replay(tracker.eval(), lines, args.window)
        gc.unfreeze()
        # the first line joins every node: apart
        ordered = sorted(seconds[1:])
        print(json.dumps(dict(
            method=method, scenario=args.scenario, lag=args.lag,
            window=args.window,
            steps=len(seconds), threads=args.threads,
            first_ms=round(1e3 * seconds[0], 2),
            median_ms=round(1e3 * statistics.median(seconds[1:]), 2),
            mean_ms=round(1e3 * statistics.mean(seconds[1:]), 2),
            p90_ms=round(1e3 * ordered[int(0.9 * len(ordered))], 2),
            max_ms=round(1e3 * ordered[-1], 2),
            update_median_ms=round(1e3 * statistics.median(updates[1:]),
                                   2))))


if __name__ == '__main__':
    main()
