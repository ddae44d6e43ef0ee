r"""Seconds per realization of the posterior CRB and the centralized IEKF
(joint and marginals-only) on the paper's test network, the median of 3
timed runs after a warm-up, one torch thread: the figures of the docs'
guide page on the bound. An earlier tree is measured the same way from its
checkout:

    python benchmarks/yardstick_speed.py
    PYTHONPATH=/path/to/old/checkout python benchmarks/yardstick_speed.py
"""
import json
import statistics
import time

import torch

import tg_nebp
from tg_nebp.bounds import PosteriorCRB
from tg_nebp.datasets import Scenario
from tg_nebp.filters import CentralizedIEKF


def main():
    torch.set_num_threads(1)
    scenario = Scenario.load('paper_test')
    data = scenario.generate(torch.Generator().manual_seed(0))
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    methods = dict(pcrb=PosteriorCRB(**models),
                   iekf=CentralizedIEKF(**models),
                   iekf_marginal=CentralizedIEKF(marginal=True, **models))
    seconds = {}
    with torch.no_grad():
        for name, method in methods.items():
            method(data)  # a warm-up
            times = []
            for _ in range(3):
                start = time.perf_counter()
                method(data)
                times.append(time.perf_counter() - start)
            seconds[name] = round(statistics.median(times), 3)
    print(json.dumps(dict(package=tg_nebp.__file__, seconds=seconds)))


if __name__ == '__main__':
    main()
