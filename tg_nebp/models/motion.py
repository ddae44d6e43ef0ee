import math
from typing import Optional, Tuple

import torch
from torch import Tensor

from tg_nebp.data.validation import check_number
from tg_nebp.models.base import MotionModel
from tg_nebp.models.layout import StateLayout, wrap_angle
from tg_nebp.utils import row_linearization, symmetrize

__all__ = ['ConstantVelocityDrag', 'ConstantVelocity', 'UnicycleOdometry']


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


class UnicycleOdometry(MotionModel, name='unicycle-odometry'):
    r"""A wheeled robot moved by its odometry: the state :math:`\mathbf{x}
    = [x, y, \theta]` (position, heading), the known input of a step
    :math:`\mathbf{u} = [\delta_d, \delta_\theta]` (the distance driven
    forward and the change of heading that the odometry measured over the
    step), and

    .. math::
        \mathbf{x}_n = f(\mathbf{x}_{n-1}, \mathbf{u}_n - \mathbf{m}_n)
        = \begin{bmatrix} x + \tilde{\delta}_d \cos(\theta +
        \tilde{\delta}_\theta / 2) \\ y + \tilde{\delta}_d \sin(\theta +
        \tilde{\delta}_\theta / 2) \\ \theta + \tilde{\delta}_\theta
        \end{bmatrix}, \quad \mathbf{m}_n \sim \mathcal{N}(\mathbf{0},
        \mathbf{M}(\mathbf{u}_n)),

    (the midpoint of the turn), with noise on the inputs that grows with
    the distance and the turn, as odometry error does,

    .. math::
        \mathbf{M} = \operatorname{diag}\big(\sigma_d^2 + (s_d
        \delta_d)^2,\; \sigma_\theta^2 + (s_\theta \delta_\theta)^2 +
        (s_{\theta d} \delta_d)^2\big).

    The particle methods draw the inputs' noise (:meth:`sample`); the
    Gaussian methods and the bound take :math:`f(\mathbf{x}, \mathbf{u})`
    (:meth:`mean`) and the noise propagated to the state by the model's
    own Jacobian with respect to the input, :math:`\mathbf{Q} = \mathbf{G}
    \mathbf{M} \mathbf{G}^\top`, :math:`\mathbf{G} = \partial f /
    \partial \mathbf{u}` (:meth:`noise_covariance`).

    **A step without input** (a row of NaN, or no :obj:`control` at all)
    is a random walk: the robot is predicted where it was, with
    independent noise of :obj:`idle_position` metres on each coordinate
    and :obj:`idle_heading` radians on the heading.

    The heading is an angle (:meth:`layout`): :math:`f` leaves it on the
    real line (a lift), and every residual and report wraps it.

    Args:
        sigma_distance (float, optional): :math:`\sigma_d`, metres.
            (default: :obj:`0.005`)
        distance_scale (float, optional): :math:`s_d`, metres of error per
            metre driven. (default: :obj:`0.05`)
        sigma_turn (float, optional): :math:`\sigma_\theta`, radians.
            (default: :obj:`0.005`)
        turn_scale (float, optional): :math:`s_\theta`, radians of error
            per radian turned. (default: :obj:`0.05`)
        turn_per_distance (float, optional): :math:`s_{\theta d}`, radians
            of heading error per metre driven. (default: :obj:`0.02`)
        idle_position (float, optional): Standard deviation of a step
            without input, metres per coordinate. (default: :obj:`0.5`)
        idle_heading (float, optional): Standard deviation of a step
            without input, radians. (default: :obj:`0.5`)

    Shapes:
        - **input:** states :math:`(*, 3)`, inputs :math:`(*, 2)`
          (broadcast against the states' leading dimensions)
        - **output:** states :math:`(*, 3)`
    """
    state_dim = 3
    control_dim = 2

    def __init__(self, sigma_distance: float = 0.005,
                 distance_scale: float = 0.05, sigma_turn: float = 0.005,
                 turn_scale: float = 0.05, turn_per_distance: float = 0.02,
                 idle_position: float = 0.5, idle_heading: float = 0.5):
        self.sigma_distance = check_number(sigma_distance, 'sigma_distance')
        self.distance_scale = check_number(distance_scale, 'distance_scale',
                                           inclusive=True)
        self.sigma_turn = check_number(sigma_turn, 'sigma_turn')
        self.turn_scale = check_number(turn_scale, 'turn_scale',
                                       inclusive=True)
        self.turn_per_distance = check_number(
            turn_per_distance, 'turn_per_distance', inclusive=True)
        self.idle_position = check_number(idle_position, 'idle_position')
        self.idle_heading = check_number(idle_heading, 'idle_heading')

    def params(self) -> dict:
        return dict(sigma_distance=self.sigma_distance,
                    distance_scale=self.distance_scale,
                    sigma_turn=self.sigma_turn, turn_scale=self.turn_scale,
                    turn_per_distance=self.turn_per_distance,
                    idle_position=self.idle_position,
                    idle_heading=self.idle_heading)

    def layout(self, size: int) -> StateLayout:
        r""":math:`[x, y, \theta]`: a 2-D position and a heading."""
        return StateLayout(size, 2, (2, ))

    def with_time_step(self, dt: float) -> 'UnicycleOdometry':
        r"""Itself: the odometry input carries the step, whatever its
        duration (a step without input is one random-walk step)."""
        return self

    def rigidly_moved(self, states: Tensor, rotation: Tensor,
                      offset: Tensor) -> Tensor:
        r"""The states :math:`(*, 3)` moved rigidly (see
        :meth:`MotionModel.rigidly_moved
        <tg_nebp.models.MotionModel.rigidly_moved>`): the position
        :math:`\mathbf{R} \mathbf{p} + \mathbf{b}`, the heading that of
        :math:`\mathbf{R}` times the heading's direction (a reflection
        turns a left turn into a right one, which the odometry's inputs
        then contradict), kept on the lift within :math:`\pi` of the
        old."""
        position = (rotation @ states[..., :2].unsqueeze(-1)).squeeze(-1)
        heading = states[..., 2]
        facing = (rotation @ torch.stack([heading.cos(), heading.sin()],
                                         -1).unsqueeze(-1)).squeeze(-1)
        turned = torch.atan2(facing[..., 1], facing[..., 0])
        turned = heading + wrap_angle(turned - heading)
        return torch.cat([position + offset, turned.unsqueeze(-1)], -1)

    @staticmethod
    def propagate(states: Tensor, control: Tensor) -> Tensor:
        r"""The move :math:`f(\mathbf{x}, \mathbf{u})` of states
        :math:`(*, 3)` by inputs :math:`(*, 2)`, without noise."""
        distance, turn = control[..., 0], control[..., 1]
        heading = states[..., 2] + 0.5 * turn
        return torch.stack([states[..., 0] + distance * torch.cos(heading),
                            states[..., 1] + distance * torch.sin(heading),
                            states[..., 2] + turn], -1)

    @staticmethod
    def propagate_derivatives(states: Tensor, control: Tensor
                              ) -> Tuple[Tensor, Tensor, Tensor]:
        r""":meth:`propagate` and its Jacobians in the states,
        :math:`\mathbf{F} = \partial f / \partial \mathbf{x}` :math:`(*, 3,
        3)`, and in the inputs, :math:`\mathbf{G} = \partial f / \partial
        \mathbf{u}` :math:`(*, 3, 2)`, in closed form (with :math:`h =
        \theta + \delta_\theta / 2`: :math:`\partial (x, y) / \partial
        \theta = \delta_d (-\sin h, \cos h)`, :math:`\partial (x, y) /
        \partial \delta_d = (\cos h, \sin h)` and :math:`\partial (x, y) /
        \partial \delta_\theta = \frac{1}{2} \partial (x, y) / \partial
        \theta`): the derivatives of the formula above, which automatic
        differentiation of :meth:`propagate` gives too (a test holds them
        equal) at a fraction of its cost on the few states of a live
        step. Differentiable: training through a tracker reads them."""
        distance, turn = control[..., 0], control[..., 1]
        heading = states[..., 2] + 0.5 * turn
        cos, sin = torch.cos(heading), torch.sin(heading)
        zero, one = torch.zeros_like(cos), torch.ones_like(cos)
        jacobian = torch.stack([
            torch.stack([one, zero, -distance * sin], -1),
            torch.stack([zero, one, distance * cos], -1),
            torch.stack([zero, zero, one], -1)], -2)
        gain = torch.stack([
            torch.stack([cos, -0.5 * distance * sin], -1),
            torch.stack([sin, 0.5 * distance * cos], -1),
            torch.stack([zero, one], -1)], -2)
        return UnicycleOdometry.propagate(states, control), jacobian, gain

    def _inputs(self, states: Tensor, control: Optional[Tensor]):
        # the inputs broadcast to the states, zero where missing, and the
        # mask of the missing ones
        shape = states.shape[:-1] + (2, )
        if control is None:
            return (states.new_zeros(shape),
                    torch.ones(shape[:-1], dtype=torch.bool,
                               device=states.device))
        control = torch.broadcast_to(control.to(states.dtype), shape)
        missing = torch.isnan(control).any(-1)
        return torch.where(missing.unsqueeze(-1), 0.0, control), missing

    #: See :meth:`representable`.
    input_limit = ('an input whose heading noise, one standard deviation '
                   'of the model\'s M, is at most pi radians')

    def representable(self, control: Tensor) -> Tensor:
        r"""Whether each input's heading noise stays within half a turn,
        :math:`\sqrt{M_{\theta\theta}(\mathbf{u})} \le \pi`: beyond, the
        heading after the step is unknown, no linearization of :math:`f`
        in it holds, and the position noise :math:`\mathbf{G} \mathbf{M}
        \mathbf{G}^\top` reaches scales that the Gaussian methods' joint
        covariances cannot hold beside the others (a robot driving a
        kilometre, or turning a thousand radians, in one step under the
        default noise: a corrupted odometry row). NaN rows are
        :obj:`True`."""
        # NaN compares false: a row without input is representable
        return ~(self.input_variances(control)[..., 1] > math.pi ** 2)

    def input_variances(self, control: Tensor) -> Tensor:
        r"""The variances :math:`(*, 2)` of the inputs' noise,
        :math:`\operatorname{diag} \mathbf{M}(\mathbf{u})`."""
        distance, turn = control[..., 0], control[..., 1]
        return torch.stack([
            self.sigma_distance**2 + (self.distance_scale * distance)**2,
            self.sigma_turn**2 + (self.turn_scale * turn)**2 +
            (self.turn_per_distance * distance)**2], -1)

    def measure(self, control: Tensor,
                generator: Optional[torch.Generator] = None) -> Tensor:
        r"""What the odometry reads of the true inputs :obj:`control`
        :math:`(*, 2)`: the inputs plus noise of covariance
        :math:`\mathbf{M}` (the model's own noise, for generating
        scenarios)."""
        noise = torch.randn(control.shape, dtype=control.dtype,
                            device=control.device, generator=generator)
        return control + noise * self.input_variances(control).sqrt()

    def _idle_variances(self, like: Tensor) -> Tensor:
        return like.new_tensor([self.idle_position**2] * 2 +
                               [self.idle_heading**2])

    def sample(self, states: Tensor,
               generator: Optional[torch.Generator] = None,
               control: Optional[Tensor] = None) -> Tensor:
        r"""Draws :math:`\mathbf{x}_n`: the inputs with their noise, or a
        random-walk step where there is no input (three normal draws per
        state either way)."""
        control, missing = self._inputs(states, control)
        noise = torch.randn(states.shape, dtype=states.dtype,
                            device=states.device, generator=generator)
        moved = self.propagate(states, control + noise[..., :2] *
                               self.input_variances(control).sqrt())
        idle = states + noise * self._idle_variances(states).sqrt()
        return torch.where(missing.unsqueeze(-1), idle, moved)

    def mean(self, states: Tensor,
             control: Optional[Tensor] = None) -> Tensor:
        r""":math:`f(\mathbf{x}, \mathbf{u})`; the state itself where
        there is no input."""
        control, missing = self._inputs(states, control)
        return torch.where(missing.unsqueeze(-1), states,
                           self.propagate(states, control))

    def noise_covariance(self, states: Tensor,
                         control: Optional[Tensor] = None) -> Tensor:
        r""":math:`\mathbf{G} \mathbf{M} \mathbf{G}^\top` :math:`(*, 3,
        3)`, with :math:`\mathbf{G}` the Jacobian of :meth:`propagate` in
        the inputs (:meth:`propagate_derivatives`; by automatic
        differentiation where a subclass moves the robot by a
        :meth:`propagate` of its own); the random walk's diagonal where
        there is no input."""
        return self._one_pass(states, control)[2]

    def linearize(self, states: Tensor, control: Optional[Tensor] = None
                  ) -> Tuple[Tensor, Tensor, Tensor]:
        r""":meth:`mean`, :meth:`~tg_nebp.models.MotionModel.jacobian` and
        :meth:`noise_covariance` from one pass of :meth:`propagate` and its
        Jacobians in the state and in the inputs
        (:meth:`propagate_derivatives`, or one backward pass of a
        subclass's own :meth:`propagate`): the
        identity Jacobian and the random walk where there is no input. A
        subclass that overrides one of the three gets the three calls (the
        role's default), so that its own formula is what the trackers
        read."""
        if any(getattr(type(self), name) is not getattr(UnicycleOdometry,
                                                        name)
               for name in ('mean', 'jacobian', 'noise_covariance')):
            return super().linearize(states, control)
        return self._one_pass(states, control)

    def _one_pass(self, states: Tensor, control: Optional[Tensor]
                  ) -> Tuple[Tensor, Tensor, Tensor]:
        # f, F and Q of this class's formula from one pass of propagate
        control, missing = self._inputs(states, control)
        if type(self).propagate is UnicycleOdometry.propagate:
            moved, jacobian, gain = self.propagate_derivatives(states,
                                                               control)
        else:  # a subclass's own move: differentiated as it is written
            moved, (jacobian, gain) = row_linearization(
                self.propagate, (states, control))  # F (*, 3, 3), G (*, 3, 2)
        cov = (gain * self.input_variances(control).unsqueeze(-2)) @ \
            gain.transpose(-1, -2)
        idle = torch.diag_embed(self._idle_variances(states).expand(
            states.shape))
        eye = torch.eye(3, dtype=jacobian.dtype, device=jacobian.device)
        square = missing.view(missing.shape + (1, 1))
        return (torch.where(missing.unsqueeze(-1), states, moved),
                torch.where(square, eye, jacobian),
                torch.where(square, idle, symmetrize(cov)))
