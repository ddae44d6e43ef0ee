import copy
import dataclasses
import re

import pytest
import torch

from tg_nebp import NEBP
from tg_nebp.cli import main
from tg_nebp.datasets import CooperativeLocalizationDataset
from tg_nebp.evaluation import summarize, track_dataset
from tg_nebp.experiments.compare import (compare, compare_methods,
                                         compare_table, floor_ratios,
                                         run_compare)
from tg_nebp.filters import CentralizedIEKF, GaussianNEBP
from tg_nebp.io import read_json, write_json
from tg_nebp.models import NLOSRange, StudentTRange
from tg_nebp.training import save_checkpoint

from helpers import tiny_scenario


def scenario_files(folder, **changes):
    clean = tiny_scenario(steps=3).replace(**changes)
    nlos = clean.replace(name='tiny_nlos', measurement=NLOSRange())
    paths = []
    for scenario in (clean, nlos):
        path = folder / f'{scenario.name}.json'
        write_json(path, dataclasses.asdict(scenario))
        paths.append(str(path))
    return paths


def test_rows_in_order_with_the_scenario_likelihood():
    rows = list(compare_methods(tiny_scenario().replace(
        measurement=NLOSRange())))
    assert rows == ['pcrb', 'iekf gaussian', 'iekf student-t', 'iekf nlos',
                    'iekf-marginal gaussian', 'iekf-marginal student-t',
                    'iekf-marginal nlos', 'gbp gaussian', 'gbp-plain gaussian',
                    'gbp student-t', 'gbp-plain student-t', 'gbp nlos',
                    'gbp-plain nlos', 'hybrid nlos', 'bp-paper nlos',
                    'bp-recommended nlos']
    built = compare_methods(tiny_scenario())['iekf-marginal student-t'][1]()
    assert isinstance(built, CentralizedIEKF) and built.marginal
    assert built.measurement == StudentTRange()


def test_compare_runs_resumes_and_adds_checkpoints(tmp_path):
    scenarios = scenario_files(tmp_path)
    lines = []
    common = dict(root=str(tmp_path / 'data'), scenarios=scenarios,
                  realizations=2, seed=3, out=tmp_path / 'out',
                  log=lines.append)
    result = run_compare(methods=['pcrb', 'iekf '], **common)
    rows = result['results']['tiny']
    assert list(rows) == ['pcrb', 'iekf gaussian', 'iekf student-t']
    assert list(result['results']['tiny_nlos']) == [
        'pcrb', 'iekf gaussian', 'iekf student-t', 'iekf nlos']
    assert len(lines) == 7
    # a row is what the evaluation layer gives for that method
    dataset = CooperativeLocalizationDataset(
        str(tmp_path / 'data'), scenarios[0], 2, seed=3, log=False)
    tracked = track_dataset(CentralizedIEKF(), dataset, seed=3)
    expected = summarize(tracked['errors'], tracked['nees'])
    for field in ('rmse', 'outage', 'accept'):
        assert rows['iekf gaussian'][field] == expected[field]
    assert rows['pcrb']['accept']['0.95'] == 0.95
    assert floor_ratios(rows)['pcrb'] == (1.0, 0.0)
    assert floor_ratios(rows)['iekf gaussian'][0] > 1.0

    # resuming skips what is there; a checkpoint adds its row only
    checkpoint = tmp_path / 'nebp.pt'
    torch.manual_seed(0)
    save_checkpoint(checkpoint, NEBP(num_particles=16))
    lines.clear()
    again = run_compare(methods=['pcrb', 'iekf ', 'nebp'],
                        checkpoints=[checkpoint], **common)
    assert len(lines) == 2 and all('nebp nebp.pt' in x for x in lines)
    assert again['results']['tiny']['pcrb'] == rows['pcrb']
    assert read_json(tmp_path / 'out' / 'compare.json') == again
    table = compare_table(again)
    assert table.count('| `nebp nebp.pt ') == 2
    assert '### `tiny_nlos`' in table
    # both acceptance levels of every row, as the row holds them
    iekf = rows['iekf gaussian']['accept']
    assert f"| {iekf['0.95']:.3f} / {iekf['0.99']:.3f} |" in table
    assert '| 0.950 / 0.990 |' in table  # the bound's: the levels

    # a row whose method's description changed since is run again, alone
    stored = read_json(tmp_path / 'out' / 'compare.json')
    described = stored['results']['tiny']['iekf gaussian']['method']
    stored['results']['tiny']['iekf gaussian']['method'] = 'an older IEKF'
    write_json(tmp_path / 'out' / 'compare.json', stored, sort_keys=False)
    lines.clear()
    rerun = run_compare(methods=['pcrb', 'iekf '], **common)
    assert [line.split(':')[:2] for line in lines if 'run again' not in
            line] == [['tiny', ' iekf gaussian']]
    assert sum("('an older IEKF'): run again" in line for line in lines) == 1
    assert rerun['results']['tiny']['iekf gaussian']['method'] == described
    assert rerun['results']['tiny']['iekf gaussian']['rmse'] == rows[
        'iekf gaussian']['rmse']


def test_changed_scenario_under_the_same_name_is_refused(tmp_path):
    common = dict(root=str(tmp_path / 'data'), realizations=1,
                  out=tmp_path / 'out', methods=['pcrb'], log=print)
    run_compare(scenarios=scenario_files(tmp_path), **common)
    changed = scenario_files(tmp_path, num_agents=4)
    with pytest.raises(ValueError, match='holds a comparison made with'):
        run_compare(scenarios=changed, **common)


def test_two_scenarios_of_one_name_are_refused_before_any_work(tmp_path):
    # the second was skipped as done, its fingerprint over the first's rows
    first = scenario_files(tmp_path)[0]
    second = scenario_files(tmp_path / 'other', num_agents=4)[0]
    with pytest.raises(ValueError, match=r"the scenarios '.*/tiny.json' and "
                       r"'.*/other/tiny.json' are both named 'tiny'"):
        run_compare(root=str(tmp_path / 'data'), scenarios=[first, second],
                    realizations=1, out=tmp_path / 'out', methods=['pcrb'])
    assert not (tmp_path / 'data').exists()
    assert not (tmp_path / 'out').exists()


def test_arguments_are_checked_before_any_work(tmp_path):
    scenarios = scenario_files(tmp_path)
    checkpoint = tmp_path / 'nebp.pt'
    save_checkpoint(checkpoint, NEBP(num_particles=8))
    common = dict(root=str(tmp_path / 'data'), scenarios=scenarios,
                  realizations=1, out=tmp_path / 'out', methods=['pcrb'])
    for changes, error, message in [
            # one string where a list belongs was iterated letter by letter
            (dict(methods='pcrb'), TypeError, "'methods' must be a list"),
            (dict(scenarios=scenarios[0]), TypeError,
             "'scenarios' must be a list"),
            (dict(checkpoints=str(checkpoint)), TypeError,
             "'checkpoints' must be a list"),
            (dict(methods=['pcrb', 1]), TypeError,
             r"'methods'\[1\] must be a str"),
            (dict(scenarios=[scenarios[0], 7]), TypeError,
             r"'scenarios'\[1\] must be a scenario name"),
            (dict(scenarios=[]), ValueError, "'scenarios' is empty"),
            (dict(methods=[]), ValueError, "'methods' is empty"),
            (dict(batch_size=0), ValueError, "'batch_size' must be positive"),
            (dict(realizations=0), ValueError,
             "'realizations' must be positive"),
            # without CUDA, or without a 100th GPU
            (dict(device='cuda:99'), ValueError, "'device' is 'cuda:99', "
             "but"),
            (dict(seed=-1), ValueError, "'seed' must be non-negative"),
            # these ran nothing, then failed in the figure
            (dict(methods=['pcrb', 'pcrbb']), ValueError,
             r"'methods'\[1\] = 'pcrbb' selects no row of any scenario; the "
             r"rows start with pcrb, iekf, iekf-marginal, gbp, gbp-plain, "
             r"hybrid, bp-paper, bp-recommended \(and nebp or gnebp, with a "
             r"checkpoint\)"),
            (dict(methods=['nebp']), ValueError, r"'methods'\[0\] = 'nebp' "
             r"selects NEBP's rows, which need a checkpoint"),
            (dict(checkpoints=[checkpoint]), ValueError, r"the checkpoint "
             r"of the row 'nebp nebp.pt \w+' was given, but 'methods' does "
             r"not select its row")]:
        with pytest.raises(error, match=message):
            run_compare(**{**common, **changes})
        assert not (tmp_path / 'data').exists()
        assert not (tmp_path / 'out').exists()


def test_damaged_rows_are_refused_on_resume(tmp_path):
    common = dict(root=str(tmp_path / 'data'),
                  scenarios=scenario_files(tmp_path)[:1], realizations=2,
                  out=tmp_path / 'out', methods=['pcrb', 'iekf g'],
                  log=print)
    good = copy.deepcopy(run_compare(**common))
    path = tmp_path / 'out' / 'compare.json'

    def damaged(where, value):
        content = copy.deepcopy(good)
        *inner, last = where
        entry = content['results']['tiny']
        for key in inner:
            entry = entry[key]
        entry[last] = value
        write_json(path, content)
        return content

    realizations = ('spread', 'realizations')
    for where, value, message in [
            # both a ZeroDivisionError in floor_ratios before
            (('iekf gaussian', *realizations), [], 'is a list of length 0, '
             'not 2'),
            (('pcrb', *realizations, 1, 2), 0.0, 'is 0.0, not a finite '
             'number > 0'),
            (('iekf gaussian', *realizations, 0), [0.1, 0.2],
             'is a list of length 2, not 3'),
            (('iekf gaussian', 'outage', '1.0'), 1.5,
             'is 1.5, not a finite number in [0, 1]'),
            (('iekf gaussian', 'rmse'), float('inf'),
             'is inf, not a finite number >= 0')]:
        damaged(where, value)
        keys = ('tiny', *where)
        entry = "'results'" + ''.join(f'[{key!r}]' for key in keys)
        with pytest.raises(ValueError, match=re.escape(
                f"compare.json' is damaged: {entry} {message}; remove the "
                f"file")):
            run_compare(**common)
    # a scenario the settings do not name would be shown as if run
    content = copy.deepcopy(good)
    content['results']['stranger'] = content['results']['tiny']
    write_json(path, content)
    with pytest.raises(ValueError, match=re.escape(
            "compare.json' is damaged: 'results'['stranger'] is no scenario "
            "of its settings")):
        run_compare(**common)
    # a tracker's RMSE divides nothing: zero is a value
    kept = damaged(('iekf gaussian', *realizations, 0, 2), 0.0)
    assert run_compare(**common) == kept
    # called directly, floor_ratios refuses what the file check refuses
    rows = copy.deepcopy(good['results']['tiny'])
    rows['pcrb']['spread']['realizations'][1][2] = 0.0
    with pytest.raises(ValueError, match="needs a positive floor"):
        floor_ratios(rows)
    rows = copy.deepcopy(good['results']['tiny'])
    rows['iekf gaussian']['spread']['realizations'].pop()
    with pytest.raises(ValueError, match=re.escape(
            "'iekf gaussian' holds 1 realizations, the bound's ('pcrb') 2")):
        floor_ratios(rows)


def test_rows_stay_in_the_order_of_the_methods(tmp_path):
    clean, nlos = scenario_files(tmp_path)
    out = tmp_path / 'out'
    # neither the scenarios nor the rows in alphabetical order
    common = dict(root=str(tmp_path / 'data'), scenarios=[nlos, clean],
                  realizations=1, out=out, log=print)
    everything = ['pcrb', 'iekf-marginal g', 'gbp-plain g']
    expected = ['pcrb', 'iekf-marginal gaussian', 'gbp-plain gaussian']

    def check(result, file=True):
        table = (out / 'compare.md').read_text()
        assert re.findall(r'^### `(.*)`', table, re.M) == ['tiny_nlos',
                                                           'tiny']
        assert re.findall(r'^\| `([^`]*)`', table, re.M) == expected * 2
        read = [result['results']]
        if file:  # as written, when a row ran
            read.append(read_json(out / 'compare.json')['results'])
        for results in read:
            assert list(results) == ['tiny_nlos', 'tiny']
            assert all(list(rows) == expected for rows in results.values())

    compare(methods=everything[1:], **common)
    check(compare(methods=everything, **common))  # adds the bound's rows
    # a rerun with nothing left to do rewrote the table alphabetically
    check(compare(methods=everything, **common))
    # rows this run does not select keep their places
    check(compare(methods=['iekf-marginal g'], **common))
    # a file with its keys sorted, as earlier versions wrote it
    write_json(out / 'compare.json', read_json(out / 'compare.json'))
    assert list(read_json(out / 'compare.json')['results']) == [
        'tiny', 'tiny_nlos']
    check(compare(methods=everything, **common), file=False)


def test_cli_compare_writes_table_and_figure(tmp_path, capsys):
    scenarios = scenario_files(tmp_path)
    assert main(['compare', '--scenario', *scenarios, '--realizations',
                 '1', '--methods', 'pcrb', 'iekf-marginal', '--root',
                 str(tmp_path / 'data'), '--out', str(tmp_path / 'out'),
                 '--quiet']) == 0
    out = capsys.readouterr().out
    assert out.strip().endswith('compare.png')
    for name in ('compare.json', 'compare.md', 'compare.png'):
        assert (tmp_path / 'out' / name).stat().st_size > 0
    assert main(['compare', '--checkpoint', str(tmp_path / 'missing.pt'),
                 '--root', str(tmp_path / 'data'), '--out',
                 str(tmp_path / 'out2'), '--realizations', '1',
                 '--scenario', *scenarios, '--quiet']) == 2
    err = capsys.readouterr().err
    assert err.startswith('error: the NEBP checkpoint') and err.count(
        '\n') == 1


def test_a_gaussian_nebp_checkpoint_gets_its_own_row(tmp_path):
    # the row of a Gaussian NEBP checkpoint is 'gnebp <file> <hash>', built
    # from the checkpoint of its base; 'methods' must select it by 'gnebp'
    scenarios = scenario_files(tmp_path)[:1]
    checkpoint = tmp_path / 'g.pt'
    torch.manual_seed(0)
    save_checkpoint(checkpoint, GaussianNEBP(hidden_dim=4))
    rows = compare_methods(tiny_scenario(), [checkpoint])
    key = [k for k in rows if k.startswith('gnebp ')]
    assert len(key) == 1 and key[0].split(' ')[1] == 'g.pt'
    assert isinstance(rows[key[0]][1](), GaussianNEBP)
    common = dict(root=str(tmp_path / 'data'), scenarios=scenarios,
                  realizations=1, out=tmp_path / 'out', log=lambda _: None)
    with pytest.raises(ValueError, match=r"add 'gnebp' or leave the "
                       r"checkpoint out"):
        run_compare(methods=['pcrb'], checkpoints=[checkpoint], **common)
    result = run_compare(methods=['gbp-plain gaussian', 'gnebp'],
                         checkpoints=[checkpoint], **common)
    table = result['results']['tiny']
    # untrained, the correction is plain Gaussian BP: the same numbers (to
    # rounding: plain Gaussian BP sends rank-one messages, the correction
    # weights the general ones)
    plain, learned = table['gbp-plain gaussian'], table[key[0]]
    assert plain['outage'] == learned['outage']
    assert plain['rmse'] == pytest.approx(learned['rmse'], rel=1e-9)


def test_a_window_checkpoint_gets_a_smoothers_two_rows(tmp_path):
    # the correction trained in a window of 3: 'gnebp-lag3 <file> <hash>'
    # (filtered) and 'gnebp-lag3-smoothed ...', divided by the smoothing
    # bound at its lag; untrained it is the recommended window's numbers
    from tg_nebp.experiments.compare import floor_row
    from tg_nebp.filters import FixedLagGaussianNEBP, Smoothed
    checkpoint = tmp_path / 'w.pt'
    save_checkpoint(checkpoint, FixedLagGaussianNEBP.recommended(
        lag=3, hidden_dim=4))
    rows = compare_methods(tiny_scenario(), [checkpoint], lag=3)
    keys = [k for k in rows if k.startswith('gnebp')]
    assert [k.split(' ')[:2] for k in keys] == [
        ['gnebp-lag3', 'w.pt'], ['gnebp-lag3-smoothed', 'w.pt']]
    assert isinstance(rows[keys[0]][1](), FixedLagGaussianNEBP)
    smoothed = rows[keys[1]][1]()
    assert isinstance(smoothed, Smoothed) and isinstance(
        smoothed.tracker, FixedLagGaussianNEBP)
    assert [floor_row(k) for k in keys] == ['pcrb', 'pcrb-lag3']
    # at another lag of the table, or none, the bound at the checkpoint's
    # own lag joins it, so that its smoothed row has a floor (it had none
    # under 'compare --lag 2 --checkpoint' of a window of 3)
    for lag in (None, 2):
        other = compare_methods(tiny_scenario(), [checkpoint], lag=lag)
        assert all(floor_row(k) in other for k in other), lag
        assert 'pcrb-lag3' in other
    result = run_compare(
        methods=['pcrb', 'gbp-lag3 gaussian', 'gbp-lag3-smoothed gaussian',
                 'gnebp-lag3'], checkpoints=[checkpoint], lag=3,
        root=str(tmp_path / 'data'), scenarios=scenario_files(tmp_path)[:1],
        realizations=1, out=tmp_path / 'out', log=lambda _: None)
    table = result['results']['tiny']
    for window, learned in zip(('gbp-lag3 gaussian',
                                'gbp-lag3-smoothed gaussian'), keys):
        assert table[window]['rmse'] == pytest.approx(table[learned]['rmse'],
                                                      rel=1e-9)


def test_smoother_rows_each_beside_its_bound(tmp_path, capsys):
    # with a lag the smoothers join the table, their smoothed rows divided
    # by the smoothing bound of the same realizations and lag
    from tg_nebp.experiments.compare import floor_row
    from tg_nebp.filters import (CentralizedSmoother, FixedLagGaussianBP,
                                 IncrementalSmoother, Smoothed)
    rows = list(compare_methods(tiny_scenario(), lag=3))
    assert rows[:3] == ['pcrb', 'pcrb-lag3', 'pcrb-smoother']
    for key in ('iekf-lag3 gaussian', 'iekf-lag3-smoothed gaussian',
                'iekf-smoother gaussian', 'gbp-lag3 gaussian',
                'gbp-lag3-smoothed gaussian', 'gbp-lag3 student-t',
                'gbp-lag3-smoothed student-t'):
        assert key in rows
    built = compare_methods(tiny_scenario(), lag=3)
    assert isinstance(built['gbp-lag3 student-t'][1](), FixedLagGaussianBP)
    smoothed = built['iekf-lag3-smoothed gaussian'][1]()
    assert isinstance(smoothed, Smoothed) and isinstance(
        smoothed.tracker, CentralizedSmoother)
    assert 'pcrb-lag3' not in compare_methods(tiny_scenario())
    incremental = built['iekf-incremental-smoothed gaussian'][1]()
    assert isinstance(incremental, Smoothed) and isinstance(
        incremental.tracker, IncrementalSmoother)
    assert [floor_row(k) for k in (
        'pcrb', 'pcrb-lag3', 'pcrb-smoother', 'pcrb-range-only',
        'gbp-lag3 gaussian', 'gbp-lag3-smoothed gaussian',
        'iekf-lag3-smoothed student-t', 'iekf-smoother gaussian',
        'gbp-plain gaussian', 'iekf-incremental gaussian',
        'iekf-incremental-smoothed gaussian',
        'iekf-smoother-escape gaussian')] == [
            'pcrb', 'pcrb-lag3', 'pcrb-smoother', 'pcrb', 'pcrb',
            'pcrb-lag3', 'pcrb-lag3', 'pcrb-smoother', 'pcrb', 'pcrb',
            'pcrb-smoother', 'pcrb-smoother']
    scenarios = scenario_files(tmp_path)[:1]
    assert main(['compare', '--scenario', *scenarios, '--realizations',
                 '2', '--lag', '3', '--methods', 'pcrb', 'gbp-lag3 gaussian',
                 'gbp-lag3-smoothed gaussian', 'iekf-smoother', '--root',
                 str(tmp_path / 'data'), '--out', str(tmp_path / 'out'),
                 '--quiet']) == 0
    result = read_json(tmp_path / 'out' / 'compare.json')['results']['tiny']
    ratios = floor_ratios(result)
    for key, bound in (('gbp-lag3-smoothed gaussian', 'pcrb-lag3'),
                       ('iekf-smoother gaussian', 'pcrb-smoother'),
                       ('gbp-lag3 gaussian', 'pcrb')):
        per = [r[2] / f[2] for r, f in zip(
            result[key]['spread']['realizations'],
            result[bound]['spread']['realizations'])]
        assert ratios[key][0] == pytest.approx(sum(per) / 2)
    # the smoothing floor lies below the filtering one (of three steps, a
    # window of three is the whole sequence)
    assert result['pcrb-smoother']['rmse'] == pytest.approx(
        result['pcrb-lag3']['rmse'], rel=1e-12)
    assert result['pcrb-lag3']['rmse'] < result['pcrb']['rmse']
    with pytest.raises(SystemExit):
        main(['compare', '--scenario', *scenarios, '--lag', '1', '--quiet'])
    assert 'must be at least 2' in capsys.readouterr().err
    with pytest.raises(ValueError, match="'lag' must be at least 2"):
        run_compare(scenarios=scenarios, lag=1)


def test_range_only_rows_divided_by_the_bound_of_the_ranges_alone():
    # on a scenario with bearings the range-only likelihood ('gaussian')
    # reads the ranges alone: its filtered rows stand beside the filtering
    # bound of the ranges alone, its smoothed rows beside the smoothing
    # bound of the ranges alone at their lag; the other likelihoods beside
    # the bounds of everything measured
    from tg_nebp.bounds import PosteriorCRB
    from tg_nebp.datasets import Scenario
    built = compare_methods(Scenario.load('robots_test'), lag=3)
    bound = built['pcrb-lag3-range-only'][1]()
    assert isinstance(bound, PosteriorCRB) and bound.lag == 3
    assert bound.measurement.features == ('range', )
    assert 'pcrb-lag3-range-only' not in compare_methods(tiny_scenario(),
                                                         lag=3)

    def row(*rmse):
        return dict(spread=dict(realizations=[(0.0, 0.0, r) for r in rmse]))

    rows = {'pcrb': row(1.0, 2.0), 'pcrb-range-only': row(2.0, 4.0),
            'pcrb-lag3': row(0.5, 1.0), 'pcrb-lag3-range-only': row(1.0, 2.0),
            'gbp gaussian': row(3.0, 6.0),
            'gbp-lag3-smoothed gaussian': row(1.5, 3.0),
            'gbp-lag3-smoothed range-bearing': row(1.5, 3.0)}
    ratios = floor_ratios(rows)
    assert ratios['gbp gaussian'] == (1.5, 0.0)
    assert ratios['gbp-lag3-smoothed gaussian'] == (1.5, 0.0)
    assert ratios['gbp-lag3-smoothed range-bearing'] == (3.0, 0.0)
    # the bound of the ranges alone, beside the bound of everything: what
    # the bearings are worth
    assert ratios['pcrb-range-only'] == (2.0, 0.0)
    # without the bound of the ranges alone (a scenario without bearings)
    del rows['pcrb-lag3-range-only']
    assert floor_ratios(rows)['gbp-lag3-smoothed gaussian'] == (3.0, 0.0)
