r"""The binning that every real dataset shares (tg_nebp/datasets/recording.py:
step_of and merge_links), against plain loops over the rows."""
import math

import numpy as np
import pytest
import torch

from tg_nebp.datasets import merge_links, step_of


def _step_by_loop(time, t0, dt, steps):
    # step k holds (t0 + k dt, t0 + (k + 1) dt]
    for k in range(steps):
        if t0 + k * dt < time <= t0 + (k + 1) * dt:
            return k
    return -1


def test_steps_are_half_open_intervals_after_t0():
    t0, dt, steps = 10.0, 0.5, 4
    times = np.array([9.0, 10.0, 10.0001, 10.5, 10.50001, 11.75, 12.0,
                      12.0001, 13.0])
    expected = [_step_by_loop(t, t0, dt, steps) for t in times]
    assert expected == [-1, -1, 0, 0, 1, 3, 3, -1, -1]
    assert step_of(times, t0, dt, steps).tolist() == expected
    rng = np.random.default_rng(0)
    times = rng.uniform(9.5, 12.5, 500)
    assert step_of(times, t0, dt, steps).tolist() == [
        _step_by_loop(t, t0, dt, steps) for t in times]


def _merge_by_loop(rows, merge):
    # rows: (time, step, receiver, sender, sensor, values); one dict per link
    links = {}
    for row in rows:
        links.setdefault(row[1:5], []).append(row)
    out = []
    for key in sorted(links):
        group = links[key]
        if merge == 'mean':
            width = len(group[0][5])
            value = [math.fsum(r[5][c] for r in group) / len(group)
                     for c in range(width)]
        else:
            latest = group[0]
            for r in group[1:]:
                if r[0] >= latest[0]:  # of equal times the later row
                    latest = r
            value = list(latest[5])
        out.append((key, value))
    return out, len(rows) - len(links)


@pytest.mark.parametrize('merge', ['mean', 'latest'])
def test_links_merge_each_steps_rows_of_a_pair(merge):
    rng = np.random.default_rng(1)
    count = 400
    time = np.round(rng.uniform(0, 5, count), 1)  # repeated times
    step = rng.integers(0, 4, count)
    receiver = rng.integers(0, 3, count)
    sender = rng.integers(3, 6, count)
    sensor = rng.integers(0, 2, count)
    values = rng.normal(5.0, 1.0, (count, 2))
    links = merge_links(step, receiver, sender, values, merge, times=time,
                        sensor=sensor)
    rows = [(time[k], int(step[k]), int(receiver[k]), int(sender[k]),
             int(sensor[k]), values[k].tolist()) for k in range(count)]
    expected, merged = _merge_by_loop(rows, merge)
    assert links.merged == merged > 0
    assert links.edge_time.tolist() == [k[0] for k, _ in expected]
    assert links.edge_index[1].tolist() == [k[1] for k, _ in expected]
    assert links.edge_index[0].tolist() == [k[2] for k, _ in expected]
    assert links.sensor.tolist() == [k[3] for k, _ in expected]
    assert links.edge_attr.dtype == torch.float32
    # float32 of a float64 mean: within one float32 rounding of the exact
    torch.testing.assert_close(
        links.edge_attr.double(),
        torch.tensor([v for _, v in expected], dtype=torch.float64),
        rtol=2**-23, atol=0)


def test_latest_needs_times_and_merges_are_named():
    with pytest.raises(ValueError, match="'times'"):
        merge_links(np.zeros(1), np.zeros(1), np.ones(1), np.ones((1, 1)),
                    'latest')
    with pytest.raises(ValueError, match="'merge' must be one of"):
        merge_links(np.zeros(1), np.zeros(1), np.ones(1), np.ones((1, 1)),
                    'median')


def test_no_rows_are_no_links():
    empty = np.zeros(0, np.int64)
    links = merge_links(empty, empty, empty, np.zeros((0, 2)), 'mean')
    assert links.edge_index.shape == (2, 0)
    assert links.edge_attr.shape == (0, 2)
    assert links.edge_time.shape == (0, ) and links.merged == 0
