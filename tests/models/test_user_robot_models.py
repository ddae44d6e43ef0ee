r"""A user's own robot models (:mod:`user_robot`, a file no library module
knows) in every method and the bound: a linear model with a known input
against a Kalman filter written in the tests, and a unicycle driven by
measured velocities with range-bearing links, tracked by every method,
live and offline alike."""
import math

import numpy as np
import pytest
import torch

from tg_nebp.bounds import PosteriorCRB
from tg_nebp.data import Realization
from tg_nebp.filters import (CentralizedIEKF, GaussianBP, GaussianNEBP,
                             ParticleBP, TrackingSession)
from tg_nebp.metrics import angle_errors
from tg_nebp.models import GaussianRangeBearing

from helpers import (gen, linear_kalman_filter, linear_offset_model,
                     randomize, simulate_robots)
from user_robot import LinearInput, VelocityUnicycle


def _linear_realization(links, steps=5, seed=0):
    # three agents and an anchor with the links given ((sender, receiver)
    # every step), states [x, y, b] moved by known inputs (one step's
    # input missing: the input-free prediction) and measured by the
    # linear offset model
    motion, measurement = LinearInput(), linear_offset_model()(0.3)
    g = gen(seed)
    count = 3
    control = 0.5 * torch.randn(count, steps, 2, dtype=torch.float64,
                                generator=g)
    control[1, 2] = math.nan
    start = torch.randn(count, 3, dtype=torch.float64, generator=g) * 3
    anchor_state = torch.zeros(1, 3, dtype=torch.float64)
    state, states, attr, index, times = start, [], [], [], []
    edges = torch.tensor(links).t()
    for t in range(steps):
        state = motion.sample(state, g, control=control[:, t])
        every = torch.cat([state, anchor_state])
        states.append(every)
        attr.append(measurement.sample_features(every[edges[0]],
                                                every[edges[1]], None,
                                                edges, g))
        index.append(edges)
        times.append(torch.full((edges.size(1), ), t))
    prior_cov = torch.diag_embed(torch.tensor(
        [1.0, 1.0, 0.5], dtype=torch.float64).expand(4, 3)).clone()
    prior_cov[3] = 0
    data = Realization(
        states=torch.stack(states, 1), edge_index=torch.cat(index, 1),
        edge_attr=torch.cat(attr), edge_time=torch.cat(times),
        anchor=torch.tensor([False, False, False, True]),
        prior_mean=torch.cat([start + 0.5, anchor_state]),
        prior_cov=prior_cov, num_steps=steps, num_nodes=4,
        control=torch.cat([control, torch.full((1, steps, 2), math.nan,
                                               dtype=torch.float64)]),
        position_dim=2)
    return data, motion, measurement


def test_iekf_with_a_known_input_equals_a_kalman_filter():
    # a cycle of links: the joint matters
    data, motion, measurement = _linear_realization(
        [(3, 0), (0, 1), (1, 2), (2, 0), (3, 2)])
    means, covs, agents = linear_kalman_filter(data, motion, measurement)
    out = CentralizedIEKF(motion=motion, measurement=measurement)(data)
    assert np.allclose(out.mean[agents].numpy(), means, atol=1e-9)
    assert np.allclose(out.cov[agents].numpy(), covs, atol=1e-9)


def test_gaussian_bp_on_a_tree_equals_a_kalman_filter_of_marginals():
    # a tree every step, independent priors: Gaussian BP's beliefs are the
    # exact marginals of each step, what a Kalman filter that drops the
    # cross-agent covariances after each step holds
    data, motion, measurement = _linear_realization([(3, 0), (0, 1), (1, 2)])
    means, covs, agents = linear_kalman_filter(data, motion, measurement,
                                               marginal=True)
    out = GaussianBP(num_iterations=10, tolerance=None, motion=motion,
                     measurement=measurement)(data)
    assert np.allclose(out.mean[agents].numpy(), means, atol=1e-9)
    assert np.allclose(out.cov[agents].numpy(), covs, atol=1e-9)
    marginal = CentralizedIEKF(motion=motion, measurement=measurement,
                               marginal=True)(data)
    assert np.allclose(marginal.mean[agents].numpy(), means, atol=1e-9)


def _robots(seed=0, steps=12):
    motion = VelocityUnicycle()
    measurement = GaussianRangeBearing(sigma=0.1, sigma_bearing=0.05,
                                       max_range=6.0)
    g = gen(seed)
    count = 4
    control = torch.stack([
        0.3 + 0.1 * torch.rand(count, steps, dtype=torch.float64,
                               generator=g),
        0.2 * torch.randn(count, steps, dtype=torch.float64, generator=g),
        torch.full((count, steps), 0.5, dtype=torch.float64)], -1)
    control[2, 3] = math.nan  # a step without input
    start = torch.cat([4 * torch.rand(count, 2, dtype=torch.float64,
                                      generator=g),
                       torch.rand(count, 1, dtype=torch.float64,
                                  generator=g) * 6 - 3], 1)
    anchors = torch.tensor([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0],
                            [5.0, 5.0]], dtype=torch.float64)
    data = simulate_robots(motion, measurement, control, anchors, start,
                           [0.04, 0.04, 0.01], seed=seed + 1)
    return data, motion, measurement


def _trackers(motion, measurement):
    return {
        'iekf': CentralizedIEKF(motion=motion, measurement=measurement),
        'gbp': GaussianBP.recommended(motion=motion,
                                      measurement=measurement),
        'bp': ParticleBP.recommended(num_particles=300, motion=motion,
                                     measurement=measurement),
        'gnebp': randomize(GaussianNEBP.recommended(
            hidden_dim=8, motion=motion, measurement=measurement), seed=5,
            scale=0.1),
    }


def test_a_users_robot_runs_in_every_method_and_the_bound():
    data, motion, measurement = _robots()
    bound = PosteriorCRB(motion, measurement)(data)
    agents = ~data.anchor
    floor = bound[agents][..., :2, :2].diagonal(
        dim1=-2, dim2=-1).sum(-1).mean().sqrt()
    assert 0 < float(floor) < 0.2
    for name, tracker in _trackers(motion, measurement).items():
        out = tracker(data, gen(2))
        error = (out.mean[agents, :, :2] -
                 data.states[agents, :, :2]).norm(dim=-1)
        rmse = float(error.square().mean().sqrt())
        # every method tracks: within a few times the floor
        assert rmse < 4 * float(floor), (name, rmse, float(floor))
        # the reported headings wrapped, their errors small
        heading = out.mean[agents, :, 2]
        assert bool(((heading > -math.pi) & (heading <= math.pi)).all())
        assert float(angle_errors(heading, data.states[agents, :, 2]).max()
                     ) < 0.2, name
        cov = out.cov[agents].double()
        assert torch.allclose(cov, cov.transpose(-1, -2))
        assert float(torch.linalg.eigvalsh(cov).min()) > 0


@pytest.mark.parametrize('name', ['iekf', 'gbp', 'bp'])
def test_a_users_robot_streams_live_as_offline(name):
    data, motion, measurement = _robots(steps=5)
    tracker = _trackers(motion, measurement)[name]
    offline = list(tracker.steps(data, gen(3)))
    agents = (~data.anchor).nonzero().view(-1).tolist()
    session = TrackingSession(tracker, generator=gen(3), dtype=torch.float64)
    from tg_nebp.filters import AgentPrior, AnchorAt
    join = {}
    for i in range(data.num_nodes):
        join[i] = (AnchorAt(data.prior_mean[i, :2].tolist())
                   if bool(data.anchor[i]) else
                   AgentPrior(data.prior_mean[i].tolist(),
                              data.prior_cov[i].tolist()))
    for t, ((edge_index, edge_attr), control) in enumerate(zip(
            data.edges_by_step(), data.controls_by_step())):
        given = {i: control[i].tolist() for i in agents
                 if not bool(torch.isnan(control[i]).any())}
        out = session.update(edge_index.t().tolist(), edge_attr.tolist(),
                             join=join if t == 0 else None, control=given)
        assert torch.equal(out.mean, offline[t].mean)
        assert torch.equal(out.cov, offline[t].cov)
