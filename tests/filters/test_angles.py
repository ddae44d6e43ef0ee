r"""Headings across the cut at :math:`\pm \pi`: a robot that drives in
circles is tracked by every method without a jump of a turn in its
estimate's error, and every reported heading is wrapped."""
import math

import pytest
import torch

from tg_nebp.filters import (CentralizedIEKF, GaussianBP, GaussianNEBP,
                             ParticleBP)
from tg_nebp.metrics import angle_errors
from tg_nebp.models import GaussianRangeBearing, UnicycleOdometry

from helpers import gen, randomize, simulate_robots


def _circling(steps=40):
    # two robots on circles of 2 m radius, starting just below +pi and
    # just above -pi, turning both ways: both headings cross the cut
    motion = UnicycleOdometry()
    measurement = GaussianRangeBearing(sigma=0.1, sigma_bearing=0.05,
                                       max_range=8.0)
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
}


@pytest.mark.parametrize('name', list(TRACKERS))
def test_a_heading_across_the_cut(name):
    data, motion, measurement = _circling()
    truth = data.states[:2, :, 2]
    # the true headings cross the cut (a jump of about a turn, wrapped)
    assert bool((truth.diff(dim=1).abs() > math.pi).any(-1).all())
    out = TRACKERS[name](motion, measurement)(data, gen(1))
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
