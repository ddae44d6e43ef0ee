import json
import math
import os
import subprocess
import sys

from typing import NamedTuple

import pytest
import torch
import helpers
from helpers import (PACKAGE_ROOT, NonNegativeRange, gen, live_trackers,
                     loads_after_bit_flips, stream_realization,
                     tiny_scenario)

from tg_nebp.gaussian import bounded_inflation
from tg_nebp.filters import (AgentPrior, AnchorAt, CentralizedIEKF,
                             CentralizedSmoother, FixedLagGaussianBP,
                             GaussianBP, ParticleBP, Smoothed, StateField,
                             TrackingSession, check_state)
from tg_nebp.models import ConstantVelocityDrag, GaussianRange, MotionModel

STEPS = 6
# the step at which a session is saved, an agent joins or one leaves
SPLIT = 3
# tiny_scenario: agents 0-2, then anchors 3-5; the late agent is the last
LATE = 2
ORDER = [0, 1, 3, 4, 5, 2]


@pytest.fixture(scope='module')
def data():
    return tiny_scenario(STEPS).generate(gen(3))


def assert_same_outputs(ours, theirs, particles=False):
    assert len(ours) == len(theirs)
    for a, b in zip(ours, theirs):
        assert a.t == b.t
        assert torch.equal(a.mean, b.mean)
        assert torch.equal(a.cov, b.cov)
        if particles:
            assert torch.equal(a.particles, b.particles)
            assert torch.equal(a.log_weights, b.log_weights)


@pytest.mark.parametrize('name', list(live_trackers()))
def test_streaming_equals_the_offline_loop(data, name):
    # the session calls the offline loop's step function: the same bits,
    # the particle trackers with the same generator
    tracker = live_trackers()[name]()
    with torch.no_grad():
        offline = list(tracker.steps(data, gen(8)))
        online = stream_realization(TrackingSession(tracker,
                                                    generator=gen(8)), data)
    assert_same_outputs(online, offline,
                        particles=offline[0].particles is not None)


def _isolated_until(data, node, t):
    # the realization without the links of 'node' before time index t
    keep = ~((data.edge_index == node).any(0) & (data.edge_time < t))
    out = data.clone()
    out.edge_index = data.edge_index[:, keep]
    out.edge_attr = data.edge_attr[keep]
    out.edge_time = data.edge_time[keep]
    return out


def _belief(session, row):
    # a node's belief in a Gaussian tracker's state (the IEKF's joint
    # holds the agents in row order)
    state = session.state
    if hasattr(state, 'joints'):
        agent = int((~session.anchor[:row]).sum())
        size = state.mean.size(1)
        block = slice(agent * size, (agent + 1) * size)
        return state.mean[row], state.joints[0][block, block]
    return state.mean[row], state.cov[row]


def _links(data, t, without=()):
    # the links of time index t, and their ranges, but those of the nodes
    # 'without'
    edge_index, edge_attr = data.edges_by_step()[t]
    pairs, ranges = [], []
    for (j, i), z in zip(edge_index.t().tolist(), edge_attr[:, 0].tolist()):
        if not {j, i} & set(without):
            pairs.append((f'n{j}', f'n{i}'))
            ranges.append(z)
    return pairs, ranges


def assert_close_outputs(ours, theirs, exact):
    if exact:
        assert_same_outputs(ours, theirs)
        return
    assert len(ours) == len(theirs)
    for a, b in zip(ours, theirs):
        torch.testing.assert_close(a.mean, b.mean, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(a.cov, b.cov, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('make, exact', [(GaussianBP, True),
                                         (CentralizedIEKF, False)])
def test_an_agent_that_joins_equals_one_present_with_that_prior(data, make,
                                                                exact):
    # the late agent has no links before SPLIT. In one run it is there from
    # the start (its row last); in the other it joins at SPLIT with the
    # belief that the first run holds for it then. From SPLIT on both give
    # the same for every node: Gaussian BP bit for bit (float64 priors:
    # nothing is rounded; a joined prior is not inflated, so plain Gaussian
    # BP), the IEKF to rounding (the first run's joint holds round-off
    # between the lonely agent and the others where the second's holds
    # zeros)
    tracker = make()
    lonely = _isolated_until(data, LATE, SPLIT)
    present = TrackingSession(tracker, dtype=torch.float64)
    stream_realization(present, lonely, steps=SPLIT, order=ORDER)
    mean, cov = _belief(present, ORDER.index(LATE))
    after = stream_realization(present, lonely, start=SPLIT)

    late = TrackingSession(tracker, dtype=torch.float64)
    stream_realization(late, lonely, steps=SPLIT, order=ORDER[:-1])
    assert f'n{LATE}' not in late.ids
    joined = [late.update(*_links(lonely, SPLIT), join={
        f'n{LATE}': AgentPrior(mean.tolist(), cov.tolist())})]
    joined += stream_realization(late, lonely, start=SPLIT + 1)
    assert late.ids == present.ids
    assert_close_outputs(joined, after, exact)
    # it did take part: its estimate moved off its prior
    assert float((after[-1].mean[-1, :2] - mean[:2]).norm()) > 0.1


@pytest.mark.parametrize('make, exact', [
    (GaussianBP, True), (lambda: CentralizedIEKF(marginal=True), False)])
def test_an_agent_that_leaves_no_longer_influences_anyone(data, make,
                                                          exact):
    # one run keeps the agent without links from SPLIT on, the other lets
    # it leave at SPLIT: the others' estimates agree (Gaussian BP: bit for
    # bit; the IEKF of marginals: the same arithmetic on a joint without
    # the leaver's independent block)
    tracker = make()
    stay = TrackingSession(tracker, dtype=torch.float64)
    stream_realization(stay, data, steps=SPLIT, order=ORDER)
    stayed = stream_realization(stay, data, start=SPLIT, leave_links=[LATE])
    gone = TrackingSession(tracker, dtype=torch.float64)
    stream_realization(gone, data, steps=SPLIT, order=ORDER)
    left = [gone.update(*_links(data, SPLIT, without=[LATE]),
                        leave=[f'n{LATE}'])]
    left += stream_realization(gone, data, start=SPLIT + 1)
    assert gone.ids == stay.ids[:-1]
    assert len(left) == STEPS - SPLIT
    assert_close_outputs(left, [o._replace(mean=o.mean[:-1], cov=o.cov[:-1])
                                for o in stayed], exact)
    with pytest.raises(ValueError, match=r"'links\[0\]' \['n0', 'n2'\]: "
                       r"unknown identifier 'n2'"):
        gone.update([('n0', 'n2')], [3.0])


def test_particle_agents_join_from_their_prior_and_leave(data):
    # a joining agent's particles are draws of its prior (uniform weights,
    # not resampled before their first prediction); a leaving agent's row
    # is gone
    session = TrackingSession(ParticleBP(num_particles=4000),
                              generator=gen(1))
    stream_realization(session, data, steps=SPLIT, order=ORDER[:-1])
    prior = AgentPrior([5.0, 6.0, 0.5, -0.25],
                       torch.diag(torch.tensor([4.0, 1.0, 0.01,
                                                0.04])).tolist())
    out = session.update(*_links(data, SPLIT, without=[LATE]),
                         join={'late': prior})
    # no links: its belief is its prior predicted by the motion model
    motion = session.tracker.motion
    start = torch.tensor([prior.mean], dtype=torch.float64)
    jacobian = motion.jacobian(start)[0]
    mean = motion.mean(start)[0]
    cov = (jacobian @ torch.tensor(prior.cov, dtype=torch.float64) @
           jacobian.t() + motion.noise_covariance(start)[0])
    spread = cov.diagonal().sqrt()
    # the sample mean of 4000 draws: within 5 standard errors (the drag
    # is nearly linear over the prior's velocity spread)
    assert bool(((out.mean[-1].double() - mean).abs() <=
                 5 * spread / 4000 ** 0.5).all())
    torch.testing.assert_close(out.cov[-1].double().diagonal(),
                               cov.diagonal(), rtol=0.1, atol=1e-4)
    session.update(leave=['late', 'n0'])
    assert session.ids == ['n1', 'n3', 'n4', 'n5']
    assert session.state.particles.size(0) == 4


def _all_nodes(data):
    return {f'n{i}': (AnchorAt(data.prior_mean[i, :2].tolist())
                      if bool(data.anchor[i]) else
                      AgentPrior(data.prior_mean[i].tolist(),
                                 data.prior_cov[i].tolist()))
            for i in range(data.num_nodes)}


def test_a_time_step_per_step_equals_the_model_of_that_time_step(data):
    # dt = 0.5 given per step equals the motion model whose dt is 0.5, and
    # so does 'time'; the clock follows
    half = GaussianBP(motion=ConstantVelocityDrag(dt=0.5))
    theirs = stream_realization(TrackingSession(half), data)
    by_dt = TrackingSession(GaussianBP())
    ours = stream_realization(by_dt, data, dt=0.5)
    assert_same_outputs(ours, theirs)
    assert by_dt.time == 0.5 * STEPS
    by_time = TrackingSession(GaussianBP(), time=10.0)
    first = by_time.update(*_links(data, 0), time=10.5,
                           join=_all_nodes(data))
    assert torch.equal(first.mean, theirs[0].mean)
    with pytest.raises(ValueError, match="'time' = 10.5 does not come "
                       "after the last step's time 10.5"):
        by_time.update(time=10.5)
    # the particle trackers take it too: the same draws, another motion
    particle = stream_realization(
        TrackingSession(ParticleBP(num_particles=30), generator=gen(2)),
        data, dt=0.5)
    offline = list(ParticleBP(num_particles=30, motion=ConstantVelocityDrag(
        dt=0.5)).steps(data, gen(2)))
    assert_same_outputs(particle, offline, particles=True)
    # a dt of the model's own is the model itself
    motion = ConstantVelocityDrag()
    assert motion.with_time_step(1.0) is motion


class Stepless(MotionModel, name='test-stepless'):
    r"""A random walk whose time step is not a parameter."""
    def sample(self, states, generator=None):
        return states + torch.randn(states.shape, generator=generator,
                                    dtype=states.dtype)

    def params(self):
        return {}


def test_a_motion_model_without_a_time_step_says_so(data):
    session = TrackingSession(ParticleBP(num_particles=10,
                                         motion=Stepless()))
    stream_realization(session, data, steps=1)  # its own step: fine
    with pytest.raises(ValueError, match=r"the motion model Stepless\(\) "
                       r"has no time step 'dt' among its parameters: it "
                       r"cannot move by a time step of 0.5 s"):
        session.update(dt=0.5)
    assert session.num_steps == 1


def test_a_saved_session_continues_in_a_new_process(data, tmp_path):
    # every tracker: saved at SPLIT, loaded by another Python process,
    # continued to the end: the uninterrupted run's bits
    expected = {}
    for name, make in live_trackers().items():
        session = TrackingSession(make(), generator=gen(8))
        with torch.no_grad():
            stream_realization(session, data, steps=SPLIT)
            session.save(tmp_path / f'{name}.pt')
            expected[name] = stream_realization(session, data, start=SPLIT)
    worker = os.path.join(os.path.dirname(__file__), 'session_worker.py')
    # this tg_nebp, and the tests' folder for the helpers
    tests = os.path.dirname(os.path.abspath(helpers.__file__))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([PACKAGE_ROOT, tests]))
    done = subprocess.run([sys.executable, worker, str(tmp_path),
                           str(SPLIT), *expected], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    for name, outputs in expected.items():
        continued = torch.load(tmp_path / f'{name}.out.pt',
                               weights_only=True)
        assert len(continued) == STEPS - SPLIT, name
        for (mean, cov), output in zip(continued, outputs):
            assert torch.equal(mean, output.mean), name
            assert torch.equal(cov, output.cov), name


class Foreign:
    pass


def test_loading_refuses_another_tracker_model_network_or_code(
        tmp_path, data):
    path = tmp_path / 'session.pt'
    session = TrackingSession(GaussianBP())
    stream_realization(session, data, steps=1)
    session.save(path)
    assert TrackingSession.load(path, GaussianBP()).num_steps == 1
    for tracker, match in (
            (CentralizedIEKF(), r"saved by another tracker: GaussianBP "
             r"\(this session: CentralizedIEKF\)"),
            (GaussianBP(motion=ConstantVelocityDrag(sigma_a=0.1)),
             'saved by another motion model'),
            (GaussianBP(measurement=GaussianRange(sigma=2.0)),
             'saved by another measurement model'),
            (GaussianBP(inflation=1.5), 'saved by another configuration')):
        with pytest.raises(ValueError, match=match):
            TrackingSession.load(path, tracker)
    trackers = live_trackers()
    learned = TrackingSession(trackers['gnebp']())
    stream_realization(learned, data, steps=1)
    learned.save(path)
    other = trackers['gnebp']()
    with torch.no_grad():
        next(other.parameters()).add_(1.0)
    with pytest.raises(ValueError, match='saved by another network'):
        TrackingSession.load(path, other)
    # a file that would run code is refused unread; so is a foreign one
    torch.save(dict(format='tg_nebp-session', code=Foreign()), path)
    with pytest.raises(ValueError, match='objects other than tensors and '
                       'primitives: refused'):
        TrackingSession.load(path, GaussianBP())
    torch.save(dict(weights=torch.zeros(2)), path)
    with pytest.raises(ValueError, match='not a saved tg_nebp tracking '
                       'session'):
        TrackingSession.load(path, GaussianBP())


def _snapshot(session):
    saved = session.state_dict()
    plain = {k: v for k, v in saved.items()
             if not isinstance(v, (dict, torch.Tensor))}
    return json.dumps(plain, sort_keys=True), saved


def _assert_same_state(a, b):
    assert a[0] == b[0]
    for key in ('anchor', 'generator'):
        assert torch.equal(a[1][key], b[1][key])
    for name, value in a[1]['state'].items():
        other = b[1]['state'][name]
        if isinstance(value, list):
            assert all(torch.equal(x, y) for x, y in zip(value, other))
        elif value is not None:
            assert torch.equal(value, other), name


@pytest.mark.parametrize('update, match', [
    (dict(links=[('n0', 'zz')], ranges=[3.0]),
     r"'links\[0\]' \['n0', 'zz'\]: unknown identifier 'zz'"),
    (dict(links=[('n1', 'n1')], ranges=[3.0]), 'a link to itself'),
    (dict(links=[('n0', 'n1')], ranges=[1e300]),
     r"'ranges\[0\]' of 'links\[0\]' \['n0', 'n1'\] is too large"),
    (dict(links=[('n0', 'n1')], ranges=[10**400]), 'is too large'),
    (dict(links=[('n0', 'n1')], ranges=[[3.0, 123.0, -7.0]]),
     r"'ranges\[0\]' of 'links\[0\]' \['n0', 'n1'\] has 3 features; "
     r"the measurement model reads 1 \(range\)"),
    (dict(links=[('n0', 'n1')], ranges=[float('nan')]), 'is not finite'),
    (dict(links=[('n0', 'n3')], ranges=[3.0]),
     "'n3' is an anchor, and anchors never measure"),
    (dict(links=[('n0', 'n1'), ('n0', 'n1')], ranges=[3.0, 3.1]),
     r"the same link as 'links\[0\]'"),
    (dict(links=[('n0', 'n1')], ranges=[]), '1 links but 0 ranges'),
    (dict(join={'n0': AgentPrior([0.0] * 4, torch.eye(4).tolist())}),
     'already in use'),
    (dict(join={'x': AgentPrior([0.0] * 4, [
        [1.0, 2.0, 0, 0], [0.0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])}),
     'cov is not symmetric'),
    (dict(join={'x': AgentPrior([0.0] * 4, (-torch.eye(4)).tolist())}),
     'not positive semi-definite'),
    (dict(join={'x': AgentPrior([0.0, float('nan'), 0.0, 0.0],
                                torch.eye(4).tolist())}),
     r"'join\[0\]' \('x'\) mean: non-finite prior mean"),
    (dict(join={'x': AnchorAt([1e30, 0.0])}),
     r"'join\[0\]' \('x'\) mean holds a position beyond"),
    (dict(join={'x': AgentPrior([0.0] * 6, torch.eye(6).tolist())}),
     r"'join\[0\]' \('x'\) mean must have shape \[4\]"),
    (dict(leave=['nobody']), r"'leave\[0\]': unknown identifier"),
    (dict(leave=['n0', 'n0']), r"'leave\[1\]': 'n0' is repeated"),
    (dict(links=['n0n1'], ranges=[3.0]), 'a link is a pair'),
    (dict(links=[('n0', 1.0)], ranges=[3.0]),
     'an identifier is a string or an integer, got 1.0'),
    (dict(dt=0.0), "'dt' must be a finite number above 0"),
    (dict(dt=10**400), "'dt' must be a finite number above 0"),
    (dict(dt=1e300), r"'dt' must be a finite number above 0 \(at most"),
    (dict(time=10**400), "'time' must be a finite number"),
    (dict(join={'x': AgentPrior([10**400, 0.0, 0.0, 0.0],
                                torch.eye(4).tolist())}),
     r"'join\[0\]' \('x'\) mean holds a number too large"),
    (dict(join={'x': AnchorAt([10**400, 0.0])}), 'too large for a float'),
    (dict(join={'x': AnchorAt([1.0, 2.0])}, links=[('x', 'n9')],
          ranges=[1.0]), "unknown identifier 'n9'"),
])
def test_a_bad_step_names_its_field_and_changes_nothing(data, update,
                                                        match):
    session = TrackingSession(ParticleBP(num_particles=10),
                              generator=gen(4))
    stream_realization(session, data, steps=1)
    before = _snapshot(session)
    with pytest.raises(ValueError, match=match):
        session.update(**update)
    _assert_same_state(_snapshot(session), before)
    assert session.num_steps == 1 and session.time == 1.0


def test_a_step_that_fails_inside_the_tracker_changes_nothing(data):
    # every particle of the receiver gets zero likelihood in the middle of
    # the step (after draws): the state and the generator are as before,
    # and the next step is the one an untouched session takes
    def session():
        made = TrackingSession(ParticleBP(num_particles=10,
                                          measurement=GaussianRange(1e-6)),
                               generator=gen(4))
        stream_realization(made, data, steps=1)
        return made

    failed, clean = session(), session()
    before = _snapshot(failed)
    # the tracker names the row: the session adds its identifier
    with pytest.raises(ValueError, match=r"node 0 at time index 1: .*zero "
                       r"likelihood.* \(node 0 is 'n0'\)"):
        failed.update([('n3', 'n0')], [1e14])
    _assert_same_state(_snapshot(failed), before)
    assert_same_outputs(stream_realization(failed, data, start=1, steps=2),
                        stream_realization(clean, data, start=1, steps=2),
                        particles=True)


@pytest.mark.parametrize('make', [GaussianBP.recommended, CentralizedIEKF])
def test_a_step_without_links_predicts_and_a_joined_prior_is_not_inflated(
        data, make):
    # a step without measurements is the motion model's prediction alone:
    # of the filter's own belief inflated (Gaussian BP's kappa = 1.5), of a
    # prior that joins at that step not
    tracker = make()
    session = TrackingSession(tracker, dtype=torch.float64)
    last = stream_realization(session, data, steps=SPLIT)[-1]
    kappa = getattr(tracker, 'inflation', 1.0)
    # Gaussian BP's inflation goes no further than the last step's
    # prediction (the IEKF has none)
    held = getattr(session.state, 'predicted', None)
    prior = AgentPrior([5.0, 6.0, 0.5, -0.25], torch.diag(torch.tensor(
        [4.0, 1.0, 0.01, 0.04], dtype=torch.float64)).tolist())
    mean, cov = session.estimates(last)['n0']
    if held is not None:
        # what it carries is its belief (the estimate it reports may be
        # inflated further: report_inflation), inflated by kappa
        cov = bounded_inflation(session.state.cov[:1], held[:1],
                                torch.tensor([kappa]))[0]
    beliefs = [(0, mean, cov, 1.0),
               (-1, torch.tensor(prior.mean, dtype=torch.float64),
                torch.tensor(prior.cov, dtype=torch.float64), 1.0)]
    out = session.update(dt=2.0, join={'late': prior})
    motion = tracker.motion.with_time_step(2.0)
    for row, mean, cov, inflation in beliefs:
        start = mean.view(1, -1)
        jacobian = motion.jacobian(start)[0]
        predicted = (inflation * jacobian @ cov @ jacobian.t() +
                     motion.noise_covariance(start)[0])
        torch.testing.assert_close(out.mean[row], motion.mean(start)[0],
                                   rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(out.cov[row], predicted, rtol=1e-9,
                                   atol=1e-12)


def keep_first(log_weights, num_samples, generator):
    r"""A resampler that keeps particle 0 of every node."""
    return torch.zeros(log_weights.shape[:-1] + (num_samples, ),
                       dtype=torch.long)


def test_a_joined_prior_is_not_resampled_before_its_prediction(data):
    # the resampler collapses every belief to one particle: the old agents
    # keep the motion noise's spread only, the joining agent its prior's
    session = TrackingSession(ParticleBP(num_particles=2000,
                                         resampler=keep_first),
                              generator=gen(6))
    stream_realization(session, data, steps=SPLIT)
    out = session.update(join={'late': AgentPrior(
        [5.0, 6.0, 0.5, -0.25], torch.diag(torch.tensor(
            [4.0, 1.0, 0.01, 0.04])).tolist())})
    assert float(out.cov[0, 0, 0]) < 0.01
    assert 3.0 < float(out.cov[-1, 0, 0]) < 5.5


@pytest.mark.parametrize('name', ['gbp', 'bp'])
def test_links_in_any_order(data, name):
    # the session sorts a step's links by receiver, as the layers need:
    # links fed in reverse give the offline result (to the rounding of
    # another summation order)
    tracker = live_trackers()[name]()
    offline = list(tracker.steps(data, gen(8)))
    session = TrackingSession(tracker, _all_nodes(data), generator=gen(8))
    for t in range(STEPS):
        links, ranges = _links(data, t)
        out = session.update(links[::-1], ranges[::-1])
        torch.testing.assert_close(out.mean, offline[t].mean, rtol=1e-5,
                                   atol=1e-5)


@pytest.mark.parametrize('make', [GaussianBP, CentralizedIEKF])
def test_an_anchor_added_midway_informs_its_neighbours(data, make):
    # an anchor joins at SPLIT where agent 0 truly is one step later, and
    # agent 0 measures its range to it: it is reported at its position with
    # no uncertainty, and agent 0's estimate is pulled by that range
    tracker = make()
    with_anchor, without = (TrackingSession(tracker) for _ in range(2))
    for session in (with_anchor, without):
        stream_realization(session, data, steps=SPLIT)
    where = (data.states[0, SPLIT, :2] + torch.tensor([3.0, 4.0])).tolist()
    links, ranges = _links(data, SPLIT)
    out = with_anchor.update(links + [('beacon', 'n0')], ranges + [5.0],
                             join={'beacon': AnchorAt(where)})
    plain = without.update(links, ranges)
    assert with_anchor.ids[-1] == 'beacon' and bool(with_anchor.anchor[-1])
    assert torch.equal(out.mean[-1, :2].float(), torch.tensor(where))
    assert float(out.cov[-1].abs().max()) == 0.0
    assert float((out.mean[0] - plain.mean[0]).abs().max()) > 1e-4
    assert 'beacon' not in with_anchor.estimates(out)


def test_models_of_more_link_features_run_live():
    # the NLOS model reads the range only, while generated data carry the
    # true NLOS flag too: the live links hold the range alone, and particle
    # BP's pair factors (ends='both') and the oracle model that reads the
    # flag run on them; a step without links predicts with either
    from tg_nebp.models import NLOSRange
    nlos = NLOSRange(0.8, 0.3, 2.0)
    data = tiny_scenario(4).replace(measurement=nlos).generate(gen(5))
    tracker = ParticleBP(num_particles=20, ends='both', num_iterations=2,
                         measurement=nlos)
    offline = list(tracker.steps(data, gen(3)))
    session = TrackingSession(tracker, generator=gen(3))
    assert_same_outputs(stream_realization(session, data), offline,
                        particles=True)
    session.update(dt=1.0)
    oracle = TrackingSession(GaussianBP(measurement=NLOSRange(
        0.8, 0.3, 2.0, oracle=True)), _all_nodes(data))
    edge_index, edge_attr = data.edges_by_step()[0]
    oracle.update([(f'n{j}', f'n{i}') for j, i in edge_index.t().tolist()],
                  edge_attr.tolist())
    oracle.update()
    with pytest.raises(ValueError, match=r"has 1 features; the measurement "
                       r"model reads 2 \(range, nlos\)"):
        oracle.update([('n3', 'n0')], [2.0])


def test_a_negative_range_is_a_measurement_where_the_likelihood_takes_it(
        data):
    # two close nodes' calibrated range below zero: taken by the Gaussian
    # likelihood (it moves the estimate as the offline loop with that
    # range does), refused by name by a model that needs it non-negative
    negative = data.clone()
    negative.edge_attr = data.edge_attr.clone()
    negative.edge_attr[0, 0] = -0.01
    session = TrackingSession(GaussianBP())
    streamed = stream_realization(session, negative)
    offline = list(GaussianBP().steps(negative))
    assert_same_outputs(streamed, offline)
    other = list(GaussianBP().steps(data))
    assert not torch.equal(other[0].mean, offline[0].mean)
    session = TrackingSession(GaussianBP(measurement=NonNegativeRange()))
    with pytest.raises(ValueError, match=r"is negative: -0\.0099\d* \(the "
                       r"likelihood of .* needs ranges of at least 0\)"):
        stream_realization(session, negative, steps=1)
    with pytest.raises(ValueError, match=r"'edge_attr\[0\]' = -0\.0099\d* is "
                       r"a negative range"):
        GaussianBP(measurement=NonNegativeRange())(negative)


def test_a_bad_link_dropped_costs_that_link_only(data):
    # under bad_links='drop' the step goes on with the good links, as the
    # same step without the bad ones, and names what it left out
    edge_index, edge_attr = data.edges_by_step()[0]
    links = [(f'n{j}', f'n{i}') for j, i in edge_index.t().tolist()]
    ranges = edge_attr[:, 0].tolist()
    bad_links = links + [('n0', 'n0'), ('n0', 'zz'), ('n1', 'n3')]
    bad_ranges = ranges + [2.0, 2.0, 2.0]
    bad_ranges[1] = math.nan
    dropped = TrackingSession(GaussianBP(), _all_nodes(data))
    out = dropped.update(bad_links, bad_ranges, bad_links='drop')
    assert [k for k, _ in dropped.refused_links] == [1, len(links),
                                                     len(links) + 1,
                                                     len(links) + 2]
    assert 'not finite' in dropped.refused_links[0][1]
    assert 'a link to itself' in dropped.refused_links[1][1]
    assert "unknown identifier 'zz'" in dropped.refused_links[2][1]
    assert 'anchors never measure' in dropped.refused_links[3][1]
    clean = TrackingSession(GaussianBP(), _all_nodes(data))
    expected = clean.update(links[:1] + links[2:], ranges[:1] + ranges[2:])
    assert torch.equal(out.mean, expected.mean)
    assert torch.equal(out.cov, expected.cov)
    assert clean.refused_links == []
    with pytest.raises(ValueError, match="'bad_links' must be one of"):
        clean.update(bad_links='ignore')


def test_a_damaged_saved_session_is_refused_whole(data, tmp_path):
    session = TrackingSession(GaussianBP())
    stream_realization(session, data, steps=1)
    saved = session.state_dict()
    fresh = TrackingSession(GaussianBP(), seed=5)
    before = fresh.generator.get_state()
    for damage, match in (
            (dict(time=None), 'a damaged saved session'),
            (dict(dtype='Tensor'), 'a damaged saved session'),
            (dict(ids='["n0", "n1"]'), r'2 identifiers, 6 anchor flags and '
             r'6 state rows'),
            (dict(generator=torch.zeros(3, dtype=torch.uint8)),
             'another kind of device')):
        with pytest.raises(ValueError, match=match):
            fresh.load_state_dict({**saved, **damage})
        # nothing of it was loaded
        assert fresh.ids == [] and fresh.state is None
        assert torch.equal(fresh.generator.get_state(), before)
    fresh.load_state_dict(saved)
    assert fresh.ids == session.ids and fresh.num_steps == 1


def test_joining_takes_any_sequence_of_numbers(data):
    # lists, tensors and tuples alike; the first node sets the state size
    session = TrackingSession(GaussianBP(), {
        'a': AnchorAt(torch.tensor([0.0, 0.0])),
        'b': AgentPrior(torch.tensor([1.0, 1.0, 0.0, 0.0]),
                        torch.eye(4)),
        'c': AgentPrior((2.0, 1.0, 0.0, 0.0), torch.eye(4).tolist())})
    out = session.update([('a', 'b'), ('b', 'c')], [1.4, 1.0])
    assert session.ids == ['a', 'b', 'c'] and out.mean.shape == (3, 4)
    with pytest.raises(ValueError, match=r"'join\[0\]' \('d'\) mean must "
                       r"have shape \[4\], got \[6\]"):
        session.update(join={'d': AgentPrior(torch.zeros(6), torch.eye(6))})


def _robot_session():
    from tg_nebp.models import GaussianRangeBearing, UnicycleOdometry
    session = TrackingSession(GaussianBP(motion=UnicycleOdometry(),
                                         measurement=GaussianRangeBearing()),
                              dtype=torch.float64)
    session.update(join={'r1': AgentPrior([0.0, 0.0, 0.0],
                                          torch.eye(3).tolist()),
                         'r2': AgentPrior([1.0, 0.0, 3.0],
                                          torch.eye(3).tolist()),
                         'L': AnchorAt([2.0, 2.0])})
    return session


@pytest.mark.parametrize('control,match', [
    ({'r9': [0.1, 0.0]}, r"'control\['r9'\]': unknown identifier"),
    ({'L': [0.1, 0.0]}, "'L' is an anchor"),
    ({'r1': [0.1]}, r"'control\['r1'\]' must have shape \[2\]"),
    ({'r1': [0.1, float('nan')]}, "must be finite"),
    ([[0.1, 0.0]], "must map identifiers"),
    ({'r1': [True, False]}, r"'control\['r1'\]' must be numbers, not true"),
    # a turn of 1e30 rad raised a raw linear-algebra error
    ({'r1': [0.0, 1e30]}, r"'control\['r1'\]' = \[0.0, 1e\+30\] is beyond "
     r"the inputs the motion model UnicycleOdometry"),
])
def test_bad_control_is_named_and_changes_nothing(control, match):
    session = _robot_session()
    before = session.state_dict()
    with pytest.raises(ValueError, match=match):
        session.update(control=control)
    after = session.state_dict()
    assert torch.equal(before['state']['mean'], after['state']['mean'])
    assert session.num_steps == 1


@pytest.mark.parametrize('make', [
    lambda: CentralizedSmoother(3), lambda: CentralizedSmoother(None),
    lambda: Smoothed(FixedLagGaussianBP(3))])
def test_a_tracker_without_live_state_is_refused_when_the_session_starts(
        make):
    # the offline smoothers and the reader of finished windows keep no
    # state between lines: refused at once, not at the first update
    with pytest.raises(ValueError, match='does not run live'):
        TrackingSession(make())


def test_control_moves_the_robot_and_a_missing_one_is_input_free():
    session = _robot_session()
    # JSON object keys are strings: r1 by name; r2 gets no input
    out = session.update(control={'r1': [1.0, 0.0]})
    assert out.mean[0].tolist() == pytest.approx([1.0, 0.0, 0.0])
    assert out.mean[1].tolist() == pytest.approx([1.0, 0.0, 3.0])
    # every input-free prediction (this and the joining step's) widens by
    # the model's idle noise
    assert float(out.cov[1, 0, 0]) == pytest.approx(1.0 + 2 * 0.25)


def test_control_for_a_model_without_inputs_is_refused():
    session = TrackingSession(GaussianBP(), dtype=torch.float64)
    with pytest.raises(ValueError, match='takes no known inputs'):
        session.update(join={'a': AgentPrior([0.0] * 4,
                                             torch.eye(4).tolist())},
                       control={'a': [1.0]})


def test_the_shipped_robots_correction_runs_live():
    # a robot's [x, y, heading] is 2-D positions, as the checkpoint's
    from tg_nebp.training import gaussian_nebp_from_checkpoint
    session = TrackingSession(gaussian_nebp_from_checkpoint('robots'),
                              dtype=torch.float64)
    out = session.update(join={'a': AgentPrior([0.0, 0.0, 0.1],
                                               (0.25 * torch.eye(3)).tolist()),
                               'L': AnchorAt([3.0, 1.0])},
                         control={'a': [0.1, 0.0]})
    assert out.mean[0, :2].tolist() == pytest.approx(
        [0.1 * math.cos(0.1), 0.1 * math.sin(0.1)])


def _damaged(value, kind, how):
    # one field's tensor damaged 'how': a non-finite entry (infinity where
    # NaN means 'none'), a wrong size, a wrong dtype or a wrong value
    if how == 'nonfinite':
        if not value.is_floating_point() or value.numel() == 0:
            return None
        out = value.clone()
        out[(0, ) * out.dim()] = math.inf if kind in ('nan', 'log_weights') \
            else math.nan
        return out
    if how == 'shape':
        return torch.cat([value, value.narrow(-1, 0, 1)], -1) \
            if value.dim() and value.size(-1) else value.new_zeros(1)
    if how == 'dtype':
        return value.float() if value.dtype == torch.float64 else \
            value.double() if value.is_floating_point() else \
            value.to(torch.int32 if kind == 'index' else torch.uint8)
    if kind == 'cov' and value.numel():
        return -value - torch.eye(value.size(-1), dtype=value.dtype)
    if kind == 'log_weights':
        return value + 1.0
    if kind == 'index' and value.numel():
        return value - value.max() - 1
    return None


@pytest.mark.parametrize('name', list(live_trackers()))
def test_a_saved_state_with_any_field_damaged_is_refused(data, name):
    # every field of the tracker's state, and the session's own, damaged
    # one at a time: refused by the field's name, and the session that
    # loads it is unchanged
    make = live_trackers()[name]
    session = TrackingSession(make())
    stream_realization(session, data, steps=3)
    saved = session.state_dict()
    fresh = TrackingSession(make(), seed=5)
    before = fresh.generator.get_state()
    fields = session.tracker.state_type.FIELDS
    refused = 0
    for field, spec in fields.items():
        value = saved['state'][field]
        if value is None:
            continue
        elements = list(enumerate(value)) if spec.tuple else [(None, value)]
        for k, tensor in elements:
            for how in ('nonfinite', 'shape', 'dtype', 'value'):
                bad = _damaged(tensor, spec.kind, how)
                if bad is None:
                    continue
                if k is None:
                    damaged = bad
                else:
                    damaged = list(value)
                    damaged[k] = bad
                state = dict(saved['state'], **{field: damaged})
                with pytest.raises(ValueError, match=f"'{field}'|particles"):
                    fresh.load_state_dict(dict(saved, state=state))
                assert fresh.ids == [] and fresh.state is None
                assert torch.equal(fresh.generator.get_state(), before)
                refused += 1
    for damage, match in (
            (dict(anchor=saved['anchor'].double() * 0.5), "'anchor'"),
            (dict(time=math.nan), "'time'"), (dict(num_steps=-1),
                                              "'num_steps'"),
            (dict(num_steps=2.5), "'num_steps'"),
            (dict(state_size=saved['state_size'] + 2), 'shape|entries')):
        with pytest.raises(ValueError, match=match):
            fresh.load_state_dict({**saved, **damage})
        assert fresh.ids == [] and fresh.state is None
    assert refused >= 3 * len([f for f in fields
                               if saved['state'][f] is not None])
    fresh.load_state_dict(saved)
    assert fresh.ids == session.ids


def _covariances(state, fields):
    # every covariance of a tracker's state: (field name, tensor)
    for name, spec in fields.items():
        value = getattr(state, name)
        if spec.kind == 'cov' and value is not None:
            yield from ((name, item) for item in (
                value if spec.tuple else (value, )))


@pytest.mark.parametrize('dtype', [torch.float32, torch.float64])
def test_every_trackers_covariances_are_symmetric_and_reload(data, dtype,
                                                             tmp_path):
    # every tracker in both precisions (the particle trackers compute in
    # the session's): each step's estimated covariances and those of its
    # state exactly symmetric (formed so, in whatever order the BLAS at
    # hand sums a product's two triangles), and the session saved after
    # each step loads in another session; the same covariances made
    # asymmetric far beyond rounding are refused by name
    for name, make in live_trackers().items():
        session = TrackingSession(make(), generator=gen(8), dtype=dtype)
        fields = session.tracker.state_type.FIELDS
        for t in range(STEPS):
            with torch.no_grad():
                out, = stream_realization(session, data, start=t,
                                          steps=t + 1)
            known = ~out.cov.isnan().flatten(1).any(1)
            assert torch.equal(out.cov[known], out.cov[known].mT), name
            covariances = list(_covariances(session.state, fields))
            assert covariances, name
            for field, cov in covariances:
                assert torch.equal(cov, cov.mT), (name, field, t)
            session.save(tmp_path / 'session.pt')
            TrackingSession.load(tmp_path / 'session.pt', make())
        saved = session.state_dict()
        for field, cov in _covariances(session.state, fields):
            if not cov.numel() or not bool(cov.abs().amax() > 0):
                continue
            skew = cov.clone()
            skew[..., 0, 1] += 1e-2 * cov.abs().amax()
            spec = fields[field]
            value = tuple(skew if c is cov else c for c in getattr(
                session.state, field)) if spec.tuple else skew
            with pytest.raises(ValueError, match=f"'{field}'.* not symmetric"):
                TrackingSession(make()).load_state_dict(dict(
                    saved, state=dict(saved['state'], **{field: value})))


def test_the_state_check_allows_rounding_of_the_dtype_only():
    # a covariance off symmetric or below zero by less than half the
    # digits of its dtype (relative to its largest entry) is rounding;
    # by more it is damage: float32 and float64 alike
    fields = dict(cov=StateField(('N', 'S', 'S'), 'cov'))
    for dtype, rounding, damage in ((torch.float32, 1e-5, 1e-3),
                                    (torch.float64, 1e-10, 1e-7)):
        for scale in (1e-6, 1.0, 1e6):
            for off, ok in ((rounding, True), (damage, False)):
                skew = scale * torch.tensor([[1.0, 0.5 + off], [0.5, 0.5]],
                                            dtype=torch.float64)
                low = scale * torch.tensor([[1.0, 0.0], [0.0, -off]],
                                           dtype=torch.float64)
                for cov, what in ((skew, 'not symmetric'),
                                  (low, 'not positive semi-definite')):
                    state = _OneCov(cov.to(dtype).unsqueeze(0))
                    if ok:
                        check_state(state, fields, 1, 2)
                    else:
                        with pytest.raises(ValueError, match=what):
                            check_state(state, fields, 1, 2)


class _OneCov(NamedTuple):
    cov: torch.Tensor


def _same(a, b) -> bool:
    # bit for bit, through dicts, lists and tuples
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and \
            a.shape == b.shape and torch.equal(a.view(torch.uint8) if
                                               a.numel() else a, b.view(
                                                   torch.uint8) if b.numel()
                                               else b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(
            _same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(
            _same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and (a == b or a != a and b != b)


def test_a_saved_session_with_a_bit_flipped_is_refused_or_unchanged(
        data, tmp_path):
    # 600 single bits flipped at seeded places of a saved session: each
    # file is refused whole, or loads exactly what was saved (a flip that
    # the format ignores)
    session = TrackingSession(FixedLagGaussianBP.recommended(lag=3))
    stream_realization(session, data, steps=3)
    path = tmp_path / 'session.pt'
    session.save(path)
    expected = TrackingSession.load(path, session.tracker).state_dict()
    refused, loaded = loads_after_bit_flips(
        path, lambda p: TrackingSession.load(p, session.tracker), 600, 9)
    for place, other in loaded:
        assert _same(other.state_dict(), expected), place
    assert refused > 500


@pytest.mark.parametrize('name', ['gbp-lag4-settled', 'hybrid-lag3'])
def test_a_session_saved_before_an_optional_field_existed_loads(data, name):
    # a saved state that lacks an optional field added since (a window's
    # entry_point) loads with it absent, as a state without it holds:
    # the hybrid state's fields (a NamedTuple without defaults) included
    tracker = live_trackers()[name]()
    session = TrackingSession(tracker, generator=gen(8))
    stream_realization(session, data, steps=SPLIT)
    saved = session.state_dict()
    saved['state'] = {key: value for key, value in saved['state'].items()
                      if key != 'entry_point'}
    resumed = TrackingSession(live_trackers()[name](), generator=gen(8))
    resumed.load_state_dict(saved)
    assert resumed.state.entry_point is None
    assert resumed.num_steps == session.num_steps
