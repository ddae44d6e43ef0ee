import dataclasses

import pytest
import torch

from tg_nebp import NEBP
from tg_nebp.cli import main
from tg_nebp.datasets import CooperativeLocalizationDataset
from tg_nebp.evaluation import summarize, track_dataset
from tg_nebp.experiments.compare import (compare_methods, compare_table,
                                         floor_ratios, run_compare)
from tg_nebp.filters import CentralizedIEKF
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
                    'gbp-plain nlos', 'bp-paper nlos', 'bp-recommended nlos']
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


def test_changed_scenario_under_the_same_name_is_refused(tmp_path):
    common = dict(root=str(tmp_path / 'data'), realizations=1,
                  out=tmp_path / 'out', methods=['pcrb'], log=print)
    run_compare(scenarios=scenario_files(tmp_path), **common)
    changed = scenario_files(tmp_path, num_agents=4)
    with pytest.raises(ValueError, match='holds a comparison made with'):
        run_compare(scenarios=changed, **common)


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
