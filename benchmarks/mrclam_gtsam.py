r"""GTSAM's iSAM2 as an outside-solver reference on the UTIAS MRCLAM robots.

iSAM2 (incremental smoothing, the standard robotics solver) on the same
realizations and fitted noise as benchmarks/mrclam.py, in its three
information settings (range only, without odometry; range and odometry;
range, bearing and odometry).

Each robot has a Pose2 per step; the prior at t_0 is a prior factor;
each step's odometry a between factor on the two poses (the unicycle's
own move and covariance, tg_nebp.models.UnicycleOdometry; a step without
odometry a between factor of no motion with the model's random-walk
noise); each link a range factor, and with bearings a bearing factor
(relative to the measuring robot's heading, as tg_nebp's bearing), to a
landmark (a Point2 held at its surveyed position by a tight prior) or to
the other robot's pose of the same step. Two noise rows: Gaussian with
the fitted scales (tg_nebp.datasets.fit_models) and the fitted Student-t
itself (GTSAM's Cauchy m-estimator, exactly the Student-t's loss: see
noise()). iSAM2 takes every step's factors in one update: the filtered
estimate of step t is the newest poses' estimate and marginal covariance
right after step t's update, the smoothed estimate that of every pose
after the last update (and its marginal covariance).

Prints first a check of the factors at the ground truth (check_at_truth:
the residuals' medians near 0 where GTSAM's conventions agree with the
data's), then per setting and row the metrics of benchmarks/mrclam.py
(its row(): RMSE, median, P_out at 0.5 and 1 m, the largest error, the
two-sided P(accept 0.95), the heading's RMSE, milliseconds per step) and
the one-sided P(NEES <= 5.991). The time per step of a filtered row is
the incremental run (every update, the newest poses' estimates and
covariances); a smoothed row's adds the final estimate and covariances
of every pose. The 600 s protocol took 12 to 19 minutes on two shared
cores, most of it the range-only settings.

GTSAM is an optional extra for this benchmark only (not a dependency of
tg_nebp): pip install gtsam (4.3.0 was used); then, from the repository
root (the default sequence's path is relative to it),

    python benchmarks/mrclam_gtsam.py [--sequence PATH_TO_MRCLAM_DatasetN.zip]
"""
import argparse
import math
import sys
import time
from importlib.metadata import version
from types import SimpleNamespace

import numpy as np
import torch
from scipy.stats import chi2

from mrclam import SEQUENCE_6, row  # benchmarks/mrclam.py, beside this one
from tg_nebp.datasets import fit_models, mrclam_realization, read_mrclam
from tg_nebp.metrics import nees

try:
    import gtsam
except ImportError:  # reported by main(), after --help
    gtsam = None

SETTINGS = ('range only', 'range, odometry', 'range, bearing, odometry')
#: Metres: the surveyed landmarks are variables held by a prior this
#: tight (GTSAM has no bearing or range factor to a known point), far
#: below the range noise, so they act as known.
LANDMARK_STD = 1e-3
#: The NEES bound of the one-sided 95 % test, chi-square of 2 degrees.
NEES_95 = float(chi2.ppf(0.95, 2))


def realizations(sequence, duration):
    # the three realizations of benchmarks/mrclam.py's settings()
    return {
        'range only': mrclam_realization(sequence, duration=duration,
                                         features=('range', ),
                                         odometry=False)[0],
        'range, odometry': mrclam_realization(sequence, duration=duration,
                                              features=('range', ))[0],
        'range, bearing, odometry': mrclam_realization(
            sequence, duration=duration)[0]}


def pose_key(robot, step, robots):
    return gtsam.symbol('x', step * robots + robot)


def landmark_key(node):
    return gtsam.symbol('l', node)


def _frame(heading):
    # the rotation taking world [x, y, theta] into a pose's own frame:
    # Pose2's tangent space at heading 'heading' (first order)
    c, s = math.cos(heading), math.sin(heading)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def move(motion, control):
    r"""The between factor's measured relative pose and its covariance in
    GTSAM's tangent space for one robot-step of input :obj:`control`
    :math:`(2)` (NaN, or None, for none): the unicycle's move
    :math:`f(\mathbf{0}, \mathbf{u})` and covariance
    :math:`\mathbf{G} \mathbf{M} \mathbf{G}^\top` from the start pose's
    frame (:class:`~tg_nebp.models.UnicycleOdometry`'s own), turned into
    the end pose's frame, where BetweenFactorPose2 measures its error."""
    start = torch.zeros(3, dtype=torch.float64)
    rel = motion.mean(start, control)
    cov = motion.noise_covariance(start, control).numpy()
    if control is not None and bool(torch.isfinite(control).all()):
        # G M G^T has rank 2 (no sideways slip); a factor needs full rank:
        # sideways across the move, the model's own floor of distance noise
        across = np.array([-math.sin(0.5 * float(control[1])),
                           math.cos(0.5 * float(control[1])), 0.0])
        cov = cov + motion.sigma_distance**2 * np.outer(across, across)
    frame = _frame(float(rel[2]))
    return gtsam.Pose2(*rel.tolist()), frame @ cov @ frame.T


def noise(sigma, robust, nu):
    r"""A 1-D noise model of scale :obj:`sigma`: Gaussian, or the
    Student-t of :math:`\nu` degrees: GTSAM's Cauchy m-estimator
    :math:`\frac{k^2}{2} \log(1 + e^2 / k^2)` on the residual whitened by
    :math:`\sigma \sqrt{\nu / (\nu + 1)}` with :math:`k = \sqrt{\nu + 1}`
    is :math:`\frac{\nu + 1}{2} \log(1 + r^2 / (\nu \sigma^2))`, the
    Student-t's negative log-likelihood (and its weights the library's
    StudentTRangeBearing.residual_weights)."""
    if not robust:
        return gtsam.noiseModel.Isotropic.Sigma(1, sigma)
    return gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Cauchy.Create(math.sqrt(nu + 1)),
        gtsam.noiseModel.Isotropic.Sigma(1, sigma * math.sqrt(nu / (nu + 1))))


def factors(data, motion, measurement, robust):
    r"""Per step :math:`0..T`, its factors as :obj:`(kind, factor)` pairs,
    and the robots' relative moves :math:`(T, R)` (the initial guesses).
    Range and bearing are separate factors: independent noise, the same as
    one bearing-range factor when Gaussian, and each with its own
    m-estimator when robust (GTSAM robustifies a factor's whole residual
    jointly)."""
    robots = int((~data.anchor).sum())
    steps = int(data.num_steps)
    range_noise = noise(measurement.sigma, robust, measurement.nu)
    bearing = data.edge_attr.size(1) == 2
    if bearing:
        bearing_noise = noise(measurement.sigma_bearing, robust,
                              measurement.nu)
    out = [[] for _ in range(steps + 1)]
    for r in range(robots):
        mean = data.prior_mean[r].double()
        frame = _frame(float(mean[2]))
        out[0].append(('prior', gtsam.PriorFactorPose2(
            pose_key(r, 0, robots), gtsam.Pose2(*mean.tolist()),
            gtsam.noiseModel.Gaussian.Covariance(
                frame @ data.prior_cov[r].double().numpy() @ frame.T))))
    for node in torch.nonzero(data.anchor).flatten().tolist():
        out[0].append(('landmark', gtsam.PriorFactorPoint2(
            landmark_key(node), data.states[node, 0, :2].double().numpy(),
            gtsam.noiseModel.Isotropic.Sigma(2, LANDMARK_STD))))
    control = getattr(data, 'control', None)
    moves = []
    for t in range(1, steps + 1):
        moves.append([])
        for r in range(robots):
            rel, cov = move(motion, None if control is None
                            else control[r, t - 1].double())
            moves[-1].append(rel)
            out[t].append(('odometry', gtsam.BetweenFactorPose2(
                pose_key(r, t - 1, robots), pose_key(r, t, robots), rel,
                gtsam.noiseModel.Gaussian.Covariance(cov))))
    for (j, i), z, k in zip(data.edge_index.t().tolist(),
                            data.edge_attr.double().tolist(),
                            data.edge_time.tolist()):
        t = k + 1  # edge_time k: the measurements of step k + 1
        receiver = pose_key(i, t, robots)
        if data.anchor[j]:
            sender, to = landmark_key(j), 'landmark'
            kinds = (gtsam.RangeFactor2D, gtsam.BearingFactor2D)
        else:
            sender, to = pose_key(j, t, robots), 'robot'
            kinds = (gtsam.RangeFactorPose2, gtsam.BearingFactorPose2)
        out[t].append((f'range to {to}',
                       kinds[0](receiver, sender, z[0], range_noise)))
        if bearing:
            out[t].append((f'bearing to {to}', kinds[1](
                receiver, sender, gtsam.Rot2(z[1]), bearing_noise)))
    return out, moves


def truth_values(data):
    robots = int((~data.anchor).sum())
    values = gtsam.Values()
    states = data.states.double()
    for r in range(robots):
        values.insert(pose_key(r, 0, robots),
                      gtsam.Pose2(*data.prior_mean[r].double().tolist()))
        for t in range(1, int(data.num_steps) + 1):
            values.insert(pose_key(r, t, robots),
                          gtsam.Pose2(*states[r, t - 1].tolist()))
    for node in torch.nonzero(data.anchor).flatten().tolist():
        values.insert(landmark_key(node), states[node, 0, :2].numpy())
    return values


def check_at_truth(data, steps):
    r"""Per kind of measurement or move, the factors at the ground truth:
    the median residual (measured minus predicted, by GTSAM's own range,
    bearing and between: near 0 where the conventions agree) and the
    squared Mahalanobis distance's median and mean beside the
    chi-square's: the links' scales are fitted robustly, so their median
    should match; the odometry's by the mean square, so its mean should
    be near 2, its two fitted input dimensions (the third, sideways, is
    move()'s floor)."""
    values = truth_values(data)
    residuals, distances = {}, {}
    for kind, factor in (pair for step in steps for pair in step):
        if kind in ('prior', 'landmark'):  # zero at the truth by design
            continue
        residuals.setdefault(kind, []).append(
            -factor.unwhitenedError(values))
        distances.setdefault(kind, []).append(2 * factor.error(values))
    for kind, found in residuals.items():
        found, dim = np.array(found), len(found[0])
        print(f'check at truth | {kind} ({len(found)}): median residual '
              f'{np.array2string(np.median(found, 0), precision=4)}, '
              f'Mahalanobis^2 median {np.median(distances[kind]):.2f} '
              f'(chi2 {chi2.median(dim):.2f}), mean '
              f'{np.mean(distances[kind]):.2f} (chi2 {dim})')


def tangent_to_world(pose, cov):
    # a Pose2 marginal covariance (its own tangent space) in world [x, y,
    # theta]: first order, the pose's rotation
    frame = _frame(pose.theta()).T
    return frame @ cov @ frame.T


def run(data, steps, moves):
    r"""iSAM2 over the steps: the filtered and smoothed means :math:`(R,
    T, 3)` and world-frame covariances :math:`(R, T, 3, 3)`, and the
    seconds of the incremental part (every update with the newest poses'
    estimates and covariances) and of the final smoothed estimate and
    covariances."""
    robots = int((~data.anchor).sum())
    count = int(data.num_steps)
    params = gtsam.ISAM2Params()
    # relinearize any variable that moved more than 1 cm or 0.01 rad, at
    # every update: an accurate reference rather than the fastest
    params.setRelinearizeThreshold(0.01)
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    filtered_mean = np.zeros((robots, count, 3))
    filtered_cov = np.zeros((robots, count, 3, 3))
    start = time.perf_counter()
    for t, step in enumerate(steps):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for _, factor in step:
            graph.add(factor)
        if t == 0:
            latest = [gtsam.Pose2(*data.prior_mean[r].double().tolist())
                      for r in range(robots)]
            for node in torch.nonzero(data.anchor).flatten().tolist():
                values.insert(landmark_key(node),
                              data.states[node, 0, :2].double().numpy())
        else:
            latest = [pose.compose(rel)
                      for pose, rel in zip(latest, moves[t - 1])]
        for r in range(robots):
            values.insert(pose_key(r, t, robots), latest[r])
        isam.update(graph, values)
        if t == 0:
            continue
        for r in range(robots):
            key = pose_key(r, t, robots)
            latest[r] = isam.calculateEstimatePose2(key)
            filtered_mean[r, t - 1] = (latest[r].x(), latest[r].y(),
                                       latest[r].theta())
            filtered_cov[r, t - 1] = tangent_to_world(
                latest[r], isam.marginalCovariance(key))
    incremental = time.perf_counter() - start
    start = time.perf_counter()
    estimate = isam.calculateEstimate()
    smoothed_mean = np.zeros_like(filtered_mean)
    smoothed_cov = np.zeros_like(filtered_cov)
    for r in range(robots):
        for t in range(1, count + 1):
            key = pose_key(r, t, robots)
            pose = estimate.atPose2(key)
            smoothed_mean[r, t - 1] = (pose.x(), pose.y(), pose.theta())
            smoothed_cov[r, t - 1] = tangent_to_world(
                pose, isam.marginalCovariance(key))
    final = time.perf_counter() - start
    return (filtered_mean, filtered_cov), (smoothed_mean, smoothed_cov), \
        incremental, final


def report(data, mean, cov, seconds):
    # benchmarks/mrclam.py's row() on the agents' estimates (the anchors
    # left at zero, row() reads the agents only), and the one-sided test
    full_mean = torch.zeros(data.num_nodes, int(data.num_steps), 3,
                            dtype=torch.float64)
    full_cov = torch.zeros(full_mean.shape + (3, ), dtype=torch.float64)
    agents = ~data.anchor
    full_mean[agents] = torch.from_numpy(mean)
    full_cov[agents] = torch.from_numpy(cov)
    value = nees(full_mean[agents][..., :2], full_cov[agents][..., :2, :2],
                 data.states[agents, :, :2].double())
    accepted = float((value <= NEES_95).double().mean())
    out = SimpleNamespace(mean=full_mean, cov=full_cov)
    return f'{row(data, out, seconds)}, P(NEES <= {NEES_95:.3f}) ' \
        f'{accepted:.3f}'


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--sequence', default=SEQUENCE_6)
    parser.add_argument('--fit', default=SEQUENCE_6,
                        help='the sequence the noise is fitted on')
    parser.add_argument('--duration', type=float, default=600.0,
                        help='seconds of the sequence (the protocol: 600)')
    parser.add_argument('--settings', nargs='+', choices=SETTINGS,
                        default=list(SETTINGS), metavar='SETTING',
                        help=f'a subset of {list(SETTINGS)}')
    args = parser.parse_args()
    if gtsam is None:
        print('mrclam_gtsam.py needs GTSAM, an optional extra for this '
              'benchmark only: pip install gtsam', file=sys.stderr)
        sys.exit(2)
    fitted_on, _ = mrclam_realization(read_mrclam(args.fit))
    motion, measurement, fitted = fit_models(fitted_on)
    print(f'GTSAM {version("gtsam")}\nfitted: {motion}\n        '
          f'{measurement}\n        {fitted}', flush=True)
    data_of = realizations(read_mrclam(args.sequence), args.duration)
    check_at_truth(data_of['range, bearing, odometry'],
                   factors(data_of['range, bearing, odometry'], motion,
                           measurement, robust=False)[0])
    for setting in args.settings:
        data = data_of[setting]
        for name, robust in (('Gaussian', False),
                             (f'Student-t, nu {measurement.nu:g} (Cauchy)',
                              True)):
            steps, moves = factors(data, motion, measurement, robust)
            filtered, smoothed, incremental, final = run(data, steps, moves)
            print(f'{setting} | iSAM2 {name}, filtered: '
                  f'{report(data, *filtered, incremental)}', flush=True)
            print(f'{setting} | iSAM2 {name}, smoothed: '
                  f'{report(data, *smoothed, incremental + final)}',
                  flush=True)


if __name__ == '__main__':
    main()
