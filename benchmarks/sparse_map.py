r"""The whole sequence's MAP on the sparse network, from GTSAM: the
reference that a relocation with hindsight is measured against (issue 64).

On the test realizations of ``paper_test_sparse`` (the same as ``tg-nebp
evaluate --scenario paper_test_sparse --realizations R --seed S``), with
the scenario's own models (benchmarks/uwb_gtsam.py's factors: the prior,
each transition by the motion model's own mean, Jacobian and noise, each
range a Gaussian factor), the whole sequence's MAP by Levenberg-Marquardt
started from the true states: the best basin the data allow (the truth
only starts the solver; the optimum is the posterior's, and its cost is
printed). With ``--isam2`` it also runs from iSAM2's estimate after the
last step (the issue's reference: a solver that starts where an
incremental one left it), and iSAM2's filtered estimates are scored (each
step's right after its update); iSAM2 relinearizes the drag model's
transitions through Python callbacks, minutes per realization.

Printed: each realization's RMSE, P_out(1 m), largest error and number of
agents beyond 5 m at the last step, then the pooled figures over all
realizations.

GTSAM is an optional extra for this benchmark only (not a dependency of
tg_nebp): pip install gtsam; then, from the repository root,

    python benchmarks/sparse_map.py --realizations 20 --seed 0
"""
import argparse
import sys

import numpy as np
import torch

from uwb_gtsam import run, state_key, step_factors  # beside this one
from tg_nebp.datasets import load_datasets
from tg_nebp.experiments.evaluate import scenario_of

#: The transitions' noise given full rank by this share of its largest
#: variance (a 1 % relative spread): the drag model's noise over one second
#: is 100 times smaller than the UWB recordings', and a millionth left
#: iSAM2's systems indeterminate.
JITTER = 1e-4

try:
    import gtsam
except ImportError:  # reported by main(), after --help
    gtsam = None


def whole_map(data, motion, measurement, start):
    r"""The whole sequence's MAP :math:`(A, T, S)` by Levenberg-Marquardt
    from the states :obj:`start` :math:`(A, T + 1, S)` (the prior's step
    first), and its cost."""
    steps, agents, _ = step_factors(data, motion, measurement, False,
                                    JITTER)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for factors in steps:
        for factor in factors:
            graph.add(factor)
    count, total = len(agents), int(data.num_steps)
    for k in range(count):
        for t in range(total + 1):
            values.insert(state_key(k, t, count), start[k, t])
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(200)
    params.setRelativeErrorTol(1e-9)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values,
                                               params).optimize()
    mean = np.stack([np.stack([result.atVector(state_key(k, t, count))
                               for t in range(1, total + 1)])
                     for k in range(count)])
    return mean, graph.error(result)


def errors(data, agents, mean):
    # every agent's position error (A, T)
    dim = data.states.size(-1) // 2
    truth = data.states[agents].double()[..., :dim].numpy()
    return np.linalg.norm(mean[..., :dim] - truth, axis=-1)


def line(error):
    return (f"RMSE {np.sqrt(np.mean(error ** 2)):.3f} m, P_out(1 m) "
            f"{np.mean(error > 1):.4f}, max {error.max():.2f} m, beyond 5 m "
            f"at the last step {int(np.sum(error[:, -1] > 5))}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenario', default='paper_test_sparse')
    parser.add_argument('--realizations', type=int, default=20)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--root', default='datasets')
    parser.add_argument('--isam2', action='store_true')
    args = parser.parse_args()
    if gtsam is None:
        sys.exit('error: this benchmark needs GTSAM (pip install gtsam)')
    scenario = scenario_of(args.scenario)
    dataset, = load_datasets(args.root, (scenario, args.realizations,
                                         args.seed))
    motion = scenario.motion_model
    measurement = scenario.measurement_model
    pooled = {'MAP': [], 'iSAM2 filtered': [], 'MAP from iSAM2': []}
    for index, data in enumerate(dataset):
        agents = torch.nonzero(~data.anchor).flatten().tolist()
        prior = data.prior_mean[agents].double().numpy()[:, None]
        truth = data.states[agents].double().numpy()
        mean, cost = whole_map(data, motion, measurement,
                               np.concatenate([prior, truth], 1))
        rows = {'MAP': errors(data, agents, mean)}
        text = f"realization {index}: MAP {line(rows['MAP'])}, cost {cost:.1f}"
        if args.isam2:
            (filtered, _), (smoothed, _), _ = run(data, motion, measurement,
                                                  False, JITTER)
            mean, cost = whole_map(data, motion, measurement,
                                   np.concatenate([prior, smoothed], 1))
            rows['iSAM2 filtered'] = errors(data, agents, filtered)
            rows['MAP from iSAM2'] = errors(data, agents, mean)
            text += (f"; iSAM2 filtered {line(rows['iSAM2 filtered'])}; MAP "
                     f"from iSAM2 {line(rows['MAP from iSAM2'])}, cost "
                     f"{cost:.1f}")
        print(text, flush=True)
        for key, value in rows.items():
            pooled[key].append(value)
    for key, value in pooled.items():
        if value:
            print(f"{key}, {len(value)} realizations: "
                  f"{line(np.concatenate(value))}")


if __name__ == '__main__':
    main()
