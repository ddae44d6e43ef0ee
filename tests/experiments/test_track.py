r"""The live path from the command line: :obj:`tg-nebp record`,
:obj:`track` (in process, and as a subprocess fed through a pipe) and
:obj:`score`."""
import dataclasses
import json
import os
import random
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from helpers import PACKAGE_ROOT, tiny_scenario

from tg_nebp.cli import main
from tg_nebp.datasets import Scenario
from tg_nebp.io import write_json

STEPS = 6


def scenario_file(folder):
    path = folder / 'tiny.json'
    path.write_text(json.dumps(vars(tiny_scenario(steps=STEPS))))
    return path


def test_a_replay_through_track_scores_as_evaluate(tmp_path, capsys):
    # the acceptance: a recorded test realization replayed through the
    # live path has the metrics that evaluate gives on that realization
    root, out = str(tmp_path / 'data'), tmp_path / 'out'
    measurements, truth = tmp_path / 'm.jsonl', tmp_path / 't.jsonl'
    estimates = tmp_path / 'e.jsonl'
    assert main(['record', '--scenario', 'paper_test', '--root', root,
                 '--measurements', str(measurements), '--truth',
                 str(truth)]) == 0
    assert main(['track', '--method', 'gbp', '--input', str(measurements),
                 '--output', str(estimates)]) == 0
    capsys.readouterr()
    assert main(['score', '--estimates', str(estimates), '--truth',
                 str(truth)]) == 0
    scored = capsys.readouterr().out
    assert main(['evaluate', '--method', 'gbp', '--realizations', '1',
                 '--root', root, '--out', str(out), '--quiet']) == 0
    entry = json.loads((out / 'metrics.json').read_text())['gbp']
    assert scored.startswith(
        f"RMSE {entry['rmse']:.3f} m, outage {entry['outage']}, P(accept) "
        f"{entry['accept']}, 50 steps, 5000 estimates")
    from tg_nebp.experiments.track import score_files
    exact = score_files(str(estimates), str(truth))
    assert exact['rmse'] == entry['rmse']
    assert exact['outage'] == entry['outage']
    assert exact['accept'] == entry['accept']


def _process(*args, stdin=subprocess.PIPE):
    env = dict(os.environ, PYTHONPATH=PACKAGE_ROOT, OMP_NUM_THREADS='1')
    # the estimate lines must come flushed by track itself
    env.pop('PYTHONUNBUFFERED', None)
    return subprocess.Popen(
        [sys.executable, '-m', 'tg_nebp', 'track', *map(str, args)],
        stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, env=env, bufsize=1)


def _read_line(stream, timeout=60.0):
    # one line of a pipe within the timeout (None if none came)
    selector = selectors.DefaultSelector()
    selector.register(stream, selectors.EVENT_READ)
    ready = selector.select(timeout)
    selector.close()
    return stream.readline() if ready else None


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
    folder = tmp_path_factory.mktemp('recorded')
    scenario = scenario_file(folder)
    measurements, truth = folder / 'm.jsonl', folder / 't.jsonl'
    assert main(['record', '--scenario', str(scenario), '--root',
                 str(folder / 'data'), '--measurements', str(measurements),
                 '--truth', str(truth)]) == 0
    uninterrupted = folder / 'e.jsonl'
    assert main(['track', '--method', 'bp', '--particles', '50',
                 '--scenario', str(scenario), '--input', str(measurements),
                 '--output', str(uninterrupted)]) == 0
    return dict(scenario=scenario, lines=measurements.read_text().split(
        '\n')[:-1], estimates=uninterrupted.read_text().split('\n')[:-1])


def test_track_answers_every_line_before_the_next_and_skips_bad_ones(
        recorded, tmp_path):
    # a feeder writes a line, pauses, and waits for its estimate line
    # before the next: every estimate comes flushed; the bad lines of each
    # kind (lines that cannot be read: a bad link costs that link only) are
    # reported with their line numbers and skipped, and the saved state
    # after a bad line is the state before it
    state = tmp_path / 'state.pt'
    process = _process('--method', 'bp', '--particles', '50', '--scenario',
                       recorded['scenario'], '--on-error', 'skip',
                       '--save-state', state)
    bad = ['not json', '{"leave": 3}', '{"links": 5}', '{"dt": -1}',
           '{"control": 5}']
    lines = recorded['lines']
    feed = [lines[0], *bad, *lines[1:]]
    outputs, saved = [], []
    try:
        for number, line in enumerate(feed, 1):
            process.stdin.write(line + '\n')
            process.stdin.flush()
            time.sleep(0.05)
            if number not in (2, 3, 4, 5, 6):  # a good line: its estimate
                answer = _read_line(process.stdout)
                assert answer is not None, f'no estimate for line {number}'
                outputs.append(answer.rstrip('\n'))
            _wait_saved(state, number)
            saved.append(torch.load(state, weights_only=True))
        process.stdin.close()
        assert process.wait(60) == 0
        errors = process.stderr.read().splitlines()
    finally:
        process.kill()
    assert outputs == recorded['estimates']
    assert [e.split(':')[0] for e in errors[:5]] == [
        f'skipped line {n}' for n in (2, 3, 4, 5, 6)]
    assert errors[5] == '5 bad line(s) skipped'
    for after in saved[1:6]:  # after each bad line: the state of line 1
        for key in ('generator', 'anchor'):
            assert torch.equal(after[key], saved[0][key])
        for name, value in after['state'].items():
            assert torch.equal(value, saved[0]['state'][name]), name


def _wait_saved(path, lines, timeout=120.0):
    # until the saved state holds the first 'lines' lines
    deadline = time.time() + timeout
    while time.time() < deadline and (
            _progress(path) or {}).get('lines') != lines:
        time.sleep(0.05)
    assert (_progress(path) or {}).get('lines') == lines


def _progress(path):
    try:
        return json.loads(torch.load(path, weights_only=True)['progress'])
    except Exception:  # not written yet, or being replaced
        return None


def test_track_stops_at_a_bad_line_with_one_error(recorded, tmp_path):
    process = _process('--method', 'gbp', '--scenario', recorded['scenario'])
    out, err = process.communicate(
        recorded['lines'][0] + '\n{"links": [[0, 1, 3.0]\n' +
        recorded['lines'][1] + '\n', timeout=120)
    assert process.returncode == 2
    assert len(out.splitlines()) == 1
    assert err.splitlines() == [err.splitlines()[0]]
    assert err.startswith('error: line 2: not JSON: ')


def test_killed_and_resumed_track_writes_the_uninterrupted_lines(
        recorded, tmp_path):
    # killed (SIGKILL) after a random step, resumed from its saved state
    # with the same input: the output file is the uninterrupted run's
    rng = random.Random(30)
    kill_after = rng.randrange(1, STEPS - 1)
    state, output = tmp_path / 'state.pt', tmp_path / 'e.jsonl'
    args = ('--method', 'bp', '--particles', '50', '--scenario',
            recorded['scenario'], '--save-state', state, '--output', output)
    process = _process(*args)
    try:
        for line in recorded['lines'][:kill_after]:
            process.stdin.write(line + '\n')
            process.stdin.flush()
        _wait_saved(state, kill_after)
    finally:
        process.kill()
        process.wait()
    # a kill between a step's estimate line and its save leaves a line
    # that the resumed run writes again: the resumed run drops it
    with open(output, 'a') as stream:
        stream.write(recorded['estimates'][kill_after] + '\n')
    full = tmp_path / 'm.jsonl'
    full.write_text(''.join(line + '\n' for line in recorded['lines']))
    resumed = _process(*args, '--resume', state, '--input', full,
                       stdin=subprocess.DEVNULL)
    out, err = resumed.communicate(timeout=120)
    assert resumed.returncode == 0, err
    assert output.read_text().split('\n')[:-1] == recorded['estimates']


def test_files_with_a_byte_order_mark_are_read(recorded, tmp_path, capsys):
    # saved by a common editor: a UTF-8 byte-order mark first; the input,
    # the truth and a scenario file read as without it
    measurements = tmp_path / 'm.jsonl'
    measurements.write_text('\ufeff' + ''.join(
        line + '\n' for line in recorded['lines']), encoding='utf-8')
    scenario = tmp_path / 'scenario.json'
    scenario.write_text('\ufeff' + Path(recorded['scenario']).read_text(),
                        encoding='utf-8')
    output = tmp_path / 'e.jsonl'
    assert main(['track', '--method', 'bp', '--particles', '50',
                 '--scenario', str(scenario), '--input', str(measurements),
                 '--output', str(output)]) == 0
    assert output.read_text().split('\n')[:-1] == recorded['estimates']
    # standard input: the first line's mark
    written = []
    from tg_nebp.live import track_lines
    from tg_nebp.filters import GaussianBP, TrackingSession
    track_lines(TrackingSession(GaussianBP()), ['\ufeff' + recorded[
        'lines'][0]], written.append)
    assert len(written) == 1
    truth = tmp_path / 't.jsonl'
    truth.write_text('\ufeff' + (Path(recorded['scenario']).parent /
                                 't.jsonl').read_text(), encoding='utf-8')
    capsys.readouterr()
    assert main(['score', '--estimates', str(output), '--truth',
                 str(truth)]) == 0
    assert capsys.readouterr().out.startswith('RMSE ')


def test_ctrl_c_ends_track_with_one_line_saying_where(recorded, tmp_path):
    # SIGINT while track waits for its third line: one line on standard
    # error, no traceback, exit status 130; the saved state and the
    # output hold the two lines tracked
    state = tmp_path / 'state.pt'
    process = _process('--method', 'gbp', '--scenario', recorded['scenario'],
                       '--save-state', state)
    try:
        for line in recorded['lines'][:2]:
            process.stdin.write(line + '\n')
            process.stdin.flush()
            assert _read_line(process.stdout) is not None
        _wait_saved(state, 2)
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 130, err  # what it said instead
    assert err == ('interrupted: stopped at line 3: lines 1-2 tracked (0 '
                   'skipped), 2 estimate lines written; the saved state '
                   'holds lines 1-2\n')
    assert _progress(state)['lines'] == 2


def test_a_resume_with_another_input_is_refused_naming_where(
        recorded, tmp_path, capsys):
    # five lines read and saved; resumed with an input whose line 3, or
    # line 5, differs, or that ends early: refused, naming the lines
    # between the saved digests where it first differs; the same input
    # resumes
    state = tmp_path / 'state.pt'
    lines = recorded['lines']
    first = tmp_path / 'first.jsonl'
    first.write_text(''.join(line + '\n' for line in lines[:5]))
    args = ['track', '--method', 'gbp', '--scenario',
            str(recorded['scenario']), '--save-state', str(state),
            '--output', str(tmp_path / 'e.jsonl')]
    assert main(args + ['--input', str(first)]) == 0
    for changed, match in ((2, 'lines 3-4'), (4, 'lines 5-5'),
                           (None, 'ended after 4 lines')):
        other = list(lines)
        if changed is None:
            other = lines[:4]
        else:
            other[changed] = lines[changed + 1]
        path = tmp_path / 'other.jsonl'
        path.write_text(''.join(line + '\n' for line in other))
        capsys.readouterr()
        assert main(args + ['--input', str(path), '--resume',
                            str(state)]) == 2
        assert match in capsys.readouterr().err
    full = tmp_path / 'full.jsonl'
    full.write_text(''.join(line + '\r\n' for line in lines))
    assert main(args + ['--input', str(full), '--resume', str(state)]) == 0


def test_robots_replay_with_odometry_scores_as_evaluate(tmp_path, capsys):
    # simulated robots: their odometry and bearings travel in the lines
    # ("control", a link's second feature), and the replay scores as the
    # evaluation of the same realization, to the last bit
    root, out = str(tmp_path / 'data'), tmp_path / 'out'
    measurements, truth = tmp_path / 'm.jsonl', tmp_path / 't.jsonl'
    estimates = tmp_path / 'e.jsonl'
    scenario = Scenario.load('robots_test').replace(num_steps=12)
    path = tmp_path / 'robots.json'
    write_json(path, dataclasses.asdict(scenario))
    assert main(['record', '--scenario', str(path), '--root', root,
                 '--measurements', str(measurements), '--truth',
                 str(truth)]) == 0
    first = json.loads(measurements.read_text().splitlines()[0])
    assert len(first['control']) == scenario.num_agents
    assert all(len(link) == 4 for link in first['links'])
    assert main(['track', '--method', 'gbp', '--scenario', str(path),
                 '--input', str(measurements), '--output',
                 str(estimates)]) == 0
    assert main(['evaluate', '--method', 'gbp', '--scenario', str(path),
                 '--realizations', '1', '--root', root, '--out', str(out),
                 '--quiet']) == 0
    entry = json.loads((out / 'metrics.json').read_text())['gbp']
    from tg_nebp.experiments.track import score_files
    exact = score_files(str(estimates), str(truth))
    assert exact['rmse'] == entry['rmse']
    assert exact['accept'] == entry['accept']
    assert 'heading_rmse' in entry
    # without the odometry the replay is another (worse) run
    assert main(['track', '--method', 'gbp', '--scenario', str(path),
                 '--no-control', '--input', str(measurements), '--output',
                 str(estimates)]) == 0
    assert score_files(str(estimates), str(truth))['rmse'] > entry['rmse']


def test_hybrid_tracks_live(recorded, tmp_path):
    # hybrid BP through the live path, alone and over a window: a line out
    # per line in, and (nothing relocated on this network) the lines of
    # its Gaussian tracker
    measurements = tmp_path / 'm.jsonl'
    measurements.write_text('\n'.join(recorded['lines']) + '\n')
    for extra in ([], ['--lag', '2']):
        lines = {}
        for method in ('hybrid', 'gbp'):
            out = tmp_path / f'{method}{len(extra)}.jsonl'
            assert main(['track', '--method', method, '--scenario',
                         str(recorded['scenario']), '--input',
                         str(measurements), '--output', str(out)] +
                        (['--particles', '20'] if method == 'hybrid' else
                         []) + extra) == 0
            lines[method] = [json.loads(line) for line in
                             out.read_text().split('\n')[:-1]]
        assert len(lines['hybrid']) == len(recorded['lines'])
        assert lines['hybrid'] == lines['gbp']


def test_track_window_final_writes_the_step_leaving_the_window(recorded,
                                                              tmp_path):
    # --window final: fixed-lag Gaussian BP's line holds the oldest step of
    # its full window alone, as --window all writes it, and the same
    # estimates; nothing of the window before it is full
    measurements = tmp_path / 'm.jsonl'
    measurements.write_text('\n'.join(recorded['lines']) + '\n')
    lines = {}
    for window in ('all', 'final'):
        out = tmp_path / f'{window}.jsonl'
        assert main(['track', '--method', 'gbp', '--lag', '3', '--scenario',
                     str(recorded['scenario']), '--input', str(measurements),
                     '--output', str(out), '--window', window]) == 0
        lines[window] = [json.loads(line) for line in
                         out.read_text().split('\n')[:-1]]
    assert len(lines['final']) == len(recorded['lines']) == STEPS
    for every, final in zip(lines['all'], lines['final']):
        assert final['estimates'] == every['estimates']
        full = len(every.get('window', [])) == 2
        assert final.get('window') == (every['window'][:1] if full else
                                       None)
    assert sum('window' in line for line in lines['final']) == STEPS - 2


def test_the_incremental_smoother_tracks_live_and_resumes(recorded,
                                                          tmp_path):
    # the incremental smoother through the live path: a line out per line
    # in; saved after every line, a run stopped half-way and resumed ends
    # as the uninterrupted one; the batch smoother is refused by name
    measurements = tmp_path / 'm.jsonl'
    lines = recorded['lines']
    measurements.write_text('\n'.join(lines) + '\n')
    command = ['track', '--method', 'iekf', '--lag', 'all', '--incremental',
               '--scenario', str(recorded['scenario'])]
    whole = tmp_path / 'whole.jsonl'
    assert main(command + ['--input', str(measurements), '--output',
                           str(whole)]) == 0
    expected = whole.read_text().split('\n')[:-1]
    assert len(expected) == len(lines)
    half = tmp_path / 'half.jsonl'
    half.write_text('\n'.join(lines[:len(lines) // 2]) + '\n')
    resumed, state = tmp_path / 'resumed.jsonl', tmp_path / 'state.pt'
    assert main(command + ['--input', str(half), '--output', str(resumed),
                           '--save-state', str(state)]) == 0
    assert main(command + ['--input', str(measurements), '--output',
                           str(resumed), '--resume', str(state)]) == 0
    assert resumed.read_text().split('\n')[:-1] == expected
    assert main(['track', '--method', 'iekf', '--lag', 'all', '--scenario',
                 str(recorded['scenario']), '--input', str(measurements),
                 '--output', str(tmp_path / 'refused.jsonl')]) == 2
    assert not (tmp_path / 'refused.jsonl').exists()


@pytest.mark.parametrize('args, carries', [
    (['--method', 'gbp'], 'no window'),
    (['--method', 'iekf'], 'no window'),
    (['--method', 'hybrid'], 'no window'),
    (['--method', 'iekf', '--lag', 'all', '--incremental'],
     'the newest states only')])
def test_a_window_option_to_a_tracker_without_one_is_refused(
        tmp_path, capsys, args, carries):
    # --window final was silently ignored by a filter, and the incremental
    # smoother wrote no window under --window all
    empty = tmp_path / 'm.jsonl'
    empty.write_text('')
    assert main(['track', *args, '--window', 'final', '--input',
                 str(empty), '--output', str(tmp_path / 'e.jsonl')]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith(
        "error: 'window' (--window) is for a smoother") and carries in \
        error[0]
    assert not (tmp_path / 'e.jsonl').exists()
    # a window of more than one step takes it
    assert main(['track', '--method', 'gbp', '--lag', '3', '--window',
                 'final', '--input', str(empty), '--output',
                 str(tmp_path / 'e.jsonl')]) == 0
