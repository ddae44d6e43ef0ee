r"""Tests of the accuracy-cost frontier (:mod:`tg_nebp.experiments.frontier`)
and of :obj:`tg-nebp frontier`."""
import itertools
import json
import math

import pytest
import torch

from tg_nebp.cli import main
from tg_nebp.datasets import CooperativeLocalizationDataset
from tg_nebp.evaluation import summarize, track_dataset
from tg_nebp.filters import ParticleBP
from tg_nebp.experiments.frontier import (GridPoint, grid, pareto_front,
                                          run_frontier)

from helpers import tiny_scenario


def brute_force_front(costs, losses):
    # a point is on the front unless some other point is at least as good in
    # both and better in one; enumerates every ordered pair
    n = len(costs)
    keep = [losses[i] == losses[i] for i in range(n)]
    for i, j in itertools.permutations(range(n), 2):
        if (costs[j] <= costs[i] and losses[j] <= losses[i]
                and (costs[j], losses[j]) != (costs[i], losses[i])):
            keep[i] = False
    return keep


def test_pareto_front_equals_brute_force():
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        # few distinct values: ties in one coordinate and duplicates occur
        costs = torch.randint(0, 4, (7, ), generator=g).tolist()
        losses = torch.randint(0, 4, (7, ), generator=g).tolist()
        assert pareto_front(costs, losses) == brute_force_front(costs, losses)
    # a NaN loss is never on the front and dominates nothing
    assert pareto_front([1.0, 2.0, 3.0], [math.nan, 0.5, 0.2]) == [
        False, True, True]


def test_grid_is_the_product_without_impossible_points():
    points = grid([4, 16], [1, 8, 'all'], ['multinomial', 'systematic'],
                  [None, 'silverman'], [None, 0.5])
    # M = 8 > K = 4 does not exist; 'all' exists at every K
    assert len(points) == (2 + 3) * 2 * 2 * 2
    assert all(p['samples'] in (1, 'all') for p in points
               if p['particles'] == 4)
    work = [p['particles'] * (p['particles'] if p['samples'] == 'all'
                              else p['samples']) for p in points]
    assert work == sorted(work)
    assert len({p.key for p in points}) == len(points)
    assert points[0].key == ('particles=4 samples=1 resampler=multinomial '
                             'regularize=None ess_threshold=None')


@pytest.fixture
def dataset(tmp_path):
    return CooperativeLocalizationDataset(tmp_path / 'data',
                                          tiny_scenario(steps=3), 2, seed=3,
                                          log=False)


def test_points_are_the_trackers_on_the_same_draws(dataset, tmp_path):
    points = grid([8], [1, 'all'], ['systematic'], [None, 0.3])
    lines = []
    result = run_frontier(points, dataset, tmp_path / 'f', seed=5,
                          log=lines.append)
    assert len(lines) == 4 and len(result['points']) == 4
    saved = json.loads((tmp_path / 'f' / 'frontier.json').read_text())
    assert saved == result
    for point in points:
        entry = result['points'][point.key]
        # an independent run of the same configuration and seed
        tracker = ParticleBP(8, num_samples=point['samples'],
                             resampler='systematic',
                             regularize=point['regularize'])
        tracked = track_dataset(tracker, dataset, seed=5)
        expected = summarize(tracked['errors'], tracked['nees'])
        assert entry['outage'] == expected['outage']
        assert entry['accept'] == expected['accept']
        assert entry['seconds_per_realization'] > 0
        assert set(entry['pareto']) == {'outage', 'accept'}
    # the fronts are those of the recorded figures
    entries = list(result['points'].values())
    assert [e['pareto']['outage'] for e in entries] == brute_force_front(
        [e['seconds_per_realization'] for e in entries],
        [e['outage']['1.0'] for e in entries])


def test_resumes_and_refuses_another_setting(dataset, tmp_path):
    out = tmp_path / 'f'
    first = run_frontier(grid([8], [1]), dataset, out, log=lambda _: None)
    lines = []
    second = run_frontier(grid([8], [1, 2]), dataset, out,
                          log=lines.append)
    # the point already in the file is not run again
    assert len(lines) == 1 and lines[0].startswith('particles=8 samples=2')
    key = GridPoint(particles=8, samples=1, resampler='multinomial',
                    regularize=None, ess_threshold=None).key
    assert second['points'][key]['seconds'] == first['points'][key][
        'seconds']
    with pytest.raises(ValueError, match="holds a frontier made with .*"
                       "'seed': 0.*not .*'seed': 1"):
        run_frontier(grid([8], [1]), dataset, out, seed=1)
    # a bad option fails before any point runs
    with pytest.raises(ValueError, match="'ess_threshold' must lie in"):
        run_frontier(grid([8], [4], ess_thresholds=[None, 2.0]), dataset,
                     tmp_path / 'g')
    assert not (tmp_path / 'g' / 'frontier.json').exists()


def test_frontier_command(tmp_path, capsys):
    scenario = tiny_scenario(steps=3)
    path = tmp_path / 'tiny.json'
    path.write_text(json.dumps(vars(scenario)))
    out = tmp_path / 'out'
    argv = ['frontier', '--scenario', str(path), '--realizations', '2',
            '--particles', '4', '8', '--samples', '1', '8', '--regularize',
            'none', 'silverman', '--ess-threshold', 'none', '0.5', '--root',
            str(tmp_path / 'data'), '--out', str(out), '--quiet']
    assert main(argv) == 0
    result = json.loads((out / 'frontier.json').read_text())
    # K = 4 with M = 8 does not exist
    assert len(result['points']) == 3 * 2 * 2
    assert (out / 'frontier.png').stat().st_size > 0
    table = (out / 'frontier.md').read_text().splitlines()
    rows = [line for line in table if line.startswith('| ') and
            line[2].isdigit()]
    assert len(rows) == 12
    # fastest first, and the fastest point is on both fronts
    seconds = [float(row.split('|')[8]) for row in rows]
    assert seconds == sorted(seconds) and rows[0].endswith('| ** |')
    assert '12 points' in capsys.readouterr().out
    # resumed: nothing to run, the same figures
    assert main(argv) == 0
    assert json.loads((out / 'frontier.json').read_text()) == result
    assert main(argv[:-1] + ['--seed', '1', '--quiet']) == 2
    assert 'use another --out folder' in capsys.readouterr().err
    assert main(['frontier', '--particles', '4', '--samples', '8', '--out',
                 str(out)]) == 2
    assert 'the grid is empty' in capsys.readouterr().err


def test_changed_scenario_under_the_same_name_is_refused(tmp_path, capsys):
    # the same name, other contents: the settings hold the fingerprint
    path, out = tmp_path / 'tiny.json', tmp_path / 'out'
    argv = ['frontier', '--scenario', str(path), '--realizations', '2',
            '--particles', '4', '--samples', '1', '--root',
            str(tmp_path / 'data'), '--out', str(out), '--quiet']
    path.write_text(json.dumps(vars(tiny_scenario(steps=3))))
    assert main(argv) == 0
    before = (out / 'frontier.json').read_text()
    changed = dict(vars(tiny_scenario(steps=3)), num_agents=5)
    path.write_text(json.dumps(changed))
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'holds a frontier made with' in err[0]
    assert (out / 'frontier.json').read_text() == before


@pytest.mark.parametrize('damage, message', [
    (lambda f: f.update(points=[1, 2]), r"'points' is not an object"),
    (lambda f: f.pop('points'), r"'points' is not an object"),
    (lambda f: next(iter(f['points'].values())).pop('outage'),
     r"'points'\['particles=8 .*'\] has no field 'outage'"),
    (lambda f: next(iter(f['points'].values()))['outage'].update(
        {'1.0': 'high'}), r"'points'\[.*\]\['outage'\]\['1.0'\] is not of"),
])
def test_damaged_points_are_one_clear_error(dataset, tmp_path, damage,
                                            message):
    out = tmp_path / 'f'
    run_frontier(grid([8], [1]), dataset, out, log=lambda _: None)
    path = out / 'frontier.json'
    content = json.loads(path.read_text())
    damage(content)
    path.write_text(json.dumps(content))
    with pytest.raises(ValueError, match=f"frontier.json' is damaged: "
                       f"{message}"):
        run_frontier(grid([8], [1]), dataset, out, log=lambda _: None)


def test_points_without_their_marks_are_marked_again(dataset, tmp_path):
    out = tmp_path / 'f'
    run_frontier(grid([8], [1, 2]), dataset, out, log=lambda _: None)
    path = out / 'frontier.json'
    content = json.loads(path.read_text())
    for entry in content['points'].values():
        del entry['pareto']
    path.write_text(json.dumps(content))
    resumed = run_frontier(grid([8], [1, 2]), dataset, out,
                           log=lambda _: None)
    assert all(set(e['pareto']) == {'outage', 'accept'}
               for e in resumed['points'].values())
