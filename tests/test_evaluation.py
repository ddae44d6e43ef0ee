r"""Tests of :mod:`tg_nebp.evaluation`."""
import pytest
import torch

from tg_nebp import ParticleBP
from tg_nebp.cli import main
from tg_nebp.evaluation import track_dataset
from tg_nebp.io import read_json
from tg_nebp.utils import derive_seed

from helpers import gen, tiny_scenario, torchrun


def test_results_do_not_depend_on_the_batch_size():
    # every realization draws from its own stream (derive_seed(seed, r))
    data = [tiny_scenario(steps=3).generate(gen(r)) for r in range(5)]
    tracker = ParticleBP(32)
    one = track_dataset(tracker, data, batch_size=1, seed=7)
    for batch_size in (2, 5):
        other = track_dataset(tracker, data, batch_size=batch_size, seed=7)
        # one order (realization, agent, time step) for every batch size
        assert torch.equal(one['realization'], other['realization'])
        assert torch.allclose(one['errors'], other['errors'], atol=1e-5)
        assert torch.allclose(one['nees'], other['nees'], rtol=1e-4)
    # the first realization's float32 estimates, to the errors' 1e-5 m:
    # particle BP does not promise a batch bit for bit (a batch's kernels
    # may sum in another order than one graph's alone)
    torch.testing.assert_close(one['first_mean'], track_dataset(
        tracker, data, batch_size=2, seed=7)['first_mean'], rtol=0,
        atol=1e-5)


def test_progress_counts_realization_steps_and_realizations_are_named():
    # a progress bar of len(dataset) * T ends full for any batch size; every
    # value says which realization it belongs to
    data = [tiny_scenario(steps=3).generate(gen(r)) for r in range(5)]
    for batch_size in (1, 2, 5):
        ticks = []
        result = track_dataset(ParticleBP(16), data, batch_size=batch_size,
                               seed=7, progress=ticks.append)
        assert sum(ticks) == 5 * 3
        agents = 3  # tiny_scenario's
        owners = result['realization']
        assert owners.shape == result['errors'].shape
        assert torch.bincount(owners).tolist() == [agents * 3] * 5


def test_values_are_ordered_by_realization_agent_and_time():
    # against each realization tracked alone, its steps read one by one
    data = [tiny_scenario(steps=3).generate(gen(r)) for r in range(3)]
    tracker = ParticleBP(16)
    result = track_dataset(tracker, data, batch_size=2, seed=7)
    assert result['realization'].tolist() == sorted(
        result['realization'].tolist())
    for r, d in enumerate(data):
        alone = [step.mean[:, :2] for step in tracker.steps(
            d, [torch.Generator().manual_seed(derive_seed(7, r))])]
        agents = (~d.anchor).nonzero().flatten().tolist()
        want = [float((alone[t][i] - d.states[i, t, :2]).norm())
                for i in agents for t in range(3)]
        got = result['errors'][result['realization'] == r].tolist()
        assert len(got) == len(want)
        for g, w in zip(got, want):
            assert abs(g - w) <= 1e-5 * (1 + w)


def test_torchrun_evaluate_shards_and_equals_one_process(tmp_path, capsys):
    # 3 realizations over 2 processes: rank 0 tracks 0 and 2, rank 1 tracks
    # 1; rank 0 gathers, prints and writes metrics equal to one process's
    args = ['evaluate', '--particles', '32', '--realizations', '3',
            '--seed', '4', '--root', tmp_path / 'data', '--quiet']
    stdout = torchrun('-m', 'tg_nebp', *args, '--out', tmp_path / 'ddp')
    assert stdout.count('bp: RMSE') == 1
    assert main([*map(str, args), '--out', str(tmp_path / 'one')]) == 0
    capsys.readouterr()
    sharded = read_json(tmp_path / 'ddp' / 'metrics.json')['bp']
    single = read_json(tmp_path / 'one' / 'metrics.json')['bp']
    sharded.pop('seconds')
    single.pop('seconds')
    assert sharded == single


def test_an_agent_without_truth_is_tracked_not_scored():
    # its estimates are made and its links used, but it has no error: the
    # values are those of the other agents, and the bound refuses
    from tg_nebp.bounds import PosteriorCRB
    from tg_nebp.evaluation import bound_dataset
    from tg_nebp.filters import GaussianBP
    data = tiny_scenario(steps=3).generate(gen(0))
    agents = (~data.anchor).nonzero().flatten().tolist()
    tracker = GaussianBP()
    full = track_dataset(tracker, [data])
    blind = data.clone()
    blind.states[agents[1]] = float('nan')
    result = track_dataset(tracker, [blind])
    assert result['errors'].numel() == (len(agents) - 1) * 3
    # the same estimates (the tracker never reads the truth)
    keep = [k for k in range(len(agents)) if k != 1]
    torch.testing.assert_close(
        result['errors'], full['errors'].view(len(agents), 3)[keep]
        .flatten(), rtol=0, atol=0)
    with pytest.raises(ValueError, match=rf"node {agents[1]} has none"):
        bound_dataset(PosteriorCRB(), [blind])


def test_bound_dataset_orders_and_summarizes_like_a_tracker():
    from tg_nebp.bounds import PosteriorCRB
    from tg_nebp.evaluation import (bound_dataset, spread, summarize_bound,
                                    summarize_result)
    from tg_nebp.metrics import gaussian_outage

    data = [tiny_scenario(steps=3).generate(gen(r)) for r in range(3)]
    bound = PosteriorCRB()
    result = bound_dataset(bound, data, batch_size=2)
    assert result['realization'].tolist() == [0] * 9 + [1] * 9 + [2] * 9
    # realization 1 alone, agent-major then time, as track_dataset orders
    cov = bound(data[1])[~data[1].anchor][..., :2, :2]
    mine = result['realization'] == 1
    torch.testing.assert_close(result['squared_error'][mine],
                               cov.diagonal(dim1=-2, dim2=-1).sum(-1)
                               .flatten())
    torch.testing.assert_close(result['outage'][mine], gaussian_outage(
        cov, (0.5, 1.0, 2.0)).flatten(0, 1))
    entry = summarize_result(result)
    assert entry == summarize_bound(result['squared_error'],
                                    result['outage'])
    assert entry['rmse'] == pytest.approx(
        float(result['squared_error'].mean().sqrt()))
    assert entry['accept'] == {'0.50': 0.5, '0.95': 0.95, '0.99': 0.99}
    per = spread(result)
    assert len(per['realizations']) == 3
    floors = [float(result['squared_error'][result['realization'] == r]
                    .mean().sqrt()) for r in range(3)]
    assert [row[2] for row in per['realizations']] == pytest.approx(floors)
    assert per['rmse']['mean'] == pytest.approx(sum(floors) / 3)


def test_evaluate_writes_the_bound_and_the_iekf(tmp_path, capsys):
    common = ['--realizations', '2', '--root', str(tmp_path / 'data'),
              '--out', str(tmp_path), '--quiet', '--scenario',
              str(tmp_path / 'tiny.json')]
    from tg_nebp.io import write_json
    import dataclasses
    write_json(tmp_path / 'tiny.json',
               {k: v for k, v in dataclasses.asdict(
                   tiny_scenario(steps=3)).items()})
    assert main(['evaluate', '--method', 'pcrb', *common]) == 0
    assert main(['evaluate', '--method', 'iekf', '--marginal', *common]) == 0
    out = capsys.readouterr().out
    assert 'pcrb: RMSE floor' in out and 'iekf-marginal: RMSE' in out
    written = read_json(tmp_path / 'metrics.json')
    assert written['pcrb']['accept']['0.95'] == 0.95
    assert written['iekf-marginal']['marginal'] is True
    assert written['iekf-marginal']['iterations'] == 5
    assert written['pcrb']['rmse'] < written['iekf-marginal']['rmse']


@pytest.mark.parametrize('changes,message', [
    (dict(batch_size=0), "'batch_size' must be positive, got 0"),
    (dict(batch_size=1.5), "'batch_size' must be an integer"),
    (dict(device='cuda:99'), "'device' is 'cuda:99', but"),
])
def test_a_bad_batch_size_or_device_is_named(changes, message):
    from tg_nebp.bounds import PosteriorCRB
    from tg_nebp.evaluation import bound_dataset
    data = [tiny_scenario(steps=2).generate(gen(0))]
    for run in (lambda: track_dataset(ParticleBP(8), data, **changes),
                lambda: bound_dataset(PosteriorCRB(), data, **changes)):
        with pytest.raises((ValueError, TypeError), match=message):
            run()
