import math

import numpy as np
import pytest
import torch

from tg_nebp.bounds import PosteriorCRB
from tg_nebp.data import Realization
from tg_nebp.datasets import Scenario
from tg_nebp.models import ConstantVelocity, GaussianRange

from helpers import (assert_batch_equals_alone, gen, linear_kalman_filter,
                     linear_rts_smoother, linear_scenario, tiny_scenario)


def test_linear_gaussian_bound_is_the_kalman_covariance():
    # linear motion and measurements with Gaussian noise: the bound is
    # attained, and equals the covariance of a Kalman filter written
    # independently (numpy, one measurement at a time, Joseph form)
    scenario = linear_scenario(steps=5, num_agents=4)
    data = scenario.generate(gen(3))
    _, covs, agents = linear_kalman_filter(data, scenario.motion_model,
                                           scenario.measurement_model)
    bound = PosteriorCRB(scenario.motion_model,
                         scenario.measurement_model)(data)
    np.testing.assert_allclose(bound[agents].numpy(), covs, rtol=1e-9,
                               atol=1e-12)
    assert bound[data.anchor].abs().max() == 0


def static_three_anchors(steps):
    # one agent that does not move (no driving noise, a prior velocity of
    # 1e-6 m/s spread), a flat prior on its position, three anchors
    anchors = ((0.0, 0.0), (20.0, 0.0), (5.0, 15.0))
    agent = torch.tensor([7.0, 4.0], dtype=torch.float64)
    states = torch.cat([agent, torch.zeros(2, dtype=torch.float64)])
    nodes = torch.cat([states.view(1, 4), torch.tensor(
        [[x, y, 0.0, 0.0] for x, y in anchors], dtype=torch.float64)])
    edge_index = torch.tensor([[1, 2, 3] * steps, [0, 0, 0] * steps])
    distances = (nodes[1:, :2] - agent).norm(dim=-1)
    data = Realization(
        states=nodes.unsqueeze(1).expand(-1, steps, -1).clone(),
        edge_index=edge_index,
        edge_attr=distances.repeat(steps).view(-1, 1),
        edge_time=torch.arange(steps).repeat_interleave(3),
        anchor=torch.tensor([False, True, True, True]),
        prior_mean=nodes.clone(),
        prior_cov=torch.diag_embed(torch.tensor(
            [[1e8, 1e8, 1e-12, 1e-12]] + [[0.0] * 4] * 3,
            dtype=torch.float64)),
        num_steps=steps, num_nodes=4)
    unit = (nodes[1:, :2] - agent) / distances.view(-1, 1)
    return data, unit


@pytest.mark.parametrize('steps', [1, 4])
def test_static_agent_with_three_anchors_is_the_closed_form(steps):
    # the classic geometric bound: after T looks at three anchors through
    # ranges of variance sigma^2, (T sum_k u_k u_k^T / sigma^2)^-1
    sigma = 0.7
    data, unit = static_three_anchors(steps)
    bound = PosteriorCRB(ConstantVelocity(sigma_a=0.0),
                         GaussianRange(sigma))(data)
    closed = torch.linalg.inv(steps * unit.t() @ unit / sigma**2)
    np.testing.assert_allclose(bound[0, -1, :2, :2].numpy(),
                               closed.numpy(), rtol=1e-6)


def test_batch_equals_each_graph_alone():
    assert_batch_equals_alone(PosteriorCRB(), fields=None, rtol=1e-12,
                              atol=1e-14)


def test_generic_fisher_information_gives_the_same_bound():
    # a range model that keeps GaussianRange's formula but not its
    # closed-form information gets the Monte Carlo of its squared score
    class Plain(GaussianRange, name='test-plain-gaussian'):
        def log_likelihood_of_distance(self, z, distances):
            return super().log_likelihood_of_distance(z, distances)

    Plain.fisher_samples = 4000
    data = tiny_scenario(steps=3).generate(gen(4))
    exact = PosteriorCRB()(data)
    sampled = PosteriorCRB(measurement=Plain())(data, gen(5))
    agents = ~data.anchor
    # 4,000 draws per link: the information's relative error is about
    # sqrt(2 / 4000) = 2 %, the bound's variances' less (links add up)
    variances = [b[agents].diagonal(dim1=-2, dim2=-1)
                 for b in (sampled, exact)]
    torch.testing.assert_close(*variances, rtol=0.03, atol=0)


def test_needs_true_states_and_a_gaussian_motion_form():
    data = tiny_scenario(steps=2).generate(gen(0))
    del data.states
    with pytest.raises(ValueError, match="true 'states'"):
        PosteriorCRB()(data)

    from tg_nebp.models import MotionModel

    class Jump(MotionModel, name='test-jump'):
        def params(self):
            return {}

        def sample(self, states, generator=None):
            return states

    with pytest.raises(NotImplementedError, match='additive-Gaussian'):
        PosteriorCRB(Jump())(tiny_scenario(steps=2).generate(gen(0)))


def test_refuses_a_joint_that_does_not_fit(monkeypatch):
    import tg_nebp.gaussian as gaussian
    monkeypatch.setattr(gaussian, 'free_memory_bytes',
                        lambda device: 5 * 2**20)
    data = Scenario.load('paper_test').replace(num_steps=1).generate(gen(0))
    with pytest.raises(ValueError, match=r'100 agents needs dense 400 x 400'
                       r'.*runs up to about 82 agents'):
        next(PosteriorCRB().steps(data))


def test_bound_grows_without_measurements():
    # no links at a step: the bound is the prediction's covariance
    data, _ = static_three_anchors(2)
    data.edge_time = torch.zeros_like(data.edge_time)
    motion = ConstantVelocity(sigma_a=0.3)
    bound = PosteriorCRB(motion, GaussianRange())(data)
    state = torch.zeros(1, 4, dtype=torch.float64)
    F, Q = motion.jacobian(state)[0], motion.noise_covariance(state)[0]
    expected = F @ bound[0, 0] @ F.t() + Q
    torch.testing.assert_close(bound[0, 1], expected, rtol=1e-9, atol=1e-12)
    assert math.isclose(float(torch.linalg.det(bound[0, 1, :2, :2])),
                        float(torch.linalg.det(expected[:2, :2])),
                        rel_tol=1e-9)


@pytest.mark.parametrize('lag', [2, 3, None])
def test_linear_gaussian_smoothing_bound_is_the_rts_covariance(lag):
    # linear-Gaussian: the smoothing bound at a lag (and of the whole
    # sequence) is the covariance of a Rauch-Tung-Striebel smoother
    # written in the test over the Kalman filter's joints
    scenario = linear_scenario(steps=6, num_agents=3)
    data = scenario.generate(gen(3))
    _, covs, agents = linear_rts_smoother(data, scenario.motion_model,
                                          scenario.measurement_model, lag)
    bound = PosteriorCRB(scenario.motion_model, scenario.measurement_model,
                         lag=lag)
    steps = list(bound.steps(data))
    assert [s.t for s in steps] == list(range(6))  # in order
    out = torch.stack([s.cov for s in steps], 1)
    np.testing.assert_allclose(out[agents].numpy(), covs, rtol=1e-9,
                               atol=1e-12)
    assert out[data.anchor].abs().max() == 0


def test_smoothing_bound_is_never_above_the_filtering_bound():
    # ranges (nonlinear): more measurements never raise the floor, step by
    # step and agent by agent; a longer lag never raises it either, and
    # the last step of a sequence has nothing later
    data = tiny_scenario(steps=6).generate(gen(2))
    agents = ~data.anchor
    floors = {}
    for lag in (1, 2, 4, None):
        cov = PosteriorCRB(lag=lag)(data)[agents][..., :2, :2]
        floors[lag] = cov.diagonal(dim1=-2, dim2=-1).sum(-1)
    tight = 1e-12
    assert bool((floors[2] <= floors[1] + tight).all())
    assert bool((floors[4] <= floors[2] + tight).all())
    assert bool((floors[None] <= floors[4] + tight).all())
    assert bool((floors[2] < floors[1] - 1e-6).any())
    torch.testing.assert_close(floors[None][:, -1], floors[1][:, -1])


def test_smoothing_bound_of_a_batch_equals_each_alone():
    assert_batch_equals_alone(PosteriorCRB(lag=3), fields=None, rtol=1e-12,
                              atol=1e-12)


def test_smoothing_bound_refuses_a_lag_below_one():
    with pytest.raises(ValueError, match="'lag' must be positive"):
        PosteriorCRB(lag=0)
    with pytest.raises(TypeError, match="'lag' must be an integer"):
        PosteriorCRB(lag=2.5)
