import numpy as np
import pytest
import torch
from scipy.optimize import minimize

from tg_nebp.datasets import Scenario
from tg_nebp.filters import CentralizedIEKF
from tg_nebp.gaussian import block_diagonal
from tg_nebp.models import NLOSRange, StudentTRange

from helpers import (assert_batch_equals_alone,
                     assert_symmetric_positive_definite, gen,
                     linear_kalman_filter, linear_scenario, tiny_scenario)


def test_linear_gaussian_iekf_is_the_kalman_filter():
    # linear motion and measurements: one Gauss-Newton step solves the
    # update exactly, and the filter is a Kalman filter (written
    # independently: numpy, one measurement at a time, Joseph form)
    scenario = linear_scenario(steps=5, num_agents=4)
    data = scenario.generate(gen(3))
    means, covs, agents = linear_kalman_filter(
        data, scenario.motion_model, scenario.measurement_model)
    out = CentralizedIEKF(motion=scenario.motion_model,
                          measurement=scenario.measurement_model)(data)
    np.testing.assert_allclose(out.mean[agents].numpy(), means, rtol=1e-9,
                               atol=1e-9)
    np.testing.assert_allclose(out.cov[agents].numpy(), covs, rtol=1e-9,
                               atol=1e-12)
    anchors = data.anchor
    torch.testing.assert_close(out.mean[anchors],
                               data.prior_mean[anchors].double()
                               .unsqueeze(1).expand(-1, 5, -1))
    assert out.cov[anchors].abs().max() == 0


@pytest.mark.parametrize('measurement', [None, StudentTRange(nu=3.0),
                                         NLOSRange()])
def test_update_reaches_the_map_of_scipy(measurement):
    # one update with many Gauss-Newton iterations against scipy's BFGS on
    # the same cost: the prior's quadratic form minus the model's own
    # log-likelihood of every range
    scenario = tiny_scenario(steps=1)
    data = scenario.generate(gen(7))
    iekf = CentralizedIEKF(num_iterations=50, measurement=measurement)
    agents = (~data.anchor).nonzero().view(-1)
    index = torch.full((data.num_nodes, ), -1)
    index[agents] = torch.arange(agents.numel())
    mean, cov = iekf.predict(data.prior_mean.double()[agents],
                             block_diagonal(data.prior_cov.double()[agents]))
    src, dst = data.edge_index
    known = data.prior_mean.double()[src]
    z = data.edge_attr.double()
    state, _ = iekf.update(mean, cov, z, index[src], index[dst], known)

    info = torch.linalg.inv(cov)
    model = iekf.measurement

    def cost(x):
        x = torch.from_numpy(x).view_as(mean)
        offset = (x - mean).reshape(-1)
        sender = torch.where((index[src] >= 0).view(-1, 1),
                             x[index[src].clamp_min(0)], known)
        distances = (sender[:, :2] - x[index[dst], :2]).norm(dim=-1)
        log_lik = model.log_likelihood_of_distance(z, distances.view(-1, 1))
        return float(0.5 * offset @ info @ offset - log_lik.sum())

    found = minimize(cost, mean.numpy().ravel(), method='BFGS',
                     options=dict(gtol=1e-10, maxiter=10_000))
    assert cost(state.numpy().ravel()) <= found.fun + 1e-7
    np.testing.assert_allclose(state.numpy().ravel(), found.x, atol=1e-4)


def test_batch_equals_each_graph_alone():
    assert_batch_equals_alone(CentralizedIEKF(marginal=True))


def test_marginal_drops_the_cross_covariances():
    # two agents that measure each other: the joint filter's next
    # prediction keeps their correlation, the marginal one forgets it, so
    # their second updates differ while their first ones agree
    scenario = tiny_scenario(steps=2)
    data = scenario.generate(gen(5))
    joint = list(CentralizedIEKF().steps(data))
    marginal = list(CentralizedIEKF(marginal=True).steps(data))
    torch.testing.assert_close(joint[0].mean, marginal[0].mean)
    torch.testing.assert_close(joint[0].cov, marginal[0].cov)
    assert not torch.allclose(joint[1].cov, marginal[1].cov)


def test_covariances_are_symmetric_positive_definite():
    data = Scenario.load('paper_test').replace(
        num_agents=20, num_steps=3).generate(gen(0))
    out = CentralizedIEKF(measurement=NLOSRange())(data)
    assert_symmetric_positive_definite(out.cov[~data.anchor], atol=1e-12)


def test_refuses_a_joint_that_does_not_fit(monkeypatch):
    import tg_nebp.gaussian as gaussian
    monkeypatch.setattr(gaussian, 'free_memory_bytes', lambda device: 2**20)
    data = tiny_scenario(steps=1).replace(num_agents=60).generate(gen(0))
    with pytest.raises(ValueError, match='the centralized IEKF of a graph '
                       'of 60 agents needs dense 240 x 240'):
        next(CentralizedIEKF().steps(data))


def test_options_are_checked():
    with pytest.raises(TypeError, match="'marginal' must be a bool"):
        CentralizedIEKF(marginal=1)
    with pytest.raises(ValueError, match="'num_iterations' must be "
                       "positive"):
        CentralizedIEKF(num_iterations=0)
    assert CentralizedIEKF(marginal=True).settings()['marginal'] is True
