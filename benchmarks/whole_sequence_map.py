r"""The whole sequence's MAP of each realization, the reference of issue 64:
the centralized full smoother (``tg-nebp evaluate --method iekf --lag
all``, the scenario's own models) by its Gauss-Newton iterations started
from the true states (:meth:`CentralizedSmoother.smoothed_from
<tg_nebp.filters.CentralizedSmoother.smoothed_from>`: the optimum of the
truth's basin, the best the data allow; the truth only starts the
solver), and started from a method's smoothed estimates (fixed-lag
Gaussian BP of ``--lag`` steps with the relocation with hindsight,
:class:`~tg_nebp.filters.TrajectorySearch`), whose basin is the one a
method without the truth reaches. On the test realizations of ``tg-nebp
evaluate --scenario S --realizations R --seed K``, one torch thread.
Printed: each realization's RMSE and agents more than 5 m off at the last
step, the window's and each MAP's, then the pooled RMSE, P_out(1 m),
largest error, lost agents and seconds per realization of each.

    python benchmarks/whole_sequence_map.py --scenario paper_test_sparse \
        --realizations 20 --seed 0 --lag 10
"""
import argparse
import time

import torch

from lost_agents import line, realizations, scored  # beside this one
from tg_nebp.filters import (CentralizedSmoother, FixedLagGaussianBP,
                             Smoothed, TrajectorySearch)


def main():
    args, dataset, models = realizations(argparse.ArgumentParser(
        description=__doc__.splitlines()[0]))
    smoother = CentralizedSmoother(None, **models)
    window = Smoothed(FixedLagGaussianBP.recommended(
        lag=args.lag, relocation=TrajectorySearch(), **models))
    name = f'gbp-lag{args.lag} + TrajectorySearch, smoothed'
    starts = {'from the truth': lambda data, _: data.states,
              f'from {name}': lambda _, smoothed: smoothed}
    pooled = {key: ([], [], 0.0) for key in [name] + list(starts)}
    for index, data in enumerate(dataset):
        began = time.perf_counter()
        with torch.no_grad():
            smoothed = window(data)
        error, lost = scored(smoothed, data)
        errors, losts, total = pooled[name]
        pooled[name] = (errors + [error], losts + [lost],
                        total + time.perf_counter() - began)
        text = [f"{name}: RMSE {float(error.square().mean().sqrt()):.3f} m, "
                f"lost {lost}"]
        for key, start in starts.items():
            began = time.perf_counter()
            with torch.no_grad():
                out = smoother.smoothed_from(data, start(data,
                                                         smoothed.mean))
            seconds = time.perf_counter() - began
            error, lost = scored(out, data)
            errors, losts, total = pooled[key]
            pooled[key] = (errors + [error], losts + [lost],
                           total + seconds)
            text.append(f"MAP {key}: RMSE "
                        f"{float(error.square().mean().sqrt()):.3f} m, "
                        f"lost {lost}")
        print(f"realization {index}: " + '; '.join(text), flush=True)
    for key, (errors, losts, total) in pooled.items():
        print(line(key if key == name else f'MAP {key}', errors, losts,
                   total / len(dataset)))


if __name__ == '__main__':
    main()
