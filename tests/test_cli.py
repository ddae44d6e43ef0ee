r"""Tests of the :obj:`tg-nebp` commands in process (the user errors are
in :mod:`test_cli_errors`)."""
import json

import pytest

from tg_nebp.cli import main
from tg_nebp.filters import FixedLagGaussianNEBP
from tg_nebp.models import NLOSRange
from tg_nebp.training import (gaussian_nebp_from_checkpoint,
                              nebp_from_checkpoint)

from helpers import tiny_scenario


def nlos_scenario_file(folder):
    scenario = tiny_scenario(steps=3).replace(
        name='tiny-nlos', measurement=NLOSRange(0.8, 0.3, 2.0))
    path = folder / 'tiny_nlos.json'
    fields = {k: v for k, v in vars(scenario).items()}
    path.write_text(json.dumps(fields))
    return path


@pytest.mark.parametrize('measurement,expected', [
    (None, {'name': 'nlos', 'params': NLOSRange(0.8, 0.3, 2.0).params()}),
    ('gaussian', {'name': 'gaussian',
                  'params': {'sigma': 0.8, 'max_range': 20.0}}),
    ('student-t', {'name': 'student-t',
                   'params': {'sigma': 0.8, 'nu': 3.0, 'max_range': 20.0}}),
])
def test_evaluate_with_another_likelihood(tmp_path, measurement, expected):
    path = nlos_scenario_file(tmp_path)
    out = tmp_path / 'out'
    argv = ['evaluate', '--scenario', str(path), '--realizations', '2',
            '--particles', '16', '--root', str(tmp_path / 'data'), '--out',
            str(out), '--quiet']
    if measurement is not None:
        argv += ['--measurement', measurement]
    assert main(argv) == 0
    entry = json.loads((out / 'metrics.json').read_text())['bp']
    assert entry['measurement'] == expected
    assert entry['scenario'] == 'tiny-nlos'


def test_train_with_another_likelihood(tmp_path):
    # NEBP trained on NLOS data with a Gaussian likelihood inside, the
    # model-mismatch experiment; the checkpoint records the likelihood
    path = nlos_scenario_file(tmp_path)
    out = tmp_path / 'out'
    assert main(['train', '--scenario', str(path), '--realizations', '1',
                 '--val-realizations', '1', '--epochs', '1', '--batch-size',
                 '1', '--particles', '8', '--variant', 'equivariant',
                 '--measurement', 'gaussian', '--root',
                 str(tmp_path / 'data'), '--out', str(out), '--quiet']) == 0
    model = nebp_from_checkpoint(out / 'nebp.pt')
    assert model.measurement.config() == {
        'name': 'gaussian', 'params': {'sigma': 0.8, 'max_range': 20.0}}


def test_measurement_is_not_for_nebp(tmp_path, capsys):
    argv = ['evaluate', '--method', 'nebp', '--checkpoint', 'x.pt',
            '--measurement', 'gaussian', '--realizations', '1',
            '--root', str(tmp_path / 'data'), '--out', str(tmp_path / 'o'),
            '--quiet']
    assert main(argv) == 2
    assert ("'measurement' (--measurement) is for method bp or iekf or gbp "
            "or hybrid or pcrb, not nebp") in capsys.readouterr().err


def test_samples_flag(tmp_path):
    path = nlos_scenario_file(tmp_path)
    out = tmp_path / 'out'
    argv = ['evaluate', '--scenario', str(path), '--realizations', '1',
            '--particles', '16', '--root', str(tmp_path / 'data'), '--out',
            str(out), '--quiet']
    assert main(argv + ['--samples', '4']) == 0
    sampled = json.loads((out / 'metrics.json').read_text())['bp']
    assert main(argv + ['--samples', 'all']) == 0
    exact = json.loads((out / 'metrics.json').read_text())['bp']
    assert sampled['rmse'] != exact['rmse']
    with pytest.raises(SystemExit) as info:
        main(argv + ['--samples', 'some'])
    assert info.value.code == 2


def test_resampling_flags(tmp_path):
    path = nlos_scenario_file(tmp_path)
    out = tmp_path / 'out'
    argv = ['evaluate', '--scenario', str(path), '--realizations', '1',
            '--particles', '16', '--root', str(tmp_path / 'data'), '--out',
            str(out), '--quiet', '--resampler', 'residual']
    assert main(argv + ['--regularize', '--ess-threshold', '0.5']) == 0
    entry = json.loads((out / 'metrics.json').read_text())['bp']
    assert (entry['regularize'], entry['ess_threshold']) == ('silverman',
                                                             0.5)
    assert main(argv + ['--regularize', '0.2']) == 0
    assert json.loads((out / 'metrics.json').read_text())['bp'][
        'regularize'] == 0.2
    for bad in (['--ess-threshold', '2'], ['--regularize', 'wide']):
        with pytest.raises(SystemExit) as info:
            main(argv + bad)
        assert info.value.code == 2


def test_equivariant_variant_trains_once_and_runs_at_any_k(tmp_path, capsys):
    path = tmp_path / 'tiny.json'
    path.write_text(json.dumps(vars(tiny_scenario(steps=2))))
    common = ['--scenario', str(path), '--root', str(tmp_path / 'data'),
              '--quiet']
    train = ['train', '--realizations', '2', '--val-realizations', '1',
             '--epochs', '1', '--batch-size', '1', '--particles', '8']
    for variant in ('paper', 'equivariant'):
        assert main(train + common + ['--variant', variant, '--out',
                                      str(tmp_path / variant)]) == 0
    evaluate = ['evaluate', '--method', 'nebp', '--realizations', '1',
                '--particles', '24'] + common
    out = tmp_path / 'eval'
    assert main(evaluate + ['--checkpoint',
                            str(tmp_path / 'equivariant' / 'nebp.pt'),
                            '--out', str(out)]) == 0
    assert json.loads((out / 'metrics.json').read_text())['nebp'][
        'particles'] == 24
    capsys.readouterr()
    assert main(evaluate + ['--checkpoint',
                            str(tmp_path / 'paper' / 'nebp.pt'),
                            '--out', str(out)]) == 2
    assert "train --variant equivariant for any K" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(train + common + ['--variant', 'other'])
    assert info.value.code == 2


def test_evaluate_gaussian_bp_and_particle_bp_with_both_ends(tmp_path,
                                                              capsys):
    import dataclasses
    from tg_nebp.io import read_json, write_json
    from helpers import tiny_scenario
    write_json(tmp_path / 'tiny.json',
               dataclasses.asdict(tiny_scenario(steps=3)))
    common = ['--realizations', '2', '--root', str(tmp_path / 'data'),
              '--out', str(tmp_path), '--quiet', '--scenario',
              str(tmp_path / 'tiny.json')]
    assert main(['evaluate', '--method', 'gbp', '--inflation', '1',
                 '--tolerance', '0', '--iterations', '3', *common]) == 0
    assert main(['evaluate', '--method', 'bp', '--ends', 'both',
                 '--iterations', '2', '--particles', '32', *common]) == 0
    written = read_json(tmp_path / 'metrics.json')
    gbp = written['gbp']
    assert (gbp['inflation'], gbp['tolerance'], gbp['iterations'],
            gbp['ends']) == (1.0, None, 3, 'both')
    assert (written['bp']['ends'], written['bp']['iterations']) == ('both',
                                                                    2)
    assert 'gbp: RMSE' in capsys.readouterr().out


def test_train_gaussian_nebp_on_a_mix_of_scenarios(tmp_path, capsys):
    # an NLOS scenario (range and NLOS flag) mixed with a clean one (range
    # only): the tracker reads the ranges alone, so they batch together
    nlos = nlos_scenario_file(tmp_path)
    clean = tmp_path / 'tiny_clean.json'
    scenario = tiny_scenario(steps=3).replace(name='tiny-clean')
    clean.write_text(json.dumps(dict(vars(scenario))))
    out = tmp_path / 'out'
    common = ['--realizations', '2', '--val-realizations', '1', '--epochs',
              '1', '--batch-size', '2', '--root', str(tmp_path / 'data'),
              '--quiet']
    assert main(['train', '--base', 'gaussian', '--scenario', str(clean),
                 str(nlos), '--measurement', 'gaussian', '--iterations', '4',
                 '--hidden-dim', '8', '--out', str(out), *common]) == 0
    assert 'negative log-likelihood' in capsys.readouterr().out
    model = gaussian_nebp_from_checkpoint(out / 'nebp.pt')
    assert (model.num_iterations, model.conv.hidden_dim) == (4, 8)
    assert model.measurement.config()['name'] == 'gaussian'
    # the particle options are the particle base's
    assert main(['train', '--base', 'gaussian', '--scenario', str(clean),
                 '--particles', '8', '--out', str(tmp_path / 'o2'),
                 *common]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: 'particles' (--particles) is for the "
                          "particle base") and err.count('\n') == 1
    assert not (tmp_path / 'o2' / 'nebp.pt').exists()
    # and the embedding size is the gaussian base's
    assert main(['train', '--scenario', str(clean), '--hidden-dim', '8',
                 '--out', str(tmp_path / 'o3'), *common]) == 2
    assert capsys.readouterr().err.startswith(
        "error: 'hidden_dim' (--hidden-dim) is for the gaussian base")
    # and so is the window
    assert main(['train', '--scenario', str(clean), '--lag', '3',
                 '--out', str(tmp_path / 'o4'), *common]) == 2
    assert capsys.readouterr().err.startswith(
        "error: 'lag' (--lag) is for the gaussian base")


def test_train_gaussian_nebp_in_a_window(tmp_path, capsys):
    # trained through the window's iterations on the loss of every window
    # step; its checkpoint rebuilds the window, trained
    scenario = tmp_path / 'tiny.json'
    scenario.write_text(json.dumps(dict(vars(tiny_scenario(steps=4)))))
    out = tmp_path / 'out'
    assert main(['train', '--base', 'gaussian', '--lag', '3', '--scenario',
                 str(scenario), '--realizations', '2', '--val-realizations',
                 '1', '--epochs', '1', '--batch-size', '2', '--iterations',
                 '4', '--hidden-dim', '8', '--lr', '0.01', '--root',
                 str(tmp_path / 'data'), '--out', str(out), '--quiet']) == 0
    assert 'negative log-likelihood' in capsys.readouterr().out
    model = gaussian_nebp_from_checkpoint(out / 'nebp.pt')
    assert isinstance(model, FixedLagGaussianNEBP)
    assert (model.lag, model.num_iterations, model.inflation) == (3, 4, 1.5)
    assert float(model.correction.weight_head.weight.abs().sum()) > 0


def test_fit_then_evaluate_record_track_and_score_a_real_sequence(
        tmp_path, capsys):
    # a sequence in the MRCLAM format: fitted, written as a scenario file,
    # which evaluate reads with --root, record writes as lines, track
    # follows and score scores as evaluate does
    from helpers import write_mrclam
    write_mrclam(tmp_path / 'MRCLAM_Dataset9')
    root, fitted = str(tmp_path), str(tmp_path / 'fit9.json')
    assert main(['fit', '--sequence', '9', '--root', root, '--output',
                 fitted]) == 0
    # every command that reads a sequence says what it kept and dropped
    assert ("MRCLAM sequence 9 (the fit's window): 3 links in 1 window; 1 "
            "measurement(s) of barcodes") in capsys.readouterr().err
    fields = json.loads((tmp_path / 'fit9.json').read_text())
    assert (fields['sequence'], fields['measurement']['name']) == (
        9, 'student-t-range-bearing')
    fields['duration'] = 10.0
    (tmp_path / 'fit9.json').write_text(json.dumps(fields))
    out = tmp_path / 'out'
    assert main(['evaluate', '--method', 'iekf', '--scenario', fitted,
                 '--root', root, '--out', str(out), '--quiet']) == 0
    entry = json.loads((out / 'metrics.json').read_text())['iekf']
    assert ("MRCLAM sequence 9 ('mrclam-9'): 3 links in 1 window; "
            in capsys.readouterr().err)
    lines, truth = tmp_path / 'm.jsonl', tmp_path / 't.jsonl'
    assert main(['record', '--scenario', fitted, '--root', root,
                 '--measurements', str(lines), '--truth', str(truth)]) == 0
    first = json.loads(lines.read_text().splitlines()[0])
    assert first['time'] == 0.5 and len(first['join']) == 7
    estimates = tmp_path / 'e.jsonl'
    assert main(['track', '--method', 'iekf', '--scenario', fitted,
                 '--input', str(lines), '--output', str(estimates)]) == 0
    capsys.readouterr()
    assert main(['score', '--estimates', str(estimates), '--truth',
                 str(truth)]) == 0
    assert f"RMSE {entry['rmse']:.3f} m" in capsys.readouterr().out


def test_train_a_gaussian_nebp_on_windows_of_a_real_sequence(tmp_path,
                                                             capsys):
    # windows of the first half to train on, the second half to validate
    # on: a real sequence's windows are the same for every seed, so the
    # validation windows must be named
    from helpers import write_mrclam
    from tg_nebp.datasets import MRCLAMScenario
    write_mrclam(tmp_path / 'MRCLAM_Dataset9')
    train = tmp_path / 'train.json'
    MRCLAMScenario.load('mrclam-9-first-half').replace(
        name='train', duration=4.0, stride=4.0).save(train)
    argv = ['train', '--base', 'gaussian', '--hidden-dim', '4',
            '--iterations', '2', '--epochs', '1', '--batch-size', '1',
            '--scenario', str(train), '--root', str(tmp_path), '--out',
            str(tmp_path / 'out'), '--quiet']
    assert main(argv) == 2
    assert "give validation windows elsewhere" in capsys.readouterr().err
    assert main(argv + ['--val-scenario', 'mrclam-9-second-half']) == 0
    tracker = gaussian_nebp_from_checkpoint(tmp_path / 'out' / 'nebp.pt')
    assert tracker.motion.name == 'unicycle-odometry'
    assert 'negative log-likelihood' in capsys.readouterr().out
