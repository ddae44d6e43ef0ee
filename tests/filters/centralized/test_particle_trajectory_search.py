import numpy as np
import pytest
import torch

from tg_nebp.filters import (CentralizedSmoother, IncrementalSmoother,
                             ParticleTrajectorySearch, Smoothed)
from tg_nebp.filters.centralized.centralized_smoother import _Slot as Slot
from tg_nebp.filters.centralized.particle_trajectory_search import (
    _unlinked_movers, agent_costs, held_slot, link_log_likelihoods)
from tg_nebp.gaussian import GraphLayout

from helpers import Given, gen, mirror, tiny_scenario

#: The third anchor of the mirror's test: 1.5 m off the line of the other
#: two, so that the whole sequence's links decide the side (the smoother's
#: own test of a start's basin).
THIRD = (20.0, 1.5)


def flipped(data):
    # the truth with the agent reflected across the anchors' line (y = 0),
    # its velocity too: a start on the mirror
    start = data.states.double().clone()
    start[0, :, 1] = -start[0, :, 1]
    start[0, :, 3] = -start[0, :, 3]
    return start


def broad_mirror(third=THIRD):
    # the agent moving along the anchors' line at 5 m, its prior on the
    # line and broad, so that either side is as likely before the links
    return mirror(third, steps=12, third_from=0, velocity=0.3, prior_y=0.0,
                  prior_sd=5.0)


def test_a_start_on_the_mirror_is_left_for_the_better_basin():
    data, models = broad_mirror()
    truth = data.states[0, :, :2].double()
    plain = CentralizedSmoother(None, **models)
    kept = plain.smoothed_from(data, flipped(data))
    # without the search the smoother keeps the start's basin
    assert float((kept.mean[0, :, :2] - truth).norm(dim=-1).min()) > 8
    searching = CentralizedSmoother(None, search=ParticleTrajectorySearch(),
                                    **models)
    found = searching.smoothed_from(data, flipped(data), gen(0))
    assert float((found.mean[0, :, :2] - truth).norm(dim=-1).max()) < 1.5
    # the basin it moved to is the truth's: its optimum, to the
    # iterations' tolerance
    reference = plain.smoothed_from(data, data.states)
    torch.testing.assert_close(found.mean, reference.mean, rtol=0,
                               atol=1e-5)


def test_a_truly_ambiguous_agent_is_never_moved():
    # two anchors only and a prior on their line: the mirror costs the same
    data, models = broad_mirror(third=None)
    plain = CentralizedSmoother(None, **models).smoothed_from(
        data, flipped(data))
    searched = CentralizedSmoother(
        None, search=ParticleTrajectorySearch(), **models).smoothed_from(
        data, flipped(data), gen(0))
    assert torch.equal(searched.mean, plain.mean)
    assert torch.equal(searched.cov, plain.cov)


def test_of_several_starts_the_lowest_cost_basin_wins_in_either_order():
    data, models = broad_mirror()
    plain = CentralizedSmoother(None, **models)
    truth_basin = plain.smoothed_from(data, data.states.double()).mean
    on_mirror = Given(flipped(data), **models)
    on_truth = Given(data.states.double(), **models)
    alone = CentralizedSmoother(None, start=on_mirror, **models)(data).mean
    assert float((alone[0, :, :2] - truth_basin[0, :, :2]).norm(
        dim=-1).min()) > 8  # the mirror's start alone keeps its basin
    for starts in ([on_mirror, on_truth], (on_truth, on_mirror)):
        smoother = CentralizedSmoother(None, start=starts, **models)
        torch.testing.assert_close(smoother(data).mean, truth_basin,
                                   rtol=0, atol=1e-9)
        assert smoother.starts == tuple(starts)
        assert len(smoother.settings()['start']) == 2
    with pytest.raises(TypeError, match="'start' must be a Tracker, a "
                       "non-empty sequence"):
        CentralizedSmoother(None, start=[])
    with pytest.raises(TypeError, match=r"'start\[1\]' must be a Tracker"):
        CentralizedSmoother(None, start=[on_truth, 'incremental'])
    with pytest.raises(ValueError, match='needs lag=None'):
        CentralizedSmoother(4, start=[on_truth])


def smoother_problem(seed=2):
    # a tiny scenario's whole sequence as the smoother holds it: its prior,
    # every step's links, and the filter's estimates, a solution to hold
    data = tiny_scenario(steps=6).generate(gen(seed))
    smoother = CentralizedSmoother(None)
    layout = GraphLayout.of(data)
    base, slots, (points, ) = smoother._problem(data, layout)[0]
    return data, smoother, base, slots, points


def costs_by_loops(smoother, data, slots, held_at, states):
    # every agent's negative log-posterior (up to constants that cancel
    # between two trajectories), float64 loops: the prior of its first
    # step (the data's prior predicted one step), each transition's
    # residual weighted by the pseudo-inverse of its noise, and the
    # Gaussian range of every link it has, the other end held at
    # 'held_at'
    motion, sigma = smoother.motion, smoother.measurement.sigma
    agents = (~data.anchor).nonzero().flatten().tolist()
    out = []
    for a, node in enumerate(agents):
        mean0 = data.prior_mean[node].double()
        jac = motion.jacobian(mean0).numpy()
        p0 = jac @ data.prior_cov[node].double().numpy() @ jac.T + \
            motion.noise_covariance(mean0).numpy()
        r = states[0][a].numpy() - motion.mean(mean0).numpy()
        cost = 0.5 * r @ np.linalg.solve(p0, r)
        for k in range(1, len(states)):
            r = (states[k][a] - motion.mean(states[k - 1][a])).numpy()
            q = motion.noise_covariance(states[k - 1][a]).numpy()
            cost += 0.5 * r @ np.linalg.pinv(q, rcond=1e-9) @ r
        for k, slot in enumerate(slots):
            for e in range(slot.z.numel()):
                s, i = int(slot.sender[e]), int(slot.receiver[e])
                if a not in (s, i):
                    continue
                other = (held_at[k][i] if s == a else
                         held_at[k][s] if s >= 0 else slot.known[e])
                d = np.linalg.norm(states[k][a][:2].numpy() -
                                   other[:2].numpy())
                cost += 0.5 * (float(slot.z[e]) - d)**2 / sigma**2
        out.append(cost)
    return np.array(out)


def test_agent_costs_equal_plain_loops():
    data, smoother, base, slots, points = smoother_problem()
    held = [held_slot(slot, here) for slot, here in zip(slots, points)]
    g = gen(5)
    moved = [here + torch.randn(here.shape, generator=g,
                                dtype=here.dtype) for here in points]
    got = (agent_costs(smoother, base, held, moved) -
           agent_costs(smoother, base, held, points)).numpy()
    want = costs_by_loops(smoother, data, slots, points, moved) - \
        costs_by_loops(smoother, data, slots, points, points)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-8)
    # an agent's gain, its neighbours held, is the whole sequence's: the
    # smoother's own cost changes by it when that agent alone moves
    alone = [torch.where(torch.arange(here.size(0)).view(-1, 1) == 1,
                         move, here) for move, here in zip(moved, points)]
    whole = smoother._cost_of(base, slots, alone) - \
        smoother._cost_of(base, slots, points)
    np.testing.assert_allclose(float(whole), got[1], rtol=1e-9)


def test_link_log_likelihoods_equal_plain_loops():
    data, smoother, base, slots, points = smoother_problem()
    particles = points[0].unsqueeze(1) + torch.randn(
        (points[0].size(0), 7, 4), generator=gen(6), dtype=torch.float64)
    slot = slots[0]
    got = link_log_likelihoods(smoother, slot, points[0], particles)
    sigma = smoother.measurement.sigma
    want = torch.zeros_like(got)
    for e in range(slot.z.numel()):
        s, i = int(slot.sender[e]), int(slot.receiver[e])
        for a, other in ((i, points[0][s] if s >= 0 else slot.known[e]),
                         (s, points[0][i])):
            if a < 0:
                continue
            for p in range(7):
                d = float((particles[a, p, :2] - other[:2]).norm())
                want[a, p] += -0.5 * (float(slot.z[e]) - d)**2 / sigma**2 \
                    - np.log(sigma * np.sqrt(2 * np.pi))
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)


def test_lineages_keep_the_current_trajectory_and_are_the_models_own():
    data, smoother, base, slots, points = smoother_problem()
    search = ParticleTrajectorySearch(num_particles=50, candidates=3,
                                      separation=0.5)
    chosen = search.lineages(smoother, base, slots, points, gen(7))
    current = torch.stack(points)
    for trajectory, exists in chosen:
        # far enough from the current trajectory at some step, else absent
        apart = (trajectory[..., :2] - current[..., :2]).norm(dim=-1)
        assert bool((apart.amax(0)[exists] > 0.5).all())
        # a lineage follows the motion model's draws: every transition
        # lies on its noise's subspace (a constant-velocity model's: the
        # velocity's change fixes the position's)
        for k in range(1, len(points)):
            r = trajectory[k] - smoother.motion.mean(trajectory[k - 1])
            torch.testing.assert_close(r[:, :2], 0.5 * r[:, 2:],
                                       rtol=0, atol=1e-9)
    # the same generator's seed, the same candidates
    again = search.lineages(smoother, base, slots, points, gen(7))
    for (a, x), (b, y) in zip(chosen, again):
        assert torch.equal(a, b) and torch.equal(x, y)


def test_a_move_lowers_the_smoothers_cost_by_its_gain_at_least():
    data, models = broad_mirror()
    smoother = CentralizedSmoother(None, **models)
    base, slots, (start, ) = smoother._problem(data, GraphLayout.of(data), [[
        [state[~data.anchor].unsqueeze(0)] for state in
        flipped(data).unbind(1)]])[0]
    solved = smoother._solve(base, slots, start)[0]
    search = ParticleTrajectorySearch()
    result = search.sweep(smoother, base, slots, solved, gen(0))
    assert result.moved.tolist() == [True]
    # the best lineage away from the mirror, before its Gauss-Newton
    # iterations, already follows the truth: the links rank the lineages
    (lineage, exists), = ParticleTrajectorySearch(candidates=1).lineages(
        smoother, base, slots, solved, gen(0))
    assert exists.tolist() == [True]
    assert float((lineage[:, 0, :2] - data.states[0, :, :2].double()).norm(
        dim=-1).max()) < 1.5
    gain = float(result.cost[0] - result.candidate_cost[0].min())
    assert gain > search.margin
    escaped = search.escaped(smoother, base, slots, (solved, None),
                             gen(0))[0]
    # (the moved agent's optimum is already the whole sequence's here, so
    # the two sides are equal up to rounding: two sums of the same terms)
    before = float(smoother._cost_of(base, slots, solved))
    assert float(smoother._cost_of(base, slots, escaped)) <= \
        before - gain + 1e-9 * before


def test_agents_that_share_a_link_do_not_move_in_one_sweep():
    # agents 0 and 1 share a link at the second step, 2 has only an
    # anchor's: of 0 and 1 the one that gains more moves, and 2 with it;
    # a gain within the margin never moves
    z = torch.zeros(1, 1)
    anchor = Slot(z, torch.tensor([-1]), torch.tensor([2]),
                  torch.zeros(1, 4), None)
    pair = Slot(z, torch.tensor([0]), torch.tensor([1]), torch.zeros(1, 4),
                None)
    slots = [anchor, pair]
    moved = _unlinked_movers(torch.tensor([20.0, 30.0, 15.0]), 10.0, slots)
    assert moved.tolist() == [False, True, True]
    moved = _unlinked_movers(torch.tensor([40.0, 30.0, 9.0]), 10.0, slots)
    assert moved.tolist() == [True, False, False]


def test_refusals():
    with pytest.raises(ValueError, match='needs lag=None'):
        CentralizedSmoother(5, search=ParticleTrajectorySearch())
    with pytest.raises(TypeError, match="'search' must be"):
        CentralizedSmoother(None, search='particles')
    with pytest.raises(ValueError, match="'num_particles' must be at least"):
        ParticleTrajectorySearch(num_particles=1)
    with pytest.raises(ValueError, match="'resampler' must be one of"):
        ParticleTrajectorySearch(resampler='best')
    smoother = CentralizedSmoother(None, search=ParticleTrajectorySearch())
    assert smoother.settings()['search']['num_particles'] == 500
    assert 'ParticleTrajectorySearch(num_particles=500' in repr(smoother)


def test_the_incremental_start_is_the_incremental_smoothers_last_step():
    data = tiny_scenario(steps=6).generate(gen(4))
    incremental = IncrementalSmoother()
    *_, last = incremental.steps(data)
    smoother = CentralizedSmoother(None, start=Smoothed(incremental))
    from_it = smoother.smoothed_from(data, last.window_mean)
    torch.testing.assert_close(smoother(data).mean, from_it.mean, rtol=0,
                               atol=1e-12)
    assert smoother.settings()['start'] == dict(incremental.settings(),
                                                smoothed=True)
    assert 'start' not in CentralizedSmoother(None).settings()
    with pytest.raises(TypeError, match="'start' must be a Tracker"):
        CentralizedSmoother(None, start='incremental')
    assert smoother.starts == (smoother.start, )
    assert CentralizedSmoother(None).starts == ()
    with pytest.raises(ValueError, match='needs lag=None'):
        CentralizedSmoother(4, start=Smoothed(incremental))


def test_the_sequence_cost_is_the_smoothers_and_lower_at_the_better_basin():
    data, models = broad_mirror()
    smoother = CentralizedSmoother(None, **models)
    truth_basin = smoother.smoothed_from(data, data.states)
    mirror_basin = smoother.smoothed_from(data, flipped(data))
    base, slots, (points, ) = smoother._problem(data, GraphLayout.of(data), [[
        [state[~data.anchor].unsqueeze(0)] for state in
        truth_basin.mean.double().unbind(1)]])[0]
    assert float(smoother.sequence_cost(data, truth_basin.mean)) == float(
        smoother._cost_of(base, slots, points))
    # the third anchor's ranges decide: its basin is the better by far
    assert float(smoother.sequence_cost(data, mirror_basin.mean)) > float(
        smoother.sequence_cost(data, truth_basin.mean)) + 10
    with pytest.raises(ValueError, match="'states' must be a tensor"):
        smoother.sequence_cost(data, data.states[:, :3])
