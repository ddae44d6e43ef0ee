r"""Fixed-lag Gaussian BP: a window of one step is Gaussian BP; on a network
whose space-time graph is a tree it is exact (the Kalman filter and the
Rauch-Tung-Striebel smoother, written in the test), on a loopy one its means
are and its covariances fall short; settled steps are exact where their
messages cannot change and, relinearized, bring a wrong mode back; each
graph of a batch converges on its own; streaming and save/resume are in
tests/filters/live/test_session.py (live_trackers)."""
import numpy as np
import pytest
import torch

from tg_nebp.datasets import Scenario
from tg_nebp.filters import (AgentPrior, CentralizedSmoother,
                             FixedLagGaussianBP, GaussianBP, Smoothed,
                             TrackingSession)
from tg_nebp.models import ConstantVelocity, StudentTRange

from helpers import (anchor_links_only, assert_batch_equals_alone, gen,
                     linear_kalman_filter, linear_rts_smoother,
                     linear_scenario, stream_realization, tiny_scenario,
                     tree_realization)


@pytest.mark.parametrize('options', [
    dict(), dict(inflation=1.5), dict(ends='receiver'),
    dict(damping=0.3, num_iterations=30, tolerance=1e-3),
    dict(measurement=StudentTRange())])
def test_a_one_step_window_is_gaussian_bp_bit_for_bit(options):
    # the same arithmetic: the step's prior, the conv's messages and
    # beliefs, the early stop, the inflation before the next prediction
    data = tiny_scenario(steps=6).generate(gen(3))
    expected = GaussianBP(**options)(data)
    out = FixedLagGaussianBP(1, **options)(data)
    assert torch.equal(out.mean, expected.mean)
    assert torch.equal(out.cov, expected.cov)


def test_on_a_space_time_tree_it_is_the_kalman_filter_and_smoother():
    # a window as long as the sequence never slides: every step's newest
    # state is the Kalman filter's and the last window is the full
    # smoother's, means and covariances, once the messages converge
    scenario, data = tree_realization()
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    tracker = FixedLagGaussianBP(4, num_iterations=60, tolerance=1e-12,
                                 **models)
    steps = list(tracker.steps(data))
    means, covs, agents = linear_kalman_filter(data, *models.values())
    mean = torch.stack([s.mean for s in steps], 1)
    cov = torch.stack([s.cov for s in steps], 1)
    np.testing.assert_allclose(mean[agents].numpy(), means, atol=1e-8)
    np.testing.assert_allclose(cov[agents].numpy(), covs, atol=1e-8)
    means, covs, _ = linear_rts_smoother(data, *models.values())
    np.testing.assert_allclose(steps[-1].window_mean[agents].numpy(), means,
                               atol=1e-8)
    np.testing.assert_allclose(steps[-1].window_cov[agents].numpy(), covs,
                               atol=1e-8)
    # a shorter window slides: its smoothed estimates beat its filtered
    # ones, and its covariances stay symmetric positive definite
    tracker = FixedLagGaussianBP(2, num_iterations=60, tolerance=1e-12,
                                 **models)
    smoothed = Smoothed(tracker)(data)
    assert bool((smoothed.cov[agents].diagonal(dim1=-2, dim2=-1).sum(-1)[
        :, :-1] < tracker(data).cov[agents].diagonal(
            dim1=-2, dim2=-1).sum(-1)[:, :-1]).all())
    torch.testing.assert_close(smoothed.cov, smoothed.cov.transpose(-1, -2),
                               rtol=0, atol=0)
    assert bool((torch.linalg.eigvalsh(smoothed.cov[agents]) > 0).all())


def test_on_a_loopy_space_time_graph_means_are_exact_and_variances_short():
    # where the window's graph has loops (four agents measuring each other
    # at every step: loops across the time chains), the converged window's
    # means are the exact smoother's, but its covariances are too small,
    # the exact minus Gaussian BP's positive definite at every agent and
    # step (Gaussian BP's fixed point on a loopy Gaussian graph, Weiss and
    # Freeman 2001: a loop's information is counted again). Here the
    # traces are 0.78 to 0.83 of the exact ones: the variance shortfall of
    # long windows, which the settled inflation makes up for, is this, not
    # a scheduling or weighting error (on a tree, above, they are exact)
    scenario = linear_scenario(steps=5, num_agents=4)
    data = scenario.generate(gen(0))
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    window = list(FixedLagGaussianBP(5, num_iterations=300, tolerance=1e-13,
                                     **models).steps(data))[-1]
    means, covs, agents = linear_rts_smoother(data, *models.values())
    np.testing.assert_allclose(window.window_mean[agents].numpy(), means,
                               atol=1e-9)
    cov = window.window_cov[agents].numpy()
    assert np.linalg.eigvalsh(covs - cov).min() > 1e-5
    assert np.linalg.eigvalsh(cov).min() > 0
    ratio = np.trace(cov, axis1=-2, axis2=-1) / np.trace(covs, axis1=-2,
                                                         axis2=-1)
    assert 0.7 < ratio.min() and ratio.max() < 0.9


def test_smoothing_ranges_beats_filtering():
    # ranges on a loopy network: over a few realizations the smoothed
    # estimates are closer to the truth than Gaussian BP's, and so is the
    # filtered estimate of the relinearized window
    errors = {'gbp': 0.0, 'filtered': 0.0, 'smoothed': 0.0}
    for seed in range(3):
        data = tiny_scenario(steps=10).generate(gen(20 + seed))
        agents = ~data.anchor
        for name, method in (
                ('gbp', GaussianBP.recommended()),
                ('filtered', FixedLagGaussianBP.recommended(lag=4)),
                ('smoothed', Smoothed(FixedLagGaussianBP.recommended(
                    lag=4)))):
            out = method(data)
            errors[name] += float((out.mean[agents, :, :2] - data.states[
                agents, :, :2]).square().sum())
    assert errors['smoothed'] < 0.8 * errors['gbp']
    assert errors['filtered'] < errors['gbp']


def test_each_graph_of_a_batch_converges_on_its_own():
    # bit for bit on every CPU path: see assert_batch_equals_alone
    assert_batch_equals_alone(FixedLagGaussianBP.recommended(lag=3), rtol=0,
                              atol=0)
    assert_batch_equals_alone(Smoothed(FixedLagGaussianBP.recommended(
        lag=3)), rtol=0, atol=0)


def _windows(tracker, data, graph_of, num_graphs):
    # every step's window means, the step loop run with the graphs given
    state = tracker.initial_state(data)
    out = []
    for t, ((edge_index, edge_attr), control) in enumerate(zip(
            data.edges_by_step(), tracker.controls_of(data))):
        step, state = tracker.step(state, edge_index, edge_attr, data.anchor,
                                   t, graph_of=graph_of,
                                   num_graphs=num_graphs, control=control)
        out.append(step.window_mean)
    return out


def test_residual_scheduling_iterates_only_the_agents_that_move():
    # every agent measured by anchors only: each is its own component, so
    # the residual schedule on one graph stops each agent where it stops
    # as a graph of its own under full sweeps (its moves under the
    # tolerance), while full sweeps on one graph iterate every agent
    # until the slowest has converged
    data = tiny_scenario(steps=6).replace(num_agents=5).generate(gen(4))
    keep = data.anchor[data.edge_index[0]]
    data.edge_index = data.edge_index[:, keep]
    data.edge_attr = data.edge_attr[keep]
    data.edge_time = data.edge_time[keep]
    num = data.num_nodes
    one = torch.zeros(num, dtype=torch.long)
    each = torch.arange(num)
    options = dict(lag=3, tolerance=0.05, num_iterations=30)
    residual = _windows(FixedLagGaussianBP(schedule='residual', **options),
                        data, one, 1)
    alone = _windows(FixedLagGaussianBP(**options), data, each, num)
    swept = _windows(FixedLagGaussianBP(**options), data, one, 1)
    for ours, theirs in zip(residual, alone):
        torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-12)
    assert max(float((s - a).abs().max()) for s, a in zip(swept, alone)) > 1e-6


def test_residual_scheduling_with_a_tiny_tolerance_is_the_sweep():
    # nothing stops moving before it has converged: the same estimates on
    # a loopy network
    data = tiny_scenario(steps=6).replace(num_agents=5).generate(gen(5))
    options = dict(lag=3, tolerance=1e-11, num_iterations=200)
    residual = FixedLagGaussianBP(schedule='residual', **options)(data)
    swept = FixedLagGaussianBP(**options)(data)
    torch.testing.assert_close(residual.mean, swept.mean, rtol=0, atol=1e-8)
    torch.testing.assert_close(residual.cov, swept.cov, rtol=0, atol=1e-8)
    assert_batch_equals_alone(FixedLagGaussianBP.recommended(
        lag=3, schedule='residual'), rtol=0, atol=0)


def test_the_window_of_every_step():
    data = tiny_scenario(steps=5).generate(gen(3))
    steps = list(FixedLagGaussianBP(3).steps(data))
    assert [s.window_mean.size(1) for s in steps] == [1, 2, 3, 3, 3]
    for s in steps:
        assert torch.equal(s.window_mean[:, -1], s.mean)
        assert torch.equal(s.window_cov[:, -1], s.cov)
        # anchors: their known state, no uncertainty, in every window step
        assert s.window_cov[data.anchor].abs().max() == 0
    smoothed = list(Smoothed(FixedLagGaussianBP(3)).steps(data))
    assert [s.t for s in smoothed] == list(range(5))
    # a step's smoothed estimate is its window's oldest as it leaves
    assert torch.equal(smoothed[1].mean, steps[3].window_mean[:, 0])
    assert torch.equal(smoothed[4].mean, steps[4].window_mean[:, 2])


def test_settings_and_errors():
    tracker = FixedLagGaussianBP(3)
    assert tracker.settings()['lag'] == 3
    assert 'lag=3' in repr(tracker)
    assert Smoothed(tracker).settings()['smoothed'] is True
    with pytest.raises(ValueError, match="'lag' must be positive"):
        FixedLagGaussianBP(0)
    assert "schedule='sweep'" in repr(tracker)
    with pytest.raises(ValueError, match="'schedule' must be one of"):
        FixedLagGaussianBP(3, schedule='random')
    with pytest.raises(ValueError, match="needs a 'tolerance'"):
        FixedLagGaussianBP(3, schedule='residual', tolerance=None)
    assert ('iterated=None, relinearize_threshold=0.1, relinearize_skip=10, '
            'settled_inflation=1.0' in repr(tracker))
    assert FixedLagGaussianBP(3, iterated=2).settings()['iterated'] == 2
    with pytest.raises(ValueError, match="'iterated' must be positive"):
        FixedLagGaussianBP(3, iterated=0)
    with pytest.raises(ValueError, match="'relinearize_threshold' must be"):
        FixedLagGaussianBP(3, relinearize_threshold=-1.0)
    with pytest.raises(ValueError, match="'relinearize_skip' must be"):
        FixedLagGaussianBP(3, relinearize_skip=0)
    with pytest.raises(ValueError, match="'settled_inflation' must be"):
        FixedLagGaussianBP(3, settled_inflation=0.5)


@pytest.mark.parametrize('iterated', [1, 2, 3])
def test_settled_steps_are_exact_where_their_messages_cannot_change(
        iterated):
    # linear links from anchors only: no message depends on a belief, so
    # the settled steps (their messages held, their forward pass the prior
    # of the iterated ones, one backward pass into them) give every
    # window of the full iteration, which is the Kalman smoother's (above)
    scenario, data = tree_realization(steps=6)
    data = anchor_links_only(data)
    options = dict(num_iterations=60, tolerance=1e-12,
                   motion=scenario.motion_model,
                   measurement=scenario.measurement_model)
    full = list(FixedLagGaussianBP(4, **options).steps(data))
    split = list(FixedLagGaussianBP(4, iterated=iterated,
                                    **options).steps(data))
    for ours, theirs in zip(split, full):
        torch.testing.assert_close(ours.window_mean, theirs.window_mean,
                                   rtol=0, atol=1e-12)
        torch.testing.assert_close(ours.window_cov, theirs.window_cov,
                                   rtol=0, atol=1e-12)


@pytest.mark.parametrize('options', [
    dict(relinearize_threshold=None),
    dict(relinearize_threshold=None, settled_inflation=1.5),
    dict(relinearize_threshold=0.5, relinearize_skip=1),
    dict(relinearize_threshold=0.5, relinearize_skip=3)])
def test_the_settled_forward_pass_kept_is_the_one_computed_afresh(options):
    # the state keeps the settled steps' filtered means and covariances
    # from one time step to the next (the window slides, and a
    # relinearized step and those after it are filtered again): each step
    # gives what it gives when the state holds none and every settled
    # step is filtered again
    data = tiny_scenario(steps=14).generate(gen(20))
    tracker = FixedLagGaussianBP.recommended(lag=6, iterated=2, **options)

    def windows(drop):
        state, out, kept = tracker.initial_state(data), [], 0
        for t, ((edge_index, edge_attr), control) in enumerate(zip(
                data.edges_by_step(), tracker.controls_of(data))):
            if drop:
                state = state._replace(settled_mean=None, settled_cov=None)
            elif state.settled_mean is not None:
                kept += state.settled_mean.size(1)
            step, state = tracker.step(state, edge_index, edge_attr,
                                       data.anchor, t, control=control)
            out.append(step.window_mean)
        return out, kept

    kept, count = windows(False)
    afresh, _ = windows(True)
    assert count >= (10 if options["relinearize_threshold"] is None else 5)
    for ours, theirs in zip(kept, afresh):
        torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-12)


def _mirrored_start():
    # one agent between two anchors on the x axis for its first four
    # steps, its prior's mean mirrored across them (a range-only wrong
    # mode the first steps converge to); from step 4 a third anchor above
    # tells the modes apart
    scenario = Scenario(name='mirror', num_agents=1,
                        anchor_positions=((-6.0, 0.0), (6.0, 0.0),
                                          (0.0, 9.0)),
                        agent_start_low=3.0, agent_start_high=5.0,
                        num_steps=12)
    data = scenario.generate(gen(7))
    data.prior_mean[0, 1] = -data.states[0, 0, 1]
    data.prior_mean[0, 0] = data.states[0, 0, 0]
    late = (data.edge_index == 3).any(0) & (data.edge_time < 4)
    out = data.clone()
    out.edge_index = data.edge_index[:, ~late]
    out.edge_attr = data.edge_attr[~late]
    out.edge_time = data.edge_time[~late]
    return out


def test_relinearized_settled_steps_recover_a_wrong_linearization():
    # the first steps converge to the mirrored mode; the window of 8 steps
    # learns the truth from step 4. Iterating every step of it (and the
    # batch smoother) brings the first steps back; with only the newest 2
    # iterated, the settled steps' messages must be relinearized where the
    # backward pass moves them: held as they were linearized (the
    # marginal prior of a fixed-lag smoother), the first steps stay in the
    # wrong mode, and so does a window of 2 steps
    data = _mirrored_start()
    options = dict(num_iterations=50, tolerance=1e-6, relinearize_skip=1)

    def errors(tracker):
        out = tracker(data)
        return (out.mean[0, :, :2] - data.states[0, :, :2]).norm(dim=-1)

    batch = errors(CentralizedSmoother(None))
    full = errors(Smoothed(FixedLagGaussianBP(8, **options)))
    settled = errors(Smoothed(FixedLagGaussianBP(8, iterated=2, **options)))
    held = errors(Smoothed(FixedLagGaussianBP(
        8, iterated=2, relinearize_threshold=None, **options)))
    short = errors(Smoothed(FixedLagGaussianBP(2, **options)))
    assert float(batch.max()) < 1.0 and float(full.max()) < 1.0
    # step 0 leaves the window one step after the relinearization reached
    # it; every later step is within 0.15 m of the batch smoother's error
    assert float(settled[0]) < 1.5
    assert float((settled[1:] - batch[1:]).abs().max()) < 0.15
    assert bool((held[:6] > 2.5).all()) and bool((short[:6] > 2.5).all())


def _without_links(data, node, steps):
    # the realization without the links of 'node' at the time indices of
    # 'steps'
    drop = (data.edge_index == node).any(0) & torch.isin(
        data.edge_time, torch.tensor(list(steps)))
    out = data.clone()
    out.edge_index = data.edge_index[:, ~drop]
    out.edge_attr = data.edge_attr[~drop]
    out.edge_time = data.edge_time[~drop]
    return out


# tiny_scenario: agents 0-2, anchors 3-5; the late agent is the last row
STEPS, SPLIT, LATE, ORDER = 7, 4, 2, [0, 1, 3, 4, 5, 2]


def test_an_agent_that_joins_equals_one_present_with_that_prior():
    # the late agent has no links before SPLIT. In one session it is there
    # from the start (its row last), in the other it joins at SPLIT with
    # the belief the first holds for it then: from SPLIT on the newest
    # estimates of every node agree, and the joined agent's window rows
    # before its join hold its prior predicted into its first step. (With
    # a linear motion model: the first session's window relinearizes the
    # lonely agent's chain where its first link moves it, a drag model's
    # prediction changes by 1e-4 m/s there)
    data = _without_links(tiny_scenario(STEPS).generate(gen(3)), LATE,
                          range(SPLIT))
    tracker = FixedLagGaussianBP(3, tolerance=None,
                                 motion=ConstantVelocity(0.05))
    present = TrackingSession(tracker, dtype=torch.float64)
    before = stream_realization(present, data, steps=SPLIT, order=ORDER)
    mean, cov = before[-1].mean[-1], before[-1].cov[-1]
    after = stream_realization(present, data, start=SPLIT)
    late = TrackingSession(tracker, dtype=torch.float64)
    stream_realization(late, data, steps=SPLIT, order=ORDER[:-1])
    edge_index, edge_attr = data.edges_by_step()[SPLIT]
    links = [(f'n{j}', f'n{i}') for j, i in edge_index.t().tolist()]
    joined = [late.update(links, edge_attr[:, 0].tolist(), join={
        f'n{LATE}': AgentPrior(mean.tolist(), cov.tolist())})]
    joined += stream_realization(late, data, start=SPLIT + 1)
    assert late.ids == present.ids
    for ours, theirs in zip(joined, after):
        torch.testing.assert_close(ours.mean, theirs.mean, rtol=0,
                                   atol=1e-12)
        torch.testing.assert_close(ours.cov, theirs.cov, rtol=0,
                                   atol=1e-12)
    assert float((after[-1].mean[-1, :2] - mean[:2]).norm()) > 0.1
    window = joined[0].window_mean
    assert window.size(1) == 3 and torch.equal(window[-1, 0], window[-1, 1])
    assert torch.equal(joined[0].window_cov[-1, 0],
                       joined[0].window_cov[-1, 1])


def test_an_agent_that_leaves_no_longer_influences_anyone():
    # the leaver has no links in the window when it leaves: the others'
    # estimates are those of a session where it stays without links; one
    # that leaves with links in the window takes them along (the others'
    # window estimates lose them) and the session goes on
    data = _without_links(tiny_scenario(STEPS).generate(gen(4)), LATE,
                          range(SPLIT - 2, STEPS))
    tracker = FixedLagGaussianBP(3, tolerance=None)
    stay = TrackingSession(tracker, dtype=torch.float64)
    stream_realization(stay, data, steps=SPLIT, order=ORDER)
    stayed = stream_realization(stay, data, start=SPLIT)
    gone = TrackingSession(tracker, dtype=torch.float64)
    stream_realization(gone, data, steps=SPLIT, order=ORDER)
    edge_index, edge_attr = data.edges_by_step()[SPLIT]
    links = [(f'n{j}', f'n{i}') for j, i in edge_index.t().tolist()]
    left = [gone.update(links, edge_attr[:, 0].tolist(),
                        leave=[f'n{LATE}'])]
    left += stream_realization(gone, data, start=SPLIT + 1)
    assert gone.ids == stay.ids[:-1]
    for ours, theirs in zip(left, stayed):
        torch.testing.assert_close(ours.mean, theirs.mean[:-1], rtol=0,
                                   atol=1e-9)
        torch.testing.assert_close(ours.cov, theirs.cov[:-1], rtol=0,
                                   atol=1e-9)
    linked = TrackingSession(tracker, dtype=torch.float64)
    full = tiny_scenario(STEPS).generate(gen(4))
    stream_realization(linked, full, steps=SPLIT, order=ORDER)
    assert linked.state.links.size(1) > 0
    out = linked.update([], [], leave=[f'n{LATE}'])
    assert bool(torch.isfinite(out.window_cov).all())


def test_links_with_features_the_model_does_not_read():
    # generated NLOS links carry their true NLOS flag after the range; a
    # Gaussian model reads the range: the window holds the links as given
    from tg_nebp.models import NLOSRange
    data = tiny_scenario(steps=4).replace(
        measurement=NLOSRange()).generate(gen(1))
    assert data.edge_attr.size(1) == 2
    assert torch.equal(FixedLagGaussianBP(1)(data).mean,
                       GaussianBP()(data).mean)
    steps = list(FixedLagGaussianBP(3).steps(data))
    assert bool(torch.isfinite(steps[-1].window_mean).all())


def test_a_numpy_lag_is_a_lag():
    # a NumPy count of 80 settles the window as an int 80 does (an
    # isinstance(lag, int) check dropped the settled configuration)
    from tg_nebp.experiments.evaluate import method_tracker
    from tg_nebp.datasets import load_scenario
    for lag in (80, np.int64(80), np.int32(6)):
        assert FixedLagGaussianBP.recommended(lag=lag).settings() == \
            FixedLagGaussianBP.recommended(lag=int(lag)).settings()
    assert FixedLagGaussianBP.recommended(lag=80).iterated is not None
    tracker, _ = method_tracker('gbp', load_scenario('paper_test'),
                                lag=np.int64(80))
    assert tracker.settings() == FixedLagGaussianBP.recommended(
        lag=80).settings()
    for lag, error in (('80', TypeError), (True, TypeError), (0, ValueError)):
        with pytest.raises(error, match="'lag'"):
            FixedLagGaussianBP.recommended(lag=lag)
