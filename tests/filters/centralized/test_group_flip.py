import pytest
import torch
from torch_geometric.loader import DataLoader

from tg_nebp.filters import (CentralizedSmoother, GroupExchange, GroupFlip,
                             ParticleTrajectorySearch)
from tg_nebp.gaussian import GraphLayout
from tg_nebp.models import ConstantVelocity, GaussianRange

from helpers import (Given, assert_each_graph, gen, link_slots,
                     ranged_realization)

STEPS = 12
#: Every agent's velocity: the hinges' line moves, so that each step has
#: its own mirror.
VELOCITY = (0.3, 0.2)
#: The pair (agents 0 and 1) ranges to each other and to three hinge
#: agents (2, 3, 4) only, never to an anchor; the hinges range to three
#: anchors each step. Two hinges lie on y = 0.2 k at step k, the third
#: 'third_y' off that line.
PAIR = ((5.0, 5.0), (12.0, 4.0))
HINGES = ((0.0, 0.0), (10.0, 0.0), (20.0, None))
ANCHORS = ((-10.0, -12.0), (30.0, -12.0), (10.0, -25.0))


def hinged_pair(third_y=1.5):
    # every agent moving at VELOCITY; the pair's prior on the hinges' line
    # and broad, so that either side is as likely before the
    # links; the hinges' priors at the truth
    places = list(PAIR) + [(x, third_y if y is None else y)
                           for x, y in HINGES]
    count = len(places)
    num = count + len(ANCHORS)
    states = torch.zeros(num, STEPS, 4)
    for a, (x, y) in enumerate(places):
        for axis, (start, speed) in enumerate(zip((x, y), VELOCITY)):
            states[a, :, axis] = start + speed * torch.arange(STEPS)
            states[a, :, 2 + axis] = speed
    states[count:, :, :2] = torch.tensor(ANCHORS).unsqueeze(1)
    step = [(0, 1)] + [(h, a) for a in (0, 1) for h in (2, 3, 4)] + [
        (count + k, h) for h in (2, 3, 4) for k in range(len(ANCHORS))]
    prior_cov = torch.zeros(num, 4, 4)
    prior_cov[:2] = torch.diag(torch.tensor([25.0, 25.0, 0.01, 0.01]))
    prior_cov[2:count] = torch.diag(torch.tensor([0.25, 0.25, 0.01, 0.01]))
    data = ranged_realization(states, step, count, prior_cov, loose=2)
    return data, dict(motion=ConstantVelocity(sigma_a=0.05),
                      measurement=GaussianRange(sigma=0.3))


def mirrored(data):
    # the truth with the pair reflected at each step k across the line
    # y = 0.2 k, their velocities those of the reflected positions (the
    # line moves by 0.2 a step: v_y -> 0.4 - v_y, not -v_y): a start with
    # the pair on the mirror of the hinges' line
    start = data.states.double().clone()
    line = VELOCITY[1] * torch.arange(STEPS, dtype=torch.float64)
    start[:2, :, 1] = 2 * line - start[:2, :, 1]
    start[:2, :, 3] = 2 * VELOCITY[1] - start[:2, :, 3]
    return start


def off(estimate, data):
    # each of the pair's distance from the truth, the least over the steps
    return (estimate[:2, :, :2] - data.states[:2, :, :2].double()).norm(
        dim=-1).amin(1)


def test_a_pair_on_the_mirror_of_its_hinges_is_flipped_back():
    data, models = hinged_pair()
    plain = CentralizedSmoother(None, **models)
    truth_basin = plain.smoothed_from(data, data.states.double()).mean
    stays = plain.smoothed_from(data, mirrored(data)).mean
    assert bool((off(stays, data) > 6).all())  # the mirror's basin
    flipping = CentralizedSmoother(None, flip=GroupFlip(), **models)
    found = flipping.smoothed_from(data, mirrored(data)).mean
    torch.testing.assert_close(found, truth_basin, rtol=0, atol=1e-5)
    assert float(plain.sequence_cost(data, found)) < float(
        plain.sequence_cost(data, stays)) - 10
    # the same as a start tracker, and after an exchange (which has
    # nothing to take from two equal starts)
    start = Given(mirrored(data), **models)
    torch.testing.assert_close(CentralizedSmoother(
        None, start=[start, start], exchange=GroupExchange(),
        flip=GroupFlip(), **models)(data).mean, found, rtol=0, atol=1e-12)
    # the search, one agent at a time with the other held, leaves the pair
    # on the mirror: each alone would break their link
    searching = CentralizedSmoother(None, start=start,
                                    search=ParticleTrajectorySearch(),
                                    **models)
    assert bool((off(searching(data, gen(0)).mean, data) > 6).all())


def test_a_flip_the_links_leave_open_is_never_taken():
    # every hinge on the line: the mirror costs what the truth does, so the
    # margin keeps the solution as it is
    data, models = hinged_pair(third_y=0.0)
    smoother = CentralizedSmoother(None, **models)
    plain = smoother.smoothed_from(data, mirrored(data))
    flipped = CentralizedSmoother(None, flip=GroupFlip(),
                                  **models).smoothed_from(data,
                                                          mirrored(data))
    assert bool((off(plain.mean, data) > 6).all())
    # the flip is tried (its hinges lie on their line), and refused
    _, slots, _ = smoother._problem(data, GraphLayout.of(data))[0]
    assert GroupFlip().reflected(smoother, slots, [
        state[:5] for state in plain.mean.unbind(1)],
        torch.tensor([0, 1])) is not None
    assert torch.equal(flipped.mean, plain.mean)
    assert torch.equal(flipped.cov, plain.cov)
    # where the data decide, a margin beyond the gain keeps it too
    data, models = hinged_pair()
    plain = CentralizedSmoother(None, **models).smoothed_from(
        data, mirrored(data))
    beyond = CentralizedSmoother(None, flip=GroupFlip(margin=1e6),
                                 **models).smoothed_from(data,
                                                         mirrored(data))
    assert torch.equal(beyond.mean, plain.mean)


def test_the_groups_are_the_agents_no_anchor_reaches_connected_by_links():
    data, models = hinged_pair()
    smoother = CentralizedSmoother(None, **models)
    _, slots, _ = smoother._problem(data, GraphLayout.of(data))[0]
    assert [group.tolist() for group in GroupFlip.groups(slots, 5)] == [
        [0, 1]]
    # a path 0-1-2 over several steps, 3 linked to 2 but a sender into an
    # anchor (-1 as a receiver: it ranged to an anchor), 4 and 5 linked to
    # each other, 6 to nothing (a single agent: the search's)
    slots = link_slots([[(0, 1)], [(1, 2)], [(3, -1), (2, 3)], [(4, 5)]])
    assert [group.tolist() for group in GroupFlip.groups(slots, 7)] == [
        [0, 1, 2], [4, 5]]


def test_the_reflection_is_across_the_hinges_line_at_each_step():
    data, models = hinged_pair(third_y=0.0)
    smoother = CentralizedSmoother(None, **models)
    _, slots, _ = smoother._problem(data, GraphLayout.of(data))[0]
    truth = [state[:5] for state in data.states.double().unbind(1)]
    reflected = GroupFlip().reflected(smoother, slots, truth,
                                      torch.tensor([0, 1]))
    # (the realization's states are float32: 1e-6)
    torch.testing.assert_close(torch.stack(reflected, 1), mirrored(data)[
        :5], rtol=0, atol=1e-6)
    # hinges off their line by more than the spread: not tried
    data, models = hinged_pair(third_y=1.5)
    _, slots, _ = smoother._problem(data, GraphLayout.of(data))[0]
    truth = [state[:5] for state in data.states.double().unbind(1)]
    assert GroupFlip(spread=0.1).reflected(smoother, slots, truth,
                                           torch.tensor([0, 1])) is None
    assert GroupFlip(spread=1.0).reflected(smoother, slots, truth,
                                           torch.tensor([0, 1])) is not None
    # a group linked to one outside agent over the whole sequence: a
    # rotation about it, not a flip
    slots = link_slots([[(0, 1), (2, 1)]] * 3)
    assert GroupFlip().reflected(smoother, slots, [torch.rand(
        3, 4, generator=gen(0))] * 3, torch.tensor([0, 1])) is None


def test_a_step_without_outside_links_takes_the_nearest_steps():
    # the pair (0, 1) ranges to agents 2 and 3 at steps 0 and 3 only: at
    # steps 1 and 2 their hyperplane is that of agents 2 and 3, at those
    # steps' positions (the line y = k at step k). The velocities: those
    # of the constant-velocity model (dt = 1) that carry each reflected
    # position to the next as the original's was carried, reflected:
    # v' = R v + (b_{k+1} - b_k) for p' = R p + b_k, R = diag(1, -1),
    # b_k = (0, 2 k)
    smoother = CentralizedSmoother(None, motion=ConstantVelocity())
    slots = link_slots([[(2, 0), (3, 1)], [(0, 1)], [(0, 1)],
                        [(2, 0), (3, 0)]])
    points, expected = [], []
    for k in range(4):
        here = torch.tensor([[3.0, k + 2.0, 0.5, 0.1],
                             [6.0, k + 3.0, 0.5, 0.1],
                             [0.0, float(k), 0.0, 1.0],
                             [10.0, float(k), 0.0, 1.0]],
                            dtype=torch.float64)
        points.append(here)
        mirror = here.clone()
        mirror[:2, 1] = 2 * k - here[:2, 1]
        mirror[:2, 3] = 2.0 - here[:2, 3]
        expected.append(mirror)
    torch.testing.assert_close(torch.stack(GroupFlip().reflected(
        smoother, slots, points, torch.tensor([0, 1]))), torch.stack(
        expected), rtol=0, atol=1e-9)
    # any motion model (here with drag): its mean carries each reflected
    # state off the next step's reflected position by the original's miss,
    # reflected
    drag = CentralizedSmoother(None)
    reflected = GroupFlip().reflected(drag, slots, points,
                                      torch.tensor([0, 1]))
    flip = torch.diag(torch.tensor([1.0, -1.0], dtype=torch.float64))
    for k in range(3):
        torch.testing.assert_close(
            reflected[k + 1][:2, :2] - drag.motion.mean(reflected[k][:2])[
                :, :2], (points[k + 1][:2, :2] - drag.motion.mean(
                    points[k][:2])[:, :2]) @ flip, rtol=0, atol=1e-9)
    # a solution that is not finite has no hyperplane: nothing is tried,
    # and the flip hands it back as it is
    points[1] = points[1].clone()
    points[1][2, 0] = float('nan')
    assert GroupFlip().reflected(smoother, slots, points,
                                 torch.tensor([0, 1])) is None
    data, models = hinged_pair()
    smoother = CentralizedSmoother(None, **models)
    base, slots, _ = smoother._problem(data, GraphLayout.of(data))[0]
    points = [state[:5].clone() for state in data.states.double().unbind(1)]
    points[4][2, 1] = float('nan')
    kept = (points, None)
    assert GroupFlip().flipped(smoother, base, slots, kept) is kept


def test_each_graph_of_a_batch_flips_its_own_groups():
    data, models = hinged_pair()
    batch = next(iter(DataLoader([data, data], batch_size=2)))
    truth_basin = CentralizedSmoother(None, **models).smoothed_from(
        data, data.states.double()).mean
    # both graphs start on the mirror
    start = torch.cat([mirrored(data), mirrored(data)])
    found = CentralizedSmoother(None, start=Given(start, **models),
                                flip=GroupFlip(), **models)(batch)
    assert_each_graph(found.mean, truth_basin, 2, atol=1e-5)


def test_settings_and_refusals():
    smoother = CentralizedSmoother(None, flip=GroupFlip(spread=1.0))
    assert smoother.settings()['flip'] == dict(flip='group', spread=1.0,
                                               margin=10.0)
    assert 'flip=GroupFlip(spread=1.0, margin=10.0)' in repr(smoother)
    assert 'flip' not in CentralizedSmoother(None).settings()
    assert GroupFlip() == GroupFlip()
    assert GroupFlip() != GroupFlip(margin=5.0)
    with pytest.raises(TypeError, match="'flip' must be a GroupFlip or "
                       "None, got str"):
        CentralizedSmoother(None, flip='group')
    with pytest.raises(ValueError, match="'flip' .* needs lag=None"):
        CentralizedSmoother(5, flip=GroupFlip())
    for name in ('spread', 'margin'):
        with pytest.raises((TypeError, ValueError), match=f"'{name}'"):
            GroupFlip(**{name: float('nan')})
