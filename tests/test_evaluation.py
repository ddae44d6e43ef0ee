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
