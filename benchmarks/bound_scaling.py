r"""Time and memory of one step of the posterior CRB and of the centralized
IEKF against the number of agents (the paper's test network grown at the
same density, Scenario.grown): the figures of the docs' guide page "The
bound and the centralized reference".

    python benchmarks/bound_scaling.py --agents 100 300 1000 2000
"""
import argparse
import resource
import time

import torch

from tg_nebp.bounds import PosteriorCRB
from tg_nebp.datasets import Scenario
from tg_nebp.filters import CentralizedIEKF


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--agents', type=int, nargs='+',
                        default=[100, 300, 1000])
    parser.add_argument('--steps', type=int, default=3,
                        help='time steps; the first is not timed')
    parser.add_argument('--methods', nargs='+', default=['pcrb', 'iekf'])
    args = parser.parse_args()
    print('| agents | method | s per step (median of the steps after the '
          'first) | peak resident memory [GiB] |')
    print('| --- | --- | --- | --- |')
    for agents in args.agents:
        scenario = Scenario.load('paper_test').grown(agents).replace(
            num_steps=args.steps)
        data = scenario.generate(torch.Generator().manual_seed(0))
        for name in args.methods:
            method = (PosteriorCRB(scenario.motion_model,
                                   scenario.measurement_model)
                      if name == 'pcrb' else CentralizedIEKF(
                          motion=scenario.motion_model,
                          measurement=scenario.measurement_model))
            times, start = [], time.perf_counter()
            for _ in method.steps(data):
                now = time.perf_counter()
                times.append(now - start)
                start = now
            later = sorted(times[1:])
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
            print(f'| {agents} | {name} | {later[len(later) // 2]:.3f} | '
                  f'{peak:.2f} |', flush=True)


if __name__ == '__main__':
    main()
