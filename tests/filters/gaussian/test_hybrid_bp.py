r"""Hybrid BP: its estimates are the Gaussian tracker's where the particles
agree (the Kalman filter on a tree), its particles converge to the Kalman
posterior as their number grows, keep both modes of a mirror ambiguity with
the weights of a grid posterior where Gaussian BP keeps one, a lost agent
is relocated from its links within the search period while a consistent
one never is, a batch equals each graph alone, the same seed gives the
same draws; streaming, save/resume and damaged states are in
tests/filters/live/test_session.py (live_trackers)."""
import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2
from torch_geometric.data import Batch

from tg_nebp.filters import (CentralizedIEKF, FixedLagGaussianBP, GaussianBP,
                             GaussianNEBP, HybridBP)
from tg_nebp.filters import silverman_bandwidth
from tg_nebp.filters.gaussian.hybrid_bp import kernel_density
from tg_nebp.models import ConstantVelocity
from tg_nebp.utils import weighted_moments

from helpers import (assert_symmetric_positive_definite, gen,
                     linear_kalman_filter, linear_offset_model,
                     linear_scenario, mirror, randomize, tiny_scenario,
                     tree_realization)


def test_the_kernel_density_is_the_mixture_at_every_point():
    # every node's mixture of its centers' Gaussians, evaluated at its
    # points by plain loops in float64, in blocks of nodes of any size
    points = torch.randn(5, 4, 3, generator=gen(1), dtype=torch.float64)
    centers = torch.randn(5, 6, 3, generator=gen(2), dtype=torch.float64)
    log_weights = torch.randn(5, 6, generator=gen(3),
                              dtype=torch.float64).log_softmax(-1)
    factor = torch.randn(5, 3, 3, generator=gen(4), dtype=torch.float64)
    lower = torch.linalg.cholesky(factor @ factor.mT +
                                  0.5 * torch.eye(3, dtype=torch.float64))
    expected = torch.empty(5, 4, dtype=torch.float64)
    for n in range(5):
        for p in range(4):
            expected[n, p] = math.log(sum(
                math.exp(log_weights[n, l]) * math.exp(
                    torch.distributions.MultivariateNormal(
                        centers[n, l], scale_tril=lower[n]).log_prob(
                            points[n, p]))
                for l in range(6)))
    for size in (1, 2, 5, 512):
        torch.testing.assert_close(
            kernel_density(points, centers, log_weights, lower, size),
            expected, rtol=0, atol=1e-12)


def test_on_a_tree_it_reports_the_kalman_filter():
    # linear Gaussian links on a space-time tree, a window as long as the
    # sequence: the Gaussian tracker is the Kalman filter and no agent is
    # lost, so the reports are the filter's
    scenario, data = tree_realization(steps=4)
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    means, covs, agents = linear_kalman_filter(data, *models.values())
    tracker = HybridBP(FixedLagGaussianBP(4, num_iterations=60,
                                          tolerance=1e-12, **models))
    out = tracker(data, gen(1))
    np.testing.assert_allclose(out.mean[agents].numpy(), means, atol=1e-8)
    np.testing.assert_allclose(out.cov[agents].numpy(), covs, atol=1e-8)


def test_its_particles_converge_to_the_kalman_filter():
    # one agent, linear Gaussian links to two anchors: the particle belief
    # is the Kalman posterior sampled, up to Monte Carlo and the kernel's
    # smoothing, which both vanish as K grows: the mean error over 8 steps
    # and 3 seeds at K = 3,200 is below half of K = 200's, and every
    # particle mean lies within 5 of the posterior's standard deviations
    # over the square root of its effective sample size (plus the
    # kernel's bias, h^2 of them)
    data = linear_scenario(steps=8, num_agents=1).generate(gen(4))
    models = dict(motion=data_models(), measurement=linear_offset_model()())
    means, covs, agents = linear_kalman_filter(data, *models.values())
    errors = {}
    for count in (200, 3200):
        gaps = []
        for seed in range(3):
            tracker = HybridBP(GaussianBP(num_iterations=5, tolerance=None,
                                          **models), num_particles=count)
            for t, step in enumerate(tracker.steps(data, gen(seed))):
                weights = step.log_weights[agents].exp()
                particle = weighted_moments(step.particles[agents],
                                            step.log_weights[agents])[0]
                gap = particle[:, :2].numpy() - means[:, t, :2]
                sd = np.sqrt(covs[:, t, [0, 1], [0, 1]])
                ess = (1 / weights.square().sum(-1)).numpy()[:, None]
                h2 = silverman_bandwidth(count, 4)**2
                assert float(np.abs(gap / sd).max()) < 5 / np.sqrt(
                    ess.min()) + h2, (count, seed, t)
                gaps.append(np.abs(gap).mean())
        errors[count] = float(np.mean(gaps))
    assert errors[3200] < 0.5 * errors[200]


def data_models():
    # linear_scenario's motion model
    return ConstantVelocity(0.1)


@pytest.mark.parametrize('third', [(15.0, 3.0), (-4.0, 4.0)])
def test_a_lost_agent_is_relocated_from_its_links(third):
    # the prior on the mirror position: two anchors cannot tell, and when
    # a third one contradicts it Gaussian BP and the centralized IEKF stay
    # in the wrong local optimum; hybrid BP finds the agent within the
    # search period and is consistent again (NEES inside the 99 % band)
    data, models = mirror(third)
    truth = data.states[0, 0, :2].double()
    for method in (GaussianBP.recommended(**models),
                   CentralizedIEKF(**models)):
        last = list(method.steps(data))[-1]
        assert float((last.mean[0, :2] - truth).norm()) > 5
    hybrid = HybridBP.recommended(**models)
    steps = list(hybrid.steps(data, gen(0)))
    errors = [float((s.mean[0, :2] - truth).norm()) for s in steps]
    assert min(errors[:3]) > 8  # lost while two anchors cannot tell
    # found at its first search after the third anchor's first range
    found = next(t for t, e in enumerate(errors) if e < 1.0)
    assert 3 <= found < 3 + hybrid.gaussian.relocation.every
    for step in steps[found:]:
        error = step.mean[0, :2] - truth
        nees = float(error @ torch.linalg.solve(step.cov[0, :2, :2], error))
        assert nees < chi2.ppf(0.99, 2)


def test_consistent_agents_are_never_relocated():
    # several tiny networks, no agent off: every agent with links searched
    # in turn, none relocated, and the reports are Gaussian BP's bit for
    # bit (the same Gaussian arithmetic runs inside: the particles and the
    # search only read its beliefs)
    searched, moved = 0, 0
    for seed in range(4):
        data = tiny_scenario(steps=15).generate(gen(40 + seed))
        hybrid = HybridBP.recommended()
        solve = hybrid.gaussian.solve_step

        def counted(*args, call=solve, **kwargs):
            nonlocal searched, moved
            solved = call(*args, **kwargs)
            searched += int(solved.search.searched.sum())
            moved += int(solved.search.moved.sum())
            return solved

        hybrid.gaussian.solve_step = counted
        ours = hybrid(data, gen(seed))
        theirs = GaussianBP.recommended()(data)
        assert torch.equal(ours.mean, theirs.mean)
        assert torch.equal(ours.cov, theirs.cov)
    # each agent at its first step and every fourth after
    assert moved == 0 and searched >= 4 * 3 * 15 // 4


def test_two_modes_are_kept_with_the_weights_of_the_grid_posterior():
    # an agent measured by two anchors, its prior wide and a little above
    # their line: the posterior has two modes (the agent and its mirror);
    # on a float64 grid the mass above the line is about 0.7. The particle
    # belief holds both modes with that mass (within 0.1), Gaussian BP's
    # Gaussian puts almost all of it on one side
    data, models = mirror(third=(100.0, 100.0), prior_y=1.5, steps=1,
                          prior_sd=4.0, third_from=1)
    z = data.edge_attr[:, 0].double()
    axis = torch.linspace(-15, 15, 601, dtype=torch.float64)
    x, y = torch.meshgrid(axis + 5, axis, indexing='ij')
    points = torch.stack([x, y], -1)
    anchors = data.prior_mean[1:3, :2].double()
    log_post = -0.5 * ((points - torch.tensor([5.0, 1.5],
                                              dtype=torch.float64)
                        ).square().sum(-1) / (16.0 + 0.0025))
    for a in range(2):
        distance = (points - anchors[a]).norm(dim=-1)
        log_post = log_post - 0.5 * (z[a] - distance).square() / 0.09
    weights = torch.softmax(log_post.flatten(), 0).view(log_post.shape)
    above = float(weights[y > 0].sum())
    assert 0.6 < above < 0.8
    hybrid = HybridBP.recommended(num_particles=2000, **models)
    step, = hybrid.steps(data, gen(3))
    mass = step.log_weights[0].exp()
    particle_above = float(mass[step.particles[0, :, 1] > 0].sum())
    assert particle_above == pytest.approx(above, abs=0.1)
    # each mode where the grid puts it
    for sign in (1, -1):
        side = (step.particles[0, :, 1] * sign > 0)
        mode = (mass[side].unsqueeze(-1) * step.particles[0, side, :2]
                ).sum(0) / mass[side].sum()
        grid_side = (y * sign > 0)
        grid_mode = torch.stack([(weights * x)[grid_side].sum(),
                                 (weights * y)[grid_side].sum()]) / \
            weights[grid_side].sum()
        assert float((mode - grid_mode).norm()) < 0.3
    gaussian = GaussianBP.recommended(**models)(data)
    sd = float(gaussian.cov[0, 0, 1, 1].sqrt())
    below = 0.5 * math.erfc(float(gaussian.mean[0, 0, 1]) / (sd * math.sqrt(
        2)))
    assert min(below, 1 - below) < 0.05


def test_a_batch_equals_each_graph_alone_and_a_seed_its_draws():
    # one generator per graph: each graph of a batch gets its draws alone
    scenario = tiny_scenario(steps=4)
    graphs = [scenario.generate(gen(1)),
              scenario.replace(num_agents=5).generate(gen(2))]
    tracker = HybridBP.recommended(num_particles=30)
    alone = [list(tracker.steps(d, [gen(10 + k)]))
             for k, d in enumerate(graphs)]
    batch = list(tracker.steps(Batch.from_data_list(graphs),
                               [gen(10), gen(11)]))
    for t, step in enumerate(batch):
        for field in ('mean', 'cov', 'particles', 'log_weights'):
            torch.testing.assert_close(
                getattr(step, field), torch.cat([getattr(a[t], field)
                                                 for a in alone]),
                rtol=1e-10, atol=1e-12)
    again = list(tracker.steps(graphs[0], [gen(10)]))
    other = list(tracker.steps(graphs[0], [gen(12)]))
    assert all(torch.equal(a.particles, b.particles)
               for a, b in zip(again, alone[0]))
    assert not torch.equal(other[-1].particles, again[-1].particles)


@pytest.mark.parametrize('make', [
    lambda: HybridBP.recommended(lag=3),
    lambda: HybridBP(randomize(GaussianNEBP.recommended(hidden_dim=8),
                               seed=5, scale=0.1))])
def test_any_gaussian_tracker_inside(make):
    # over a window (the filtered estimates of fixed-lag Gaussian BP) or a
    # learned correction: the reports are that tracker's where nothing is
    # lost, and every covariance is symmetric positive definite
    data = tiny_scenario(steps=6).generate(gen(3))
    hybrid = make()
    with torch.no_grad():
        ours = hybrid(data, gen(0))
        theirs = hybrid.gaussian(data)
    assert torch.equal(ours.mean, theirs.mean)
    agents = ~data.anchor
    assert_symmetric_positive_definite(ours.cov[agents])


def test_the_particles_are_inflated_by_the_gaussians_own_factor():
    # a learned inflation reads the covariance of the belief it inflates:
    # the particles get the factor the Gaussian tracker gives its own
    # belief (on a cloud collapsed onto a particle, whose covariance is
    # subnormal, the learned factor was NaN and the whitening overflowed)
    class Recording(GaussianNEBP):
        def inflation_of(self, cov, memory, anchor):
            seen.append(cov)
            return super().inflation_of(cov, memory, anchor)

    seen = []
    data = tiny_scenario(steps=4).generate(gen(3))
    gaussian = randomize(Recording.recommended(hidden_dim=8), seed=5,
                         scale=0.1)
    hybrid = HybridBP(gaussian, num_particles=30)
    with torch.no_grad():
        states = [state for _, state in _stepped(hybrid, data)]
    # each step after the first: the particles' call and the tracker's
    # read the same covariance, the Gaussian belief's of the step before
    assert len(seen) == 2 * (len(states) - 1)
    for t in range(1, len(states)):
        particle_call, gaussian_call = seen[2 * t - 2], seen[2 * t - 1]
        assert torch.equal(particle_call, states[t - 1].cov)
        assert torch.equal(gaussian_call, states[t - 1].cov)


def _stepped(hybrid, data):
    # (output, state) after every step of one realization
    state = hybrid.initial_state(data, gen(0))
    for t, (edge_index, edge_attr) in enumerate(data.edges_by_step()):
        output, state = hybrid.step(state, edge_index, edge_attr,
                                    data.anchor, t, gen(t))
        yield output, state


def test_robots_and_three_dimensions_run():
    # odometry inputs and range-bearing links (the general messages of a
    # model without a closed form) and positions in 3-D
    from tg_nebp.datasets import load_scenario
    for name, steps in (('robots_test', 8), ('box3d_test', 4)):
        scenario = load_scenario(name).replace(num_steps=steps)
        if name == 'box3d_test':
            scenario = scenario.replace(num_agents=6)
        data = scenario.generate(gen(2))
        models = dict(motion=scenario.motion_model,
                      measurement=scenario.measurement_model)
        out = HybridBP.recommended(num_particles=40, **models)(data, gen(1))
        gaussian = GaussianBP.recommended(**models)(data)
        agents = ~data.anchor
        assert bool(torch.isfinite(out.mean).all())
        # nothing lost in a short run: Gaussian BP's estimates
        torch.testing.assert_close(out.mean[agents], gaussian.mean[agents])


def test_bad_settings_are_refused_by_name():
    for options, match in ((dict(proposal=0.0), "'proposal'"),
                           (dict(proposal=0.9, modes=0.1),
                            r"'proposal' \+ 'modes'"),
                           (dict(spread=0.5), "'spread'"),
                           (dict(bandwidth=1.0), "'bandwidth'"),
                           (dict(num_particles=0), "'num_particles'")):
        with pytest.raises(ValueError, match=match):
            HybridBP(**options)
    with pytest.raises(TypeError, match="'gaussian'"):
        HybridBP(gaussian=CentralizedIEKF())
    with pytest.raises(ValueError, match="'motion' and 'measurement'"):
        HybridBP(GaussianBP(), motion=ConstantVelocity())
    assert isinstance(HybridBP.recommended(lag=2).gaussian,
                      FixedLagGaussianBP)
