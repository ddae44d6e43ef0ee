import numpy as np
import pytest
import torch

from tg_nebp.gaussian import (WoodburyPrior, add_link_information,
                              block_diagonal, check_dense_joint, joint_cross,
                              marginal_blocks, predict_joint, range_blocks,
                              rts_backward, rts_backward_chain, scope_index,
                              unit_vectors)

from helpers import gen


def test_block_diagonal_and_marginals_round_trip():
    blocks = torch.randn(3, 4, 4, generator=gen(0), dtype=torch.float64)
    joint = block_diagonal(blocks)
    expected = np.zeros((12, 12))
    for a in range(3):
        expected[4 * a:4 * a + 4, 4 * a:4 * a + 4] = blocks[a].numpy()
    np.testing.assert_array_equal(joint.numpy(), expected)
    torch.testing.assert_close(marginal_blocks(joint, 4), blocks)


def test_predict_joint_is_the_dense_product():
    g = gen(1)
    root = torch.randn(8, 8, generator=g, dtype=torch.float64)
    cov = root @ root.t()
    jac = torch.randn(2, 4, 4, generator=g, dtype=torch.float64)
    noise = torch.randn(2, 4, 4, generator=g, dtype=torch.float64)
    noise = noise @ noise.transpose(1, 2)
    F = block_diagonal(jac)
    expected = F @ cov @ F.t() + block_diagonal(noise)
    torch.testing.assert_close(predict_joint(cov, jac, noise), expected)


def test_link_information_against_a_loop():
    # three agents and an anchor (-1); every link's 8 x 8 block on
    # [x_j; x_i] added entry by entry in plain loops
    g = gen(2)
    blocks = torch.randn(5, 8, 8, generator=g, dtype=torch.float64)
    sender = torch.tensor([0, -1, 2, 1, -1])
    receiver = torch.tensor([1, 0, 0, 2, 2])
    info = add_link_information(torch.zeros(12, 12, dtype=torch.float64),
                                blocks, sender, receiver)
    expected = np.zeros((12, 12))
    for e in range(5):
        ends = (int(sender[e]), int(receiver[e]))
        for a in range(2):
            for b in range(2):
                if ends[a] < 0 or ends[b] < 0:
                    continue
                for r in range(4):
                    for c in range(4):
                        expected[4 * ends[a] + r, 4 * ends[b] + c] += float(
                            blocks[e, 4 * a + r, 4 * b + c])
    np.testing.assert_allclose(info.numpy(), expected, rtol=1e-12,
                               atol=1e-12)


def test_range_blocks_are_the_gradient_outer_product():
    # d = |p_j - p_i| has gradient [u, 0, -u, 0] in [x_j; x_i]
    diff = torch.tensor([[3.0, 4.0], [0.0, 0.0]], dtype=torch.float64)
    lengths, unit = unit_vectors(diff)
    torch.testing.assert_close(lengths, torch.tensor([5.0, 0.0],
                                                     dtype=torch.float64))
    assert unit[1].abs().max() == 0  # no direction, no information
    blocks = range_blocks(unit, torch.tensor([2.0, 1.0],
                                             dtype=torch.float64), 4)
    grad = torch.tensor([0.6, 0.8, 0, 0, -0.6, -0.8, 0, 0],
                        dtype=torch.float64)
    torch.testing.assert_close(blocks[0], 2.0 * torch.outer(grad, grad))
    assert blocks[1].abs().max() == 0


def test_woodbury_update_is_the_inverse_of_the_updated_information():
    # (P^-1 + E^T M E)^-1 on the positions of 3 agents with states of 4,
    # against dense inverses in float64; the third agent has no link (a
    # singular M)
    g = gen(3)
    index = scope_index(3, 4, (0, 1))
    assert index.tolist() == [0, 1, 4, 5, 8, 9]
    root = torch.randn(12, 12, generator=g, dtype=torch.float64)
    cov = root @ root.T / 12 + 0.1 * torch.eye(12, dtype=torch.float64)
    part = torch.randn(6, 6, generator=g, dtype=torch.float64)
    info = part @ part.T
    info[4:], info[:, 4:] = 0.0, 0.0
    embedded = torch.zeros(12, 12, dtype=torch.float64)
    embedded[index.view(-1, 1), index] = info
    expected = torch.linalg.inv(torch.linalg.inv(cov) + embedded)
    update = WoodburyPrior.of(cov, index).updated(info)
    covariance = update.covariance()
    torch.testing.assert_close(covariance, expected, rtol=1e-10, atol=1e-12)
    assert torch.equal(covariance, covariance.T)
    vector = torch.randn(12, generator=g, dtype=torch.float64)
    torch.testing.assert_close(update.solve(vector), expected @ vector,
                               rtol=1e-10, atol=1e-12)


def test_dense_joint_check_names_the_sizes():
    check_dense_joint(100, 4, 'the test', free=10**9)
    with pytest.raises(ValueError, match=r'the test of a graph of 10000 '
                       r'agents needs dense 40000 x 40000 float64 matrices, '
                       r'about 71.5 GiB .* 1 GiB are free on cpu: it runs up '
                       r'to about 1182 agents'):
        check_dense_joint(10_000, 4, 'the test', free=2**30)


def _belief_and_prediction(seed, count, size=4):
    # random belief covariances (count, size, size) and their predictions,
    # wider in a 2-D subspace only: the links measured two directions, the
    # others not at all
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(count, size, size, generator=g, dtype=torch.float64)
    cov = a @ a.transpose(-1, -2) + 0.1 * torch.eye(size)
    b = torch.randn(count, size, 2, generator=g, dtype=torch.float64)
    return cov, cov + 3.0 * b @ b.transpose(-1, -2)


def test_bounded_inflation_against_the_generalized_eigenproblem():
    # a slow reference: scipy's generalized eigenvectors V of (P, C)
    # (V^T C V = I, V^T P V = diag(lambda)); the inflated covariance is
    # V^-T diag(min(kappa, max(lambda, 1))) V^-1, one matrix at a time
    import scipy.linalg
    from tg_nebp.gaussian import bounded_inflation
    count = 6
    cov, predicted = _belief_and_prediction(3, count)
    kappa = torch.linspace(0.9, 4.0, count, dtype=torch.float64)
    out = bounded_inflation(cov, predicted, kappa)
    for n in range(count):
        lam, v = scipy.linalg.eigh(predicted[n].numpy(), cov[n].numpy())
        factor = np.minimum(float(kappa[n]), np.maximum(lam, 1.0))
        inv = np.linalg.inv(v)
        expected = inv.T @ np.diag(factor) @ inv
        np.testing.assert_allclose(out[n].numpy(), expected, rtol=1e-9,
                                   atol=1e-10)
        # never wider than the prediction, never narrower than the belief
        # where kappa >= 1
        assert np.linalg.eigvalsh(predicted[n].numpy() -
                                  out[n].numpy()).min() > -1e-9
        if kappa[n] >= 1:
            assert np.linalg.eigvalsh(out[n].numpy() -
                                      cov[n].numpy()).min() > -1e-9
    # links that narrowed every direction at least kappa times: kappa C
    wide = bounded_inflation(cov, 10 * cov, torch.full((count, ), 1.5,
                                                       dtype=torch.float64))
    torch.testing.assert_close(wide, 1.5 * cov, rtol=1e-10, atol=1e-10)


def test_the_inflation_map_moves_a_cloud_as_the_covariance_is_inflated():
    # A C A^T is bounded_inflation's covariance; a cloud with no usable
    # Cholesky factor (an anchor's zero, a cloud collapsed onto one
    # particle: a covariance of subnormal entries, whose factor whitens
    # the prediction beyond float64's range) stays where it is
    from tg_nebp.gaussian import bounded_inflation, bounded_inflation_map
    count, size = 5, 4
    cov, predicted = _belief_and_prediction(4, count, size)
    kappa = torch.linspace(1.2, 4.0, count, dtype=torch.float64)
    cov[3] = 0.0
    cov[4] = torch.diag(torch.tensor([1.5e-318, 3e-317, 2e-319, 4.5e-320],
                                     dtype=torch.float64))
    mapping = bounded_inflation_map(cov, predicted, kappa)
    assert bool(torch.isfinite(mapping).all())
    inflated = bounded_inflation(cov, predicted, kappa)
    torch.testing.assert_close(mapping[:3] @ cov[:3] @ mapping[:3].mT,
                               inflated[:3], rtol=1e-9, atol=1e-12)
    eye = torch.eye(size, dtype=torch.float64).expand(2, -1, -1)
    assert torch.equal(mapping[3:], eye)


def test_rts_step_is_the_conditional_of_the_joint_gaussian():
    # x0 ~ N(m, P), x1 = F x0 + w (w singular: the constant-velocity
    # models'), y = H x1 + v: the smoothed x0 given y from one backward
    # step equals the conditional of the dense joint of (x0, x1, y)
    g = gen(4)
    size, count = 4, 3
    A = torch.randn(count * size, count * size, dtype=torch.float64,
                    generator=g)
    P = A @ A.t() + 0.5 * torch.eye(count * size, dtype=torch.float64)
    m = torch.randn(count * size, dtype=torch.float64, generator=g)
    blocks = torch.randn(count, size, size, dtype=torch.float64,
                         generator=g)
    F = block_diagonal(blocks)
    W = torch.randn(count * size, 2, dtype=torch.float64, generator=g)
    Q = W @ W.t()
    H = torch.randn(5, count * size, dtype=torch.float64, generator=g)
    R = 0.3 * torch.eye(5, dtype=torch.float64)
    y = torch.randn(5, dtype=torch.float64, generator=g)
    # the filter: predict, update; the backward step
    predicted = F @ P @ F.t() + Q
    predicted_mean = F @ m
    gain = predicted @ H.t() @ torch.linalg.inv(H @ predicted @ H.t() + R)
    updated_mean = predicted_mean + gain @ (y - H @ predicted_mean)
    updated = predicted - gain @ H @ predicted
    cross = joint_cross(P, blocks)
    torch.testing.assert_close(cross, P @ F.t())
    mean, cov = rts_backward(P, cross, predicted, updated, m,
                             predicted_mean, updated_mean)
    # the dense joint of (x0, y): cov(x0, y) = P F^T H^T
    cov_xy = P @ F.t() @ H.t()
    cov_yy = H @ predicted @ H.t() + R
    expected = m + cov_xy @ torch.linalg.solve(cov_yy, y - H @ predicted_mean)
    expected_cov = P - cov_xy @ torch.linalg.solve(cov_yy, cov_xy.t())
    torch.testing.assert_close(mean, expected, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(cov, expected_cov, rtol=1e-9, atol=1e-10)
    assert torch.equal(cov, cov.t())
    # the covariance alone, and many small ones at once
    _, alone = rts_backward(P, cross, predicted, updated)
    torch.testing.assert_close(alone, cov)
    _, batched = rts_backward(P.expand(2, -1, -1), cross.expand(2, -1, -1),
                              predicted.expand(2, -1, -1),
                              updated.expand(2, -1, -1))
    torch.testing.assert_close(batched[1], cov)


@pytest.mark.parametrize('count', [1, 2, 7, 8])
def test_the_backward_pass_of_a_chain_at_once_is_step_by_step(count):
    # a random linear chain (two chains side by side, singular driving
    # noise): the parallel prefix equals K steps of rts_backward
    g = torch.Generator().manual_seed(count)
    size = 3

    def spd(*shape):
        a = torch.randn(*shape, size, size, dtype=torch.float64, generator=g)
        return a @ a.transpose(-1, -2) + 0.1 * torch.eye(size,
                                                         dtype=torch.float64)

    filtered_mean = torch.randn(2, count, size, dtype=torch.float64,
                                generator=g)
    filtered_cov = spd(2, count)
    jacobian = torch.randn(2, count, size, size, dtype=torch.float64,
                           generator=g)
    root = torch.randn(2, count, size, 1, dtype=torch.float64, generator=g)
    cross = filtered_cov @ jacobian.transpose(-1, -2)
    predicted_cov = jacobian @ cross + root @ root.transpose(-1, -2)
    predicted_mean = (jacobian @ filtered_mean.unsqueeze(-1)).squeeze(-1)
    smoothed_mean = torch.randn(2, size, dtype=torch.float64, generator=g)
    smoothed_cov = spd(2)
    mean, cov = rts_backward_chain(filtered_mean, filtered_cov,
                                   predicted_mean, predicted_cov, cross,
                                   smoothed_mean, smoothed_cov)
    after_mean, after_cov = smoothed_mean, smoothed_cov
    for k in range(count - 1, -1, -1):
        after_mean, after_cov = rts_backward(
            filtered_cov[:, k], cross[:, k], predicted_cov[:, k], after_cov,
            filtered_mean[:, k], predicted_mean[:, k], after_mean)
        torch.testing.assert_close(mean[:, k], after_mean, rtol=1e-9,
                                   atol=1e-10)
        torch.testing.assert_close(cov[:, k], after_cov, rtol=1e-9,
                                   atol=1e-10)
    assert torch.equal(cov, cov.transpose(-1, -2))
