r"""Tests of the model roles (:mod:`tg_nebp.models.base`): the registry and
configurations, and the gate that keeps a subclass's formula away from its
parent's fast pieces."""
import pytest
import torch

import tg_nebp.nn.conv.particle_bp_conv as conv_module
from tg_nebp.models import (MODELS, ConstantVelocity, ConstantVelocityDrag,
                            GaussianRange, NLOSRange, RangeModel,
                            StudentTRange, model_from_config, model_like)
from tg_nebp.nn.conv import ParticleBPConv

from helpers import gen, random_graph

LIBRARY_MODELS = [
    ('motion', ConstantVelocityDrag(0.1, 0.02, 0.5)),
    ('motion', ConstantVelocity(0.2, 2.0)),
    ('measurement', GaussianRange(0.7, 15.0)),
    ('measurement', StudentTRange(0.5, 4.0, 25.0)),
    ('measurement', NLOSRange(1.0, 0.3, 2.0, oracle=True, max_range=30.0)),
]


@pytest.mark.parametrize('role,model', LIBRARY_MODELS,
                         ids=[type(m).__name__ for _, m in LIBRARY_MODELS])
def test_configuration_round_trip(role, model):
    config = model.config()
    assert set(config) == {'name', 'params'}
    assert MODELS[role][config['name']] is type(model)
    rebuilt = model_from_config(config, role)
    assert type(rebuilt) is type(model) and rebuilt == model
    assert rebuilt.params() == model.params()


def test_unknown_or_malformed_configuration():
    with pytest.raises(ValueError, match=r"unknown measurement model 'laser'; "
                       r"registered: \[.*'gaussian'.*\] \(import the module"):
        model_from_config({'name': 'laser', 'params': {}}, 'measurement')
    with pytest.raises(ValueError, match=r"must be \{'name'"):
        model_from_config({'name': 'gaussian'}, 'measurement')
    with pytest.raises(ValueError, match=r"measurement model 'gaussian': .*"
                       r"unexpected keyword argument 'colour'"):
        model_from_config({'name': 'gaussian', 'params': {'colour': 1}},
                          'measurement')


def test_a_taken_name_is_refused():
    with pytest.raises(ValueError, match="name 'gaussian' is taken"):
        class Other(RangeModel, name='gaussian'):
            pass


def test_subclass_without_a_name_cannot_be_stored():
    # it would be stored, and rebuilt, as its parent
    with pytest.raises(ValueError, match='Doubled has no registered name of '
                       'its own'):
        Doubled().config()


class Doubled(GaussianRange):
    r"""Overrides the likelihood only: the Gaussian's fast pieces compute
    another formula and must stay closed."""
    def log_likelihood_of_distance(self, z, distances):
        return 2 * super().log_likelihood_of_distance(z, distances)


def test_fast_pieces_follow_the_formula():
    for piece in ('log_likelihood_of_distance_', 'distance_gradient',
                  'fused_log_pdf'):
        assert GaussianRange().provides(piece)
        assert not Doubled().provides(piece)
    assert not StudentTRange().provides('distance_gradient')


@pytest.mark.parametrize('grad', [False, True])
def test_subclass_never_reaches_the_parents_fast_path(monkeypatch, grad):
    # pretend CUDA: the fused kernel is then chosen for the Gaussian only
    calls = []

    def fused(pos_x, pos_y, sender, ranges, src, ptr, log_pdf, constants):
        calls.append(log_pdf)
        raise AssertionError('the fused kernel computes the Gaussian')

    monkeypatch.setattr(conv_module, 'fused_bp_available', lambda t: True)
    monkeypatch.setattr(conv_module, 'fused_bp_segment_sum', fused)
    particles, lw, ei, ea, anchor = random_graph(gen(5), 5, 2, 6,
                                                 dtype=torch.float32)
    particles.requires_grad_(grad)
    conv = ParticleBPConv(Doubled(), chunk_size=3)
    out, _ = conv(particles, lw, ei, ea, anchor=anchor,
                  return_messages=False)
    assert not calls
    # the subclass's own formula, as the materialized messages give it
    expected, _ = ParticleBPConv(Doubled())(particles, lw, ei, ea,
                                            anchor=anchor)
    gaussian, _ = ParticleBPConv(GaussianRange())(particles, lw, ei, ea,
                                                  anchor=anchor)
    torch.testing.assert_close(out, expected)
    assert not torch.allclose(out, gaussian)
    if not grad:
        with pytest.raises(AssertionError, match='fused kernel'):
            ParticleBPConv(GaussianRange())(particles, lw, ei, ea,
                                            anchor=anchor,
                                            return_messages=False)
        assert calls == [GaussianRange.fused_log_pdf]


def test_model_like_keeps_shared_parameters():
    nlos = NLOSRange(0.7, 0.3, 2.0, max_range=15.0)
    gaussian = model_like('gaussian', 'measurement', nlos)
    assert gaussian == GaussianRange(0.7, 15.0)
    assert model_like('nlos', 'measurement', nlos) is nlos
    assert model_like('student-t', 'measurement', gaussian) == StudentTRange(
        0.7, 3.0, 15.0)  # nu: the model's default
    with pytest.raises(ValueError, match="unknown measurement model 'x'"):
        model_like('x', 'measurement', nlos)


@pytest.mark.parametrize('config, role, message', [
    ({'name': 'gaussian', 'params': {}}, 'sensor',
     "unknown model role 'sensor'; the roles are"),
    ({'name': ['gaussian'], 'params': {}}, 'measurement',
     "must be {'name': <str>"),
    ({'name': 'gaussian', 'params': {'sigma': 'one'}}, 'measurement',
     "'sigma' must be a number"),
])
def test_model_from_config_errors_name_the_field(config, role, message):
    from tg_nebp.models import model_from_config
    with pytest.raises((ValueError, TypeError), match=message):
        model_from_config(config, role)
