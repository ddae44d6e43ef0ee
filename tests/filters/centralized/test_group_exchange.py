import pytest
import torch
from torch_geometric.loader import DataLoader

from tg_nebp.filters import (CentralizedSmoother, GroupExchange,
                             ParticleTrajectorySearch)
from tg_nebp.gaussian import GraphLayout
from tg_nebp.models import ConstantVelocity, GaussianRange

from helpers import (Given, assert_each_graph, gen, link_slots,
                     ranged_realization)

#: Two clusters 100 m apart, each with anchors on a line (y = 0) and a
#: third 1.5 m off it, so that the whole sequence's links decide each
#: agent's side: agents 0 and 1 (which range to each other) by the first,
#: agent 2 by the second (as the search's mirror test).
CLUSTERS = ((0.0, ((5.0, 5.0), (12.0, 5.0))), (100.0, ((105.0, 5.0), )))
STEPS = 12
VELOCITY = 0.3


def two_groups(third_y=1.5):
    # the agents moving along x at 0.3 m/s, their priors on the anchors'
    # line and broad, so that either side is as likely before the links;
    # the third anchor of each cluster 'third_y' off the line (0: every
    # link symmetric about it, the mirror as likely as the truth)
    agents, anchors, owner = [], [], []
    for offset, starts in CLUSTERS:
        base = len(anchors)
        anchors += [(offset, 0.0), (offset + 10.0, 0.0),
                    (offset + 20.0, third_y)]
        for start in starts:
            agents.append(start)
            owner.append(base)
    count = len(agents)
    num = count + len(anchors)
    states = torch.zeros(num, STEPS, 4)
    for a, (x, y) in enumerate(agents):
        states[a, :, 0] = x + VELOCITY * torch.arange(STEPS)
        states[a, :, 1] = y
        states[a, :, 2] = VELOCITY
    states[count:, :, :2] = torch.tensor(anchors).unsqueeze(1)
    step = []
    for a in range(count):
        step += [(count + owner[a] + k, a) for k in range(3)]
        if a == 1:  # agents 0 and 1 range to each other
            step.append((0, 1))
    prior_cov = torch.zeros(num, 4, 4)
    prior_cov[:count] = torch.diag(torch.tensor([25.0, 25.0, 0.01, 0.01]))
    data = ranged_realization(states, step, count, prior_cov)
    return data, dict(motion=ConstantVelocity(sigma_a=0.05),
                      measurement=GaussianRange(sigma=0.3))


def flipped(data, agents):
    # the truth with 'agents' reflected across their anchors' line (y = 0),
    # their velocities too: a start with that group lost on the mirror
    start = data.states.double().clone()
    start[agents, :, 1] = -start[agents, :, 1]
    start[agents, :, 3] = -start[agents, :, 3]
    return start


def lost(estimate, data):
    # the agents farther than 8 m from the truth at every step
    error = (estimate[:3, :, :2] - data.states[:3, :, :2].double()).norm(
        dim=-1)
    return (error.amin(1) > 8).nonzero().flatten().tolist()


def test_groups_lost_in_different_starts_are_exchanged_into_one_solution():
    data, models = two_groups()
    plain = CentralizedSmoother(None, **models)
    truth_basin = plain.smoothed_from(data, data.states.double()).mean
    # each start lost a different group: the pair in one, agent 2 in the
    # other
    starts = [Given(flipped(data, [0, 1]), **models),
              Given(flipped(data, [2]), **models)]
    for order in (starts, starts[::-1]):
        chosen = CentralizedSmoother(None, start=order, **models)(data).mean
        assert lost(chosen, data) in ([0, 1], [2])  # one basin or the other
        exchanging = CentralizedSmoother(None, start=order,
                                         exchange=GroupExchange(), **models)
        found = exchanging(data).mean
        assert lost(found, data) == []
        torch.testing.assert_close(found, truth_basin, rtol=0, atol=1e-5)
        assert float(plain.sequence_cost(data, found)) < float(
            plain.sequence_cost(data, chosen)) - 10
        # the same from the states themselves
        torch.testing.assert_close(exchanging.smoothed_from(data, [
            start.states for start in order]).mean, found, rtol=0,
            atol=1e-12)
    # the search, one agent at a time with its neighbours held, cannot move
    # the pair: each of its agents alone would break their link
    searching = CentralizedSmoother(None, start=starts[0],
                                    search=ParticleTrajectorySearch(),
                                    **models)
    assert lost(searching(data, gen(0)).mean, data) == [0, 1]


def test_groups_are_the_differing_agents_connected_by_their_links():
    data, models = two_groups()
    smoother = CentralizedSmoother(None, **models)
    layout = GraphLayout.of(data)
    base, slots, _ = smoother._problem(data, layout)[0]
    truth = [state[:3] for state in data.states.double().unbind(1)]

    def groups(agents, separation=2.0):
        other = [state[:3] for state in flipped(data, agents).unbind(1)]
        return [group.tolist() for group in GroupExchange(
            separation).groups(smoother, slots, truth, other)]

    assert groups([0, 1, 2]) == [[0, 1], [2]]  # the largest first
    assert groups([2, 0]) == [[0], [2]]  # linked only if both differ
    assert groups([1]) == [[1]]
    # 10 m apart at most (the flip of y = 5): not farther than 10
    assert groups([0, 1, 2], separation=10.0) == []


def test_a_chain_of_links_over_several_steps_is_one_group():
    # a path 0-1-2-3-4-5, one link per step (agents 0 and 5 never linked,
    # nor linked to a common one), 6 and 7 to an anchor only, 6 also to a
    # held end (-1 as a receiver), 8 to nothing: all differ, 7 by less than
    # the separation
    smoother = CentralizedSmoother(None)
    links = [[(k, k + 1)] for k in range(5)] + [[(-1, 6), (-1, 7), (6, -1)]]
    slots = link_slots(links)
    here = [torch.zeros(9, 4)] * len(links)
    apart = torch.full((9, 4), 3.0)
    apart[7] = 1.0
    assert [group.tolist() for group in GroupExchange().groups(
        smoother, slots, here, [apart] * len(links))] == [
        [0, 1, 2, 3, 4, 5], [6], [8]]


def test_basins_the_data_do_not_separate_are_never_exchanged():
    # every link symmetric about the anchors' line: each start's optimum
    # costs what its mirror does, so the margin keeps the better one as it
    # is
    data, models = two_groups(third_y=0.0)
    starts = [Given(flipped(data, [0, 1]), **models),
              Given(flipped(data, [2]), **models)]
    chosen = CentralizedSmoother(None, start=starts, **models)(data)
    exchanged = CentralizedSmoother(None, start=starts,
                                    exchange=GroupExchange(), **models)(data)
    assert lost(chosen.mean, data) != []
    assert torch.equal(exchanged.mean, chosen.mean)
    assert torch.equal(exchanged.cov, chosen.cov)
    # where they do, a margin beyond the gain keeps the better as it is too
    data, models = two_groups()
    starts = [Given(flipped(data, [0, 1]), **models),
              Given(flipped(data, [2]), **models)]
    chosen = CentralizedSmoother(None, start=starts, **models)(data)
    beyond = CentralizedSmoother(None, start=starts, exchange=GroupExchange(
        margin=1e6), **models)(data)
    assert torch.equal(beyond.mean, chosen.mean)


def test_each_graph_of_a_batch_exchanges_its_own_groups():
    data, models = two_groups()
    batch = next(iter(DataLoader([data, data], batch_size=2)))
    # the first graph lost the pair in the first start, the second graph
    # in the second
    first = torch.cat([flipped(data, [0, 1]), flipped(data, [2])])
    second = torch.cat([flipped(data, [2]), flipped(data, [0, 1])])
    truth_basin = CentralizedSmoother(None, **models).smoothed_from(
        data, data.states.double()).mean
    found = CentralizedSmoother(None, start=[Given(first, **models),
                                             Given(second, **models)],
                                exchange=GroupExchange(), **models)(batch)
    assert_each_graph(found.mean, truth_basin, 2, atol=1e-5)


def test_settings_and_refusals():
    data, models = two_groups()
    starts = [Given(data.states, **models)] * 2
    smoother = CentralizedSmoother(None, start=starts,
                                   exchange=GroupExchange(rounds=3))
    assert smoother.settings()['exchange'] == dict(
        exchange='group', separation=2.0, margin=10.0, rounds=3)
    assert 'exchange=GroupExchange(separation=2.0' in repr(smoother)
    assert 'exchange' not in CentralizedSmoother(None).settings()
    assert GroupExchange() == GroupExchange()
    assert GroupExchange() != GroupExchange(margin=5.0)
    with pytest.raises(TypeError, match="'exchange' must be a "
                       "GroupExchange or None, got str"):
        CentralizedSmoother(None, start=starts, exchange='group')
    with pytest.raises(ValueError, match="'exchange' .* needs lag=None"):
        CentralizedSmoother(5, exchange=GroupExchange())
    with pytest.raises(ValueError, match=r"'start\[1\]' must be a tensor "
                       r"of shape \(N, T, S\)"):
        smoother.smoothed_from(data, [data.states, data.states[:, 1:]])
    with pytest.raises(ValueError, match="'rounds'"):
        GroupExchange(rounds=0)
    for name in ('separation', 'margin'):
        with pytest.raises((TypeError, ValueError), match=f"'{name}'"):
            GroupExchange(**{name: float('nan')})
    for start in (None, data.states.numpy(), []):
        with pytest.raises(ValueError, match="'start' must be a tensor of "
                           "shape"):
            smoother.smoothed_from(data, start)
