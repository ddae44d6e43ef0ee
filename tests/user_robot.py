r"""A user's own robot models, in a file of their own that no library file
knows (imported by the tests that use them): a unicycle driven by measured
velocities and the step's duration (additive noise on the state, unlike
the library's odometry model), and a linear model with a known input for
the Kalman filter checks."""
import math

import torch

from tg_nebp.models import MotionModel, StateLayout


class VelocityUnicycle(MotionModel, name='test-velocity-unicycle'):
    r"""State :math:`[x, y, \theta]`, input :math:`[v, \omega, \Delta]`
    (speed, turn rate, the step's duration): an Euler step plus Gaussian
    noise of :math:`\sigma^2 \Delta` per entry; no input: no move, noise
    of one second."""
    state_dim = 3
    control_dim = 3

    def __init__(self, sigma_position=0.05, sigma_heading=0.02):
        self.sigma_position = sigma_position
        self.sigma_heading = sigma_heading

    def params(self):
        return dict(sigma_position=self.sigma_position,
                    sigma_heading=self.sigma_heading)

    def layout(self, size):
        return StateLayout(size, 2, (2, ))

    def _given(self, states, control):
        if control is None:
            control = states.new_full(states.shape[:-1] + (3, ), math.nan)
        control = torch.broadcast_to(control.to(states.dtype),
                                     states.shape[:-1] + (3, ))
        missing = torch.isnan(control).any(-1, keepdim=True)
        return torch.where(missing, 0.0, control), missing

    def mean(self, states, control=None):
        v, w, dt = self._given(states, control)[0].unbind(-1)
        return torch.stack([states[..., 0] + v * dt * torch.cos(
            states[..., 2]), states[..., 1] + v * dt * torch.sin(
                states[..., 2]), states[..., 2] + w * dt], -1)

    def noise_covariance(self, states, control=None):
        given, missing = self._given(states, control)
        dt = torch.where(missing[..., 0], 1.0, given[..., 2])
        scale = states.new_tensor([self.sigma_position**2] * 2 +
                                  [self.sigma_heading**2])
        return torch.diag_embed(dt.unsqueeze(-1) * scale)

    def sample(self, states, generator=None, control=None):
        cov = self.noise_covariance(states, control)
        noise = torch.randn(states.shape, dtype=states.dtype,
                            generator=generator)
        return self.mean(states, control) + noise * cov.diagonal(
            dim1=-2, dim2=-1).sqrt()


class LinearInput(MotionModel, name='test-linear-input'):
    r"""State :math:`[x, y, b]` (an odd size, no angle): the position moves
    by the known input :math:`[\delta_x, \delta_y]`, the third entry stays;
    additive Gaussian noise. Linear in the state and the input."""
    state_dim = 3
    control_dim = 2

    def __init__(self, sigma=0.2, sigma_bias=0.05):
        self.sigma, self.sigma_bias = sigma, sigma_bias

    def params(self):
        return dict(sigma=self.sigma, sigma_bias=self.sigma_bias)

    def layout(self, size):
        return StateLayout(size, 2)

    def mean(self, states, control=None):
        if control is None:
            return states
        control = torch.broadcast_to(control.to(states.dtype),
                                     states.shape[:-1] + (2, ))
        move = torch.where(torch.isnan(control), 0.0, control)
        return torch.cat([states[..., :2] + move, states[..., 2:]], -1)

    def noise_covariance(self, states, control=None):
        cov = torch.diag(states.new_tensor([self.sigma**2] * 2 +
                                           [self.sigma_bias**2]))
        return cov.expand(states.shape + (3, ))

    def sample(self, states, generator=None, control=None):
        noise = torch.randn(states.shape, dtype=states.dtype,
                            generator=generator)
        scale = states.new_tensor([self.sigma] * 2 + [self.sigma_bias])
        return self.mean(states, control) + noise * scale
