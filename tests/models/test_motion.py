import math

import numpy as np
import pytest
import torch

from tg_nebp.models import ConstantVelocityDrag


def paper_transition(x, a, c, dt):
    r"""x_n = F x + W (-c v|v|) + W a with explicit numpy matrices."""
    eye, zero = np.eye(2), np.zeros((2, 2))
    F = np.block([[eye, dt * eye], [zero, eye]])
    W = np.vstack([0.5 * dt**2 * eye, dt * eye])
    v = x[2:]
    return F @ x + W @ (-c * v * np.abs(v)) + W @ a


@pytest.mark.parametrize('drag,dt', [(0.06, 1.0), (0.3, 0.5), (0.0, 2.0)])
def test_propagate_matches_paper_matrices(drag, dt):
    g = torch.Generator().manual_seed(0)
    states = torch.randn(7, 3, 4, generator=g, dtype=torch.float64) * 2
    accel = torch.randn(7, 3, 2, generator=g, dtype=torch.float64)
    model = ConstantVelocityDrag(sigma_a=0.05, drag=drag, dt=dt)
    out = model.propagate(states, accel)
    assert out.shape == states.shape
    x, a = states.numpy().reshape(-1, 4), accel.numpy().reshape(-1, 2)
    ref = np.stack(
        [paper_transition(xi, ai, drag, dt) for xi, ai in zip(x, a)])
    np.testing.assert_allclose(out.numpy().reshape(-1, 4), ref, rtol=1e-12,
                               atol=1e-12)


def test_drag_is_elementwise_and_opposes_velocity():
    model = ConstantVelocityDrag(sigma_a=0.05, drag=0.1, dt=1.0)
    states = torch.tensor([[0.0, 0.0, 2.0, -3.0]], dtype=torch.float64)
    out = model.propagate(states, torch.zeros(1, 2, dtype=torch.float64))
    # v_n = v - c v |v| (elementwise): [2 - 0.4, -3 + 0.9]
    np.testing.assert_allclose(out[0, 2:].numpy(), [1.6, -2.1])
    np.testing.assert_allclose(out[0, :2].numpy(), [2.0 - 0.2, -3.0 + 0.45])


def test_sample_noise_statistics():
    sigma_a, dt, n = 0.05, 1.0, 200_000
    model = ConstantVelocityDrag(sigma_a=sigma_a, drag=0.06, dt=dt)
    g = torch.Generator().manual_seed(1)
    states = torch.randn(n, 4, generator=g, dtype=torch.float64)
    out = model.sample(states, generator=torch.Generator().manual_seed(2))
    noise_free = model.propagate(states,
                                 torch.zeros(n, 2, dtype=torch.float64))
    diff = (out - noise_free).numpy()
    # the velocity part of the noise is W_v a = dt * a: recover a
    a = diff[:, 2:] / dt
    # the position part is dt^2/2 * a exactly (same draw)
    np.testing.assert_allclose(diff[:, :2], 0.5 * dt**2 * a, atol=1e-12)
    # mean: each component has std sigma_a / sqrt(n); 5-sigma bound
    assert np.all(np.abs(a.mean(0)) < 5 * sigma_a / math.sqrt(n))
    # covariance sigma_a^2 I: variance estimates have std ~ sigma^2 sqrt(2/n),
    # the covariance estimate std ~ sigma^2 / sqrt(n)
    cov = np.cov(a.T)
    tol_var = 5 * sigma_a**2 * math.sqrt(2 / n)
    tol_cov = 5 * sigma_a**2 / math.sqrt(n)
    assert abs(cov[0, 0] - sigma_a**2) < tol_var
    assert abs(cov[1, 1] - sigma_a**2) < tol_var
    assert abs(cov[0, 1]) < tol_cov


def test_sample_is_reproducible_with_generator():
    model = ConstantVelocityDrag()
    states = torch.zeros(5, 4)
    a = model.sample(states, generator=torch.Generator().manual_seed(3))
    b = model.sample(states, generator=torch.Generator().manual_seed(3))
    c = model.sample(states, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_sample_keeps_dtype_and_shape():
    model = ConstantVelocityDrag()
    states = torch.zeros(2, 3, 4, dtype=torch.float64)
    out = model.sample(states, generator=torch.Generator().manual_seed(0))
    assert out.dtype == torch.float64 and out.shape == (2, 3, 4)


def test_zero_noise_is_deterministic():
    model = ConstantVelocityDrag(sigma_a=0.0, drag=0.06)
    states = torch.randn(10, 4, generator=torch.Generator().manual_seed(0))
    out = model.sample(states, generator=torch.Generator().manual_seed(1))
    expected = model.propagate(states, torch.zeros(10, 2))
    torch.testing.assert_close(out, expected)


@pytest.mark.parametrize('name,kwargs', [
    ('sigma_a', dict(sigma_a=-0.1)),
    ('sigma_a', dict(sigma_a=float('nan'))),
    ('sigma_a', dict(sigma_a=float('inf'))),
    ('drag', dict(drag=-1.0)),
    ('drag', dict(drag=float('nan'))),
    ('dt', dict(dt=0.0)),
    ('dt', dict(dt=-1.0)),
    ('dt', dict(dt=float('inf'))),
])
def test_bad_parameters_raise(name, kwargs):
    with pytest.raises(ValueError, match=f"'{name}'"):
        ConstantVelocityDrag(**kwargs)


@pytest.mark.parametrize('drag,dt', [(0.06, 1.0), (0.3, 0.5), (0.0, 2.0)])
def test_gaussian_form_matches_paper_matrices(drag, dt):
    # mean = F x - c W (v |v|); Jacobian F - c W diag(2 |v|) on the
    # velocities; noise covariance sigma_a^2 W W^T (explicit matrices)
    sigma_a = 0.07
    model = ConstantVelocityDrag(sigma_a=sigma_a, drag=drag, dt=dt)
    states = torch.randn(6, 4, generator=torch.Generator().manual_seed(2),
                         dtype=torch.float64)
    eye, zero = np.eye(2), np.zeros((2, 2))
    F = np.block([[eye, dt * eye], [zero, eye]])
    W = np.vstack([0.5 * dt**2 * eye, dt * eye])
    for x, mean, jac, cov in zip(states.numpy(), model.mean(states),
                                 model.jacobian(states),
                                 model.noise_covariance(states)):
        np.testing.assert_allclose(mean.numpy(), paper_transition(
            x, np.zeros(2), drag, dt), rtol=1e-12, atol=1e-12)
        expected = F + W @ np.hstack([zero, -2 * drag * np.diag(
            np.abs(x[2:]))])
        np.testing.assert_allclose(jac.numpy(), expected, rtol=1e-12,
                                   atol=1e-12)
        np.testing.assert_allclose(cov.numpy(), sigma_a**2 * W @ W.T,
                                   rtol=1e-12, atol=1e-15)


def test_jacobian_keeps_leading_shape():
    model = ConstantVelocityDrag()
    states = torch.randn(2, 3, 4, dtype=torch.float64)
    assert model.jacobian(states).shape == (2, 3, 4, 4)
    assert model.noise_covariance(states).shape == (2, 3, 4, 4)


def test_a_model_without_a_gaussian_form_says_so():
    from tg_nebp.models import MotionModel

    class Teleport(MotionModel, name='test-teleport'):
        def params(self):
            return {}

        def sample(self, states, generator=None):
            return torch.rand(states.shape, generator=generator)

    for method in ('mean', 'noise_covariance', 'jacobian'):
        with pytest.raises(NotImplementedError, match='Teleport.*no '
                           'additive-Gaussian-noise form'):
            getattr(Teleport(), method)(torch.zeros(1, 4))
