r"""Headings across the cut at :math:`\pm \pi`: a robot that drives in
circles is tracked by every method, filtered and smoothed, without a jump
of a turn in its estimate's error, and every reported heading is wrapped;
every measurement model of the library on every smoother."""
import math

import numpy as np
import pytest
import torch

from tg_nebp.filters import (CentralizedIEKF, CentralizedSmoother,
                             FixedLagGaussianBP, GaussianBP, GaussianNEBP,
                             HybridBP, IncrementalSmoother, ParticleBP,
                             ParticleTrajectorySearch, Smoothed)
from tg_nebp.metrics import angle_errors
from tg_nebp.models import (GaussianRange, GaussianRangeBearing, NLOSRange,
                            StudentTRange, StudentTRangeBearing,
                            UnicycleOdometry)

from helpers import gen, randomize, simulate_robots


def _circling(steps=40, measurement=None):
    # two robots on circles of 2 m radius, starting just below +pi and
    # just above -pi, turning both ways: both headings cross the cut
    motion = UnicycleOdometry()
    measurement = measurement or GaussianRangeBearing(
        sigma=0.1, sigma_bearing=0.05, max_range=8.0)
    control = torch.tensor([[0.4, 0.2], [0.4, -0.2]],
                           dtype=torch.float64).view(2, 1, 2).expand(
                               2, steps, 2).clone()
    start = torch.tensor([[5.0, 3.0, math.pi - 0.15],
                          [5.0, 7.0, -math.pi + 0.15]], dtype=torch.float64)
    anchors = torch.tensor([[1.0, 1.0], [9.0, 1.0], [1.0, 9.0],
                            [9.0, 9.0]], dtype=torch.float64)
    data = simulate_robots(motion, measurement, control, anchors, start,
                           [0.05, 0.05, 0.01], seed=4)
    return data, motion, measurement


TRACKERS = {
    'iekf': lambda m, z: CentralizedIEKF(motion=m, measurement=z),
    'gbp': lambda m, z: GaussianBP.recommended(motion=m, measurement=z),
    'bp': lambda m, z: ParticleBP.recommended(num_particles=400, motion=m,
                                              measurement=z),
    'gnebp': lambda m, z: randomize(GaussianNEBP.recommended(
        hidden_dim=8, motion=m, measurement=z), seed=5, scale=0.1),
    # the smoothers' filtered estimates (each step's newest state)
    'gbp-lag5': lambda m, z: FixedLagGaussianBP.recommended(
        lag=5, motion=m, measurement=z),
    'iekf-lag5': lambda m, z: CentralizedSmoother(lag=5, motion=m,
                                                  measurement=z),
    'hybrid-lag3': lambda m, z: HybridBP.recommended(lag=3, motion=m,
                                                     measurement=z),
    'iekf-incremental': lambda m, z: IncrementalSmoother(motion=m,
                                                         measurement=z),
    # the whole sequence's smoother from the incremental smoother's wrapped
    # estimates, searched by particles that turn across the cut
    'iekf-escape': lambda m, z: CentralizedSmoother(
        None, start=Smoothed(IncrementalSmoother(motion=m, measurement=z)),
        search=ParticleTrajectorySearch(
            num_particles=100, separation=0.5), motion=m, measurement=z),
}
SMOOTHERS = ('gbp-lag5', 'iekf-lag5', 'hybrid-lag3', 'iekf-incremental')


@pytest.mark.parametrize('name, smoothed', [
    (name, False) for name in TRACKERS] + [(name, True) for name in SMOOTHERS])
def test_a_heading_across_the_cut(name, smoothed):
    data, motion, measurement = _circling()
    truth = data.states[:2, :, 2]
    # the true headings cross the cut (a jump of about a turn, wrapped)
    assert bool((truth.diff(dim=1).abs() > math.pi).any(-1).all())
    tracker = TRACKERS[name](motion, measurement)
    out = (Smoothed(tracker) if smoothed else tracker)(data, gen(1))
    heading = out.mean[:2, :, 2]
    assert bool(((heading > -math.pi) & (heading <= math.pi)).all())
    errors = angle_errors(heading, truth)
    assert float(errors.max()) < 0.15, name
    # the signed error never jumps by a turn
    signed = torch.remainder(heading - truth + math.pi, 2 * math.pi) - \
        math.pi
    assert float(signed.diff(dim=1).abs().max()) < 0.3
    position = (out.mean[:2, :, :2] - data.states[:2, :, :2]).norm(dim=-1)
    assert float(position.max()) < 0.5, name


MODELS = {
    'range-bearing': GaussianRangeBearing(sigma=0.1, sigma_bearing=0.05,
                                          max_range=8.0),
    'range-bearing student-t': StudentTRangeBearing(
        sigma=0.1, sigma_bearing=0.05, max_range=8.0),
    'gaussian': GaussianRange(sigma=0.1, max_range=8.0),
    'student-t': StudentTRange(sigma=0.1, max_range=8.0),
    'nlos': NLOSRange(sigma=0.1, max_range=8.0),
}


@pytest.mark.parametrize('model', list(MODELS))
@pytest.mark.parametrize('name', ['gbp-lag5', 'iekf-lag5',
                                  'iekf-incremental'])
def test_every_likelihood_on_every_smoother(name, model):
    # the circling robots measured by each likelihood of the library (the
    # data drawn from it): the smoothed estimates at most the filtered
    # ones' error (RMSE over both robots and every step, 10 % of slack
    # for a draw), both within 0.5 m and 0.25 rad of the truth
    data, motion, measurement = _circling(measurement=MODELS[model])
    tracker = TRACKERS[name](motion, measurement)
    rmse, heading = {}, {}
    for smoothed in (False, True):
        out = (Smoothed(tracker) if smoothed else tracker)(data, gen(1))
        error = (out.mean[:2, :, :2] - data.states[:2, :, :2]).norm(dim=-1)
        rmse[smoothed] = float(error.square().mean().sqrt())
        heading[smoothed] = float(angle_errors(out.mean[:2, :, 2],
                                               data.states[:2, :, 2]).max())
        assert float(error.max()) < 0.5, (name, model, smoothed)
        assert heading[smoothed] < 0.25, (name, model, smoothed)
    assert rmse[True] <= 1.1 * rmse[False], (name, model, rmse)


@pytest.mark.parametrize('lag', [1, 3])
def test_the_particles_of_hybrid_bp_stay_on_one_turn(lag):
    # the particles of one robot are drawn about the Gaussian's wrapped
    # report and from the last step's cloud: on one lift, never a turn
    # apart, so that their mean, covariance and density are the belief's;
    # their weighted mean follows the truth across the cut
    data, motion, measurement = _circling()
    tracker = HybridBP.recommended(lag=lag, motion=motion,
                                   measurement=measurement)
    for step in tracker.steps(data, gen(1)):
        heading = step.particles[:2, :, 2]
        assert float((heading.amax(-1) - heading.amin(-1)).max()) < math.pi
        weights = step.log_weights[:2].exp()
        mean = (weights.unsqueeze(-1) * step.particles[:2]).sum(1)
        truth = data.states[:2, step.t]
        assert float((mean[:, :2] - truth[:, :2]).norm(dim=-1).max()) < 0.5
        assert float(angle_errors(mean[:, 2], truth[:, 2]).max()) < 0.15


def test_a_wrapped_start_or_estimate_is_lifted_along_the_sequence():
    # the full smoother's estimates cross the cut wrapped; as a start, or
    # as the states whose cost is asked, they are the lifted track (numpy's
    # unwrap from the prior's heading), not a track that turns a whole turn
    # between two steps
    data, motion, measurement = _circling()
    smoother = CentralizedSmoother(None, motion=motion,
                                   measurement=measurement)
    wrapped = smoother(data).mean
    lifted = wrapped.clone()
    lifted[..., 2] = torch.from_numpy(np.unwrap(torch.cat([
        data.prior_mean[:, 2:].double(), wrapped[..., 2]], 1).numpy(),
        axis=1))[:, 1:]
    assert bool((lifted != wrapped).any())
    cost = float(smoother.sequence_cost(data, lifted))
    np.testing.assert_allclose(float(smoother.sequence_cost(data, wrapped)),
                               cost, rtol=1e-9)
    again = smoother.smoothed_from(data, wrapped)
    np.testing.assert_allclose(float(smoother.sequence_cost(
        data, again.mean)), cost, rtol=1e-9)
