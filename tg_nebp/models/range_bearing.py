r"""Range-bearing measurement models: a robot's sensor (a camera on a
fiducial, a UWB array, a lidar) measures the range to another node and its
bearing relative to the robot's own heading. Each is one
:class:`RangeBearingModel` whose formula is the expected measurement
(:meth:`~RangeBearingModel.expected`) and the likelihood of its residuals
(:meth:`~RangeBearingModel.log_likelihood_of_residuals`); the Jacobians,
the Fisher information and the robust weights derive from those."""
import math
from typing import Optional, Tuple

import numpy as np
import torch
from scipy.stats import t as student_t
from torch import Tensor

from tg_nebp.data.validation import check_number
from tg_nebp.models.base import (LOG_SQRT_2PI, MeasurementModel,
                                 links_within_range, redraw_negative)
from tg_nebp.models.layout import StateLayout, wrap_angle
from tg_nebp.models.measurement import NU_RANGE, SIGMA_RANGE
from tg_nebp.utils import row_jacobian

__all__ = ['RangeBearingModel', 'GaussianRangeBearing',
           'StudentTRangeBearing']


def _check_scale(value, name: str) -> float:
    value = check_number(value, name, maximum=SIGMA_RANGE[1])
    if value < SIGMA_RANGE[0]:
        raise ValueError(f"'{name}' must be at least {SIGMA_RANGE[0]:g}, "
                         f"got {value}")
    return value


class RangeBearingModel(MeasurementModel):
    r"""The base of the range-bearing models: agent :math:`i`, at
    :math:`[x_i, y_i]` with heading :math:`\theta_i`, measures for a node
    :math:`j` within :obj:`max_range` and within its field of view

    .. math::
        \mathbf{h}(\mathbf{x}_j, \mathbf{x}_i) = \begin{bmatrix}
        \|\mathbf{p}_j - \mathbf{p}_i\| \\ \operatorname{atan2}(y_j - y_i,
        x_j - x_i) - \theta_i \end{bmatrix}

    plus noise; the bearing's residual is wrapped to :math:`(-\pi, \pi]`
    (:meth:`residuals`). The states are :math:`[x, y, \theta, \dots]`: the
    model reads the first three entries of both ends (the sender's heading
    does not enter) and needs a motion model whose layout has a 2-D
    position and a heading at entry 2
    (:class:`~tg_nebp.models.UnicycleOdometry`); it refuses any other
    (:meth:`bind`).

    A subclass implements :meth:`log_likelihood_of_residuals` and the
    closed forms :meth:`residual_information` (the Fisher information of
    each residual about its location) and :meth:`residual_weights` (the
    iteratively reweighted least squares weights).

    Args:
        sigma (float, optional): Range noise scale, metres.
            (default: :obj:`0.1`)
        sigma_bearing (float, optional): Bearing noise scale, radians.
            (default: :obj:`0.05`)
        max_range (float, optional): Sensing range, metres.
            (default: :obj:`10.0`)
        field_of_view (float, optional): The sensor's field of view about
            the heading, radians, in :math:`(0, 2 \pi]`.
            (default: :obj:`2 * math.pi`)
    """
    features = ('range', 'bearing')
    generated_features = ('range', 'bearing')
    state_entries = (0, 1, 2)
    formula = 'log_likelihood_of_residuals'

    def __init__(self, sigma: float = 0.1, sigma_bearing: float = 0.05,
                 max_range: float = 10.0,
                 field_of_view: float = 2 * math.pi):
        self.sigma = _check_scale(sigma, 'sigma')
        self.sigma_bearing = _check_scale(sigma_bearing, 'sigma_bearing')
        self.max_range = check_number(max_range, 'max_range')
        self.field_of_view = check_number(field_of_view, 'field_of_view',
                                          maximum=2 * math.pi)

    def params(self) -> dict:
        return dict(sigma=self.sigma,
                    sigma_bearing=self.sigma_bearing,
                    max_range=self.max_range,
                    field_of_view=self.field_of_view)

    def bind(self, layout: StateLayout) -> 'RangeBearingModel':
        r"""The model reading states of :obj:`layout`, which must have a
        2-D position and a heading at entry 2 (a :class:`ValueError`
        otherwise)."""
        if layout.position_dim != 2 or 2 not in layout.angles:
            raise ValueError(
                f"the measurement model {self} reads [x, y, heading] "
                f"states, but the motion model's state has "
                f"{layout.position_dim}-D positions and angles at "
                f"{list(layout.angles)}: use a motion model with a heading "
                f"at entry 2 (such as UnicycleOdometry)")
        return super().bind(layout)

    def scope(self, state_dim: int) -> Tuple[int, ...]:
        if self.layout is None:
            raise ValueError(
                f"the measurement model {self} reads [x, y, heading] states "
                f"and was given no motion model that declares a heading "
                f"(a [p, v] state of size {state_dim}): use a motion model "
                f"with a heading at entry 2 (such as UnicycleOdometry)")
        return super().scope(state_dim)

    def position_dim(self, size: int) -> int:
        return 2

    def _scales(self, like: Tensor) -> Tensor:
        return like.new_tensor([self.sigma, self.sigma_bearing])

    @staticmethod
    def expected(sender: Tensor, receiver: Tensor) -> Tensor:
        r"""The noise-free measurement :math:`\mathbf{h}` :math:`(*, 2)`
        (range, bearing; the bearing not wrapped) of states
        :obj:`sender` and :obj:`receiver` :math:`(*, S \geq 3)`. At zero
        distance it is :math:`(0, -\theta_i)` with no gradient: a bearing
        there, and a range's direction, carry no information."""
        dx = sender[..., 0] - receiver[..., 0]
        dy = sender[..., 1] - receiver[..., 1]
        # two states at one point (robots that start together, a robot at
        # a landmark): range 0 and the bearing of atan2(0, 0) = 0, with no
        # gradient (a link there carries no information; the safe
        # operands keep the other branch's gradient finite)
        apart = dx * dx + dy * dy > 0
        safe_dx = torch.where(apart, dx, torch.ones_like(dx))
        safe_dy = torch.where(apart, dy, torch.zeros_like(dy))
        distance = torch.where(apart, torch.sqrt(
            safe_dx * safe_dx + safe_dy * safe_dy), torch.zeros_like(dx))
        bearing = torch.where(apart, torch.atan2(safe_dy, safe_dx) -
                              receiver[..., 2], -receiver[..., 2].detach())
        return torch.stack([distance, bearing], -1)

    def residuals(self, z: Tensor, sender: Tensor,
                  receiver: Tensor) -> Tensor:
        r"""The residuals :math:`(E, K, 2)` of link features :obj:`z`
        :math:`(E, F)` at paired states :math:`(E, K, S)`: the range's and
        the wrapped bearing's."""
        raw = z[:, None, :2] - self.expected(sender, receiver)
        return torch.stack([raw[..., 0], wrap_angle(raw[..., 1])], -1)

    def log_likelihood_of_residuals(self, residuals: Tensor) -> Tensor:
        r""":math:`\log p` :math:`(*)` of residuals :math:`(*, 2)`."""
        raise NotImplementedError

    def residual_information(self) -> Tuple[float, float]:
        r"""The Fisher information of the range's and the bearing's noise
        about their location."""
        raise NotImplementedError

    def residual_weights(self, residuals: Tensor) -> Tensor:
        r"""The iteratively reweighted least squares weights :math:`(*, 2)`
        of residuals :math:`(*, 2)`: :math:`-\partial \log p / \partial r
        \,/\, r` per residual."""
        raise NotImplementedError

    def log_likelihood(self, z: Tensor, sender: Tensor,
                       receiver: Tensor) -> Tensor:
        return self.log_likelihood_of_residuals(
            self.residuals(z, sender, receiver))

    def measurement_jacobian(self, sender: Tensor,
                             receiver: Tensor) -> Tensor:
        r"""The Jacobian :math:`(E, 2, 6)` of :meth:`expected` with respect
        to :math:`[x_j, y_j, \theta_j, x_i, y_i, \theta_i]`: in closed form
        (:meth:`expected_jacobian`), or by automatic differentiation
        (:func:`~tg_nebp.utils.row_jacobian`) of a subclass's own
        :meth:`expected`."""
        if type(self).expected is RangeBearingModel.expected:
            return self.expected_jacobian(sender, receiver)
        ends = torch.cat([sender[:, :3], receiver[:, :3]], -1)
        return row_jacobian(lambda both: self.expected(both[:, :3],
                                                       both[:, 3:]), ends)

    @staticmethod
    def expected_jacobian(sender: Tensor, receiver: Tensor) -> Tensor:
        r"""The Jacobian :math:`(E, 2, 6)` of :meth:`expected` in closed
        form: with :math:`\Delta = \mathbf{p}_j - \mathbf{p}_i` and
        :math:`d = \|\Delta\|`, the range's row :math:`[\Delta / d, 0,
        -\Delta / d, 0]` and the bearing's :math:`[\Delta^\perp / d^2, 0,
        -\Delta^\perp / d^2, -1]`, :math:`\Delta^\perp = (-\Delta_y,
        \Delta_x)`; zero at zero distance, as :meth:`expected` gives no
        gradient there. What automatic differentiation of the formula
        gives too (a test holds them equal), at a fraction of its cost on
        the few links of a live step. Differentiable."""
        dx = sender[:, 0] - receiver[:, 0]
        dy = sender[:, 1] - receiver[:, 1]
        square = dx * dx + dy * dy
        apart = square > 0
        # the safe square keeps the other branch's gradient finite
        square = torch.where(apart, square, torch.ones_like(square))
        distance = square.sqrt()
        zero = torch.zeros_like(dx)
        jacobian = torch.stack([
            torch.stack([dx / distance, dy / distance, zero,
                         -dx / distance, -dy / distance, zero], -1),
            torch.stack([-dy / square, dx / square, zero, dy / square,
                         -dx / square, -torch.ones_like(dx)], -1)], -2)
        return torch.where(apart.view(-1, 1, 1), jacobian, 0.0)

    def _ends(self, sender: Tensor, receiver: Tensor):
        # the Jacobian placed on the full states' entries of both ends
        size = sender.size(-1)
        jac = self.measurement_jacobian(sender, receiver)
        full = jac.new_zeros(jac.size(0), 2, 2 * size)
        full[:, :, :3] = jac[:, :, :3]
        full[:, :, size:size + 3] = jac[:, :, 3:]
        return full

    def fisher_information(self, z: Tensor, sender: Tensor, receiver: Tensor,
                           generator: Optional[torch.Generator] = None
                           ) -> Tensor:
        r""":math:`\mathbf{H}^\top \operatorname{diag}(I_r, I_\beta)
        \mathbf{H}` :math:`(E, 2S, 2S)`, with :math:`\mathbf{H}` the
        Jacobian of :meth:`expected` (:meth:`measurement_jacobian`) and
        :math:`I` the noise's Fisher information
        (:meth:`residual_information`): exact for additive noise."""
        full = self._ends(sender, receiver)
        info = full.new_tensor(self.residual_information())
        return (full.transpose(1, 2) * info) @ full

    def linearize(self, z: Tensor, sender: Tensor, receiver: Tensor,
                  generator: Optional[torch.Generator] = None
                  ) -> Tuple[Tensor, Tensor]:
        r"""The gradient :math:`(E, 6)` of :math:`\log p` with respect to
        the read entries of both ends (automatic differentiation of
        :meth:`log_likelihood`) and the Gauss-Newton curvature
        :math:`\mathbf{H}^\top \mathbf{W} \mathbf{H}` with the robust
        weights :math:`\mathbf{W}` of the residuals
        (:meth:`residual_weights`): one step of iteratively reweighted
        least squares, the bearing's residual wrapped."""
        both = self.scope_of_both(sender.size(-1), sender.device)
        residual = self.residuals(z, sender.unsqueeze(1),
                                  receiver.unsqueeze(1))[:, 0]
        jac = self.measurement_jacobian(sender, receiver)
        weights = self.residual_weights(residual)
        curvature = (jac.transpose(1, 2) * weights.unsqueeze(1)) @ jac
        return (self.likelihood_gradient(z, sender, receiver)[:, both],
                curvature)

    def connect(self, pos: Tensor, receiver: Tensor) -> Tensor:
        r"""The pairs within :obj:`max_range` (the field of view needs the
        headings: see :meth:`connect_states`)."""
        return links_within_range(pos, receiver, self.max_range)

    def connect_states(self, states: Tensor, receiver: Tensor) -> Tensor:
        r"""The links :obj:`[2, E]` from every node within
        :obj:`max_range` of a :obj:`receiver` node and within its field of
        view: :math:`|\beta| \leq` :obj:`field_of_view` / 2 about its
        heading."""
        edges = self.connect(states[:, :2], receiver)
        bearing = wrap_angle(self.expected(states[edges[0]],
                                           states[edges[1]])[:, 1])
        return edges[:, bearing.abs() <= 0.5 * self.field_of_view]

    def sample_noise(self, shape, like: Tensor,
                     generator: Optional[torch.Generator]) -> Tensor:
        r"""Draws of the residuals' noise :math:`(*shape, 2)`."""
        raise NotImplementedError

    def sample_features(self, states_j: Tensor, states_i: Tensor,
                        link_state, edge_index: Tensor,
                        generator: Optional[torch.Generator] = None
                        ) -> Tensor:
        expected = self.expected(states_j, states_i)

        def range_noise(shape):
            return self.sample_noise(shape, expected, generator)[..., 0]

        ranges = redraw_negative(range_noise, expected[:, 0])
        bearing = wrap_angle(expected[:, 1] + self.sample_noise(
            expected[:, 1].shape, expected, generator)[..., 1])
        return torch.stack([ranges, bearing], -1)


class GaussianRangeBearing(RangeBearingModel, name='range-bearing'):
    r"""Range and bearing with independent Gaussian noise,

    .. math::
        \log p(\mathbf{z} | \mathbf{x}_j, \mathbf{x}_i) =
        -\frac{r_d^2}{2 \sigma_d^2} - \frac{r_\beta^2}{2 \sigma_\beta^2}
        - \log(2 \pi \sigma_d \sigma_\beta),

    with :math:`r_d` the range's residual and :math:`r_\beta` the
    bearing's, wrapped (see :class:`RangeBearingModel`; a range below zero
    is redrawn in generation; a measured one is accepted, the likelihood
    being defined for it).

    Args:
        sigma (float, optional): :math:`\sigma_d`, metres.
            (default: :obj:`0.1`)
        sigma_bearing (float, optional): :math:`\sigma_\beta`, radians.
            (default: :obj:`0.05`)
        max_range (float, optional): Sensing range, metres.
            (default: :obj:`10.0`)
        field_of_view (float, optional): Field of view, radians.
            (default: :obj:`2 * math.pi`)

    Shapes:
        - **input:** link features :math:`(E, 2)`, states :math:`(E, K,
          S)` of both ends
        - **output:** log-likelihoods :math:`(E, K)`
    """
    def log_likelihood_of_residuals(self, residuals: Tensor) -> Tensor:
        scaled = residuals / self._scales(residuals)
        return -0.5 * (scaled * scaled).sum(-1) - 2 * LOG_SQRT_2PI - \
            math.log(self.sigma * self.sigma_bearing)

    def residual_information(self) -> Tuple[float, float]:
        r""":math:`1 / \sigma^2` each."""
        return self.sigma**-2, self.sigma_bearing**-2

    def residual_weights(self, residuals: Tensor) -> Tensor:
        r""":math:`1 / \sigma^2` each."""
        return (self._scales(residuals)**-2).expand_as(residuals)

    def sample_noise(self, shape, like: Tensor,
                     generator: Optional[torch.Generator]) -> Tensor:
        return torch.randn(tuple(shape) + (2, ), dtype=like.dtype,
                           device=like.device,
                           generator=generator) * self._scales(like)


class StudentTRangeBearing(RangeBearingModel,
                           name='student-t-range-bearing'):
    r"""Range and bearing with independent Student-t noise of :math:`\nu`
    degrees of freedom, the robust variant for real sensors (outlying
    ranges, a wrong fiducial): each residual :math:`r` with scale
    :math:`\sigma` contributes

    .. math::
        \log \frac{\Gamma(\frac{\nu + 1}{2})}{\Gamma(\frac{\nu}{2})
        \sqrt{\nu \pi} \sigma} - \frac{\nu + 1}{2} \log\Big(1 +
        \frac{r^2}{\nu \sigma^2}\Big).

    Defined for any measured range: a negative one is accepted.

    Args:
        sigma (float, optional): Range scale, metres.
            (default: :obj:`0.1`)
        sigma_bearing (float, optional): Bearing scale, radians.
            (default: :obj:`0.05`)
        nu (float, optional): Degrees of freedom :math:`\nu`.
            (default: :obj:`3.0`)
        max_range (float, optional): Sensing range, metres.
            (default: :obj:`10.0`)
        field_of_view (float, optional): Field of view, radians.
            (default: :obj:`2 * math.pi`)
    """
    def __init__(self, sigma: float = 0.1, sigma_bearing: float = 0.05,
                 nu: float = 3.0, max_range: float = 10.0,
                 field_of_view: float = 2 * math.pi):
        super().__init__(sigma, sigma_bearing, max_range,
                         field_of_view)
        nu = check_number(nu, 'nu')
        if not NU_RANGE[0] <= nu <= NU_RANGE[1]:
            raise ValueError(f"'nu' must lie within [{NU_RANGE[0]:g}, "
                             f"{NU_RANGE[1]:g}], got {nu}")
        self.nu = nu

    def params(self) -> dict:
        return {**super().params(), 'nu': self.nu}

    def log_likelihood_of_residuals(self, residuals: Tensor) -> Tensor:
        nu = self.nu
        log_norm = 2 * (math.lgamma((nu + 1) / 2) - math.lgamma(nu / 2) -
                        0.5 * math.log(nu * math.pi)) - math.log(
                            self.sigma * self.sigma_bearing)
        scaled = residuals / self._scales(residuals)
        return log_norm - 0.5 * (nu + 1) * torch.log1p(
            scaled * scaled / nu).sum(-1)

    def residual_information(self) -> Tuple[float, float]:
        r""":math:`(\nu + 1) / ((\nu + 3) \sigma^2)` each."""
        factor = (self.nu + 1) / (self.nu + 3)
        return (factor * self.sigma**-2,
                factor * self.sigma_bearing**-2)

    def residual_weights(self, residuals: Tensor) -> Tensor:
        r""":math:`(\nu + 1) / (\nu \sigma^2 + r^2)` each."""
        return (self.nu + 1) / (self.nu * self._scales(residuals)**2 +
                                residuals * residuals)

    def sample_noise(self, shape, like: Tensor,
                     generator: Optional[torch.Generator]) -> Tensor:
        # inverse CDF at the generator's uniforms: reproducible draws
        uniform = torch.rand(tuple(shape) + (2, ), dtype=torch.float64,
                             generator=generator).clamp_(1e-300, 1.0)
        quantile = student_t.ppf(uniform.numpy(), self.nu)
        return torch.from_numpy(np.asarray(quantile)).to(like) * \
            self._scales(like)
