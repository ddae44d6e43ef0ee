r"""Tests of :mod:`tg_nebp.utils`."""
import math

import pytest
import torch
from torch import Tensor
from torch_geometric import EdgeIndex, Index

from tg_nebp.utils import (compute_dtype, floored_exp, log_normalize,
                           logaddexp, logsumexp, plain_tensor,
                           rounding_tolerance, sort_by_receiver,
                           symmetric_psd_defects, symmetrize,
                           weighted_moments)


def test_plain_tensor_strips_pyg_subclasses_without_copying():
    edges = torch.tensor([[0, 1, 2], [1, 2, 0]])
    edge_index = EdgeIndex(edges, sparse_size=(3, 3))
    index = Index(edges[1], dim_size=3)
    for wrapped, source in ((edge_index, edges), (index, edges[1]),
                            (edge_index[1], edges[1])):
        plain = plain_tensor(wrapped)
        assert type(plain) is Tensor
        assert plain.data_ptr() == source.data_ptr()  # zero-copy
        assert torch.equal(plain, source)
    assert plain_tensor(edges) is edges  # plain tensors pass through


# --------------------------------------------------------------- log_normalize

def reference_normalized(row):
    r"""Normalized weights of one row with plain float64 loops."""
    top = max(row)
    w = [math.exp(v - top) for v in row]
    return [v / sum(w) for v in w]


@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
@pytest.mark.parametrize('offset', [0.0, -1e3, -1e6, -1e10, -3e30])
def test_log_normalize_sums_to_one_at_any_offset(dtype, offset):
    # the failure: around -1e10, x - x.logsumexp() in float32 rounds
    # max + log(sum) back to max and tied particles each get weight one
    g = torch.Generator().manual_seed(0)
    spread = torch.randn(6, 50, generator=g, dtype=torch.float64) * 3
    spread[:, 10:20] = spread[:, :1]  # ties with each other
    spread[:, 20:25] = spread.amax(-1, keepdim=True)  # ties at the maximum
    rows = (offset + spread).to(dtype)
    weights = log_normalize(rows).double().exp()
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert not torch.isnan(weights).any()
    assert torch.allclose(weights.sum(-1), torch.ones(6, dtype=torch.float64),
                          atol=tol, rtol=0)
    for r in range(6):  # against the rows as stored in dtype
        expected = reference_normalized(rows[r].double().tolist())
        assert torch.allclose(weights[r], torch.tensor(expected,
                                                       dtype=torch.float64),
                              atol=tol, rtol=0)


def test_log_normalize_keeps_zero_rows_without_nan():
    rows = torch.tensor([[0.0, -1.0, float('-inf')],
                         [float('-inf')] * 3], requires_grad=True)
    out = log_normalize(rows)
    assert torch.isneginf(out[1]).all()
    assert torch.allclose(out[0, :2].exp().sum(), torch.tensor(1.0))
    out[:, :2].sum().backward()  # a finite part of every row
    assert not torch.isnan(rows.grad).any()
    assert torch.equal(rows.grad[1], torch.zeros(3))


def reference_logsumexp(values, dim):
    # plain loops in float64 over the other dimensions
    moved = values.double().movedim(dim, -1)
    out = torch.empty(moved.shape[:-1], dtype=torch.float64)
    for index in torch.cartesian_prod(*(torch.arange(n) for n in out.shape)
                                      ).view(-1, out.dim()).tolist():
        terms = moved[tuple(index)].tolist()
        top = max(terms)
        out[tuple(index)] = top if top == -math.inf else top + math.log(
            sum(math.exp(t - top) for t in terms))
    return out


@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
def test_logsumexp_matches_a_float64_loop_over_wide_ranges(dtype):
    # terms spanning thousands of nats (far particles), -inf terms, a slice
    # of -inf only, and a finite offset that float32 cannot hold exactly
    values = torch.randn(6, 3, 5, generator=torch.Generator().manual_seed(0),
                         dtype=torch.float64) * 400 - 1e4
    values[:, 0, 0] = -math.inf
    values[2, 1, :] = -math.inf
    values = values.to(dtype)
    for dim in (0, 2):
        out = logsumexp(values, dim)
        expected = reference_logsumexp(values, dim)
        assert out.dtype == dtype
        assert torch.equal(out.isneginf(), expected.isneginf())
        finite = expected.isfinite()
        torch.testing.assert_close(out.double()[finite], expected[finite],
                                   rtol=1e-7 if dtype == torch.float32
                                   else 1e-14, atol=0)


def test_logsumexp_gradient_is_the_softmax_and_never_nan():
    values = torch.randn(5, 4, generator=torch.Generator().manual_seed(1),
                         dtype=torch.float64) * 100
    values[:, 0] = -math.inf
    values[0, 1] = -math.inf
    values.requires_grad_()
    weights = torch.randn(4, generator=torch.Generator().manual_seed(2),
                          dtype=torch.float64)
    grad, = torch.autograd.grad((logsumexp(values, 0) * weights).sum(),
                                values)
    assert not grad.isnan().any()
    # terms raised to the floor (under 1e-34 of the largest) get zero
    expected = values.detach().softmax(0).nan_to_num(0.0) * weights
    torch.testing.assert_close(grad, expected, rtol=1e-12, atol=1e-30)


def pairs_with_wide_gaps():
    # pairs a few nats apart, hundreds of nats apart, ties, -inf on one or
    # both sides, and a broadcast column
    g = torch.Generator().manual_seed(3)
    a = torch.randn(6, 5, generator=g, dtype=torch.float64) * 300
    b = torch.randn(6, 5, generator=g, dtype=torch.float64) * 3
    a[0, 0] = b[0, 0]
    a[1, :2] = -math.inf
    b[1, 1:3] = -math.inf
    return a, b


@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
def test_logaddexp_matches_a_float64_loop(dtype):
    a, b = (t.to(dtype) for t in pairs_with_wide_gaps())
    out = logaddexp(a, b)
    assert out.dtype == dtype
    for x, y, z in zip(a.double().view(-1).tolist(),
                       b.double().view(-1).tolist(), out.view(-1).tolist()):
        top = max(x, y)
        if top == -math.inf:
            assert z == -math.inf
            continue
        expected = top + math.log(math.exp(x - top) + math.exp(y - top))
        assert abs(z - expected) <= (2e-7 if dtype == torch.float32 else
                                     1e-15) * max(abs(expected), 1.0) + \
            1e-34, (x, y, z, expected)
    column = b[:, :1].to(dtype)
    torch.testing.assert_close(logaddexp(a.to(dtype), column),
                               torch.logaddexp(a.to(dtype), column))


def test_logaddexp_gradient_equals_torch_and_is_never_nan():
    a, b = pairs_with_wide_gaps()
    assert bool((a.isneginf() & b.isneginf()).any())
    a.requires_grad_()
    b.requires_grad_()
    weights = torch.randn(6, 5, generator=torch.Generator().manual_seed(4),
                          dtype=torch.float64)
    out = logaddexp(a, b)
    live = out.isfinite()
    grads = torch.autograd.grad((out[live] * weights[live]).sum(), (a, b))
    assert not any(bool(g.isnan().any()) for g in grads)
    # torch's gradient, away from its NaN at (-inf, -inf); the floor adds
    # under 1e-34 to a vanishing term's gradient
    reference = torch.logaddexp(a, b)
    expected = torch.autograd.grad(
        (reference[live] * weights[live]).sum(), (a, b))
    for got, want in zip(grads, expected):
        torch.testing.assert_close(got, want.nan_to_num(0.0), rtol=1e-12,
                                   atol=1e-33)
    assert torch.autograd.gradcheck(
        logaddexp, (torch.randn(3, 4, dtype=torch.float64,
                                requires_grad=True),
                    torch.randn(1, 4, dtype=torch.float64,
                                requires_grad=True)))


def test_floored_exp_differs_from_exp_by_under_1e_34():
    values = torch.tensor([0.0, -3.0, -79.0, -200.0, -math.inf, 2.0])
    out = floored_exp(values)
    assert torch.equal(out[:3], values[:3].exp())
    assert bool((out - values.exp()).abs().max() < 1e-34)
    assert out[-1] == values[-1].exp()


def test_weighted_moments_normalize_unnormalized_log_weights():
    g = torch.Generator().manual_seed(1)
    particles = torch.randn(3, 40, 4, generator=g, dtype=torch.float64)
    log_weights = torch.randn(3, 40, generator=g, dtype=torch.float64)
    far = (log_weights - 1e10).float()  # quantized: compare as stored
    far_mean, far_cov = weighted_moments(particles.float(), far)
    mean, cov = weighted_moments(particles, far.double().log_softmax(-1))
    assert torch.allclose(far_mean.double(), mean, atol=1e-5)
    assert torch.allclose(far_cov.double(), cov, atol=1e-5)


@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
def test_weighted_moments_match_a_float64_loop_and_are_symmetric(dtype):
    # wide clouds of many particles in either precision: the covariance
    # equals a plain float64 double loop to the dtype's rounding, and is
    # exactly symmetric (the BLAS sums a product's triangles in orders of
    # its own)
    g = torch.Generator().manual_seed(2)
    particles = (torch.randn(4, 500, 3, generator=g, dtype=torch.float64) *
                 torch.tensor([30.0, 0.1, 5.0], dtype=torch.float64) + 10.0)
    log_weights = torch.randn(4, 500, generator=g, dtype=torch.float64)
    mean, cov = weighted_moments(particles.to(dtype), log_weights.to(dtype))
    assert torch.equal(cov, cov.mT)
    for n in range(4):
        x = particles[n].to(dtype).double().tolist()
        w = log_weights[n].to(dtype).double().exp().tolist()
        total = sum(w)
        mu = [sum(wk * xk[d] for wk, xk in zip(w, x)) / total
              for d in range(3)]
        for a in range(3):
            for b in range(3):
                c = sum(wk * (xk[a] - mu[a]) * (xk[b] - mu[b])
                        for wk, xk in zip(w, x)) / total
                scale = (cov[n, a, a] * cov[n, b, b]).double().sqrt()
                assert abs(float(cov[n, a, b]) - c) <= \
                    100 * torch.finfo(dtype).eps * float(scale)


def _defects_by_loop(matrix, tolerance):
    # asymmetric, indefinite and the smallest eigenvalue of one matrix,
    # with plain loops and numpy's float64 eigenvalues
    import numpy as np
    rows = matrix.double().tolist()
    size = len(rows)
    scale = max(abs(v) for row in rows for v in row)
    asymmetry = max(abs(rows[i][j] - rows[j][i]) for i in range(size)
                    for j in range(size))
    mean = [[0.5 * (rows[i][j] + rows[j][i]) for j in range(size)]
            for i in range(size)]
    lowest = float(np.linalg.eigvalsh(np.array(mean)).min())
    return asymmetry > tolerance * scale, lowest < -tolerance * scale, lowest


@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
def test_symmetric_psd_defects_match_a_loop(dtype):
    # random matrices near the edges of the tolerance, at scales 1e-8 to
    # 1e8: the masks and eigenvalues of a plain loop
    g = torch.Generator().manual_seed(3)
    tolerance = rounding_tolerance(dtype)
    matrices = []
    for k in range(60):
        root = torch.randn(3, 3, generator=g, dtype=torch.float64)
        cov = root @ root.mT
        scale = float(cov.abs().max())
        off = tolerance * scale * (0.5 + torch.rand(1, generator=g).item())
        kind = k % 3
        if kind == 1:  # asymmetric by about the tolerance
            cov[0, 2] += off
        elif kind == 2:  # an eigenvalue about the tolerance below zero
            values, vectors = torch.linalg.eigh(cov)
            values[0] = -off
            cov = symmetrize(vectors @ torch.diag(values) @ vectors.mT)
        matrices.append(cov * 10.0 ** (16 * (k / 59) - 8))
    batch = torch.stack(matrices).to(dtype)
    asymmetric, indefinite, lowest = symmetric_psd_defects(batch)
    assert asymmetric.shape == indefinite.shape == (60, )
    for k, matrix in enumerate(batch):
        a, i, low = _defects_by_loop(matrix, tolerance)
        assert bool(asymmetric[k]) == a, k
        assert bool(indefinite[k]) == i, k
        assert float(lowest[k]) == pytest.approx(
            low, rel=1e-9, abs=1e-12 * float(matrix.abs().max()))
    # about half of each kind beyond the tolerance
    assert 5 < int(asymmetric.sum()) < 20 and 5 < int(indefinite.sum()) < 20


@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf])
def test_a_non_finite_matrix_is_a_defect(bad):
    # a NaN or infinite matrix was reported as having no defect
    batch = torch.eye(2, dtype=torch.float64).repeat(3, 1, 1)
    batch[1, 0, 1] = bad
    asymmetric, indefinite, lowest = symmetric_psd_defects(batch)
    assert asymmetric.tolist() == [False, True, False]
    assert indefinite.tolist() == [False, True, False]
    assert math.isnan(float(lowest[1])) and lowest[[0, 2]].tolist() == [
        1.0, 1.0]


def test_rounding_tolerance_is_half_the_digits_of_the_dtype():
    assert rounding_tolerance(torch.float32) == pytest.approx(3.45e-4,
                                                              rel=1e-2)
    assert rounding_tolerance(torch.float64) == pytest.approx(1.49e-8,
                                                              rel=1e-2)
    # symmetrize averages the triangles: exactly symmetric
    g = torch.Generator().manual_seed(4)
    a = torch.randn(5, 3, 3, generator=g)
    s = symmetrize(a)
    assert torch.equal(s, s.mT)
    assert torch.equal(s.diagonal(dim1=-2, dim2=-1),
                       a.diagonal(dim1=-2, dim2=-1))


def test_compute_dtype_promotes_half_precision():
    half, single = torch.zeros(1, dtype=torch.float16), torch.zeros(1)
    double = torch.zeros(1, dtype=torch.float64)
    index = torch.zeros(1, dtype=torch.long)
    assert compute_dtype(half) == torch.float32
    assert compute_dtype(half, torch.zeros(1, dtype=torch.bfloat16)) \
        == torch.float32
    assert compute_dtype(single, double) == torch.float64
    assert compute_dtype(index) == torch.float32


@pytest.mark.parametrize('dtype', [torch.int32, torch.long])
def test_sort_by_receiver_is_stable_and_int64(dtype):
    edges = torch.tensor([[0, 1, 2, 3, 1], [2, 0, 0, 2, 1]], dtype=dtype)
    attr = torch.arange(5.0).view(-1, 1)
    edge_index, sorted_attr = sort_by_receiver(edges, 4, attr)
    assert edge_index.dtype == torch.long and edge_index.is_sorted_by_col
    assert edge_index.tolist() == [[1, 2, 1, 0, 3], [0, 0, 1, 2, 2]]
    assert sorted_attr.view(-1).tolist() == [1.0, 2.0, 4.0, 0.0, 3.0]
    # an EdgeIndex already sorted by receiver is passed through
    again, same = sort_by_receiver(edge_index, 4, sorted_attr)
    assert same is sorted_attr and torch.equal(again, edge_index)


def test_joined_process_group_outside_torchrun(monkeypatch):
    from tg_nebp.utils import joined_process_group, process_group
    monkeypatch.delenv('WORLD_SIZE', raising=False)
    with joined_process_group('cpu') as device:
        assert device == 'cpu' and process_group() == (1, 0)


def test_check_device_names_what_this_machine_lacks():
    from tg_nebp.utils import check_device
    assert check_device('cpu') == 'cpu'
    assert check_device(torch.device('cpu')) == 'cpu'  # the API's callers
    for bad, message in (('tpu', "'device' must be 'cpu', 'cuda' or"),
                         (3, "'device' must be 'cpu', 'cuda' or"),
                         ('cuda:99', "'device' is 'cuda:99', but")):
        with pytest.raises(ValueError, match=message):
            check_device(bad)


def test_row_jacobian_is_the_closed_form_and_differentiable():
    # f(x) = [x0 x1, sin x2, 3 x0] row by row: its Jacobian in closed form,
    # whatever the leading dimensions; the output that does not depend on
    # the point gives zeros; and where the point requires gradients (a
    # tracker trained through) the Jacobian is differentiable: d/dx0 of
    # the sum of its entries is 1 (from d(x0 x1)/dx1) and d/dx2 is -sin x2
    from tg_nebp.utils import row_jacobian

    def f(x):
        return torch.stack([x[..., 0] * x[..., 1], torch.sin(x[..., 2]),
                            3 * x[..., 0]], -1)

    x = torch.randn(4, 5, 3, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(0))
    jac = row_jacobian(f, x)
    expected = torch.zeros(4, 5, 3, 3, dtype=torch.float64)
    expected[..., 0, 0], expected[..., 0, 1] = x[..., 1], x[..., 0]
    expected[..., 1, 2] = torch.cos(x[..., 2])
    expected[..., 2, 0] = 3
    torch.testing.assert_close(jac, expected, rtol=0, atol=1e-15)
    assert not jac.requires_grad
    constant = row_jacobian(lambda p: torch.ones_like(p), x)
    assert torch.equal(constant, torch.zeros(4, 5, 3, 3, dtype=torch.float64))
    assert row_jacobian(f, x[:0]).shape == (0, 5, 3, 3)
    leaf = x.clone().requires_grad_()
    grad, = torch.autograd.grad(row_jacobian(f, leaf).sum(), leaf)
    torch.testing.assert_close(grad[..., 0], torch.ones_like(x[..., 0]))
    torch.testing.assert_close(grad[..., 1], torch.ones_like(x[..., 1]))
    torch.testing.assert_close(grad[..., 2], -torch.sin(x[..., 2]))
    with torch.no_grad():  # no graph where gradients are off
        assert not row_jacobian(f, leaf).requires_grad


def test_row_linearization_is_each_arguments_closed_form():
    # g(x, u) = [x0 u1, x1 + u0^2] row by row: the output and both
    # Jacobians from one pass; an argument the output does not read gets
    # zeros; the output is detached unless a graph is asked for
    from tg_nebp.utils import row_linearization

    def g(x, u, unused):
        return torch.stack([x[..., 0] * u[..., 1],
                            x[..., 1] + u[..., 0] ** 2], -1)

    generator = torch.Generator().manual_seed(1)
    x = torch.randn(3, 4, 2, dtype=torch.float64, generator=generator)
    u = torch.randn(3, 4, 2, dtype=torch.float64, generator=generator)
    unused = torch.randn(3, 4, 5, dtype=torch.float64, generator=generator)
    out, (in_x, in_u, none) = row_linearization(g, (x, u, unused))
    torch.testing.assert_close(out, g(x, u, unused), rtol=0, atol=0)
    expected_x = torch.zeros(3, 4, 2, 2, dtype=torch.float64)
    expected_x[..., 0, 0], expected_x[..., 1, 1] = u[..., 1], 1.0
    expected_u = torch.zeros(3, 4, 2, 2, dtype=torch.float64)
    expected_u[..., 0, 1], expected_u[..., 1, 0] = x[..., 0], 2 * u[..., 0]
    torch.testing.assert_close(in_x, expected_x, rtol=0, atol=1e-15)
    torch.testing.assert_close(in_u, expected_u, rtol=0, atol=1e-15)
    assert torch.equal(none, torch.zeros(3, 4, 2, 5, dtype=torch.float64))
    assert not out.requires_grad
    leaf = x.clone().requires_grad_()
    out, _ = row_linearization(g, (leaf, u, unused))
    grad, = torch.autograd.grad(out.sum(), leaf)
    torch.testing.assert_close(grad[..., 0], u[..., 1])
