r"""The robot models: the odometry-driven unicycle
(:class:`~tg_nebp.models.UnicycleOdometry`) and the range-bearing
likelihoods, each against plain float64 loops of its formula, finite
differences and sample statistics; the state layout and the angle
wrapping they rely on."""
import math

import pytest
import torch

from tg_nebp.models import (GaussianRange, GaussianRangeBearing,
                            StateLayout, StudentTRangeBearing,
                            UnicycleOdometry, model_from_config,
                            resolve_models, wrap_angle)
from tg_nebp.models.base import MeasurementModel, MotionModel

from helpers import gen

NAN = float('nan')


def test_wrap_angle_lands_in_the_half_open_interval():
    angles = torch.tensor([-math.pi, math.pi, 3 * math.pi, -3 * math.pi,
                           0.5, -7.0, 7.0], dtype=torch.float64)
    wrapped = wrap_angle(angles)
    assert bool(((wrapped > -math.pi) & (wrapped <= math.pi)).all())
    assert torch.allclose(torch.cos(wrapped), torch.cos(angles))
    assert torch.allclose(torch.sin(wrapped), torch.sin(angles),
                          atol=1e-12)
    assert float(wrapped[0]) == math.pi  # -pi maps to +pi


def test_the_default_layout_is_position_then_velocity():
    from tg_nebp.models import ConstantVelocityDrag
    assert ConstantVelocityDrag().layout(4) == StateLayout(4, 2, ())
    assert ConstantVelocityDrag().layout(6) == StateLayout(6, 3, ())
    layout = UnicycleOdometry().layout(3)
    assert layout == StateLayout(3, 2, (2, ))
    states = torch.tensor([[1.0, 2.0, 4.0]])
    assert torch.equal(layout.positions(states), states[:, :2])
    assert float(layout.wrap(states)[0, 2]) == pytest.approx(
        4.0 - 2 * math.pi)


def test_nearest_puts_an_angle_on_the_lift_of_a_reference():
    # a wrapped heading moved by whole turns to within pi of the
    # reference's lift; positions untouched; no angle: the same tensor
    layout = UnicycleOdometry().layout(3)
    reference = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, -9.0],
                              [0.0, 0.0, 20.0]], dtype=torch.float64)
    states = torch.tensor([[1.0, 2.0, -3.1], [3.0, 4.0, 3.0],
                           [5.0, 6.0, 0.5]], dtype=torch.float64)
    near = layout.nearest(states, reference)
    assert torch.equal(near[:, :2], states[:, :2])
    for row in range(3):
        turns = (float(near[row, 2]) - float(states[row, 2])) / (2 * math.pi)
        assert turns == pytest.approx(round(turns), abs=1e-12)
        assert abs(float(near[row, 2]) - float(reference[row, 2])) <= math.pi
    assert float(near[0, 2]) == pytest.approx(2 * math.pi - 3.1)
    plain = torch.randn(2, 4, dtype=torch.float64)
    from tg_nebp.models import ConstantVelocityDrag
    assert ConstantVelocityDrag().layout(4).nearest(plain, plain + 9) is plain


def _unicycle_loop(state, control):
    # the odometry step written out for one state, float64 math
    x, y, theta = state
    d, turn = control
    heading = theta + turn / 2
    return [x + d * math.cos(heading), y + d * math.sin(heading),
            theta + turn]


def test_unicycle_mean_and_jacobian_against_loops_and_differences():
    model = UnicycleOdometry()
    states = torch.randn(6, 3, dtype=torch.float64, generator=gen(0))
    control = torch.rand(6, 2, dtype=torch.float64, generator=gen(1))
    control[4] = NAN  # a step without input: the robot stays
    mean = model.mean(states, control=control)
    for k in range(6):
        expected = (states[k].tolist() if k == 4 else
                    _unicycle_loop(states[k].tolist(), control[k].tolist()))
        assert mean[k].tolist() == pytest.approx(expected, abs=1e-12)
    jac = model.jacobian(states, control=control)
    eps = 1e-6
    for k in range(6):
        for j in range(3):
            step = torch.zeros(3, dtype=torch.float64)
            step[j] = eps
            column = (model.mean(states[k] + step, control=control[k]) -
                      model.mean(states[k] - step, control=control[k])) / (
                          2 * eps)
            assert torch.allclose(jac[k, :, j], column, atol=1e-8)


def _unicycle_noise(state, control):
    # G M G^T written out for UnicycleOdometry(sigma_distance=0.01,
    # distance_scale=0.1, sigma_turn=0.02, turn_scale=0.2,
    # turn_per_distance=0.05): G = df/du at the state and input
    d, turn = control.tolist()
    heading = float(state[2]) + turn / 2
    g = torch.tensor([[math.cos(heading), -d / 2 * math.sin(heading)],
                      [math.sin(heading), d / 2 * math.cos(heading)],
                      [0.0, 1.0]], dtype=torch.float64)
    m = torch.diag(torch.tensor([
        0.01**2 + (0.1 * d)**2,
        0.02**2 + (0.2 * turn)**2 + (0.05 * d)**2], dtype=torch.float64))
    return g @ m @ g.T


def test_unicycle_noise_is_the_input_noise_through_its_jacobian():
    model = UnicycleOdometry(sigma_distance=0.01, distance_scale=0.1,
                             sigma_turn=0.02, turn_scale=0.2,
                             turn_per_distance=0.05, idle_position=0.3,
                             idle_heading=0.4)
    states = torch.tensor([[1.0, 2.0, 0.7], [0.0, 0.0, -3.0],
                           [5.0, 5.0, 1.0]], dtype=torch.float64)
    control = torch.tensor([[0.4, 0.3], [1.2, -0.5], [NAN, NAN]],
                           dtype=torch.float64)
    cov = model.noise_covariance(states, control=control)
    for k in range(2):
        assert torch.allclose(cov[k], _unicycle_noise(states[k], control[k]),
                              atol=1e-14)
    assert torch.allclose(cov[2], torch.diag(torch.tensor(
        [0.09, 0.09, 0.16], dtype=torch.float64)))
    assert torch.equal(cov, cov.transpose(-1, -2))
    # without any input every state is a random-walk step
    assert torch.allclose(model.noise_covariance(states)[0], cov[2])
    assert torch.equal(model.mean(states), states)


def test_unicycle_linearize_is_its_mean_jacobian_and_noise_at_once():
    # the one-pass linearization the Gaussian methods read equals the
    # model's mean, the Jacobian of that mean (the role's default, by
    # differentiating mean()) and the closed-form noise, with and without
    # an input, and keeps the mean's graph where a tracker is trained
    model = UnicycleOdometry(sigma_distance=0.01, distance_scale=0.1,
                             sigma_turn=0.02, turn_scale=0.2,
                             turn_per_distance=0.05)
    states = torch.randn(2, 5, 3, dtype=torch.float64, generator=gen(3))
    control = torch.randn(2, 5, 2, dtype=torch.float64, generator=gen(4))
    control[1, 2] = NAN
    moved, jac, noise = model.linearize(states, control=control)
    assert torch.equal(moved, model.mean(states, control=control))
    torch.testing.assert_close(
        jac, MotionModel.jacobian(model, states, control=control),
        rtol=0, atol=1e-15)
    assert torch.equal(jac[1, 2], torch.eye(3, dtype=torch.float64))
    for k in range(5):
        torch.testing.assert_close(
            noise[0, k], _unicycle_noise(states[0, k], control[0, k]),
            rtol=0, atol=1e-15)
    assert torch.equal(noise[1, 2], torch.diag(torch.tensor(
        [0.25, 0.25, 0.25], dtype=torch.float64)))
    leaf = states.clone().requires_grad_()
    grad, = torch.autograd.grad(model.linearize(leaf, control)[0].sum(),
                                leaf)
    # d/dtheta of x' + y' + theta' (1 where the robot stays)
    torch.testing.assert_close(grad[..., 2],
                               jac[..., 0, 2] + jac[..., 1, 2] + 1)
    with torch.no_grad():
        assert not model.linearize(leaf, control)[0].requires_grad


def test_a_subclass_formula_is_what_the_trackers_linearize():
    # a unicycle whose noise covariance adds slip: the one-pass
    # linearization of the parent's formula must not hide it from the
    # Gaussian methods and the bound (they call linearize())
    class Slipping(UnicycleOdometry, name='test-slipping-unicycle'):
        def noise_covariance(self, states, control=None):
            return super().noise_covariance(states, control) + torch.eye(
                3, dtype=states.dtype)

    model = Slipping()
    states = torch.randn(4, 3, dtype=torch.float64, generator=gen(5))
    control = torch.rand(4, 2, dtype=torch.float64, generator=gen(6))
    moved, jac, noise = model.linearize(states, control)
    assert torch.equal(noise, model.noise_covariance(states, control))
    assert torch.equal(moved, model.mean(states, control))
    base = UnicycleOdometry().linearize(states, control)
    torch.testing.assert_close(noise - base[2],
                               torch.eye(3, dtype=torch.float64).expand(
                                   4, 3, 3), rtol=0, atol=1e-15)
    torch.testing.assert_close(jac, base[1], rtol=0, atol=1e-15)


def test_closed_form_derivatives_are_autograd_of_the_formula():
    # the unicycle's F and G and the range-bearing Jacobian in closed form
    # equal reverse-mode differentiation of propagate() and expected()
    # (zero distance included), and their own derivatives equal the second
    # derivatives of the formula: training differentiates through them
    from tg_nebp.utils import row_jacobian, row_linearization
    states = torch.randn(6, 3, dtype=torch.float64, generator=gen(7))
    control = torch.randn(6, 2, dtype=torch.float64, generator=gen(8))
    moved, jac, gain = UnicycleOdometry.propagate_derivatives(states,
                                                              control)
    out, (jac_ad, gain_ad) = row_linearization(UnicycleOdometry.propagate,
                                               (states, control))
    assert torch.equal(moved, out)
    torch.testing.assert_close(jac, jac_ad, rtol=0, atol=1e-15)
    torch.testing.assert_close(gain, gain_ad, rtol=0, atol=1e-15)
    sender = torch.randn(6, 3, dtype=torch.float64, generator=gen(9))
    receiver = torch.randn(6, 3, dtype=torch.float64, generator=gen(10))
    receiver[2, :2] = sender[2, :2]  # zero distance: no gradient
    model = GaussianRangeBearing()

    def autograd(snd, rcv, create_graph=None):
        return row_jacobian(lambda both: model.expected(both[:, :3],
                                                        both[:, 3:]),
                            torch.cat([snd, rcv], -1), create_graph)

    closed = model.measurement_jacobian(sender, receiver)
    torch.testing.assert_close(closed, autograd(sender, receiver), rtol=0,
                               atol=1e-14)
    assert torch.equal(closed[2], torch.zeros(2, 6, dtype=torch.float64))
    for function, reference in (
            (lambda x: model.measurement_jacobian(x, receiver),
             lambda x: autograd(x, receiver, True)),
            (lambda x: UnicycleOdometry.propagate_derivatives(x, control)[1],
             lambda x: row_linearization(UnicycleOdometry.propagate,
                                         (x, control), True)[1][0])):
        point = sender.clone().requires_grad_()
        ours = function(point)
        weights = torch.randn(ours.shape, dtype=torch.float64,
                              generator=gen(11))
        ours, = torch.autograd.grad((ours * weights).sum(), point)
        theirs, = torch.autograd.grad((reference(point) * weights).sum(),
                                      point)
        torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-13)


def test_a_subclass_own_formula_is_differentiated_as_written():
    # a subclass that moves (or measures) by a formula of its own gets its
    # derivatives by automatic differentiation of that formula, not the
    # parent's closed form
    class Slower(UnicycleOdometry, name='test-slower-unicycle'):
        @staticmethod
        def propagate(states, control):
            return UnicycleOdometry.propagate(states, control * torch.tensor(
                [0.5, 2.0], dtype=control.dtype))

    class Shifted(GaussianRangeBearing, name='test-shifted-range-bearing'):
        @staticmethod
        def expected(sender, receiver):
            return GaussianRangeBearing.expected(sender, receiver) ** 2

    states = torch.randn(4, 3, dtype=torch.float64, generator=gen(5))
    control = torch.rand(4, 2, dtype=torch.float64, generator=gen(6))
    moved, jac, _ = Slower().linearize(states, control)
    torch.testing.assert_close(moved, Slower.propagate(states, control))
    torch.testing.assert_close(
        jac, MotionModel.jacobian(Slower(), states, control=control),
        rtol=0, atol=1e-15)
    assert (jac - UnicycleOdometry().linearize(states, control)[1]).abs(
    ).max() > 0.1
    model, sender = Shifted(), states + 1.0
    both = torch.cat([sender, states], -1)
    from tg_nebp.utils import row_jacobian
    torch.testing.assert_close(
        model.measurement_jacobian(sender, states),
        row_jacobian(lambda x: model.expected(x[:, :3], x[:, 3:]), both),
        rtol=0, atol=1e-15)


def test_unicycle_samples_match_the_linearized_moments():
    # small noise: the draws' mean and covariance are f(x, u) and G M G^T
    model = UnicycleOdometry(sigma_distance=0.002, distance_scale=0.01,
                             sigma_turn=0.002, turn_scale=0.01,
                             turn_per_distance=0.005)
    state = torch.tensor([[1.0, -1.0, 2.5]], dtype=torch.float64)
    control = torch.tensor([[0.8, 0.4]], dtype=torch.float64)
    draws = model.sample(state.expand(40000, 3), gen(3),
                         control=control)
    mean = model.mean(state, control=control)[0]
    cov = model.noise_covariance(state, control=control)[0]
    offset = draws - mean
    se = (cov.diagonal() / 40000).sqrt()
    assert bool((offset.mean(0).abs() < 5 * se + 1e-7).all())
    empirical = offset.T @ offset / 40000
    assert torch.allclose(empirical, cov, rtol=0.05, atol=2e-7)
    # without input: the random walk
    idle = model.sample(state.expand(20000, 3), gen(4))
    assert torch.allclose(idle.std(0), torch.tensor(
        [0.5, 0.5, 0.5], dtype=torch.float64), rtol=0.03)


def test_unicycle_measure_adds_the_input_noise():
    model = UnicycleOdometry()
    true = torch.tensor([[0.5, 0.2]], dtype=torch.float64).expand(30000, 2)
    read = model.measure(true, gen(5))
    expected = model.input_variances(true[:1])[0].sqrt()
    assert torch.allclose((read - true).std(0), expected, rtol=0.03)
    assert model.with_time_step(0.25) is model
    assert model_from_config(model.config(), 'motion') == model


def _range_bearing_loop(z, sender, receiver, sigma, sigma_bearing):
    # the Gaussian range-bearing log-likelihood of one pair, float64 math
    dx, dy = sender[0] - receiver[0], sender[1] - receiver[1]
    d = math.hypot(dx, dy)
    bearing = math.atan2(dy, dx) - receiver[2]
    residual = z[1] - bearing
    residual = math.atan2(math.sin(residual), math.cos(residual))
    return (-0.5 * ((z[0] - d) / sigma)**2 -
            0.5 * (residual / sigma_bearing)**2 -
            math.log(2 * math.pi * sigma * sigma_bearing))


def _bound(model):
    return resolve_models(UnicycleOdometry(), model)[1]


def test_range_bearing_likelihood_against_a_loop_across_the_cut():
    model = _bound(GaussianRangeBearing(sigma=0.2, sigma_bearing=0.1))
    sender = torch.tensor([[-1.0, 0.01, 0.0], [3.0, 4.0, 1.0],
                           [0.0, -2.0, 0.5]], dtype=torch.float64)
    receiver = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, -2.0],
                             [0.0, 0.0, 3.1]], dtype=torch.float64)
    # the first link's bearing is just below pi and measured just above
    # -pi: a residual of a few hundredths, not of a turn
    z = torch.tensor([[1.1, -math.pi + 0.02], [5.2, 2.9], [1.8, 1.5]],
                     dtype=torch.float64)
    log_lik = model.log_likelihood(z, sender.unsqueeze(1),
                                   receiver.unsqueeze(1))
    for k in range(3):
        assert float(log_lik[k, 0]) == pytest.approx(_range_bearing_loop(
            z[k].tolist(), sender[k].tolist(), receiver[k].tolist(), 0.2,
            0.1), abs=1e-10)
    residual = model.residuals(z, sender.unsqueeze(1),
                               receiver.unsqueeze(1))[0, 0]
    assert float(residual[1]) == pytest.approx(
        0.02 + math.pi - math.atan2(0.01, -1.0), abs=1e-12)


@pytest.mark.parametrize('cls', [GaussianRangeBearing, StudentTRangeBearing])
def test_range_bearing_linearization(cls):
    # the gradient against finite differences of the model's own
    # likelihood, and the curvature H^T W H with H written out, at a
    # bearing near the cut
    model = _bound(cls(sigma=0.3, sigma_bearing=0.05))
    sender = torch.tensor([[-2.0, 0.05, 0.3, ], [1.0, 2.0, -1.0]],
                          dtype=torch.float64)
    receiver = torch.tensor([[0.0, 0.0, 0.0], [-1.0, 0.5, 2.0]],
                            dtype=torch.float64)
    z = torch.tensor([[2.2, -3.1], [2.4, -1.4]], dtype=torch.float64)
    grad, curvature = model.linearize(z, sender, receiver)
    assert grad.shape == (2, 6) and curvature.shape == (2, 6, 6)
    ends = torch.cat([sender, receiver], -1)
    eps = 1e-6
    for j in range(6):
        step = torch.zeros(6, dtype=torch.float64)
        step[j] = eps

        def log_lik(at):
            return model.log_likelihood(z, at[:, None, :3],
                                        at[:, None, 3:])[:, 0]

        numeric = (log_lik(ends + step) - log_lik(ends - step)) / (2 * eps)
        assert torch.allclose(grad[:, j], numeric, atol=1e-6)
    for k in range(2):
        dx, dy = (sender[k, :2] - receiver[k, :2]).tolist()
        q = dx * dx + dy * dy
        d = math.sqrt(q)
        h = torch.tensor([[dx / d, dy / d, 0, -dx / d, -dy / d, 0],
                          [-dy / q, dx / q, 0, dy / q, -dx / q, -1]],
                         dtype=torch.float64)
        r = model.residuals(z[k:k + 1], sender[k:k + 1, None],
                            receiver[k:k + 1, None])[0, 0]
        if cls is GaussianRangeBearing:
            w = torch.tensor([0.3**-2, 0.05**-2], dtype=torch.float64)
        else:
            w = (3 + 1) / (3 * torch.tensor([0.3, 0.05],
                                            dtype=torch.float64)**2 + r**2)
        assert torch.allclose(curvature[k], h.T @ torch.diag(w) @ h,
                              rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize('cls', [GaussianRangeBearing, StudentTRangeBearing])
def test_range_bearing_fisher_information_against_monte_carlo(cls):
    # the closed form against the generic Monte Carlo of the squared score
    # over the model's own draws (MeasurementModel.fisher_information)
    model = _bound(cls(sigma=0.3, sigma_bearing=0.1))
    sender = torch.tensor([[3.0, 1.0, 0.0]], dtype=torch.float64)
    receiver = torch.tensor([[0.0, 0.0, 0.4]], dtype=torch.float64)
    z = torch.zeros(1, 2, dtype=torch.float64)
    exact = model.fisher_information(z, sender, receiver)[0]
    model.fisher_samples = 200000
    generic = MeasurementModel.fisher_information(model, z, sender, receiver,
                                                  gen(7))[0]
    assert torch.allclose(generic, exact, rtol=0.03, atol=0.03 *
                          float(exact.abs().max()))


def test_field_of_view_against_a_loop():
    model = _bound(GaussianRangeBearing(max_range=5.0,
                                        field_of_view=math.pi / 2))
    states = torch.rand(30, 3, dtype=torch.float64, generator=gen(8))
    states[:, :2] *= 10
    states[:, 2] = states[:, 2] * 2 * math.pi - math.pi
    receiver = torch.arange(30) < 20
    edges = model.connect_states(states, receiver)
    expected = set()
    for i in range(20):
        for j in range(30):
            dx, dy = (states[j, :2] - states[i, :2]).tolist()
            if i == j or math.hypot(dx, dy) > 5.0:
                continue
            bearing = math.atan2(dy, dx) - float(states[i, 2])
            bearing = math.atan2(math.sin(bearing), math.cos(bearing))
            if abs(bearing) <= math.pi / 4:
                expected.add((j, i))
    assert set(map(tuple, edges.t().tolist())) == expected
    assert expected  # the test sees links


def test_range_bearing_samples():
    model = _bound(GaussianRangeBearing(sigma=0.2, sigma_bearing=0.1))
    sender = torch.tensor([[1.0, 3.0, 0.0]], dtype=torch.float64).expand(
        20000, 3)
    receiver = torch.tensor([[0.0, 0.0, -3.0]],
                            dtype=torch.float64).expand(20000, 3)
    z = model.sample_features(sender, receiver, None, None, gen(9))
    residual = model.residuals(z, sender[:, None], receiver[:, None])[:, 0]
    assert torch.allclose(residual.std(0), torch.tensor(
        [0.2, 0.1], dtype=torch.float64), rtol=0.03)
    assert bool((residual.mean(0).abs() < 0.005).all())
    assert bool(((z[:, 1] > -math.pi) & (z[:, 1] <= math.pi)).all())


def test_range_bearing_needs_a_heading():
    # a [p, v] state has none, and neither has a layout without an angle
    with pytest.raises(ValueError, match='heading'):
        resolve_models(None, GaussianRangeBearing())[1].scope(4)
    with pytest.raises(ValueError, match='heading at entry 2'):
        GaussianRangeBearing().bind(StateLayout(3, 2, ()))


def test_a_range_model_reads_the_robot_position():
    # bound to the unicycle's layout, a range model reads [x, y] of
    # [x, y, heading] (not the first half of the state)
    motion, model = resolve_models(UnicycleOdometry(), GaussianRange(0.5))
    assert model.scope(3) == (0, 1)
    assert model == GaussianRange(0.5)  # its configuration is its own
    sender = torch.tensor([[[3.0, 4.0, 2.0]]], dtype=torch.float64)
    receiver = torch.tensor([[[0.0, 0.0, -1.0]]], dtype=torch.float64)
    z = torch.tensor([[5.5]], dtype=torch.float64)
    expected = -0.5 * (0.5 / 0.5)**2 - math.log(math.sqrt(2 * math.pi) *
                                                0.5)
    assert float(model.log_likelihood(z, sender, receiver)) == \
        pytest.approx(expected)
    info = model.fisher_information(z, sender[:, 0], receiver[:, 0])[0]
    assert info.shape == (6, 6)
    assert float(info[2, 2]) == 0.0 and float(info[5, 5]) == 0.0
    assert float(info[0, 0]) == pytest.approx(0.6**2 / 0.25)


def test_a_layout_with_a_heading_binds_at_any_size():
    # [x, y, heading, speed]: the position is half the state, yet the
    # heading must be known to the model
    bound = GaussianRangeBearing().bind(StateLayout(4, 2, (2, )))
    assert bound.scope(4) == (0, 1, 2)


def _robots_at_one_point():
    # robots 0 and 1 together (the same truth, prior and odometry) with
    # range-bearing links between them, and robot 2 on a landmark with a
    # link from it, at every step: links at zero distance for every
    # method's linearization point
    from tg_nebp.datasets import Scenario
    scenario = Scenario.load('robots_train').replace(num_steps=4)
    data = scenario.generate(gen(0))
    landmark = int(data.anchor.nonzero()[0])
    data.states[1] = data.states[0]
    data.prior_mean[1] = data.prior_mean[0]
    data.control[1] = data.control[0]
    data.states[2, :, :2] = data.states[landmark, :, :2]
    data.prior_mean[2, :2] = data.states[landmark, 0, :2]
    added = [(t, j, i) for t in range(4)
             for j, i in ((0, 1), (1, 0), (landmark, 2))]
    edge_index = torch.cat([data.edge_index, torch.tensor(
        [(j, i) for _, j, i in added]).t()], 1)
    edge_attr = torch.cat([data.edge_attr, data.edge_attr.new_tensor(
        [[0.05, 0.0]] * len(added))])
    edge_time = torch.cat([data.edge_time, torch.tensor(
        [t for t, _, _ in added])])
    order = torch.argsort(edge_time * data.num_nodes + edge_index[1],
                          stable=True)
    data.edge_index, data.edge_attr = edge_index[:, order], edge_attr[order]
    data.edge_time = edge_time[order]
    return scenario, data


def test_a_range_bearing_link_at_zero_distance_carries_no_information():
    # the Jacobian there is zero, not 0/0
    model = GaussianRangeBearing()
    state = torch.tensor([[1.0, 2.0, 0.3]], dtype=torch.float64)
    jacobian = model.measurement_jacobian(state, state.clone())
    assert torch.equal(jacobian, torch.zeros_like(jacobian))
    assert model.expected(state, state).tolist() == [[0.0, -0.3]]


EVERY_METHOD = ['gbp', 'gbp-lag3', 'gbp-lag4-settled', 'iekf', 'iekf-lag3',
                'iekf-smoother', 'iekf-incremental', 'pcrb', 'pcrb-lag3',
                'bp', 'hybrid']


def _finite_run(method, scenario, data):
    # every output of the method on the data is finite
    from tg_nebp.bounds import PosteriorCRB
    from tg_nebp.filters import (CentralizedIEKF, CentralizedSmoother,
                                 FixedLagGaussianBP, GaussianBP, HybridBP,
                                 IncrementalSmoother, ParticleBP)
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    tracker = {
        'gbp': lambda: GaussianBP.recommended(**models),
        'gbp-lag3': lambda: FixedLagGaussianBP.recommended(lag=3, **models),
        'gbp-lag4-settled': lambda: FixedLagGaussianBP.recommended(
            lag=4, iterated=2, **models),
        'iekf': lambda: CentralizedIEKF(**models),
        'iekf-lag3': lambda: CentralizedSmoother(3, **models),
        'iekf-smoother': lambda: CentralizedSmoother(None, **models),
        'iekf-incremental': lambda: IncrementalSmoother(**models),
        'pcrb': lambda: PosteriorCRB(**models),
        'pcrb-lag3': lambda: PosteriorCRB(lag=3, **models),
        'bp': lambda: ParticleBP(num_particles=50, **models),
        'hybrid': lambda: HybridBP.recommended(num_particles=20, **models),
    }[method]()
    out = tracker(data, gen(1)) if method in ('bp', 'hybrid') else \
        tracker(data)
    for value in (out, ) if torch.is_tensor(out) else (out.mean, out.cov):
        assert bool(torch.isfinite(value).all())


@pytest.mark.parametrize('method', EVERY_METHOD)
def test_every_method_stays_finite_at_zero_distance(method):
    _finite_run(method, *_robots_at_one_point())


@pytest.mark.parametrize('method', EVERY_METHOD)
def test_every_method_takes_the_largest_input_and_refuses_beyond(method):
    # an odometry row of a kilometre or of 1e20 rad in one step left a
    # raw linear-algebra error steps later: the inputs whose heading noise
    # stays within pi (the model's representable()) keep every method
    # finite, at the edge too; beyond, the row is refused by name
    from tg_nebp.datasets import Scenario
    scenario = Scenario.load('robots_train').replace(num_steps=4)
    motion = scenario.motion_model
    data = scenario.generate(gen(0))
    reach = (math.pi ** 2 - motion.sigma_turn ** 2) ** 0.5
    edge = torch.tensor([[0.999 * reach / motion.turn_per_distance, 0.0],
                         [0.0, 0.999 * reach / motion.turn_scale]])
    assert bool(motion.representable(edge).all())
    assert not bool(motion.representable(1.002 * edge).any())
    assert bool(motion.representable(torch.full((2, ), math.nan)))
    data.control[0, 1], data.control[1, 2] = edge
    _finite_run(method, scenario, data)
    data.control[1, 2] = 1.002 * edge[1]
    with pytest.raises(ValueError, match=(
            r"'control\[1, 2\]' = \[0.0, 62\.8\d*\] is beyond the inputs "
            r"the motion model UnicycleOdometry\(.*\) represents \(an "
            r"input whose heading noise")):
        _finite_run(method, scenario, data)
