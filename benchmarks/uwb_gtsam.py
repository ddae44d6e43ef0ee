r"""GTSAM's iSAM2 as an outside-solver reference on real UWB ranging.

iSAM2 on the same realization and the same fitted models as the library's
rows (``tg-nebp compare --scenario tiers-uwb-test3-second-half`` and
``miluv-cirObstacles_1_random3_0-second-half``): every agent has a state
:math:`[\mathbf{p}, \mathbf{v}]` per step (a vector variable); the prior at
:math:`t_0` a Gaussian prior factor; each step's constant-velocity
transition a factor whose error is :math:`\mathbf{L}^{-1}(\mathbf{x}_t -
\mathbf{F} \mathbf{x}_{t-1})` (:math:`\mathbf{L}` the Cholesky factor of
the model's own noise covariance, :math:`\mathbf{F}` its own transition:
tg_nebp.models.ConstantVelocity's mean and noise_covariance, nothing
re-derived here); each link a range factor to the other agent's state or
to the anchor's known position, with the link's sensor's noise: the
fitted Student-t as GTSAM's Cauchy m-estimator (benchmarks/mrclam_gtsam.py's
noise(), exactly the Student-t's loss). iSAM2 takes every step's factors in
one update: the filtered estimate of step t is the newest states'
estimate and marginal covariance right after step t's update, the
smoothed one every state's after the last update.

GTSAM is an optional extra for this benchmark only (not a dependency of
tg_nebp): pip install gtsam (4.2 was used); then, from the repository root,

    python benchmarks/uwb_gtsam.py --scenario tiers-uwb-test3-second-half \
        --root ../shared/data/uwb/tiers
    python benchmarks/uwb_gtsam.py \
        --scenario miluv-cirObstacles_1_random3_0-second-half \
        --root ../shared/data/uwb/miluv
"""
import argparse
import sys
import time
from functools import partial

import numpy as np
import torch

from mrclam_gtsam import noise  # beside this one
from tg_nebp.data import scored_of
from tg_nebp.datasets import RecordingDataset, load_scenario
from tg_nebp.metrics import consistency_curve, nees

try:
    import gtsam
except ImportError:  # reported by main(), after --help
    gtsam = None


def state_key(agent, step, agents):
    return gtsam.symbol('x', step * agents + agent)


def _motion_error(transition, whitener, this, values, jacobians):
    # the constant-velocity transition's whitened error and Jacobians
    before = values.atVector(this.keys()[0])
    after = values.atVector(this.keys()[1])
    if jacobians is not None:
        jacobians[0] = -whitener @ transition
        jacobians[1] = whitener
    return whitener @ (after - transition @ before)


def _range_error(z, dim, anchor, this, values, jacobians):
    # the range's error (distance - z) to another agent or an anchor
    keys = this.keys()
    receiver = values.atVector(keys[0])
    sender = anchor if anchor is not None else values.atVector(keys[1])
    offset = receiver[:dim] - sender[:dim]
    distance = float(np.linalg.norm(offset))
    unit = offset / max(distance, 1e-9)
    if jacobians is not None:
        row = np.zeros((1, receiver.size))
        row[0, :dim] = unit
        jacobians[0] = row
        if anchor is None:
            jacobians[1] = -row
    return np.array([distance - z])


def sensor_noises(measurement, robust):
    # the noise of each sensor: one for a single-sensor likelihood
    sensors = getattr(measurement, 'sensors', [measurement])
    return [noise(s.sigma, robust, getattr(s, 'nu', None)) for s in sensors]


def step_factors(data, motion, measurement, robust):
    r"""Per step :math:`0..T` its factors: the priors at step 0, then each
    step's transitions and links."""
    agents = torch.nonzero(~data.anchor).flatten().tolist()
    index = {node: k for k, node in enumerate(agents)}
    count = len(agents)
    dim = data.states.size(-1) // 2
    size = 2 * dim
    zero = torch.zeros(1, size, dtype=torch.float64)
    # the model's own transition and noise (linear: its Jacobian at zero)
    transition = torch.autograd.functional.jacobian(
        lambda x: motion.mean(x), zero).reshape(size, size).numpy()
    cov = motion.noise_covariance(zero)[0].numpy()
    # sigma_a^2 W W^T has rank D: a factor needs full rank, so a jitter of
    # a millionth of its largest variance (a 1e-3 relative spread) along
    # the directions the acceleration does not reach
    cov = cov + 1e-6 * float(np.diag(cov).max()) * np.eye(size)
    whitener = np.linalg.inv(np.linalg.cholesky(cov))
    unit = gtsam.noiseModel.Unit.Create(size)
    noises = sensor_noises(measurement, robust)
    out = [[] for _ in range(int(data.num_steps) + 1)]
    for node in agents:
        out[0].append(gtsam.PriorFactorVector(
            state_key(index[node], 0, count),
            data.prior_mean[node].double().numpy(),
            gtsam.noiseModel.Gaussian.Covariance(
                data.prior_cov[node].double().numpy())))
    for t in range(1, int(data.num_steps) + 1):
        for k in range(count):
            out[t].append(gtsam.CustomFactor(
                unit, [state_key(k, t - 1, count), state_key(k, t, count)],
                partial(_motion_error, transition, whitener)))
    several = data.edge_attr.size(1) > 1 and len(noises) > 1
    for (j, i), z, step in zip(data.edge_index.t().tolist(),
                               data.edge_attr.double().tolist(),
                               data.edge_time.tolist()):
        t = step + 1
        model = noises[int(round(z[1])) if several else 0]
        receiver = state_key(index[i], t, count)
        if data.anchor[j]:
            anchor = data.states[j, 0, :dim].double().numpy()
            out[t].append(gtsam.CustomFactor(
                model, [receiver], partial(_range_error, z[0], dim, anchor)))
        else:
            out[t].append(gtsam.CustomFactor(
                model, [receiver, state_key(index[j], t, count)],
                partial(_range_error, z[0], dim, None)))
    return out, agents, transition


def run(data, motion, measurement, robust):
    r"""iSAM2 over the steps: the filtered and smoothed means and
    covariances :math:`(A, T, S)`, :math:`(A, T, S, S)` of the agents and
    the seconds of the incremental part."""
    steps, agents, transition = step_factors(data, motion, measurement,
                                             robust)
    count, total = len(agents), int(data.num_steps)
    size = data.states.size(-1)
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.01)
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    filtered_mean = np.zeros((count, total, size))
    filtered_cov = np.zeros((count, total, size, size))
    latest = [data.prior_mean[node].double().numpy() for node in agents]
    start = time.perf_counter()
    for t, factors in enumerate(steps):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for factor in factors:
            graph.add(factor)
        for k in range(count):
            guess = latest[k] if t == 0 else transition @ latest[k]
            values.insert(state_key(k, t, count), guess)
        isam.update(graph, values)
        if t == 0:
            continue
        for k in range(count):
            key = state_key(k, t, count)
            latest[k] = isam.calculateEstimateVector(key)
            filtered_mean[k, t - 1] = latest[k]
            filtered_cov[k, t - 1] = isam.marginalCovariance(key)
    seconds = time.perf_counter() - start
    estimate = isam.calculateEstimate()
    smoothed_mean = np.zeros_like(filtered_mean)
    smoothed_cov = np.zeros_like(filtered_cov)
    for k in range(count):
        for t in range(1, total + 1):
            key = state_key(k, t, count)
            smoothed_mean[k, t - 1] = estimate.atVector(key)
            smoothed_cov[k, t - 1] = isam.marginalCovariance(key)
    return (filtered_mean, filtered_cov), (smoothed_mean, smoothed_cov), \
        seconds


def report(data, agents, mean, cov, seconds=None):
    # the RMSE, median, largest error and P(accept 0.95) of evaluate's
    # metrics over the positions of the agents it scores (one tracked
    # without ground truth is not: scored_of)
    dim = data.states.size(-1) // 2
    scored = scored_of(data)[agents]
    truth = data.states[agents].double()[scored][..., :dim]
    mean = torch.from_numpy(mean)[scored][..., :dim]
    cov = torch.from_numpy(cov)[scored][..., :dim, :dim]
    error = (mean - truth).norm(dim=-1).flatten()
    accept = consistency_curve(nees(mean, cov, truth).flatten(), [0.95],
                               dof=dim)
    line = (f"RMSE {float(error.square().mean().sqrt()):.3f} m, median "
            f"{float(error.median()):.3f} m, max {float(error.max()):.2f} m, "
            f"P(accept 0.95) {float(accept[0]):.3f}")
    if seconds is not None:
        line += f", {1000 * seconds / int(data.num_steps):.1f} ms per step"
    return line


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--scenario', default='tiers-uwb-test3-second-half')
    parser.add_argument('--root', default='../shared/data/uwb/tiers')
    args = parser.parse_args()
    if gtsam is None:
        sys.exit('error: this benchmark needs GTSAM (pip install gtsam)')
    scenario = load_scenario(args.scenario)
    data = RecordingDataset(args.root, scenario, log=False)[0]
    agents = torch.nonzero(~data.anchor).flatten().tolist()
    motion, measurement = scenario.motion_model, scenario.measurement_model
    print(f'{args.scenario}: {len(agents)} agents, {int(data.num_steps)} '
          f'steps, {data.num_edges} links; {motion}; {measurement}')
    for robust in (False, True):
        name = 'Student-t (Cauchy)' if robust else 'Gaussian'
        filtered, smoothed, seconds = run(data, motion, measurement, robust)
        print(f'iSAM2 {name}, filtered: {report(data, agents, *filtered, seconds)}')
        print(f'iSAM2 {name}, smoothed: {report(data, agents, *smoothed)}')


if __name__ == '__main__':
    main()
