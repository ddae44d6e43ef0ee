r"""Tests of :mod:`tg_nebp.threads`: the governor's decisions from given
readings, the restored thread count, the bit-identical results of particle
BP and of the Gaussian methods at 1 and 2 threads (what makes governing
their threads safe), and
:obj:`--threads` on the command line."""
import sys

import pytest
import torch

from tg_nebp import GaussianBP, ParticleBP
from tg_nebp.bounds import PosteriorCRB
from tg_nebp.filters import CentralizedIEKF
from tg_nebp.cli import main
from tg_nebp.threads import ThreadGovernor, runnable_elsewhere

from helpers import gen, tiny_scenario


@pytest.fixture
def threads():
    initial = torch.get_num_threads()
    yield
    torch.set_num_threads(initial)


def governor(readings, **options):
    values = iter(readings)
    return ThreadGovernor(read=lambda: next(values), **options)


def test_threads_follow_the_free_cores(threads):
    torch.set_num_threads(4)
    g = governor([0, 3, 3, 3, 3, 0, 0, 0], cores=4, smoothing=1.0,
                 patience=2)
    assert g.threads == torch.get_num_threads() == 4  # idle: all
    assert g.update() == 4  # 3 others busy: asked once, not yet
    assert g.update() == 1 == torch.get_num_threads()  # asked twice
    assert g.update() == 1 and g.update() == 1
    assert g.update() == 1  # idle again: asked once
    assert g.update() == 4 == torch.get_num_threads()
    g.close()
    assert torch.get_num_threads() == 4


def test_a_passing_process_does_not_change_the_count(threads):
    torch.set_num_threads(2)
    g = governor([0, 2, 0, 2, 0, 2, 0], cores=2, smoothing=1.0, patience=2)
    assert [g.update() for _ in range(6)] == [2] * 6


def test_the_running_mean_and_the_bounds(threads):
    torch.set_num_threads(1)
    # 8 cores, others 2 then 6: the mean moves by a third of each step
    g = governor([2] + [6] * 10, cores=8, max_threads=4, smoothing=1 / 3,
                 patience=1)
    assert g.threads == 4  # 8 - 2 = 6, capped at max_threads
    counts = [g.update() for _ in range(10)]
    assert counts[0] == 4  # mean 3.33: 5 free, capped
    assert counts[-1] == 2 and min(counts) >= 2  # mean -> 6: 2 free
    g.close()
    with governor([9], cores=2) as g:
        assert g.threads == 1  # never below one
    assert torch.get_num_threads() == 1


def test_an_unreadable_load_leaves_the_count(threads):
    torch.set_num_threads(2)
    g = governor([None, None], cores=8)
    assert g.threads == 2 and g.update() == 2
    with pytest.raises(ValueError, match='patience'):
        ThreadGovernor(patience=0)


@pytest.mark.skipif(not sys.platform.startswith('linux'),
                    reason='/proc is Linux')
def test_runnable_elsewhere_reads_proc():
    value = runnable_elsewhere()
    assert isinstance(value, int) and value >= 0


@pytest.mark.parametrize('options', [
    dict(num_particles=300),
    dict(num_particles=300, num_samples=8, regularize='silverman'),
    dict(num_particles=300, resampler='systematic', ess_threshold=0.5),
])
def test_bp_is_bit_identical_at_one_and_two_threads(threads, options):
    # why --threads auto is BP's default: the count changes the speed only
    data = tiny_scenario(steps=6).grown(30).generate(gen(3))
    runs = []
    for count in (1, 2):
        torch.set_num_threads(count)
        runs.append([(s.mean, s.log_weights) for s in ParticleBP(
            **options).steps(data, gen(5))])
    for (mean1, log1), (mean2, log2) in zip(*runs):
        assert torch.equal(mean1, mean2) and torch.equal(log1, log2)


@pytest.mark.parametrize('method', [
    GaussianBP.recommended, CentralizedIEKF, PosteriorCRB,
    lambda: CentralizedIEKF(marginal=True)], ids=['gbp', 'iekf', 'pcrb',
                                                  'iekf-marginal'])
def test_gaussian_methods_are_bit_identical_at_one_and_two_threads(
        threads, method):
    # why --threads auto is their default too
    data = tiny_scenario(steps=4).grown(30).generate(gen(3))
    runs = []
    for count in (1, 2):
        torch.set_num_threads(count)
        runs.append(method()(data))
    first, second = runs
    if isinstance(first, torch.Tensor):  # the bound's covariances
        assert torch.equal(first, second)
    else:
        assert torch.equal(first.mean, second.mean)
        assert torch.equal(first.cov, second.cov)


def test_cli_threads(tmp_path, capsys, threads):
    torch.set_num_threads(2)
    argv = ['evaluate', '--particles', '16', '--realizations', '1',
            '--root', str(tmp_path / 'data'), '--out', str(tmp_path),
            '--quiet']
    assert main(argv + ['--threads', '1']) == 0
    assert torch.get_num_threads() == 2  # restored
    assert main(argv + ['--threads', 'auto']) == 0
    assert torch.get_num_threads() == 2
    capsys.readouterr()
    assert main(['train', '--threads', 'auto', '--out',
                 str(tmp_path / 't')]) == 2
    err = capsys.readouterr().err
    assert err.startswith('error: --threads auto is for BP runs')
    assert err.count('\n') == 1


def test_threads_in_force_sets_and_restores():
    from tg_nebp.threads import threads_in_force
    initial = torch.get_num_threads()
    with threads_in_force(1) as governor:
        assert governor is None and torch.get_num_threads() == 1
    assert torch.get_num_threads() == initial
    with threads_in_force('auto', 'cuda') as governor:  # no governor on GPU
        assert governor is None
    with threads_in_force('auto') as governor:
        assert isinstance(governor, ThreadGovernor)
    assert torch.get_num_threads() == initial


def test_counts_given_are_used_or_refused():
    # 0 was taken as "not given" (the current count, all cores)
    from tg_nebp.threads import threads_in_force
    for options, message in ((dict(max_threads=0), "'max_threads' must be "
                              "positive, got 0"),
                             (dict(cores=0), "'cores' must be positive")):
        with pytest.raises(ValueError, match=message):
            ThreadGovernor(read=lambda: 0, **options)
    for threads, error in ((0, ValueError), (True, TypeError),
                           ('many', TypeError)):
        with pytest.raises(error, match="'threads' must be"):
            with threads_in_force(threads):
                pass
