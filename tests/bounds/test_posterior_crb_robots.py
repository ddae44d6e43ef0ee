r"""The posterior CRB of odometry-driven robots with range-bearing links
against an independent Fisher-information recursion written here: float64
numpy, the unicycle's and the range-bearing's Jacobians written out at the
true states, one joint information matrix over the agents."""
import math

import numpy as np
import torch

from tg_nebp.bounds import PosteriorCRB
from tg_nebp.datasets import Scenario

from helpers import gen


def _unicycle(state, control):
    # F = df/dx and G = df/du of the odometry step at a state and input
    _, _, theta = state
    d, turn = control
    heading = theta + turn / 2
    c, s = math.cos(heading), math.sin(heading)
    F = np.array([[1, 0, -d * s], [0, 1, d * c], [0, 0, 1.0]])
    G = np.array([[c, -d / 2 * s], [s, d / 2 * c], [0, 1.0]])
    return F, G


def _range_bearing(sender, receiver):
    # H of [range, bearing] with respect to [x_j, y_j, th_j, x_i, y_i, th_i]
    dx, dy = sender[0] - receiver[0], sender[1] - receiver[1]
    q = dx * dx + dy * dy
    d = math.sqrt(q)
    return np.array([[dx / d, dy / d, 0, -dx / d, -dy / d, 0],
                     [-dy / q, dx / q, 0, dy / q, -dx / q, -1.0]])


def test_bound_equals_an_independent_fisher_recursion():
    scenario = Scenario.load('robots_train').replace(num_steps=8)
    data = scenario.generate(gen(3))
    motion, measurement = scenario.motion_model, scenario.measurement_model
    params, noise = motion.params(), measurement.params()
    bound = PosteriorCRB(motion, measurement)(data).numpy()
    agents = np.flatnonzero(~data.anchor.numpy())
    index = {int(n): a for a, n in enumerate(agents)}
    count = len(agents)
    states = data.states.double().numpy()
    control = data.control.double().numpy()
    J = np.zeros((3 * count, 3 * count))
    for a, n in enumerate(agents):
        J[3 * a:3 * a + 3, 3 * a:3 * a + 3] = np.linalg.inv(
            data.prior_cov.double().numpy()[n])
    R = np.diag([noise['sigma']**-2, noise['sigma_bearing']**-2])
    previous = data.prior_mean.double().numpy()
    links = 0
    for t in range(scenario.num_steps):
        F = np.zeros_like(J)
        Q = np.zeros_like(J)
        for a, n in enumerate(agents):
            f, g = _unicycle(previous[n], control[n, t])
            d, turn = control[n, t]
            m = np.diag([params['sigma_distance']**2 +
                         (params['distance_scale'] * d)**2,
                         params['sigma_turn']**2 +
                         (params['turn_scale'] * turn)**2 +
                         (params['turn_per_distance'] * d)**2])
            F[3 * a:3 * a + 3, 3 * a:3 * a + 3] = f
            Q[3 * a:3 * a + 3, 3 * a:3 * a + 3] = g @ m @ g.T
        J = np.linalg.inv(Q + F @ np.linalg.inv(J) @ F.T)
        for e in np.flatnonzero(data.edge_time.numpy() == t):
            j, i = (int(v) for v in data.edge_index[:, e])
            H = _range_bearing(states[j, t], states[i, t])
            info = H.T @ R @ H
            rows = [3 * index[i] + k for k in range(3)]
            J[np.ix_(rows, rows)] += info[3:, 3:]
            if j in index:
                other = [3 * index[j] + k for k in range(3)]
                J[np.ix_(other, other)] += info[:3, :3]
                J[np.ix_(other, rows)] += info[:3, 3:]
                J[np.ix_(rows, other)] += info[3:, :3]
            links += 1
        cov = np.linalg.inv(J)
        for a, n in enumerate(agents):
            assert np.allclose(bound[n, t], cov[3 * a:3 * a + 3,
                                                3 * a:3 * a + 3],
                               rtol=1e-8, atol=1e-12)
        previous = states[:, t]
    assert links > 0
    assert np.all(bound[data.anchor.numpy()] == 0)
