import math

import pytest
import torch

from tg_nebp.data import Realization
from tg_nebp.data.realization import position_dim_of
from tg_nebp.filters import (CentralizedSmoother, IncrementalSmoother,
                             Smoothed, TrackingSession)
from tg_nebp.models import StudentTRangeBearing, UnicycleOdometry

from helpers import (assert_batch_equals_alone,
                     assert_kalman_filter_and_smoother, assert_same_minimum,
                     assert_symmetric_positive_definite, gen,
                     linear_scenario, simulate_robots, stream_realization,
                     tiny_scenario)

#: Thresholds of zero and rounds enough to converge: every step is
#: relinearized until the chain's Gauss-Newton iterations stop moving.
CONVERGED = dict(relinearize_threshold=0.0, wildfire_threshold=0.0,
                 relinearizations=30, relinearize_skip=1, num_iterations=50,
                 tolerance=0.0)


def robots(steps=25, seed=0):
    # three robots driving arcs from one side of the cut at +-pi to the
    # other, two landmarks, Student-t range and bearing
    motion = UnicycleOdometry()
    measurement = StudentTRangeBearing(0.3, 0.05, 4.0, max_range=15.0)
    control = torch.tensor([0.4, 0.12]).repeat(3, steps, 1)
    start = torch.tensor([[2.0, 1.0, 3.0], [6.0, 3.0, -3.0],
                          [4.0, 7.0, 2.8]])
    data = simulate_robots(motion, measurement, control,
                           torch.tensor([[0.0, 0.0], [9.0, 8.0]]), start,
                           torch.tensor([0.3, 0.3, 0.1]), seed=seed)
    return data, dict(motion=motion, measurement=measurement)


def prefix(data, steps):
    # the realization of the first 'steps' steps of 'data'
    kept = data.edge_time < steps
    return Realization(
        states=data.states[:, :steps], control=data.control[:, :steps],
        position_dim=position_dim_of(data),
        edge_index=data.edge_index[:, kept], edge_attr=data.edge_attr[kept],
        edge_time=data.edge_time[kept], anchor=data.anchor,
        prior_mean=data.prior_mean, prior_cov=data.prior_cov,
        num_steps=steps, num_nodes=data.num_nodes)


def test_linear_gaussian_filtered_is_the_kalman_filter_smoothed_the_rts():
    # linear motion and measurements: the newest states after every step
    # are the Kalman filter's and the smoothed ones the Rauch-Tung-Striebel
    # smoother's, both written in the test (numpy, one measurement at a
    # time)
    scenario = linear_scenario(steps=6, num_agents=3)
    data = scenario.generate(gen(3))
    models = (scenario.motion_model, scenario.measurement_model)
    smoother = IncrementalSmoother(motion=models[0], measurement=models[1])
    assert_kalman_filter_and_smoother(smoother, data, *models)


@pytest.mark.parametrize('problem', ['ranges', 'robots'])
def test_converged_incremental_smoother_is_the_batch_smoother(problem):
    # a nonlinear problem (ranges from a wide prior; robots with headings
    # across the cut and a robust likelihood): relinearizing until nothing
    # moves reaches the batch smoother's maximum a posteriori trajectory
    # and its covariances
    if problem == 'ranges':
        data, models = tiny_scenario(steps=20).generate(gen(10)), {}
    else:
        data, models = robots()
    # (to the precision that the minimum is defined by: see
    # assert_same_minimum)
    batch = CentralizedSmoother(None, 50, tolerance=0.0, **models)(data)
    out = Smoothed(IncrementalSmoother(**CONVERGED, **models))(data)
    agents = ~data.anchor
    assert_same_minimum(out.mean[agents], out.cov[agents],
                        batch.mean[agents], batch.cov[agents])


def test_relinearization_reaches_what_the_first_linearization_misses():
    # linearized once at the filter's estimates (no step relinearized),
    # the trajectory is not the batch smoother's: the relinearization is
    # what closes the gap; the defaults (one round every 10 steps and at
    # the end) close more than half of it on this wide prior, rounds to
    # convergence all of it (to the precision that the minimum is defined
    # by: see assert_same_minimum)
    data = tiny_scenario(steps=20).generate(gen(12))
    agents = ~data.anchor
    batch = CentralizedSmoother(None, 50, tolerance=0.0)(data)

    def smoothed(**options):
        return Smoothed(IncrementalSmoother(**options))(data)

    def gap(**options):
        out = smoothed(**options)
        return float((out.mean[agents] - batch.mean[agents]).abs().max())

    frozen = gap(relinearize_threshold=1e9)
    default = gap()
    assert frozen > 1e-3
    assert default < 0.5 * frozen
    out = smoothed(**CONVERGED)
    assert_same_minimum(out.mean[agents], out.cov[agents],
                        batch.mean[agents], batch.cov[agents])


def test_filtered_estimate_is_the_map_of_the_steps_so_far():
    # each step's newest states are those of the batch smoother over the
    # steps up to it (the past relinearized), at convergence (to the
    # precision that the minimum is defined by: see assert_same_minimum)
    data, models = robots(steps=12, seed=3)
    smoother = IncrementalSmoother(**CONVERGED, **models)
    filtered = smoother(data)
    agents = ~data.anchor
    for t in (0, 4, 11):
        prefix_data = prefix(data, t + 1)
        batch = CentralizedSmoother(None, 50, tolerance=0.0,
                                    **models)(prefix_data)
        assert_same_minimum(filtered.mean[agents, t], filtered.cov[agents, t],
                            batch.mean[agents, t], batch.cov[agents, t])


def test_smoothing_helps_and_headings_stay_wrapped():
    data, models = robots(seed=5)
    smoother = IncrementalSmoother(**models)
    agents = ~data.anchor
    errors = {}
    for name, method in (('filtered', smoother),
                         ('smoothed', Smoothed(smoother))):
        out = method(data)
        errors[name] = float((out.mean[agents, :, :2] - data.states[
            agents, :, :2]).square().mean())
        assert bool((out.mean[..., 2].abs() <= math.pi).all())
        assert_symmetric_positive_definite(out.cov[agents])
    assert errors['smoothed'] < 0.8 * errors['filtered']


def test_incremental_smoother_of_a_batch_equals_each_alone():
    assert_batch_equals_alone(IncrementalSmoother(), rtol=1e-9, atol=1e-9)


def test_incremental_smoother_settings_and_errors():
    smoother = IncrementalSmoother(relinearize_skip=3)
    settings = smoother.settings()
    assert settings['lag'] is None and settings['incremental'] is True
    assert settings['relinearize_skip'] == 3
    for name in ('relinearize_threshold', 'wildfire_threshold'):
        with pytest.raises(ValueError, match=name):
            IncrementalSmoother(**{name: -1.0})
    for name in ('relinearizations', 'relinearize_skip'):
        with pytest.raises(ValueError, match=name):
            IncrementalSmoother(**{name: 0})


def test_a_resumed_session_continues_as_the_uninterrupted_one():
    # live: saved half-way and loaded by a fresh tracker (which rebuilds
    # the elimination from the saved history), every later step gives the
    # uninterrupted run's output and history bit for bit, the offsets of
    # the oldest steps included (the back-substitution stops before them,
    # so they are the saved ones, not recomputed: saved after step 16,
    # the first step resumed relinearizes nothing, and a rebuild that
    # recomputed or dropped those offsets would show there)
    data = tiny_scenario(steps=30).generate(gen(21))
    split = 17

    def session():
        return TrackingSession(IncrementalSmoother(wildfire_threshold=0.02,
                                                   relinearize_skip=3))

    whole, first = session(), session()
    with torch.no_grad():
        stream_realization(whole, data, steps=split)
        stream_realization(first, data, steps=split)
        resumed = session()
        resumed.load_state_dict(first.state_dict())
        for t in range(split, 30):
            a, = stream_realization(resumed, data, start=t, steps=t + 1)
            b, = stream_realization(whole, data, start=t, steps=t + 1)
            assert torch.equal(a.mean, b.mean) and torch.equal(a.cov, b.cov)
            for name, value in whole.state._asdict().items():
                other = getattr(resumed.state, name)
                for mine, theirs in zip(value, other) if isinstance(
                        value, tuple) else [(value, other)]:
                    torch.testing.assert_close(theirs, mine, rtol=0, atol=0,
                                               equal_nan=True,
                                               msg=f'{name} at step {t}')
