r"""Tests of data-parallel training (:mod:`tg_nebp.training` under
:obj:`torchrun`): the global batches, the errors, and two real runs of two
gloo processes against single-process training, one in float64 through
:func:`train` (equal to float64 rounding), one through the
:obj:`tg-nebp train` command line (float32).

Run as a script by :obj:`torchrun`, this file is the float64 worker."""
import json
import math
import sys
from pathlib import Path

import pytest
import torch
import torch.distributed as dist

from tg_nebp import training
from tg_nebp.cli import main
from tg_nebp.datasets import Scenario
from tg_nebp.filters import NEBP, GaussianNEBP
from tg_nebp.training import (_check_global_batches, _local_batches,
                              load_checkpoint, train, validation_loss)

from tg_nebp.training_log import read_training_log

from helpers import tiny_scenario, torchrun

def realizations(count, steps=8, offset=0, dtype=torch.float32):
    scenario = Scenario.load('paper_train').replace(num_steps=steps)
    data = []
    for i in range(count):
        d = scenario.generate(torch.Generator().manual_seed(offset + i))
        for key in ('states', 'edge_attr', 'prior_mean', 'prior_cov'):
            d[key] = d[key].to(dtype)
        data.append(d)
    return data


def make_model(num_iterations=1, dtype=torch.float32):
    torch.manual_seed(0)
    return NEBP(16, num_iterations, message_dim=8,
                hidden_dim=16).to(dtype)


def assert_moved_and_equal(single, ddp, initial, rtol, atol):
    r"""Every parameter agrees within the tolerance, and training moved the
    parameters far beyond it (so the comparison is not trivially met)."""
    assert single.keys() == ddp.keys() == initial.keys()
    for name in single:
        torch.testing.assert_close(ddp[name], single[name], rtol=rtol,
                                   atol=atol, msg=name)
    moved = max(float((single[k] - initial[k]).abs().max()) for k in single)
    assert moved > 100 * atol, moved


# --------------------------------------------------------------------------
# 1. global batches
# --------------------------------------------------------------------------

@pytest.mark.parametrize('num_realizations,batch_size,world_size',
                         [(12, 4, 2), (12, 4, 4), (12, 6, 3), (8, 2, 2)])
def test_local_batches_form_the_single_process_batches(
        num_realizations, batch_size, world_size):
    dataset = list(range(num_realizations))
    local = batch_size // world_size
    orders = []
    for epoch in range(3):
        single = _local_batches(dataset, batch_size, 5, epoch)
        assert [len(b) for b in single] == \
            [batch_size] * (num_realizations // batch_size)
        assert sorted(sum(single, [])) == dataset  # a permutation
        ranks = [_local_batches(dataset, batch_size, 5, epoch, world_size,
                                rank) for rank in range(world_size)]
        for b, batch in enumerate(single):
            parts = [ranks[rank][b] for rank in range(world_size)]
            assert all(len(part) == local for part in parts)
            assert sorted(sum(parts, [])) == sorted(batch)
        orders.append(sum(single, []))
    assert orders[0] != orders[1] != orders[2]  # reshuffled every epoch
    assert _local_batches(dataset, batch_size, 6, 0) != \
        _local_batches(dataset, batch_size, 5, 0)


def test_single_process_keeps_a_partial_last_batch():
    batches = _local_batches(list(range(5)), 2, 0, 0)
    assert [len(b) for b in batches] == [2, 2, 1]
    _check_global_batches(5, 2, 1)  # fine in one process


@pytest.mark.parametrize('num_realizations,batch_size,world_size,field', [
    (8, 3, 2, 'batch_size'),
    (4, 2, 4, 'batch_size'),
    (6, 4, 2, 'train_set'),
    (5, 2, 2, 'train_set'),
])
def test_uneven_global_batches_are_refused(num_realizations, batch_size,
                                           world_size, field):
    with pytest.raises(ValueError, match=field) as info:
        _check_global_batches(num_realizations, batch_size, world_size)
    assert str(world_size if field == 'batch_size' else
               num_realizations) in str(info.value)


def test_train_refuses_uneven_batches_before_any_collective(monkeypatch):
    # a fake world of two: train must fail before touching the (absent)
    # process group
    monkeypatch.setattr(training, 'process_group', lambda: (2, 0))
    data = realizations(3, steps=2)
    with pytest.raises(ValueError, match='train_set'):
        train(make_model(), data, epochs=1, batch_size=2)
    with pytest.raises(ValueError, match='batch_size'):
        train(make_model(), data[:2], epochs=1, batch_size=1)


def test_validation_loss_does_not_depend_on_the_batch_size():
    data = realizations(3, steps=3)
    model = make_model()
    losses = [validation_loss(model, data, b, 'cpu', 7) for b in (1, 2, 3)]
    for loss in losses[1:]:
        assert math.isclose(loss, losses[0], rel_tol=1e-6)
    # the particle draws depend on the seed: the check has teeth
    assert not math.isclose(validation_loss(model, data, 3, 'cpu', 8),
                            losses[0], rel_tol=1e-4)


# --------------------------------------------------------------------------
# 2. two gloo processes against one, float64 through train()
# --------------------------------------------------------------------------

def float64_runs(out: Path, rank: int = 0):
    r"""Trains two models in float64 on 4 realizations (two global batches
    of 2), validating on 3 (uneven shards): with one NEBP iteration for 2
    epochs, recording the squared gradient norm of every step, and with two
    (the GNN called twice per backward) for 1 epoch, then resumed for a
    second. Writes rank :obj:`rank`'s histories (rank 0 writes the
    checkpoints and records the gradients)."""
    train_set = realizations(4, dtype=torch.float64)
    val_set = realizations(3, offset=10, dtype=torch.float64)
    settings = dict(batch_size=2, lr=1e-2, seed=3)
    model = make_model(1, torch.float64)
    gradients = []

    def record_gradient(info):  # called after the step: .grad is DDP's
        gradients.append(sum(float(p.grad.square().sum())
                             for p in model.parameters()))

    histories = dict(gradients=gradients, iterations1=train(
        model, train_set, val_set, epochs=2, progress=record_gradient,
        checkpoint=out / 'iterations1.pt', **settings))
    path = out / 'iterations2.pt'
    train(make_model(2, torch.float64), train_set, val_set, epochs=1,
          checkpoint=path, **settings)
    histories['iterations2'] = train(
        make_model(2, torch.float64), train_set, val_set, epochs=2,
        checkpoint=path, resume=True, **settings)
    (out / f'history{rank}.json').write_text(json.dumps(histories))


def test_two_processes_train_as_one_in_float64(tmp_path):
    single, ddp = tmp_path / 'single', tmp_path / 'ddp'
    single.mkdir()
    ddp.mkdir()
    float64_runs(single)
    torchrun(__file__, ddp)
    assert sorted(p.name for p in ddp.iterdir()) == [
        'history0.json', 'history1.json', 'iterations1.pt',
        'iterations2.pt']
    expected = json.loads((single / 'history0.json').read_text())
    for rank in (0, 1):  # every rank returns the same history
        history = json.loads((ddp / f'history{rank}.json').read_text())
        for key in ('iterations1', 'iterations2'):
            assert len(history[key]) == 2
            for got, want in zip(history[key], expected[key]):
                assert got['epoch'] == want['epoch']
                for loss in ('train_loss', 'val_loss'):
                    assert math.isclose(got[loss], want[loss],
                                        rel_tol=1e-9), (key, got, want)
    # the gradient of every step is the single process's (the loss scaling
    # undoes DDP's average; Adam alone would hide a constant factor); only
    # rank 0 reports progress
    gradients = json.loads((ddp / 'history0.json').read_text())['gradients']
    assert json.loads((ddp / 'history1.json').read_text())['gradients'] == []
    assert len(gradients) == len(expected['gradients']) == 2 * 2 * 8
    for got, want in zip(gradients, expected['gradients']):
        assert math.isclose(got, want, rel_tol=1e-7), (got, want)
    for num_iterations in (1, 2):
        name = f'iterations{num_iterations}.pt'
        a, b = load_checkpoint(single / name), load_checkpoint(ddp / name)
        assert a['config'] == b['config']
        initial = make_model(num_iterations, torch.float64).state_dict()
        # float64 rounding, amplified a little by Adam over 32 steps; the
        # parameters move by about 0.1
        assert_moved_and_equal(a['model'], b['model'], initial, rtol=1e-6,
                               atol=1e-8)


# --------------------------------------------------------------------------
# 3. the command line: torchrun -m tg_nebp train against one process
# --------------------------------------------------------------------------

def test_torchrun_cli_trains_as_one_process(tmp_path, capsys):
    # float32, as the CLI trains. The gradient sums round differently on one
    # and two processes; resampling would turn a rounding difference into a
    # different particle draw once the parameters differ enough, so the
    # learning rate is small: the runs stay equal to float32 tolerance
    args = ['train', '--particles', '16', '--realizations', '4',
            '--val-realizations', '1', '--epochs', '2', '--batch-size', '2',
            '--lr', '1e-6', '--seed', '1', '--root', tmp_path / 'data',
            '--quiet']
    stdout = torchrun('-m', 'tg_nebp', *args, '--out', tmp_path / 'ddp',
                      '--log-dir', tmp_path / 'log')
    # rank 0 alone prints and logs
    assert stdout.count('epoch 0:') == 1 and stdout.count('epoch 1:') == 1
    assert stdout.count('checkpoint ->') == 1
    assert main([*map(str, args), '--out', str(tmp_path / 'single')]) == 0
    capsys.readouterr()
    a = load_checkpoint(tmp_path / 'single' / 'nebp.pt')
    b = load_checkpoint(tmp_path / 'ddp' / 'nebp.pt')
    assert a['config'] == b['config']
    torch.manual_seed(1)  # the CLI's initial weights
    initial = NEBP(16).state_dict()
    # 200 Adam steps of 1e-6 move the parameters by about 2e-4; the runs
    # differ by about 6e-8
    assert_moved_and_equal(a['model'], b['model'], initial, rtol=1e-4,
                           atol=5e-7)
    assert len(a['progress']['history']) == len(b['progress']['history']) == 2
    log = read_training_log(tmp_path / 'log')
    assert len(log['steps']) == 2 * 2 * 50  # epochs x batches x steps
    assert [e['val_loss'] for e in log['epochs']] == [
        h['val_loss'] for h in b['progress']['history']]
    for got, want in zip(b['progress']['history'],
                         a['progress']['history']):
        for loss in ('train_loss', 'val_loss'):
            assert math.isclose(got[loss], want[loss], rel_tol=1e-5)


def test_torchrun_trains_gaussian_nebp_as_one_process(tmp_path, capsys):
    # the Gaussian base draws nothing: two gloo processes give the single
    # process's parameters up to the rounding of the gradient sums
    args = ['train', '--base', 'gaussian', '--iterations', '3',
            '--hidden-dim', '8', '--realizations', '4',
            '--val-realizations', '1', '--epochs', '1', '--batch-size', '2',
            '--lr', '1e-3', '--seed', '1', '--root', tmp_path / 'data',
            '--quiet']
    stdout = torchrun('-m', 'tg_nebp', *args, '--out', tmp_path / 'ddp')
    assert stdout.count('epoch 0:') == 1
    assert main([*map(str, args), '--out', str(tmp_path / 'single')]) == 0
    capsys.readouterr()
    a = load_checkpoint(tmp_path / 'single' / 'nebp.pt')
    b = load_checkpoint(tmp_path / 'ddp' / 'nebp.pt')
    assert a['config'] == b['config'] and a['config']['base'] == 'gaussian'
    torch.manual_seed(1)  # the CLI's initial weights
    initial = GaussianNEBP(3, hidden_dim=8).state_dict()
    assert_moved_and_equal(a['model'], b['model'], initial, rtol=1e-4,
                           atol=1e-5)
    for got, want in zip(b['progress']['history'],
                         a['progress']['history']):
        for loss in ('train_loss', 'val_loss'):
            assert math.isclose(got[loss], want[loss], rel_tol=1e-4)


def test_a_bad_scenario_under_torchrun_is_one_line_on_every_rank(tmp_path):
    fields = vars(tiny_scenario(steps=2))
    fields['num_agents'] = 2.5
    bad = tmp_path / 'bad.json'
    bad.write_text(json.dumps(fields))
    done = torchrun('-m', 'tg_nebp', 'evaluate', '--scenario', bad,
                    '--realizations', '2', '--particles', '8', '--quiet',
                    '--root', tmp_path / 'data', '--out', tmp_path / 'out',
                    check=False)
    assert done.returncode != 0
    # the workers' lines (the launcher adds its own report after them)
    lines = [line for line in (done.stdout + done.stderr).splitlines()
             if line.startswith('error:')]
    assert len(lines) == 2, done.stdout + done.stderr
    assert all("'num_agents' must be an integer" in line for line in lines)
    assert 'Connection reset' not in done.stdout + done.stderr
    assert not (tmp_path / 'out' / 'metrics.json').exists()


if __name__ == '__main__':  # the float64 worker of torchrun
    dist.init_process_group('gloo')
    try:
        float64_runs(Path(sys.argv[1]), dist.get_rank())
    finally:
        dist.destroy_process_group()
