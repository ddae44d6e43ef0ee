r"""UWB recordings as scenarios: names and files, the fit of the range
calibration and the models (recovering the biases of data simulated with
known ones), and a bag written here run through the commands."""
import json
import math

import numpy as np
import pytest

from tg_nebp.cli import main
from tg_nebp.datasets import (TIERS_TOPICS, Recording,
                              RecordingDataset, RecordingScenario,
                              fit_range_models, load_scenario,
                              recording_realization)
from tg_nebp.models import ConstantVelocity, StudentTRange

from recording_files import write_bag

#: Four nodes: two standing (anchors), two driving circles.
RADIUS, SPEED = 2.0, 0.4


def _position(node, t):
    if node == 0:
        return np.array([0.0, 0.0])
    if node == 1:
        return np.array([6.0, 0.0])
    phase = SPEED / RADIUS * t + (0.0 if node == 2 else math.pi)
    centre = np.array([3.0, 3.0 if node == 2 else -3.0])
    return centre + RADIUS * np.stack([np.cos(phase), np.sin(phase)], -1)


def simulated(biases, sigma=0.05, seconds=120.0, seed=0):
    # ranges of every pair at 10 Hz with a known bias and Gaussian noise,
    # both ends reporting the one range; the truth at 100 Hz
    rng = np.random.default_rng(seed)
    times = np.arange(0.0, seconds, 0.01)
    truth = {n: np.column_stack([times, np.broadcast_to(
        _position(n, times), (len(times), 2))]) for n in range(4)}
    rows = []
    for t in np.arange(0.013, seconds, 0.1):
        for (a, b), bias in biases.items():
            z = np.linalg.norm(_position(a, t) - _position(b, t)) + bias + \
                sigma * rng.standard_normal()
            rows += [(t, a, b, z, 0), (t, b, a, z, 0)]
    return Recording(source='simulated', nodes=['a', 'b', 'c', 'd'],
                     position_dim=2, ranges=np.array(rows), truth=truth)


def test_fitted_biases_recover_the_simulated_ones():
    biases = {(0, 2): 0.31, (0, 3): 0.18, (1, 2): 0.52, (1, 3): 0.44,
              (2, 3): 0.27}
    recording = simulated(biases)
    data, _ = recording_realization(recording, 0.5, anchors=['a', 'b'])
    motion, measurement, calibration, report = fit_range_models(
        data, recording.nodes, 0.5, horizon=1)
    names = recording.nodes
    for (a, b), bias in biases.items():
        # the median of ~240 step means of 5 ranges of 0.05 m: a few mm
        assert calibration.bias(names[a], names[b]) == pytest.approx(
            bias, abs=0.01)
        assert calibration.bias(names[b], names[a]) == pytest.approx(
            bias, abs=0.01)
    assert calibration.default == pytest.approx(np.median(list(
        biases.values())), abs=0.01)
    # a step's mean of 5 independent ranges: sigma / sqrt(5)
    assert report['uwb']['sigma_one_step'] == pytest.approx(
        0.05 / math.sqrt(5), rel=0.1)
    assert isinstance(measurement, StudentTRange) and report["uwb"]["nu_at_truth"] >= 8
    # a circle at constant speed: |a| = v^2 / r, each axis its 1/sqrt(2)
    assert isinstance(motion, ConstantVelocity) and motion.dt == 0.5
    assert motion.sigma_a == pytest.approx(SPEED**2 / RADIUS / math.sqrt(2),
                                           rel=0.05)
    # the calibration applied: the residuals centre on zero
    calibrated, _ = recording_realization(recording, 0.5,
                                          anchors=['a', 'b'],
                                          calibration=calibration)
    src, dst = calibrated.edge_index
    t = calibrated.edge_time
    distance = (calibrated.states[src, t, :2] -
                calibrated.states[dst, t, :2]).norm(dim=-1)
    residual = calibrated.edge_attr[:, 0] - distance
    assert abs(float(residual.median())) < 0.005


def test_a_node_without_truth_does_not_enter_the_fit():
    # its links have no residual: the fit is that of the others alone
    biases = {(0, 2): 0.31, (1, 2): 0.52, (1, 3): 0.44, (2, 3): 0.27}
    recording = simulated(biases, seconds=30.0)
    data, _ = recording_realization(recording, 0.5, anchors=['a', 'b'])
    alone = fit_range_models(data, recording.nodes, 0.5, horizon=1)
    recording.nodes.append('e')  # ranges 9 m off to c, no truth
    extra = np.array([(t, 2, 4, 9.0, 0) for t in np.arange(0.02, 30, 0.1)])
    recording.ranges = np.concatenate([recording.ranges, extra])
    recording.ranges = recording.ranges[np.argsort(recording.ranges[:, 0],
                                                   kind='stable')]
    data, _ = recording_realization(recording, 0.5, anchors=['a', 'b'])
    assert bool((data.edge_index == 4).any())
    motion, measurement, calibration, report = fit_range_models(
        data, recording.nodes, 0.5, horizon=1)
    assert calibration == alone[2] and report == alone[3]
    assert motion.sigma_a == alone[0].sigma_a
    assert measurement.sigma == alone[1].sigma


def test_a_static_run_keeps_the_motion_noise_and_says_so():
    recording = simulated({(0, 2): 0.3, (1, 2): 0.4}, seconds=20.0)
    for node in (2, 3):  # standing still
        recording.truth[node][:, 1:] = recording.truth[node][0, 1:]
    data, _ = recording_realization(recording, 0.5, anchors=['a', 'b'])
    motion, *_, report = fit_range_models(data, recording.nodes, 0.5,
                                          sigma_a=0.07)
    assert motion.sigma_a == 0.07
    assert 'no agent moves' in report['sigma_a']


def test_names_options_and_files(tmp_path):
    full = load_scenario('tiers-uwb-test3')
    assert isinstance(full, RecordingScenario)
    assert (full.recording, full.part, full.anchors, full.dt,
            full.position_dim) == ('case_4/ros2/test3', 'all',
                                   ('n_1', 'n_2'), 0.5, 2)
    assert full.range_calibration.pairs  # the shipped calibration
    assert load_scenario('tiers-uwb-test1-ros1').recording == \
        'case_4/ros1/test1.bag'
    assert load_scenario('tiers-uwb-test3-raw').calibration is None
    half = load_scenario('tiers-uwb-test3-second-half-raw')
    assert (half.part, half.calibration) == ('second-half', None)
    assert not full.without_truth
    assert load_scenario('tiers-uwb-test3-all-nodes').without_truth
    with pytest.raises(ValueError, match="'without_truth' must be true or"):
        full.replace(without_truth='yes')
    with pytest.raises(ValueError, match="unknown option 'fast'"):
        load_scenario('tiers-uwb-test3-fast')
    with pytest.raises(ValueError, match="'first-half' repeats or "
                       "contradicts"):
        load_scenario('tiers-uwb-test3-second-half-first-half')
    path = tmp_path / 'mine.json'
    full.replace(name='mine').save(path)
    assert load_scenario(str(path)) == full.replace(name='mine')
    fields = full.to_fields()
    fields['options'] = dict(fields['options'], ranges='/uwb/(?P<a>.*)')
    path.write_text(json.dumps(fields))
    with pytest.raises(ValueError, match="mine.json': 'options': 'ranges' "
                       ".* has no named group 'receiver'"):
        load_scenario(str(path))
    fields = full.to_fields()
    fields['calibration'] = {'pairs': {'n_1->n_2': 'far'}}
    path.write_text(json.dumps(fields))
    with pytest.raises(ValueError, match=r"'pairs\['n_1->n_2'\]' must be a "
                       r"finite number"):
        load_scenario(str(path))
    with pytest.raises(ValueError, match="'part' must be one of"):
        full.replace(part='middle')


def _bag(tmp_path):
    # a bag of the TIERS layout: n_1 and n_2 standing, n_3 driving, 30 s
    messages = []
    for k in range(30 * 30 + 1):
        t = k / 30
        for node, xy in (('1', (0.0, 0.0)), ('2', (4.0, 0.0)),
                         ('3', (1.0 + 0.05 * t, 2.0))):
            messages.append((100.0 + t, f'/vrpn_client_node/turtlebot{node}'
                             f'/pose', 'pose', (*xy, 0.0)))
    rng = np.random.default_rng(0)
    for k in range(300):
        t = k / 10 + 0.03
        p3 = np.array([1.0 + 0.05 * t, 2.0])
        for a, xy in (('1', (0.0, 0.0)), ('2', (4.0, 0.0))):
            z = np.linalg.norm(p3 - xy) + 0.4 + 0.03 * rng.standard_normal()
            messages.append((100.0 + t, f'/uwb/tof/n_3/n_{a}/distance',
                             'range', z))
    messages.sort(key=lambda m: m[0])
    return write_bag(tmp_path / 'run' / 'bag', messages, 'sqlite3')


def test_a_users_bag_through_fit_evaluate_record_and_track(tmp_path):
    _bag(tmp_path)
    scenario = RecordingScenario(
        name='mine', recording='run/bag', options=TIERS_TOPICS,
        motion=ConstantVelocity(0.1, 0.5), measurement=StudentTRange(0.1),
        anchors=('n_1', 'n_2'))
    scenario.save(tmp_path / 'mine.json')
    dataset = RecordingDataset(str(tmp_path), scenario)
    assert len(dataset) == 1 and dataset.nodes == ['n_1', 'n_2', 'n_3']
    assert dataset.scenario.num_steps == int(dataset[0].num_steps) == 59
    assert '0 not finite' in dataset.report
    root = str(tmp_path)
    fitted = tmp_path / 'fitted.json'
    assert main(['fit', '--scenario', str(tmp_path / 'mine.json'), '--root',
                 root, '--output', str(fitted)]) == 0
    calibration = load_scenario(str(fitted)).range_calibration
    assert calibration.bias('n_3', 'n_1') == pytest.approx(0.4, abs=0.02)
    out = tmp_path / 'out'
    assert main(['evaluate', '--method', 'gbp', '--scenario', str(fitted),
                 '--root', root, '--out', str(out), '--quiet']) == 0
    rmse = json.loads((out / 'metrics.json').read_text())
    assert 'gbp' in json.dumps(rmse)
    measurements, truth = tmp_path / 'm.jsonl', tmp_path / 't.jsonl'
    assert main(['record', '--scenario', str(fitted), '--root', root,
                 '--measurements', str(measurements), '--truth',
                 str(truth)]) == 0
    estimates = tmp_path / 'e.jsonl'
    assert main(['track', '--method', 'gbp', '--scenario', str(fitted),
                 '--input', str(measurements), '--output',
                 str(estimates)]) == 0
    assert len(estimates.read_text().splitlines()) == 59


def test_a_missing_recording_and_a_wrong_fit_are_one_error_line(tmp_path,
                                                                 capsys):
    assert main(['evaluate', '--method', 'gbp', '--scenario',
                 'tiers-uwb-test3', '--root', str(tmp_path), '--out',
                 str(tmp_path / 'out'), '--quiet']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('error: ')
    assert "case_4/ros2/test3' does not exist" in err[0]
    assert main(['fit', '--scenario', 'paper_test', '--output',
                 str(tmp_path / 'x.json')]) == 2
    assert 'is not a recording' in capsys.readouterr().err
    assert not (tmp_path / 'x.json').exists()
