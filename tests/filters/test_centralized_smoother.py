import numpy as np
import pytest
import torch

from tg_nebp.filters import CentralizedIEKF, CentralizedSmoother, Smoothed

from helpers import (assert_batch_equals_alone,
                     assert_kalman_filter_and_smoother,
                     assert_symmetric_positive_definite, gen,
                     linear_rts_smoother, linear_scenario, tiny_scenario)


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
    # the last iterate), equal once the iterations have converged
    data = tiny_scenario(steps=6).generate(gen(5))
    iekf = CentralizedIEKF(50, tolerance=0.0)(data)
    smoother = CentralizedSmoother(1, 50, tolerance=0.0)(data)
    torch.testing.assert_close(smoother.mean, iekf.mean, rtol=0,
                               atol=1e-7)
    torch.testing.assert_close(smoother.cov, iekf.cov, rtol=0, atol=1e-7)


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
