r"""The acceptance test of the open model layer: a likelihood and a motion
model defined here, in a test module and not in the library, work
everywhere: data generation, datasets, BP tracking, NEBP training,
checkpoints and evaluation. No library file knows them."""
import math

import torch

from tg_nebp import (NEBP, CooperativeLocalizationDataset, MotionModel,
                     ParticleBP, RangeModel)
from tg_nebp.data.validation import check_number
from tg_nebp.evaluation import summarize, track_dataset
from tg_nebp.models import redraw_negative
from tg_nebp.training import load_checkpoint, nebp_from_checkpoint, train

from helpers import gen, tiny_scenario


class LaplaceRange(RangeModel, name='test-laplace-range'):
    r"""Laplace range noise: :math:`\log p(z | d) = -|z - d| / b - \log
    2b`."""
    def __init__(self, scale=0.8, max_range=20.0):
        super().__init__(max_range)
        self.scale = check_number(scale, 'scale')

    def params(self):
        return dict(scale=self.scale, max_range=self.max_range)

    def log_likelihood_of_distance(self, z, distances):
        return -(z[:, :1] - distances).abs() / self.scale - math.log(
            2 * self.scale)

    def sample_ranges(self, distances, link_state=None, edge_index=None,
                      generator=None):
        def noise(shape):
            u = torch.rand(shape, dtype=distances.dtype,
                           generator=generator) - 0.5
            return -self.scale * u.sign() * torch.log1p(-2 * u.abs())

        return redraw_negative(noise, distances).view(-1, 1)


class Drift(MotionModel, name='test-drift'):
    r"""Positions drift by a constant velocity plus Gaussian noise; the
    velocity stays."""
    def __init__(self, sigma=0.1):
        self.sigma = check_number(sigma, 'sigma')

    def params(self):
        return dict(sigma=self.sigma)

    def sample(self, states, generator=None):
        noise = torch.randn(states.shape[:-1] + (2, ), dtype=states.dtype,
                            device=states.device, generator=generator)
        return torch.cat([states[..., :2] + states[..., 2:] +
                          self.sigma * noise, states[..., 2:]], -1)


def test_own_models_work_everywhere(tmp_path):
    scenario = tiny_scenario(steps=4).replace(
        name='tiny-laplace', motion=Drift(0.1),
        measurement=LaplaceRange(0.8))
    # generation and the dataset: the configuration is in the file name hash
    data = CooperativeLocalizationDataset(str(tmp_path), scenario, 4, seed=0,
                                          log=False)
    assert scenario.measurement == {'name': 'test-laplace-range',
                                    'params': {'scale': 0.8,
                                               'max_range': 20.0}}
    assert scenario.fingerprint() in data.processed_paths[0]
    again = CooperativeLocalizationDataset(str(tmp_path), scenario, 4,
                                           seed=0, log=False)
    assert torch.equal(again[3].edge_attr, data[3].edge_attr)
    # the ranges follow the Laplace model: mean |z - d| = b
    first = data[0]
    d = (first.states[first.edge_index[0], first.edge_time, :2] -
         first.states[first.edge_index[1], first.edge_time, :2]).norm(dim=-1)
    assert abs(float((first.edge_attr[:, 0] - d).abs().mean()) - 0.8) < 0.4
    # BP with the user's models
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model)
    bp = ParticleBP(64, **models)
    bp_result = track_dataset(bp, data, batch_size=2, seed=0)
    assert torch.isfinite(bp_result['errors']).all()
    # NEBP: a few training steps, a checkpoint, reloading and evaluation
    model = NEBP(64, message_dim=4, hidden_dim=8, **models)
    path = tmp_path / 'nebp.pt'
    before = [p.detach().clone() for p in model.parameters()]
    train(model, data, epochs=1, batch_size=2, lr=1e-2, checkpoint=path)
    assert any(not torch.equal(a, b.detach())
               for a, b in zip(before, model.parameters()))
    assert load_checkpoint(path)['config']['motion'] == {
        'name': 'test-drift', 'params': {'sigma': 0.1}}
    reloaded = nebp_from_checkpoint(path)
    assert isinstance(reloaded.motion, Drift)
    assert isinstance(reloaded.measurement, LaplaceRange)
    a = reloaded(data[0], gen(3)).mean
    b = model(data[0], gen(3)).mean
    assert torch.equal(a, b)
    entry = summarize(**{k: v for k, v in track_dataset(
        reloaded, data, batch_size=2, seed=0).items()
        if k in ('errors', 'nees')})
    assert 0 <= entry['outage']['1.0'] <= 1


def test_a_likelihood_of_the_wrong_shape_names_the_model_and_shape():
    class SummedRange(RangeModel, name='test-summed-range'):
        # sums over the particles: one number per link instead of K
        def params(self):
            return dict(max_range=self.max_range)

        def log_likelihood_of_distance(self, z, distances):
            return -(z[:, :1] - distances).square().sum(-1)

    data = tiny_scenario(steps=2).generate(gen(3))
    for grad in (False, True):
        with torch.set_grad_enabled(grad):
            try:
                ParticleBP(8, measurement=SummedRange())(data, gen(4))
            except ValueError as e:
                message = str(e)
        assert message.startswith('the measurement model SummedRange(') and \
            'of shape [' in message and ', 8], one per link and particle' \
            in message
