import json
import math

import pytest
import torch
from helpers import gen, tiny_scenario

from tg_nebp.evaluation import summarize
from tg_nebp.filters import GaussianBP, ParticleBP, TrackingSession
from tg_nebp.live import (parse_step, realization_lines, score, track_lines,
                          truth_lines)


@pytest.fixture(scope='module')
def data():
    return tiny_scenario(4).generate(gen(3))


def test_a_recorded_realization_replays_as_the_offline_loop(data):
    # measurement lines in, estimate lines out: the floats read back bit
    # for bit, and the score is the evaluation's of the same estimates
    lines = list(realization_lines(data))
    assert 'states' not in lines[0] and len(lines) == 4
    first = json.loads(lines[0])
    assert [entry['id'] for entry in first['join']] == list(range(6))
    assert 'anchor' in first['join'][3] and 'mean' in first['join'][0]
    written = []
    counts = track_lines(TrackingSession(GaussianBP()), lines,
                         written.append)
    assert counts == dict(lines=4, written=4, skipped=0)
    offline = list(GaussianBP().steps(data))
    errors, nees = [], []
    for line, step in zip(written, offline):
        estimates = json.loads(line)['estimates']
        assert [e['id'] for e in estimates] == [0, 1, 2]
        mean = torch.tensor([e['mean'] for e in estimates],
                            dtype=torch.float64)
        cov = torch.tensor([e['cov'] for e in estimates],
                           dtype=torch.float64)
        assert torch.equal(mean, step.mean[:3])
        assert torch.equal(cov, step.cov[:3])
        truth = data.states[:3, step.t, :2]
        offset = mean[:, :2] - truth
        errors.append(offset.norm(dim=-1))
        whitened = torch.linalg.solve(cov[:, :2, :2], offset.unsqueeze(-1))
        nees.append((offset.unsqueeze(-2) @ whitened
                     ).view(-1))
    entry = score(written, truth_lines(data))
    expected = summarize(torch.cat(errors), torch.cat(nees))
    assert entry['outage'] == expected['outage']
    assert entry['accept'] == expected['accept']
    assert math.isclose(entry['rmse'], expected['rmse'], rel_tol=1e-12)
    assert entry['steps'] == 4 and entry['estimates'] == 12


@pytest.mark.parametrize('line, match', [
    ('{"links": [[0, 1, 3.0]', 'not JSON'),
    ('[1, 2]', 'a line is a JSON object, got list'),
    ('{"link": []}', "unknown field 'link'"),
    ('{"join": [{"id": 7}]}', r"'join\[0\]' must hold 'mean' and 'cov'"),
    ('{"join": [{"id": 7, "anchor": [1, 2]}, {"id": 7, "anchor": [3, 4]}]}',
     "identifier 7 is repeated"),
    ('{"leave": 3}', "'leave' must be a list"),
])
def test_a_malformed_line_names_its_field(line, match):
    with pytest.raises(ValueError, match=match):
        parse_step(line)


def test_bad_lines_are_numbered_and_skipped_or_stop_the_run(data):
    # bad lines, skipped and reported with their numbers (those whose time
    # cannot be read with the clock named as possibly off); the estimates
    # are the clean stream's
    lines = list(realization_lines(data))
    bad = ['not json', '{"leave": 3}', '{"links": 5}',
           '{"dt": 1' + '0' * 400 + '}', '{"join": [{"id": 9, "anchor": '
           '[1' + '0' * 400 + ', 0]}]}']
    stream = lines[:1] + bad + [''] + lines[1:]
    written, reports = [], []
    tracker = ParticleBP(num_particles=20)
    counts = track_lines(TrackingSession(tracker, generator=gen(1)), stream,
                         written.append, 'skip', reports.append)
    assert counts == dict(lines=len(stream), written=4, skipped=5)
    assert [r.split(':')[0] for r in reports] == [
        'skipped line 2', 'skipped line 3', 'skipped line 4',
        'skipped line 5', 'skipped line 6']
    assert "'dt' must be a finite number" in reports[3]
    assert 'too large for a float' in reports[4]
    # the last can be read: its time passes (the next line's time counts)
    assert [r.endswith('(its time could not be read: the clock may be '
                       'off)') for r in reports] == [True] * 4 + [False]
    assert "'leave' must be a list" in reports[1]
    clean = []
    track_lines(TrackingSession(tracker, generator=gen(1)), lines,
                clean.append)
    assert written == clean
    with pytest.raises(ValueError, match=r"^line 2: 'leave' must be a list"):
        track_lines(TrackingSession(tracker, generator=gen(1)),
                    lines[:1] + bad[1:], written.append)
    with pytest.raises(ValueError, match="'on_error' must be one of"):
        track_lines(TrackingSession(tracker), lines, written.append,
                    'ignore')


def test_a_bad_link_costs_that_link_only(data):
    # one line's good links with bad ones added (an unknown node, a link
    # to itself, a range that is not finite, one without a range, extra
    # features): each bad one is reported by line and position and left
    # out, and the estimate is the clean line's, under either on_error
    lines = list(realization_lines(data))
    line = json.loads(lines[1])
    count = len(line['links'])
    line['links'] += [[0, 99, 3.0], [1, 1, 2.0], [0, 1, float('nan')],
                      [0, 1], [0, 2, 3.0, 123, -7]]
    dirty = lines[:1] + [json.dumps(line)] + lines[2:]
    for on_error in ('stop', 'skip'):
        written, reports = [], []
        counts = track_lines(TrackingSession(GaussianBP()), dirty,
                             written.append, on_error, reports.append)
        assert counts['written'] == len(lines) and counts['skipped'] == 0
        assert [r.split(' left out ')[0] for r in reports] == [
            'line 2:'] * 5
        assert [r.split(' left out ')[1].split(']')[0] for r in reports] \
            == [f"'links[{count}", f"'links[{count + 1}",
                f"'ranges[{count + 2}", f"'ranges[{count + 3}",
                f"'ranges[{count + 4}"]
        assert 'unknown identifier 99' in reports[0]
        assert 'a link to itself' in reports[1]
        assert 'not finite' in reports[2] and 'is missing' in reports[3]
        assert 'has 3 features; the measurement model reads 1' in reports[4]
        clean = []
        track_lines(TrackingSession(GaussianBP()), lines, clean.append)
        assert written == clean


def test_a_skipped_line_still_moves_the_clock(data):
    # a line refused after it was read (an unknown leaver) takes its dt
    # along: the next step predicts over both and is labelled with its own
    # time, as one step over the two time steps
    lines = [json.loads(line) for line in realization_lines(data)]
    for line in lines:
        line.pop('time', None)
        line['dt'] = 0.5
    stream = [json.dumps(lines[0]), json.dumps(dict(dt=0.5, leave=[77])),
              json.dumps(lines[1])]
    written, reports = [], []
    track_lines(TrackingSession(GaussianBP()), stream, written.append,
                'skip', reports.append)
    assert len(reports) == 1 and 'clock' not in reports[0]
    longer = [json.dumps(lines[0]), json.dumps(dict(lines[1], dt=1.0))]
    expected = []
    track_lines(TrackingSession(GaussianBP()), longer, expected.append)
    assert [json.loads(w)['time'] for w in written] == [0.5, 1.5]
    assert written == expected


def test_a_lost_line_is_a_longer_time_step_and_scores_by_time(data):
    # the lines carry their step's time: without line 2 the session
    # predicts over two steps at line 3, and the estimates are matched to
    # the truth of their own times
    lines = list(realization_lines(data, dt=0.5))
    assert [json.loads(line)['time'] for line in lines] == [0.5, 1.0, 1.5,
                                                            2.0]
    written = []
    track_lines(TrackingSession(GaussianBP()), lines[:1] + lines[2:],
                written.append)
    assert [json.loads(line)['time'] for line in written] == [0.5, 1.5, 2.0]
    entry = score(written, truth_lines(data, dt=0.5))
    assert entry['steps'] == 3 and entry['estimates'] == 9
    # the second estimate is scored against the truth at 1.5 s (t = 2)
    one = score(written[1:2], truth_lines(data, dt=0.5))
    squared = [sum((m - s) ** 2 for m, s in zip(
        e['mean'][:2], data.states[e['id'], 2, :2].tolist()))
        for e in json.loads(written[1])['estimates']]
    assert math.isclose(one['rmse'], math.sqrt(sum(squared) / 3),
                        rel_tol=1e-6)


@pytest.mark.parametrize('estimates, match', [
    (['{"t": 0}'], "estimates line 1: no 'time'"),
    (['{"time": 0.25, "estimates": []}'], 'no truth at that time'),
    (['', '{"time": 1.0, "estimates": [{"id": 0}]}'],
     r"estimates line 2 \(time 1.0\): an estimate without a 'mean'"),
    (['{"time": 1.0, "estimates": [{"id": 99, "mean": [], "cov": []}]}'],
     'no true state of 99'),
    (['{"time": 1.0, "estimates": []}'] * 2, 'estimated twice'),
    (['nope'], 'estimates line 1: not JSON'),
    (['{"time": 1.0, "estimates": [[0, 1]]}'],
     r"'estimates\[0\]' must be an object with an 'id'"),
    (['{"time": 1.0, "estimates": 5}'], "'estimates' must be a list"),
    (['{"time": [1.0], "estimates": []}'],
     "estimates line 1: 'time' must be a finite number"),
    (['{"time": 1.0, "estimates": [{"id": 0, "mean": [NaN, 0, 0, 0], '
      '"cov": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}'],
     'an estimate that is not finite'),
    (['{"time": 1.0, "estimates": [{"id": 0, "mean": [0, 0], '
      '"cov": [[1, 0], [0, 1]]}]}'], "of the truth's size"),
])
def test_score_names_the_line_it_cannot_read(data, estimates, match):
    with pytest.raises(ValueError, match=match):
        score(estimates, truth_lines(data))


@pytest.mark.parametrize('change, match', [
    (lambda line: dict(line, states=[7]),
     r"truth line 2: 'states\[0\]' must be an object with an 'id'"),
    (lambda line: dict(line, time=line['time'] - 1.0),
     r'truth line 2: time 1.0 is given twice'),
    (lambda line: dict(line, states=[dict(id=0, state=['a'])]),
     r"truth line 2: 'states\[0\]' must hold a 'state' of finite"),
])
def test_score_names_the_truth_line_it_cannot_read(data, change, match):
    truth = list(truth_lines(data))
    truth[1] = json.dumps(change(json.loads(truth[1])))
    with pytest.raises(ValueError, match=match):
        score([], truth)


def test_score_counts_the_truth_that_no_estimate_covers(data):
    # estimates of 2 of the 4 steps, one of them without its first agent:
    # the truth left out is counted, not passed over
    written = []
    track_lines(TrackingSession(GaussianBP()), realization_lines(data),
                written.append)
    partial = [json.loads(line) for line in written[:2]]
    partial[1]['estimates'] = partial[1]['estimates'][1:]
    entry = score([json.dumps(line) for line in partial], truth_lines(data))
    agents = int((~data.anchor).sum())
    assert entry['steps'] == 2 and entry['estimates'] == 2 * agents - 1
    assert entry['unscored_steps'] == data.num_time_steps - 2
    assert entry['unscored_states'] == \
        data.num_time_steps * agents - 2 * agents + 1


def test_an_agent_without_truth_is_estimated_and_counted_not_scored(data):
    # its truth lines say null; the score is the other agents' (as the
    # offline evaluation scores them), its estimates counted apart
    from tg_nebp.evaluation import track_dataset
    blind = data.clone()
    agent = int((~data.anchor).nonzero()[0, 0])
    blind.states[agent] = math.nan
    truth = list(truth_lines(blind))
    assert all(any(e['id'] == agent and e['state'] is None
                   for e in json.loads(line)['states']) for line in truth)
    written = []
    track_lines(TrackingSession(GaussianBP()), realization_lines(blind),
                written.append)
    entry = score(written, truth)
    agents = int((~data.anchor).sum())
    steps = data.num_time_steps
    assert entry['estimates'] == steps * (agents - 1)
    assert entry['without_truth'] == steps and entry['unscored_states'] == 0
    offline = track_dataset(GaussianBP(), [blind])
    assert entry['rmse'] == pytest.approx(
        float(offline['errors'].square().mean().sqrt()), rel=1e-6)
    # an id the truth does not know at all is still refused
    line = json.loads(written[0])
    line['estimates'][0] = dict(line['estimates'][0], id=999)
    with pytest.raises(ValueError, match="no true state of 999"):
        score([json.dumps(line)], truth)


def test_a_smoothers_line_holds_its_revised_window():
    # fixed-lag Gaussian BP: every line adds the revised estimates of the
    # window's earlier steps, oldest first, read back bit for bit; the
    # newest is the line's own estimates
    from tg_nebp.filters import FixedLagGaussianBP
    data = tiny_scenario(steps=4).generate(gen(2))
    session = TrackingSession(FixedLagGaussianBP(3))
    lines = []
    track_lines(session, realization_lines(data), lines.append)
    offline = list(FixedLagGaussianBP(3).steps(data))
    agents = ~data.anchor
    for t, (text, step) in enumerate(zip(lines, offline)):
        line = json.loads(text)
        window = line.get('window', [])
        assert [w['t'] for w in window] == list(range(max(0, t - 2), t))
        for k, entry in enumerate(window):
            means = torch.tensor([e['mean'] for e in entry['estimates']],
                                 dtype=torch.float64)
            covs = torch.tensor([e['cov'] for e in entry['estimates']],
                                dtype=torch.float64)
            assert torch.equal(means, step.window_mean[agents, k])
            assert torch.equal(covs, step.window_cov[agents, k])
    # a filter's line has none
    session = TrackingSession(GaussianBP())
    plain = []
    track_lines(session, realization_lines(data), plain.append)
    assert 'window' not in json.loads(plain[-1])


def test_a_final_window_line_is_the_smoothed_step_and_none_drops_it():
    # window='final': once the window is full a line holds the step that
    # leaves it at the next step, bit for bit Smoothed's estimate of that
    # step (the offline path), and nothing before; 'none' holds no
    # window; both keep the line's own estimates; another value is refused
    # before a line is read
    from tg_nebp.filters import FixedLagGaussianBP, Smoothed
    data = tiny_scenario(steps=6).generate(gen(2))
    lines = {}
    for window in ('all', 'final', 'none'):
        lines[window] = []
        track_lines(TrackingSession(FixedLagGaussianBP(3)),
                    realization_lines(data), lines[window].append,
                    window=window)
    smoothed = {step.t: step for step in
                Smoothed(FixedLagGaussianBP(3)).steps(data)}
    agents = ~data.anchor
    written = []
    for t, text in enumerate(lines['final']):
        window = json.loads(text).get('window', [])
        assert [entry['t'] for entry in window] == ([t - 2] if t >= 2
                                                    else [])
        for entry in window:
            step = smoothed[entry['t']]
            assert torch.equal(torch.tensor(
                [e['mean'] for e in entry['estimates']],
                dtype=torch.float64), step.mean[agents])
            assert torch.equal(torch.tensor(
                [e['cov'] for e in entry['estimates']],
                dtype=torch.float64), step.cov[agents])
            written.append(entry['t'])
    assert written == list(range(data.num_time_steps - 2))
    for window in ('final', 'none'):
        assert [json.loads(text)['estimates'] for text in lines[window]] \
            == [json.loads(text)['estimates'] for text in lines['all']]
    assert all('window' not in json.loads(text) for text in lines['none'])
    read = []
    with pytest.raises(ValueError, match="'window' must be one of"):
        track_lines(TrackingSession(FixedLagGaussianBP(3)),
                    (read.append(line) or line for line in
                     realization_lines(data)), print, window='last')
    assert read == []


def test_the_window_line_leaves_out_an_agent_before_it_rejoined():
    # agent 0 leaves at step 2 and rejoins at step 3 with a new prior: the
    # window of fixed-lag Gaussian BP then holds its prior at the steps
    # before, which are no estimate of it and stay out of the window line;
    # the others are in every step
    from tg_nebp.filters import FixedLagGaussianBP
    from tg_nebp.live import estimate_line
    data = tiny_scenario(6).generate(gen(5))
    session = TrackingSession(FixedLagGaussianBP(4))
    lines = [json.loads(line) for line in realization_lines(data)]
    prior = dict(id=0, mean=data.prior_mean[0].tolist(),
                 cov=data.prior_cov[0].tolist())

    def without_0(line):
        line['links'] = [link for link in line['links'] if 0 not in link[:2]]
        return line

    lines[2] = dict(without_0(lines[2]), leave=[0])
    lines[3] = dict(without_0(lines[3]), join=[prior])
    written = [json.loads(estimate_line(session, session.update(
        *step[:2], step.dt, step.time, step.join, step.leave, step.control)))
        for step in map(parse_step, map(json.dumps, lines))]
    for line in written[3:]:
        assert [e['id'] for e in line['estimates']] == [1, 2, 0]
        for entry in line['window']:
            ids = [e['id'] for e in entry['estimates']]
            assert ids == ([1, 2, 0] if entry['t'] >= 3 else [1, 2])
    assert [entry['t'] for entry in written[5]['window']] == [2, 3, 4]
    # before it left, it was in the window as the others
    assert [e['id'] for e in written[1]['window'][0]['estimates']] == \
        [0, 1, 2]
