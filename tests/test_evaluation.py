r"""Tests of :mod:`tg_nebp.evaluation`."""
import torch

from tg_nebp import ParticleBP
from tg_nebp.evaluation import track_dataset

from helpers import gen, tiny_scenario


def test_results_do_not_depend_on_the_batch_size():
    # every realization draws from its own stream (derive_seed(seed, r))
    data = [tiny_scenario(steps=3).generate(gen(r)) for r in range(5)]
    tracker = ParticleBP(32)
    one = track_dataset(tracker, data, batch_size=1, seed=7)
    for batch_size in (2, 5):
        other = track_dataset(tracker, data, batch_size=batch_size, seed=7)
        # per realization and step the agents' entries, in another order
        assert torch.allclose(one['errors'].sort().values,
                              other['errors'].sort().values, atol=1e-5)
    assert torch.equal(one['first_mean'], track_dataset(
        tracker, data, batch_size=2, seed=7)['first_mean'])


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
