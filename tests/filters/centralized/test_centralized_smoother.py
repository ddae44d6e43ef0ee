import math

import numpy as np
import pytest
import torch

from tg_nebp.filters import CentralizedIEKF, CentralizedSmoother, Smoothed
from tg_nebp.gaussian import GraphLayout

from helpers import (assert_batch_equals_alone,
                     assert_kalman_filter_and_smoother, assert_same_minimum,
                     assert_symmetric_positive_definite, gen,
                     linear_rts_smoother, linear_scenario, mirror,
                     tiny_scenario)


def linear_problem(steps=6):
    scenario = linear_scenario(steps=steps, num_agents=3)
    return scenario, scenario.generate(gen(3))


@pytest.mark.parametrize('lag', [2, 4])
def test_linear_gaussian_fixed_lag_smoother_is_the_rts_smoother(lag):
    # linear motion and measurements: one Gauss-Newton step solves every
    # window exactly, so the newest state is the Kalman filter's and each
    # step's estimate at the lag is a Rauch-Tung-Striebel smoother's, both
    # written in the test (numpy, one measurement at a time)
    scenario, data = linear_problem()
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    smoother = CentralizedSmoother(lag, **models)
    assert_kalman_filter_and_smoother(smoother, data, *models.values(), lag)
    # every step's window: the revised estimates of the last steps
    window = list(smoother.steps(data))[3]
    assert window.window_mean.shape == (data.num_nodes, lag, 4)
    torch.testing.assert_close(window.window_mean[:, -1], window.mean)


def test_linear_gaussian_full_smoother_is_the_rts_smoother():
    scenario, data = linear_problem()
    models = (scenario.motion_model, scenario.measurement_model)
    means, covs, agents = linear_rts_smoother(data, *models)
    out = CentralizedSmoother(None, motion=models[0],
                              measurement=models[1])(data)
    np.testing.assert_allclose(out.mean[agents].numpy(), means, rtol=1e-9,
                               atol=1e-9)
    np.testing.assert_allclose(out.cov[agents].numpy(), covs, rtol=1e-9,
                               atol=1e-12)
    # anchors: known, zero covariance
    assert out.cov[data.anchor].abs().max() == 0
    # the full smoother's steps are smoothed already: Smoothed passes them
    again = Smoothed(CentralizedSmoother(None, motion=models[0],
                                         measurement=models[1]))(data)
    torch.testing.assert_close(again.mean, out.mean)


def test_one_step_window_is_the_iekf():
    # ranges: a window of one step is the IEKF's Gauss-Newton update; the
    # step handed on is the filtered mean at the solution (the IEKF keeps
    # the last iterate), equal once the iterations have converged (to the
    # precision that the minimum is defined by: see assert_same_minimum);
    # the anchors' known states copied, bit for bit
    data = tiny_scenario(steps=6).generate(gen(5))
    iekf = CentralizedIEKF(50, tolerance=0.0)(data)
    smoother = CentralizedSmoother(1, 50, tolerance=0.0)(data)
    agents, anchors = ~data.anchor, data.anchor
    assert_same_minimum(smoother.mean[agents], smoother.cov[agents],
                        iekf.mean[agents], iekf.cov[agents])
    assert torch.equal(smoother.mean[anchors], iekf.mean[anchors])
    assert torch.equal(smoother.cov[anchors], iekf.cov[anchors])


def test_smoothing_ranges_helps_and_stays_consistent():
    # ranges: the smoothed estimates are closer to the truth than the
    # filtered ones over a few realizations, and the full smoother's
    # covariance stays symmetric positive definite
    errors = {'filtered': 0.0, 'smoothed': 0.0}
    for seed in range(3):
        data = tiny_scenario(steps=8).generate(gen(10 + seed))
        agents = ~data.anchor
        smoother = CentralizedSmoother(4)
        for name, method in (('filtered', smoother),
                             ('smoothed', Smoothed(smoother))):
            out = method(data)
            errors[name] += float((out.mean[agents, :, :2] - data.states[
                agents, :, :2]).square().sum())
        full = CentralizedSmoother(None)(data)
        assert_symmetric_positive_definite(full.cov[agents])
    assert errors['smoothed'] < 0.8 * errors['filtered']


def test_smoother_of_a_batch_equals_each_alone():
    assert_batch_equals_alone(CentralizedSmoother(3), rtol=1e-9, atol=1e-9)
    assert_batch_equals_alone(CentralizedSmoother(None), rtol=1e-9,
                              atol=1e-9)


def test_smoother_settings_and_errors():
    smoother = CentralizedSmoother(3)
    assert smoother.settings()['lag'] == 3
    with pytest.raises(ValueError, match="'lag' must be positive"):
        CentralizedSmoother(0)
    with pytest.raises(NotImplementedError, match='does not run live'):
        smoother.initial_state(tiny_scenario().generate(gen(0)))


def test_the_whole_sequence_smoother_iterates_to_its_tolerance_by_default():
    # every step of a whole sequence moves at once: 3 Gauss-Newton
    # iterations leave this wide-prior sequence more than a millimetre
    # from its optimum; the default (up to 50, stopping at a step of 1e-6)
    # reaches it to the size of its last step
    data = tiny_scenario(steps=20).generate(gen(12))
    agents = ~data.anchor
    optimum = CentralizedSmoother(None, 200, tolerance=0.0)(data)

    def gap(**options):
        out = CentralizedSmoother(None, **options)(data)
        return float((out.mean[agents] - optimum.mean[agents]).abs().max())

    assert gap(num_iterations=3) > 1e-3
    assert gap() < 1e-5
    assert CentralizedSmoother(None).num_iterations == 50
    assert CentralizedSmoother(4).num_iterations == 5


def test_the_whole_sequence_from_a_start_is_that_start_s_optimum():
    # linear-Gaussian: one optimum, reached from any start (the RTS
    # smoother's means), its own solution a fixed point
    scenario, data = linear_problem()
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    means, _, agents = linear_rts_smoother(data, models['motion'],
                                           models['measurement'])
    smoother = CentralizedSmoother(None, **models)
    far = data.states.double() + 3.0
    out = smoother.smoothed_from(data, far)
    np.testing.assert_allclose(out.mean[agents].numpy(), means, rtol=1e-7,
                               atol=1e-7)
    # a mirror: from its filter the smoother keeps the mirror its prior
    # put the agent on; from the truth it finds the true optimum
    data, models = mirror((20.0, 1.5), steps=12, third_from=0, velocity=0.3)
    smoother = CentralizedSmoother(None, **models)
    filtered_start = smoother(data)
    fixed = smoother.smoothed_from(data, filtered_start.mean)
    # (to the iterations' tolerance, 1e-6: they stop once a step moves
    # no more than that)
    torch.testing.assert_close(fixed.mean, filtered_start.mean, rtol=0,
                               atol=1e-6)
    truth = data.states[0, :, :2].double()
    assert float((filtered_start.mean[0, :, :2] - truth).norm(
        dim=-1).min()) > 8
    found = smoother.smoothed_from(data, data.states)
    assert float((found.mean[0, :, :2] - truth).norm(dim=-1).max()) < 2


def test_a_start_is_checked():
    data, models = mirror(steps=4)
    smoother = CentralizedSmoother(None, **models)
    with pytest.raises(ValueError, match="'start' must be a tensor of shape"):
        smoother.smoothed_from(data, data.states[:, :3])
    with pytest.raises(ValueError, match="'start' must be finite"):
        smoother.smoothed_from(data, torch.full_like(data.states, math.nan))
    with pytest.raises(ValueError, match='needs lag=None'):
        CentralizedSmoother(3, **models).smoothed_from(data, data.states)


def test_a_start_off_the_motion_model_s_trajectories_is_followed():
    # a filter's estimates lie off the constant-velocity model's
    # trajectories (its singular noise moves a position only together
    # with its velocity): here the truth's positions with every velocity
    # zero. The iterations start from the trajectory that follows them,
    # on the model's trajectories; the given states' own noises, rolled
    # out, add their errors up to metres
    data, models = mirror(velocity=0.3, steps=40)
    smoother = CentralizedSmoother(None, **models)
    start = data.states.double().clone()
    start[..., 2:] = 0.0
    _, slots, (points, ) = smoother._problem(data, GraphLayout.of(data), [
        [[state[:1].unsqueeze(0)] for state in start.unbind(1)]])[0]
    factors = smoother._noise_factors(slots, points)
    states, noises = smoother._followed(slots, points, factors)
    # on the model's trajectory: its own moves give back its noises, as
    # the cost reads them
    torch.testing.assert_close(torch.stack(smoother._noises(
        slots, states, factors)), torch.stack(noises), rtol=0, atol=1e-9)
    # within 0.75 m of the given positions throughout (the positions move
    # 0.3 m a step, the velocities say 0: the trajectory settles two
    # steps' moves behind); the open roll-out drifts off
    def gap(rolled):
        return float((torch.stack(rolled)[..., :2] - torch.stack(points)[
            ..., :2]).norm(dim=-1).max())
    assert gap(states) < 0.75
    assert gap(smoother._rolled_out(slots, points[0], smoother._noises(
        slots, points, factors), factors)) > 5.0
    # a start on the model's trajectories (the truth, moving evenly) is
    # kept (to the float32 rounding of the realization's states)
    truth = [state[:1] for state in data.states.double().unbind(1)]
    followed, _ = smoother._followed(slots, truth, smoother._noise_factors(
        slots, truth))
    torch.testing.assert_close(torch.stack(followed), torch.stack(truth),
                               rtol=0, atol=1e-5)
