r"""Tests of the experiments beyond the paper
(:mod:`tg_nebp.experiments.equivariant_nebp`,
:obj:`tg-nebp reproduce --preset beyond`) on tiny scenarios."""
import dataclasses
import json

import pytest
import torch

import tg_nebp.experiments.equivariant_nebp as beyond
import tg_nebp.training as training
from tg_nebp.cli import main
from tg_nebp.datasets import CooperativeLocalizationDataset
from tg_nebp.evaluation import summarize, track_dataset
from tg_nebp.filters import ParticleBP
from tg_nebp.io import write_json
from tg_nebp.models import GaussianRange, NLOSRange
from tg_nebp.training import load_checkpoint, nebp_from_checkpoint
from tg_nebp.training_log import read_training_log

from helpers import tiny_scenario


@pytest.fixture
def tiny(tmp_path, monkeypatch):
    # line-of-sight and NLOS versions of the tiny network as JSON files, and
    # a CPU configuration small enough for a test
    nlos = NLOSRange(sigma=1.0, p_nlos=0.5, bias_mean=3.0, max_range=20.0)
    paths = {}
    for key, scenario in (('los', tiny_scenario(8)), ('nlos', dataclasses.
                                                      replace(
            tiny_scenario(8), name='tiny_nlos',
            measurement=nlos.config()))):
        paths[key] = str(tmp_path / f'{scenario.name}.json')
        write_json(paths[key], dataclasses.asdict(scenario))
    config = dict(beyond.BEYOND['cpu'], train_particles=40,
                  test_particles=[20, 40], train_realizations=2,
                  val_realizations=1, epochs=1, batch_size=1,
                  test_realizations=3, eval_batch_size=2, train_samples=2,
                  samples=3, marginalized_epochs=1,
                  scenarios=dict(train=paths['los'], test=paths['los'],
                                 nlos_train=paths['nlos'],
                                 nlos_test=paths['nlos']))
    monkeypatch.setitem(beyond.BEYOND, 'cpu', config)
    return config, paths, tmp_path


def test_every_method_equals_an_independent_run(tiny):
    config, paths, tmp_path = tiny
    out, root = tmp_path / 'out', str(tmp_path / 'data')
    metrics = beyond.reproduce_beyond('cpu', out, root, log=lambda *a: None)
    names = [f'{m} K={k}' for k in (20, 40) for m in (
        'bp', 'nebp', 'bp marginalized', 'nebp marginalized')] + [
        'nlos: bp gaussian (mismatched) K=40', 'nlos: bp nlos (matched) K=40',
        'nlos: nebp gaussian K=40']
    assert list(metrics) == names
    for name in ('report.md', 'metrics.json', 'outage.png',
                 'consistency.png', 'nlos_outage.png',
                 'nlos_consistency.png', 'particles.png'):
        assert (out / name).stat().st_size > 0, name
    for model in ('paired', 'marginalized', 'nlos'):  # the training logs
        epochs = read_training_log(out / model)['epochs']
        assert epochs == [{k: h[k] for k in ('epoch', 'train_loss',
                                             'val_loss')} for h in
                          load_checkpoint(out / model / 'nebp.pt')[
                              'progress']['history']]
        assert (out / model / 'history.png').stat().st_size > 0
    report = (out / 'report.md').read_text()
    assert all(f'| {name} |' in report for name in names)
    assert '| NEBP, paper Fig. 2 | paper_test | 50000 | 400 | 0.377 |' in \
        report

    los = CooperativeLocalizationDataset(root, paths['los'], 3, 0)
    nlos = CooperativeLocalizationDataset(root, paths['nlos'], 3, 0)
    gaussian = GaussianRange(sigma=1.0, max_range=20.0)
    independent = {
        'bp K=20': (ParticleBP(20), los),
        'nebp K=40': (nebp_from_checkpoint(out / 'paired' / 'nebp.pt'), los),
        'bp marginalized K=40': (ParticleBP(40, num_samples=3,
                                            regularize='silverman'), los),
        'nebp marginalized K=20': (nebp_from_checkpoint(
            out / 'marginalized' / 'nebp.pt', 20, num_samples=3), los),
        'nlos: bp gaussian (mismatched) K=40': (ParticleBP(
            40, measurement=gaussian), nlos),
        'nlos: bp nlos (matched) K=40': (ParticleBP(
            40, measurement=nlos.scenario.measurement_model), nlos),
        'nlos: nebp gaussian K=40': (nebp_from_checkpoint(
            out / 'nlos' / 'nebp.pt'), nlos),
    }
    for name, (tracker, data) in independent.items():
        result = track_dataset(tracker.eval(), data, batch_size=1, seed=0)
        entry = summarize(result['errors'], result['nees'])
        assert metrics[name]['outage'] == pytest.approx(entry['outage']), \
            name
        assert metrics[name]['accept'] == pytest.approx(entry['accept']), \
            name
        # the spread: with one realization per batch, realization r's
        # values are the r-th of three equal, contiguous chunks
        chunks = [summarize(e, n) for e, n in zip(
            result['errors'].chunk(3), result['nees'].chunk(3))]
        per = torch.tensor([[c['outage']['1.0'], c['accept']['0.95'],
                             c['rmse']] for c in chunks],
                           dtype=torch.float64)
        spread = metrics[name]['spread']
        assert torch.tensor(spread['realizations']).double().allclose(per)
        for column, key in enumerate(('outage_1m', 'accept_0.95', 'rmse')):
            values = per[:, column]
            assert spread[key] == pytest.approx(dict(
                mean=float(values.mean()), std=float(values.std()),
                min=float(values.min()), max=float(values.max()))), name


def test_checkpoints_record_the_training_options(tiny):
    config, paths, tmp_path = tiny
    out = tmp_path / 'out'
    beyond.reproduce_beyond('cpu', out, str(tmp_path / 'data'),
                            log=lambda *a: None)
    for arm, samples, regularize, measurement in (
            ('paired', 1, None, 'gaussian'),
            ('marginalized', 2, 'silverman', 'gaussian'),
            ('nlos', 1, None, 'gaussian')):
        model = nebp_from_checkpoint(out / arm / 'nebp.pt')
        assert model.config()['variant'] == 'equivariant'
        assert model.num_particles == 40
        assert model.num_samples == samples
        assert model.regularize == regularize
        assert model.measurement.name == measurement


def test_a_second_run_resumes_and_other_settings_are_refused(tiny,
                                                             monkeypatch):
    config, paths, tmp_path = tiny
    out, root = tmp_path / 'out', str(tmp_path / 'data')
    first = beyond.reproduce_beyond('cpu', out, root, log=lambda *a: None)

    def no_work(*args, **kwargs):
        raise AssertionError('a finished part ran again')

    monkeypatch.setattr(beyond, 'evaluate_method', no_work)
    monkeypatch.setattr(training, 'train_epoch', no_work)
    again = beyond.reproduce_beyond('cpu', out, root, log=lambda *a: None)
    assert json.dumps(again, sort_keys=True) == json.dumps(first,
                                                           sort_keys=True)
    monkeypatch.setitem(beyond.BEYOND, 'cpu',
                        dict(config, test_particles=[20]))
    with pytest.raises(ValueError, match='holds a run with other settings'):
        beyond.reproduce_beyond('cpu', out, root, log=lambda *a: None)


def test_cli_refuses_options_the_preset_sets(tmp_path, capsys):
    assert main(['reproduce', '--preset', 'beyond', '--samples', '4',
                 '--out', str(tmp_path / 'o')]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith('error: ')
    assert '--samples' in err[0]
    assert not any((tmp_path / 'o').iterdir())  # nothing written
