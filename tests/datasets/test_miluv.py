r"""MILUV's layout: a small experiment folder written here read back to the
numbers written (tags carried by their arms, rigid links, the height as a
range to the floor node), every damage refused naming the file and row, and
the shipped experiment where ../shared has it."""
import math
from pathlib import Path

import numpy as np
import pytest

from tg_nebp.datasets import (RecordingDataset, load_scenario, read_miluv,
                              recording_realization)
from tg_nebp.datasets.miluv import FLOOR_DEPTH, HEIGHT, RIGID, UWB

MILUV = Path(__file__).resolve().parents[2].parent / 'shared' / 'data' / \
    'uwb' / 'miluv'
EXPERIMENT = 'cirObstacles_1_random3_0'

ANCHORS = {'0': (3.0, 3.0, 1.8), '1': (3.0, -3.0, 1.6),
           '2': (-3.0, -3.0, 1.9), '3': (-3.0, 3.0, 1.7)}
ARMS = {'10': (0.1, -0.2, -0.05), '11': (-0.2, 0.1, -0.05)}
YAW_RATE = 0.2  # rad/s about z, so the arms turn


def pose(t):
    # the robot's position and orientation quaternion (x, y, z, w)
    position = np.array([0.5 * math.cos(0.3 * t), 0.5 * math.sin(0.3 * t),
                         1.0 + 0.1 * t])
    yaw = YAW_RATE * t
    return position, np.array([0.0, 0.0, math.sin(yaw / 2),
                               math.cos(yaw / 2)])


def tag_position(tag, t):
    position, q = pose(t)
    yaw = 2 * math.atan2(q[2], q[3])
    c, s = math.cos(yaw), math.sin(yaw)
    x, y, z = ARMS[tag]
    return position + np.array([c * x - s * y, s * x + c * y, z])


def write_miluv(root: Path, height_bias=-0.05, uwb_rows=None):
    (root / 'config' / 'uwb').mkdir(parents=True)
    (root / 'config' / 'height').mkdir(parents=True)
    (root / 'config' / 'experiments.csv').write_text(
        'experiment,num_robots,num_tags_per_robot,num_anchors,'
        'anchor_constellation\nmine,1,2,4,0\n')
    (root / 'config' / 'uwb' / 'anchors.yaml').write_text(
        '"0":\n' + ''.join(f'    "{k}": "[{x}, {y}, {z}]"\n'
                           for k, (x, y, z) in ANCHORS.items()))
    (root / 'config' / 'uwb' / 'tags.yaml').write_text(
        'ifo001:\n' + ''.join(f'  "{k}": "[{x}, {y}, {z}]"\n'
                              for k, (x, y, z) in ARMS.items()))
    (root / 'config' / 'height' / 'bias.yaml').write_text(
        f'ifo001:\n  "{height_bias}"\n')
    folder = root / 'data' / 'mine' / 'ifo001'
    folder.mkdir(parents=True)
    lines = ['timestamp,pose.position.x,pose.position.y,pose.position.z,'
             'pose.orientation.x,pose.orientation.y,pose.orientation.z,'
             'pose.orientation.w']
    for k in range(1001):
        t = k / 100
        position, q = pose(t)
        lines.append(','.join(repr(float(v)) for v in (t, *position, *q)))
    (folder / 'mocap.csv').write_text('\n'.join(lines) + '\n')
    if uwb_rows is None:
        uwb_rows = []
        for k in range(80):
            t = 0.05 + k / 8
            tag, anchor = ('10', '11')[k % 2], str(k % 4)
            z = float(np.linalg.norm(tag_position(tag, t) -
                                     np.array(ANCHORS[anchor])))
            # the dataset's own truth columns, which the reader must not use
            uwb_rows.append(f'{z!r},{tag},{anchor},99.0,99.0,0.1,{t!r}')
    (folder / 'uwb_range.csv').write_text(
        'range,from_id,to_id,gt_range,bias,std,timestamp\n'
        + '\n'.join(uwb_rows) + '\n')
    lines = ['timestamp,range']
    for k in range(300):
        t = k / 30
        reading = float(pose(t)[0][2] + height_bias)  # height plus bias
        lines.append(f'{t!r},{reading!r}')
    lines.append('10.0,0.2')  # the sensor's shortest range: dropped
    (folder / 'height.csv').write_text('\n'.join(lines) + '\n')
    return root


def test_a_written_experiment_reads_back_to_the_numbers_written(tmp_path):
    root = write_miluv(tmp_path / 'miluv')
    recording = read_miluv(root, 'mine')
    assert recording.nodes == ['anchor/0', 'anchor/1', 'anchor/2',
                               'anchor/3', 'ifo001/10', 'ifo001/11', 'floor']
    assert recording.position_dim == 3
    assert recording.sensors == ['uwb', 'rigid', 'height']
    for k, xyz in enumerate(ANCHORS.values()):
        # decimal text parsed to float64: correctly rounded on every CPU
        np.testing.assert_array_equal(recording.surveyed[k], xyz)
    # the tags' truth: the pose carried by the arm (turning with the yaw)
    for node, tag in ((4, '10'), (5, '11')):
        rows = recording.truth[node]
        expected = np.array([tag_position(tag, t) for t in rows[:, 0]])
        np.testing.assert_allclose(rows[:, 1:], expected, rtol=0,
                                   atol=1e-12)
    t, receiver, sender, z, sensor = recording.ranges.T
    uwb = sensor == UWB
    assert uwb.sum() == 80
    for k in np.flatnonzero(uwb):
        tag = recording.nodes[int(receiver[k])][-2:]
        anchor = recording.nodes[int(sender[k])][-1]
        assert z[k] == pytest.approx(float(np.linalg.norm(
            tag_position(tag, t[k]) - np.array(ANCHORS[anchor]))),
            abs=1e-12)
    rigid = sensor == RIGID
    assert set(zip(receiver[rigid], sender[rigid])) == {(4, 5)}
    np.testing.assert_allclose(z[rigid], np.linalg.norm(
        np.subtract(ARMS['10'], ARMS['11'])), rtol=0, atol=1e-12)
    height = sensor == HEIGHT
    assert set(sender[height]) == {6} and height.sum() == 2 * 300
    # the floor node lies FLOOR_DEPTH below the anchors' centre; a range to
    # it is the tag's height plus that depth
    centre = np.mean(list(ANCHORS.values()), axis=0)
    np.testing.assert_allclose(recording.surveyed[6], [centre[0], centre[1],
                                                       -FLOOR_DEPTH])
    for k in np.flatnonzero(height)[:20]:
        tag = recording.nodes[int(receiver[k])][-2:]
        assert z[k] == pytest.approx(pose(t[k])[0][2] + ARMS[tag][2] +
                                     FLOOR_DEPTH, abs=1e-9)
    assert recording.counts['height_floor'] == 1
    # binned, each link names its sensor
    data, counts = recording_realization(recording, 0.5)
    assert data.edge_attr.shape[1] == 2
    assert set(data.edge_attr[:, 1].tolist()) == {0.0, 1.0, 2.0}
    assert data.anchor.tolist() == [True] * 4 + [False, False, True]


@pytest.mark.parametrize('damage, message', [
    ('no file', "uwb_range.csv' does not exist"),
    ('no column', "uwb_range.csv' has no column 'to_id'"),
    ('a word', "uwb_range.csv': row 3 has no number"),
    ('back in time', "uwb_range.csv': row 4 goes back in time"),
    ('unknown tag', "uwb_range.csv': row 2 ranges from tag 77"),
    ('unknown anchor', "uwb_range.csv': row 2 ranges to 9, neither"),
    ('no height bias', "bias.yaml' has no height bias of robot 'ifo001'"),
    ('no experiment', "experiments.csv' has no experiment 'mine'"),
])
def test_a_damaged_experiment_is_refused_naming_file_and_row(
        tmp_path, damage, message):
    root = write_miluv(tmp_path / 'miluv')
    csv = root / 'data' / 'mine' / 'ifo001' / 'uwb_range.csv'
    lines = csv.read_text().splitlines()
    if damage == 'no file':
        csv.unlink()
    elif damage == 'no column':
        csv.write_text('\n'.join([lines[0].replace('to_id', 'target')]
                                 + lines[1:]))
    elif damage == 'a word':
        lines[2] = lines[2].replace(lines[2].split(',')[0], 'far', 1)
        csv.write_text('\n'.join(lines))
    elif damage == 'back in time':
        lines[2], lines[3] = lines[3], lines[2]
        csv.write_text('\n'.join(lines))
    elif damage in ('unknown tag', 'unknown anchor'):
        words = lines[1].split(',')
        words[1 if damage == 'unknown tag' else 2] = \
            '77' if damage == 'unknown tag' else '9'
        lines[1] = ','.join(words)
        csv.write_text('\n'.join(lines))
    elif damage == 'no height bias':
        (root / 'config' / 'height' / 'bias.yaml').write_text('ifo002:\n'
                                                              '  "0.1"\n')
    elif damage == 'no experiment':
        (root / 'config' / 'experiments.csv').write_text(
            'experiment,anchor_constellation\nother,0\n')
    with pytest.raises(ValueError, match=message):
        read_miluv(root, 'mine')


def test_bad_ranges_are_dropped_and_counted(tmp_path):
    rows = ['nan,10,0,1,1,0.1,0.1', '-1.0,10,1,1,1,0.1,0.2',
            '1e6,11,2,1,1,0.1,0.3', '2.5,11,3,1,1,0.1,0.4']
    recording = read_miluv(write_miluv(tmp_path / 'm', uwb_rows=rows),
                           'mine')
    assert (recording.counts['not_finite'], recording.counts['negative'],
            recording.counts['absurd']) == (1, 1, 1)
    assert (recording.ranges[:, 4] == UWB).sum() == 1


def test_without_the_height_sensor_there_is_no_floor(tmp_path):
    root = write_miluv(tmp_path / 'miluv')
    recording = read_miluv(root, 'mine', height=False)
    assert 'floor' not in recording.nodes
    assert not (recording.ranges[:, 4] == HEIGHT).any()


@pytest.mark.skipif(not (MILUV / 'data' / EXPERIMENT).is_dir(),
                    reason='the MILUV experiment is in ../shared only')
def test_the_shipped_experiment_by_name():
    dataset = RecordingDataset(str(MILUV), f'miluv-{EXPERIMENT}')
    data = dataset[0]
    assert dataset.nodes[-1] == 'floor' and int(data.num_steps) == 412
    assert data.states.shape[-1] == 6
    assert 'height floor: 421' in dataset.report
    assert load_scenario(f'miluv-{EXPERIMENT}-no-height').options == {
        'height': False}
