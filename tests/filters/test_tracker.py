r"""The shared time loop's wrappers: :class:`~tg_nebp.filters.Smoothed`
reads and sets its smoother's use of the known inputs."""
import torch

from tg_nebp.datasets import Scenario
from tg_nebp.filters import FixedLagGaussianBP, Smoothed


def test_smoothed_ignores_the_inputs_when_told_as_its_smoother_does():
    # robots with odometry: the smoothed estimates without the inputs are
    # those of a smoother told to ignore them, and differ from those with
    scenario = Scenario.load('robots_train').replace(num_steps=6)
    data = scenario.generate(torch.Generator().manual_seed(0))

    def smoother():
        return FixedLagGaussianBP.recommended(
            lag=3, motion=scenario.motion_model,
            measurement=scenario.measurement_model)

    with_inputs = Smoothed(smoother())(data)
    blind = Smoothed(smoother())
    blind.use_control = False
    assert blind.tracker.use_control is False
    told = smoother()
    told.use_control = False
    expected = Smoothed(told)
    assert expected.use_control is False
    out = blind(data)
    assert torch.equal(out.mean, expected(data).mean)
    assert float((out.mean - with_inputs.mean).abs().max()) > 1e-3
