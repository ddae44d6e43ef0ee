from typing import Optional

import torch
from torch import Tensor

from tg_nebp.data.validation import check_number
from tg_nebp.models.base import MotionModel

__all__ = ['ConstantVelocityDrag', 'ConstantVelocity']


class ConstantVelocityDrag(MotionModel, name='constant-velocity-drag'):
    r"""Constant-velocity motion with drag and Gaussian driving noise, from
    the `"Neural Enhanced Belief Propagation for Cooperative Localization"
    <https://arxiv.org/abs/2105.12903>`_ paper

    .. math::
        \mathbf{x}_n = \mathbf{F} \mathbf{x}_{n-1}
        + \mathbf{W} \left( -c \, \mathbf{v}_{n-1} \odot
        |\mathbf{v}_{n-1}| + \mathbf{a}_n \right), \quad
        \mathbf{a}_n \sim \mathcal{N}(\mathbf{0}, \sigma_a^2 \mathbf{I}_D)

    with state :math:`\mathbf{x} = [\mathbf{p}^\top, \mathbf{v}^\top]^\top`,
    :math:`\mathbf{F} = [[\mathbf{I}, \Delta \mathbf{I}], [\mathbf{0},
    \mathbf{I}]]` and :math:`\mathbf{W} = [\Delta^2/2 \, \mathbf{I}; \Delta
    \mathbf{I}]`.

    Args:
        sigma_a (float, optional): Standard deviation :math:`\sigma_a` of the
            acceleration noise. (default: :obj:`0.05`)
        drag (float, optional): Drag coefficient :math:`c`.
            (default: :obj:`0.06`)
        dt (float, optional): Time step :math:`\Delta` in seconds.
            (default: :obj:`1.0`)

    The model moves positions of any dimension :math:`D` (the state
    :math:`[\mathbf{p}, \mathbf{v}]` has :math:`2D` entries; the paper's
    :math:`D = 2`), every axis alike.

    Shapes:
        - **input:** states :math:`(*, 2D)`
        - **output:** states :math:`(*, 2D)`
    """
    def __init__(self, sigma_a: float = 0.05, drag: float = 0.06,
                 dt: float = 1.0):
        sigma_a = check_number(sigma_a, 'sigma_a', inclusive=True)
        drag = check_number(drag, 'drag', inclusive=True)
        dt = check_number(dt, 'dt')
        self.sigma_a = sigma_a
        self.drag = drag
        self.dt = dt

    def propagate(self, states: Tensor, accel: Tensor) -> Tensor:
        r"""Applies the transition with a given acceleration noise
        :obj:`accel` :math:`(*, D)`."""
        # fused multiply-adds: few passes over the strided [..., D] views
        dim = states.size(-1) // 2
        vel = states[..., dim:]
        accel = torch.addcmul(accel, vel, vel.abs(), value=-self.drag)
        new_pos = torch.add(states[..., :dim], vel, alpha=self.dt).add_(
            accel, alpha=0.5 * self.dt**2)
        new_vel = torch.add(vel, accel, alpha=self.dt)
        return torch.cat([new_pos, new_vel], dim=-1)

    def sample(self, states: Tensor,
               generator: Optional[torch.Generator] = None) -> Tensor:
        r"""Draws :math:`\mathbf{x}_n \sim p(\mathbf{x}_n |
        \mathbf{x}_{n-1})` for every state in :obj:`states`."""
        accel = torch.randn(states.shape[:-1] + (states.size(-1) // 2, ),
                            dtype=states.dtype, device=states.device,
                            generator=generator)
        return self.propagate(states, self.sigma_a * accel)

    def mean(self, states: Tensor) -> Tensor:
        r"""The noise-free transition :math:`\mathbf{F} \mathbf{x} -
        c \mathbf{W} (\mathbf{v} \odot |\mathbf{v}|)`: the driving noise
        :math:`\mathbf{W} \mathbf{a}` is additive."""
        return self.propagate(states, states.new_zeros(
            states.shape[:-1] + (states.size(-1) // 2, )))

    def noise_covariance(self, states: Tensor) -> Tensor:
        r""":math:`\sigma_a^2 \mathbf{W} \mathbf{W}^\top` (the same at
        every state), :math:`(*, 2D, 2D)`."""
        # W as the transition's own response to a unit acceleration: the
        # model's formula, not a second copy of its matrices
        dim = states.size(-1) // 2
        eye = torch.eye(dim, dtype=states.dtype, device=states.device)
        response = (self.propagate(states.new_zeros(dim, 2 * dim), eye) -
                    self.mean(states.new_zeros(1, 2 * dim)))  # rows W^T
        cov = self.sigma_a**2 * response.transpose(0, 1) @ response
        return cov.expand(states.shape[:-1] + cov.shape)

    def params(self) -> dict:
        return dict(sigma_a=self.sigma_a, drag=self.drag, dt=self.dt)


class ConstantVelocity(ConstantVelocityDrag, name='constant-velocity'):
    r"""The nearly-constant-velocity model (white-noise acceleration) of
    tracking: :class:`~tg_nebp.models.ConstantVelocityDrag` without drag,
    stable at any speed,

    .. math::
        \mathbf{x}_n = \mathbf{F} \mathbf{x}_{n-1} + \mathbf{W}
        \mathbf{a}_n, \quad \mathbf{a}_n \sim \mathcal{N}(\mathbf{0},
        \sigma_a^2 \mathbf{I}_D).

    Args:
        sigma_a (float, optional): Standard deviation :math:`\sigma_a` of the
            acceleration noise. (default: :obj:`0.05`)
        dt (float, optional): Time step :math:`\Delta` in seconds.
            (default: :obj:`1.0`)
    """
    def __init__(self, sigma_a: float = 0.05, dt: float = 1.0):
        super().__init__(sigma_a, 0.0, dt)

    def params(self) -> dict:
        return dict(sigma_a=self.sigma_a, dt=self.dt)
