r"""The ROS bag reader: small bags written here in every storage (ROS 2
SQLite and MCAP, ROS 1) read back to the numbers written, every bad input
refused or counted, and the TIERS runs where ../shared has them (the ROS 1
and the ROS 2 copy of test1 the same realization)."""
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from tg_nebp.datasets import (TIERS_TOPICS, BagTopics, read_bag,
                              recording_realization)

from recording_files import write_bag

TIERS = Path(__file__).resolve().parents[2].parent / 'shared' / 'data' / \
    'uwb' / 'tiers'

#: The bag every test writes: three nodes with truth (n_1 and n_2 standing,
#: n_3 driving along x at 0.2 m/s), ranges of 3 pairs at 10 Hz for 4 s
#: with a known bias each, and a node n_4 that ranges but has no truth.
START = 1_000.0
BIASES = {('1', '3'): 0.3, ('3', '1'): 0.3, ('2', '3'): 0.5}


def truth(node, t):
    return {'1': (0.0, 0.0, 0.1), '2': (4.0, 0.0, 0.1),
            '3': (1.0 + 0.2 * t, 2.0, 0.1)}[node]


def distance(a, b, t):
    return math.dist(truth(a, t)[:2], truth(b, t)[:2])


def messages(extra_ranges=()):
    # (time, topic, kind, value): poses at 30 Hz, ranges at 10 Hz
    out = []
    for k in range(121):
        t = k / 30
        for node in '123':
            out.append((START + t, f'/vrpn_client_node/turtlebot{node}/pose',
                        'pose', truth(node, t)))
    for k in range(40):
        t = k / 10 + 0.03  # off the steps' bounds
        for (a, b), bias in BIASES.items():
            out.append((START + t, f'/uwb/tof/n_{a}/n_{b}/distance', 'range',
                        distance(a, b, t) + bias))
        out.append((START + t, '/uwb/tof/n_3/n_4/distance', 'range', 1.0))
    out.extend(extra_ranges)
    return sorted(out, key=lambda m: m[0])


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap', 'ros1'])
def test_a_written_bag_reads_back_to_the_numbers_written(tmp_path, storage):
    path = write_bag(tmp_path / 'bag', messages(), storage)
    recording = read_bag(path, TIERS_TOPICS)
    assert recording.nodes == ['n_1', 'n_2', 'n_3']
    assert recording.counts['untracked'] == 40  # n_4 has no truth
    assert recording.position_dim == 2
    for node in range(3):
        rows = recording.truth[node]
        assert rows.shape == (121, 3)
        expected = np.array([truth(str(node + 1), k / 30)[:2]
                             for k in range(121)])
        # float64 written and read back (serialization only, no arithmetic:
        # the same bits on every CPU)
        np.testing.assert_array_equal(rows[:, 1:], expected)
        np.testing.assert_allclose(rows[:, 0], START + np.arange(121) / 30,
                                   rtol=0, atol=1e-9)  # stamps: whole ns
    t, receiver, sender, z, _ = recording.ranges.T
    assert len(t) == 120 and bool((np.diff(t) >= 0).all())
    for k in range(len(t)):
        a, b = recording.nodes[int(receiver[k])][2:], \
            recording.nodes[int(sender[k])][2:]
        expected = distance(a, b, t[k] - START) + BIASES[(a, b)]
        # sensor_msgs/Range holds a float32
        assert z[k] == float(np.float32(expected))


def test_binning_is_the_mean_of_each_steps_ranges_less_the_bias(tmp_path):
    # a plain-loop reference of the binning: step k holds (t0 + k dt,
    # t0 + (k + 1) dt], both directions of a pair one link, n_1 an anchor
    # (so 1->3 becomes 3's range to 1), the calibrated bias subtracted
    from tg_nebp.datasets import RangeCalibration
    recording = read_bag(write_bag(tmp_path / 'bag', messages(), 'sqlite3'),
                         TIERS_TOPICS)
    calibration = RangeCalibration({'n_1->n_3': 0.3, 'n_2->n_3': 0.5})
    dt = 0.5
    data, counts = recording_realization(recording, dt, anchors=['n_1'],
                                         calibration=calibration)
    t0 = START + dt
    steps = int(math.floor((START + 4.0 - t0) / dt + 1e-9))
    assert int(data.num_steps) == steps == 7
    assert data.anchor.tolist() == [True, False, False]
    expected = {}
    for time, receiver, sender, z, _ in recording.ranges:
        if not t0 < time <= t0 + steps * dt:
            continue
        k = int(math.ceil((time - t0) / dt)) - 1
        pair = tuple(sorted((int(receiver), int(sender))))
        bias = {(0, 2): 0.3, (1, 2): 0.5}[pair]
        # the agent receives from the anchor; two agents: the first in
        # node order receives
        key = (k, 2, 0) if pair == (0, 2) else (k, 1, 2)
        expected.setdefault(key, []).append(z - bias)
    got = {(int(t), int(i), int(j)): float(a) for t, i, j, a in zip(
        data.edge_time, data.edge_index[1], data.edge_index[0],
        data.edge_attr[:, 0])}
    assert sorted(got) == sorted(expected)
    for key, values in expected.items():
        assert got[key] == pytest.approx(np.mean(values), abs=1e-6)
    assert counts['merged'] == sum(len(v) - 1 for v in expected.values())
    # the states are the truth at the steps' middles; n_1 static at t0
    middles = t0 + dt * (np.arange(steps) + 0.5) - START
    np.testing.assert_allclose(
        data.states[2, :, :2].numpy(), [[1 + 0.2 * t, 2.0] for t in middles],
        rtol=0, atol=2e-6)
    np.testing.assert_allclose(data.states[2, :, 2:].numpy(),
                               [[0.2, 0.0]] * steps, rtol=0, atol=2e-5)
    np.testing.assert_allclose(data.prior_mean[2].numpy(),
                               [1 + 0.2 * (t0 - 0.5 * dt - START), 2, 0.2, 0],
                               rtol=0, atol=2e-5)
    assert float(data.prior_cov[0].abs().sum()) == 0
    # without symmetric merging every direction is its own link
    directed, _ = recording_realization(recording, dt, symmetric=False)
    merged, _ = recording_realization(recording, dt)
    assert (directed.num_edges, merged.num_edges) == (3 * steps, 2 * steps)


def test_a_node_without_truth_is_tracked_and_used_not_scored(tmp_path):
    from tg_nebp.data import check_realization, scored_of
    path = write_bag(tmp_path / 'bag', messages(), 'sqlite3')
    recording = read_bag(path, TIERS_TOPICS, without_truth=True)
    assert recording.nodes == ['n_1', 'n_2', 'n_3', 'n_4']
    assert recording.counts['untracked'] == 0 and 3 not in recording.truth
    dt = 0.5
    data, _ = recording_realization(recording, dt, anchors=['n_1', 'n_2'],
                                    prior_std=0.5)
    check_realization(data, ('range', ))
    assert scored_of(data).tolist() == [False, False, True, False]
    assert bool(torch.isnan(data.states[3]).all())
    assert not bool(torch.isnan(data.states[:3]).any())
    # n_4's ranges are links: n_3 (first in node order) receives them
    to_n4 = data.edge_index[0] == 3
    assert int(to_n4.sum()) == int(data.num_steps)
    assert set(data.edge_index[1, to_n4].tolist()) == {2}
    # its prior: at rest at the mean of the others' positions at the
    # prior's time, as wide as their largest distance from it
    t = 0.5 * dt  # the prior's time after the truth's start
    known = np.array([truth(node, t)[:2] for node in '123'])
    centre = known.mean(0)
    extent = np.linalg.norm(known - centre, axis=-1).max()
    np.testing.assert_allclose(data.prior_mean[3].numpy(),
                               [*centre, 0, 0], rtol=0, atol=1e-5)
    np.testing.assert_allclose(
        data.prior_cov[3].diagonal().numpy(),
        [extent**2] * 2 + [0.5**2] * 2, rtol=1e-6)
    # it cannot be an anchor: nothing places it
    with pytest.raises(ValueError, match="anchor 'n_4' has neither"):
        recording_realization(recording, dt, anchors=['n_1', 'n_4'])


@pytest.mark.parametrize('value, key', [(math.nan, 'not_finite'),
                                        (math.inf, 'not_finite'),
                                        (-0.5, 'negative'),
                                        (5e4, 'absurd')])
def test_bad_ranges_are_dropped_and_counted(tmp_path, value, key):
    extra = [(START + 1.01, '/uwb/tof/n_1/n_3/distance', 'range', value)]
    recording = read_bag(write_bag(tmp_path / 'bag', messages(extra),
                                   'sqlite3'), TIERS_TOPICS)
    assert recording.counts[key] == 1
    assert len(recording.ranges) == 120
    assert np.isfinite(recording.ranges).all()


def test_bad_bags_and_topics_are_refused_naming_what(tmp_path):
    with pytest.raises(ValueError, match="'.*nowhere' does not exist"):
        read_bag(tmp_path / 'nowhere', TIERS_TOPICS)
    path = write_bag(tmp_path / 'bag', messages(), 'sqlite3')
    # patterns that match nothing list the topics there are
    with pytest.raises(ValueError, match=r"no topic matches the ranges "
                       r"pattern .*its topics: /uwb/tof"):
        read_bag(path, BagTopics(ranges=r'/uwb/(?P<receiver>x)'
                                 r'(?P<sender>y)', truth=TIERS_TOPICS.truth))
    with pytest.raises(ValueError, match="no topic matches the truth"):
        read_bag(path, BagTopics(ranges=TIERS_TOPICS.ranges,
                                 truth=r'/mocap/(?P<node>\d+)'))
    # a pattern without its groups is refused before any bag is read
    with pytest.raises(ValueError, match="'ranges' .* has no named group "
                       "'receiver'"):
        BagTopics(ranges='/uwb/.*', truth=TIERS_TOPICS.truth)
    # two truth topics of one node
    twice = messages([(START + 0.5, '/vrpn_client_node/turtlebot01/pose',
                       'pose', (0.0, 0.0, 0.0))])
    path = write_bag(tmp_path / 'twice', twice, 'sqlite3')
    topics = BagTopics(ranges=TIERS_TOPICS.ranges,
                       truth=r'/vrpn_client_node/turtlebot0?(?P<node>\d)'
                       r'/pose', node='n_{}')
    with pytest.raises(ValueError, match="node 'n_1' has two truth topics"):
        read_bag(path, topics)
    # a truth topic that holds ranges
    wrong = messages([(START + 0.5, '/vrpn_client_node/turtlebot5/pose',
                       'range', 1.0)])
    with pytest.raises(ValueError, match="truth topic '/vrpn_client_node/"
                       "turtlebot5/pose' holds sensor_msgs/msg/Range"):
        read_bag(write_bag(tmp_path / 'wrong', wrong, 'sqlite3'),
                 TIERS_TOPICS)
    # a range topic that holds poses
    posed = messages([(START + 0.5, '/uwb/tof/n_1/n_2/distance', 'pose',
                       (1.0, 2.0, 3.0))])
    with pytest.raises(ValueError, match="topic '/uwb/tof/n_1/n_2/distance' "
                       "holds geometry_msgs/msg/PoseStamped, not ranges"):
        read_bag(write_bag(tmp_path / 'posed', posed, 'sqlite3'),
                 TIERS_TOPICS)
    # a truth topic without messages
    silent = write_bag(tmp_path / 'silent', messages(), 'sqlite3', empty=[
        ('/vrpn_client_node/turtlebot6/pose', 'pose')])
    with pytest.raises(ValueError, match="truth topic '/vrpn_client_node/"
                       "turtlebot6/pose' holds no message"):
        read_bag(silent, TIERS_TOPICS)


@pytest.mark.parametrize('storage', ['sqlite3', 'ros1'])
def test_a_truncated_bag_is_refused_naming_the_file(tmp_path, storage):
    path = write_bag(tmp_path / 'bag', messages(), storage)
    data = path if path.is_file() else next(path.glob('*.db3'))
    raw = data.read_bytes()
    data.write_bytes(raw[:len(raw) // 2])
    with pytest.raises(ValueError, match=f"'{path}'.*(cannot be read|is "
                       f"damaged)"):
        read_bag(path, TIERS_TOPICS)


@pytest.mark.skipif(not (TIERS / 'case_4' / 'ros1' / 'test1.bag').exists(),
                    reason='the TIERS runs are in ../shared only')
def test_the_ros1_and_ros2_copies_of_test1_give_the_same_realization():
    ros2 = read_bag(TIERS / 'case_4' / 'ros2' / 'test1', TIERS_TOPICS)
    ros1 = read_bag(TIERS / 'case_4' / 'ros1' / 'test1.bag', TIERS_TOPICS)
    assert ros1.nodes == ros2.nodes == [f'n_{k}' for k in range(1, 8)]
    np.testing.assert_array_equal(ros1.ranges, ros2.ranges)
    a, _ = recording_realization(ros1, 0.5, anchors=['n_1', 'n_2'])
    b, _ = recording_realization(ros2, 0.5, anchors=['n_1', 'n_2'])
    for key in ('edge_index', 'edge_attr', 'edge_time', 'states',
                'prior_mean', 'prior_cov', 'anchor'):
        assert torch.equal(a[key], b[key]), key
