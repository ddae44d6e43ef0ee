r"""Tests of :mod:`tg_nebp.training_log`: the CSV files against the
checkpoint's history and an independent average of the step losses, a
resumed run's log, the TensorBoard events, the figure, and
:obj:`tg-nebp train --log-dir`."""
import csv
import json
import math

import pytest

from tg_nebp.cli import main
from tg_nebp.training import load_checkpoint
from tg_nebp.training_log import TrainingLog, read_training_log

from helpers import tiny_scenario

STEPS = 3  # time steps of the scenario


def scenario_file(folder):
    path = folder / 'tiny.json'
    path.write_text(json.dumps(vars(tiny_scenario(steps=STEPS))))
    return path


def train_argv(tmp_path, epochs, *extra):
    return ['train', '--scenario', str(scenario_file(tmp_path)),
            '--realizations', '4', '--val-realizations', '1', '--epochs',
            str(epochs), '--batch-size', '2', '--particles', '8', '--lr',
            '1e-2', '--root', str(tmp_path / 'data'), '--out',
            str(tmp_path / 'out'), '--quiet', *extra]


def raw_rows(path):
    with open(path, newline='') as f:
        return list(csv.reader(f))


def test_cli_log_agrees_with_the_checkpoint(tmp_path, capsys):
    log_dir = tmp_path / 'log'
    assert main(train_argv(tmp_path, 2, '--log-dir', str(log_dir))) == 0
    assert f'log -> {log_dir}' in capsys.readouterr().out
    history = load_checkpoint(tmp_path / 'out' / 'nebp.pt')['progress'][
        'history']
    log = read_training_log(log_dir)
    per_epoch = 2 * STEPS  # 2 batches of 2 realizations
    assert [(r['epoch'], r['step']) for r in log['steps']] == [
        (e, s) for e in range(2) for s in range(1, per_epoch + 1)]
    assert raw_rows(log_dir / 'steps.csv')[0] == ['epoch', 'step', 'loss']
    assert log['epochs'] == [{k: h[k] for k in (
        'epoch', 'train_loss', 'val_loss')} for h in history]
    # every batch has the same agents: the epoch's training loss is the
    # plain mean of its steps' losses
    for h in history:
        losses = [r['loss'] for r in log['steps'] if r['epoch'] ==
                  h['epoch']]
        assert math.isclose(sum(losses) / len(losses), h['train_loss'],
                            rel_tol=1e-6)
    assert (log_dir / 'history.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_a_resumed_run_drops_the_interrupted_epoch(tmp_path, capsys):
    log_dir = tmp_path / 'log'
    assert main(train_argv(tmp_path, 1, '--log-dir', str(log_dir))) == 0
    first = read_training_log(log_dir)
    # a run killed in its second epoch left two step rows and a cut one
    with open(log_dir / 'steps.csv', 'a') as f:
        f.write('1,1,5.0\n1,2,6.0\n1,3,')
    assert main(train_argv(tmp_path, 2, '--log-dir', str(log_dir),
                           '--resume')) == 0
    capsys.readouterr()
    resumed = read_training_log(log_dir)
    per_epoch = 2 * STEPS
    assert resumed['steps'][:per_epoch] == first['steps']
    assert [(r['epoch'], r['step']) for r in resumed['steps']] == [
        (e, s) for e in range(2) for s in range(1, per_epoch + 1)]
    assert 5.0 not in [r['loss'] for r in resumed['steps'][per_epoch:]]
    history = load_checkpoint(tmp_path / 'out' / 'nebp.pt')['progress'][
        'history']
    assert [e['epoch'] for e in resumed['epochs']] == [0, 1]
    assert resumed['epochs'][1]['val_loss'] == history[1]['val_loss']


def test_history_of_a_checkpoint_without_a_log(tmp_path):
    # a model trained before it had a log still gets its epochs drawn
    history = [dict(epoch=0, train_loss=2.0, val_loss=1.5),
               dict(epoch=1, train_loss=1.0, val_loss=float('nan'))]
    with TrainingLog(tmp_path, 4, history, tensorboard=False):
        pass
    log = read_training_log(tmp_path)
    assert log['steps'] == []
    assert log['epochs'][0] == history[0]
    assert math.isnan(log['epochs'][1]['val_loss'])
    assert (tmp_path / 'history.png').exists()
    assert not list(tmp_path.glob('events.out.tfevents.*'))


def test_tensorboard_events_equal_the_csv(tmp_path):
    pytest.importorskip('tensorboard')
    from tensorboard.backend.event_processing.event_accumulator import \
        EventAccumulator

    with TrainingLog(tmp_path, 2) as log:
        for epoch in range(2):
            for step in (1, 2):
                log.step(dict(epoch=epoch, step=step, loss=epoch + step / 4))
            log.epoch(dict(epoch=epoch, train_loss=epoch + 0.375,
                           val_loss=epoch + 0.5))
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    steps = events.Scalars('loss/train_step')
    assert [(e.step, e.value) for e in steps] == [
        (1, 0.25), (2, 0.5), (3, 1.25), (4, 1.5)]
    assert [(e.step, e.value) for e in events.Scalars('loss/validation')] \
        == [(2, 0.5), (4, 1.5)]
    assert [e.value for e in events.Scalars('loss/train_epoch')] == [
        0.375, 1.375]


def test_tensorboard_events_of_the_interrupted_epoch_are_purged(tmp_path):
    pytest.importorskip('tensorboard')
    from tensorboard.backend.event_processing.event_accumulator import \
        EventAccumulator

    first = dict(epoch=0, train_loss=0.375, val_loss=0.5)
    with TrainingLog(tmp_path, 2) as log:
        log.step(dict(epoch=0, step=1, loss=0.25))
        log.step(dict(epoch=0, step=2, loss=0.5))
        log.epoch(first)
        log.step(dict(epoch=1, step=1, loss=9.0))  # then killed
    with TrainingLog(tmp_path, 2, [first]) as log:
        log.step(dict(epoch=1, step=1, loss=1.25))
        log.step(dict(epoch=1, step=2, loss=1.5))
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    assert [(e.step, e.value) for e in events.Scalars('loss/train_step')] \
        == [(1, 0.25), (2, 0.5), (3, 1.25), (4, 1.5)]


def _log_of(folder, history, steps_per_epoch=2):
    # a finished log of 'history', as a run writes it
    with TrainingLog(folder, steps_per_epoch, tensorboard=False) as log:
        for entry in history:
            for step in range(1, steps_per_epoch + 1):
                log.step(dict(epoch=entry['epoch'], step=step,
                              loss=entry['train_loss'] + step))
            log.epoch(entry)


def test_resuming_with_another_runs_log_is_refused(tmp_path):
    mine = [dict(epoch=0, train_loss=2.0, val_loss=1.5)]
    other = [dict(epoch=0, train_loss=3.0, val_loss=2.5)]
    _log_of(tmp_path, other)
    before = (tmp_path / 'steps.csv').read_bytes()
    with pytest.raises(ValueError, match="another run's: its epoch 0"):
        TrainingLog(tmp_path, 2, mine, tensorboard=False)
    # nothing was rewritten
    assert (tmp_path / 'steps.csv').read_bytes() == before
    # the run's own log resumes, keeping its finished epoch's steps
    _log_of(tmp_path / 'own', mine)
    with TrainingLog(tmp_path / 'own', 2, mine, tensorboard=False):
        pass
    assert len(read_training_log(tmp_path / 'own')['steps']) == 2


def test_steps_of_an_epoch_the_log_does_not_show_finished_are_dropped(
        tmp_path):
    # steps.csv holds epoch-0 rows, epochs.csv none: they cannot be shown
    # to be this run's
    (tmp_path / 'steps.csv').write_text('epoch,step,loss\n0,1,9.0\n0,2,9.5\n')
    history = [dict(epoch=0, train_loss=2.0, val_loss=1.5)]
    with TrainingLog(tmp_path, 2, history, tensorboard=False):
        pass
    log = read_training_log(tmp_path)
    assert log['steps'] == [] and log['epochs'] == history


def test_a_damaged_log_names_its_file_and_does_not_block_a_new_run(
        tmp_path):
    (tmp_path / 'steps.csv').write_bytes(b'\xff\xfe\x00garbage\x80\x81')
    history = [dict(epoch=0, train_loss=2.0, val_loss=1.5)]
    with pytest.raises(ValueError, match=r"steps\.csv' is not a training "
                       r"log CSV"):
        TrainingLog(tmp_path, 2, history, tensorboard=False)
    with TrainingLog(tmp_path, 2, tensorboard=False) as log:  # a new run
        log.step(dict(epoch=0, step=1, loss=1.0))
    assert read_training_log(tmp_path)['steps'] == [
        dict(epoch=0.0, step=1.0, loss=1.0)]


def test_cli_resume_with_another_runs_log_is_one_error_line(tmp_path,
                                                             capsys):
    log_dir = tmp_path / 'log'
    assert main(train_argv(tmp_path, 1, '--log-dir', str(log_dir))) == 0
    # another run (another learning rate) into its own folder
    other = tmp_path / 'other'
    other.mkdir()
    argv = train_argv(other, 1, '--log-dir', str(other / 'log'))
    argv[argv.index('--lr') + 1] = '1e-3'
    assert main(argv) == 0
    capsys.readouterr()
    assert main(train_argv(tmp_path, 2, '--log-dir', str(other / 'log'),
                           '--resume')) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another run's" in err[0]
