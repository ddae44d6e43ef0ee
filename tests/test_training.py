r"""Tests of :mod:`tg_nebp.training`: learning, checkpoints (round trip,
refusal of foreign, malicious and mismatched files) and bitwise resume."""
import copy
import json
import math
import os
import pickle
import shlex

from pathlib import Path

import pytest
import torch
from torch_geometric.data import Batch

from tg_nebp.datasets import Scenario
from tg_nebp.filters import (NEBP, FixedLagGaussianNEBP, GaussianNEBP,
                             StepOutput)
from tg_nebp.training import (CHECKPOINT_VERSION, PRETRAINED, adam,
                              checkpoint_base, checkpoint_path,
                              gaussian_nebp_from_checkpoint,
                              gaussian_step_loss, load_checkpoint,
                              nebp_from_checkpoint, position_loss,
                              save_checkpoint, step_loss,
                              tracker_from_checkpoint, train)
from tg_nebp.utils import weighted_moments

from helpers import (embed_in_3d, gen, loads_after_bit_flips,
                     mixed_k_checkpoint, tiny_scenario)

SMALL = dict(message_dim=8, hidden_dim=16)


def tiny_data(count, steps=2, offset=0):
    scenario = tiny_scenario(steps)
    return [scenario.generate(gen(offset + i)) for i in range(count)]


def make_model(seed=0, num_particles=16, **kwargs):
    torch.manual_seed(seed)
    return NEBP(num_particles=num_particles, **{**SMALL, **kwargs})


def states_equal(a, b):
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# --------------------------------------------------------------------------
# 1. the loss and learning
# --------------------------------------------------------------------------

def test_position_loss_against_loops():
    g = gen(0)
    mean = torch.randn(5, 4, generator=g, dtype=torch.float64)
    states = torch.randn(5, 3, 4, generator=g, dtype=torch.float64)
    anchor = torch.tensor([False, True, False, False, True])
    expected = 0.0
    for i in range(5):
        if not bool(anchor[i]):
            expected += (float(mean[i, 0]) - float(states[i, 2, 0]))**2
            expected += (float(mean[i, 1]) - float(states[i, 2, 1]))**2
    assert math.isclose(float(position_loss(mean, states, 2, anchor)),
                        expected, rel_tol=1e-12)
    # an agent without ground truth (its states NaN) is not scored
    expected -= sum((float(mean[3, c]) - float(states[3, 2, c]))**2
                    for c in range(2))
    states[3] = math.nan
    assert math.isclose(float(position_loss(mean, states, 2, anchor)),
                        expected, rel_tol=1e-12)


# the equivariant layer's per-particle offsets are noisier at 1e-2
@pytest.mark.parametrize('variant,lr', [('paper', 1e-2),
                                        ('equivariant', 3e-3)])
def test_adam_steps_on_a_fixed_snapshot_lower_the_loss(variant, lr):
    data = Scenario.load('paper_train').replace(num_steps=2).generate(gen(0))
    K = 32
    model = make_model(0, K, message_dim=16, hidden_dim=32, variant=variant)
    g = gen(1)
    particles = model.predict(model.sample_prior(data, g), data.anchor, g)
    lw = torch.full(particles.shape[:2], -math.log(K))
    edge_index, edge_attr = data.edges_by_step()[1]
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    losses = []
    for _ in range(20):
        new = model.update(particles, lw, edge_index, edge_attr, data.anchor)
        mean, _ = weighted_moments(particles, new)
        loss = position_loss(mean, data.states, 1, data.anchor)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    with torch.no_grad():
        new = model.update(particles, lw, edge_index, edge_attr, data.anchor)
        final = float(position_loss(weighted_moments(particles, new)[0],
                                    data.states, 1, data.anchor))
    assert final < 0.8 * losses[0], (losses[0], final)


def test_train_history_and_progress():
    data = tiny_data(3, steps=2)
    model = make_model(1)
    before = copy.deepcopy(model.state_dict())
    calls = []
    history = train(model, data, data[:1], epochs=2, batch_size=2, lr=1e-2,
                    seed=0, progress=calls.append)
    assert [h['epoch'] for h in history] == [0, 1]
    # 2 batches (2 + 1 realizations) x 2 time steps per epoch
    assert [(c['epoch'], c['step']) for c in calls] == \
        [(e, s) for e in range(2) for s in range(1, 5)]
    agents = [6, 6, 3, 3]  # agents per step of the 2- and 1-graph batches
    for epoch in range(2):
        losses = [c['loss'] for c in calls if c['epoch'] == epoch]
        mean = sum(l * a for l, a in zip(losses, agents)) / sum(agents)
        assert math.isclose(history[epoch]['train_loss'], mean,
                            rel_tol=1e-6)
        assert math.isfinite(history[epoch]['val_loss'])
    assert not states_equal(before, model.state_dict())
    assert math.isnan(train(make_model(1), data, epochs=1,
                            batch_size=3)[0]['val_loss'])


def test_train_rejects_bad_arguments():
    data = tiny_data(1)
    for kwargs in (dict(epochs=0), dict(batch_size=0), dict(lr=0.0)):
        with pytest.raises(ValueError):
            train(make_model(), data, **kwargs)


def test_train_is_deterministic():
    data = tiny_data(2)
    a, b = make_model(2), make_model(2)
    ha = train(a, data, epochs=1, batch_size=1, lr=1e-2, seed=5)
    hb = train(b, data, epochs=1, batch_size=1, lr=1e-2, seed=5)
    assert states_equal(a.state_dict(), b.state_dict())
    assert ha[0]['train_loss'] == hb[0]['train_loss']
    c = make_model(2)
    train(c, data, epochs=1, batch_size=1, lr=1e-2, seed=6)
    assert not states_equal(a.state_dict(), c.state_dict())


# --------------------------------------------------------------------------
# 2. checkpoints
# --------------------------------------------------------------------------

def test_checkpoint_round_trip(tmp_path):
    model = make_model(3, num_particles=24, num_iterations=2,
                       correct_anchor_edges=True, resampler='systematic')
    # trained a little so the state is not the default initialization
    train(model, tiny_data(1), epochs=1, batch_size=1, lr=1e-2)
    path = tmp_path / 'model.pt'
    save_checkpoint(path, model)
    state = load_checkpoint(path)
    assert state['version'] == CHECKPOINT_VERSION
    assert state['config'] == model.config()
    rebuilt = nebp_from_checkpoint(path)
    assert rebuilt.config() == model.config()
    assert states_equal(rebuilt.state_dict(), model.state_dict())
    assert states_equal(nebp_from_checkpoint(path, num_particles=24)
                        .state_dict(), model.state_dict())
    data = tiny_data(1, steps=3, offset=10)[0]
    with torch.no_grad():
        a = model(data, gen(7))
        b = rebuilt(data, gen(7))
        other = make_model(4, num_particles=24, num_iterations=2,
                           correct_anchor_edges=True,
                           resampler='systematic')(data, gen(7))
    assert torch.equal(a.mean, b.mean) and torch.equal(a.cov, b.cov)
    assert not torch.equal(a.mean, other.mean)  # the weights matter


def test_a_checkpoint_with_non_finite_weights_is_refused_by_name(tmp_path):
    # a network whose training diverged would track nothing but NaN
    for make, load in ((make_model, nebp_from_checkpoint),
                       (make_gaussian, gaussian_nebp_from_checkpoint)):
        model = make()
        name, parameter = next(iter(model.named_parameters()))
        with torch.no_grad():
            parameter.view(-1)[0] = math.nan
        path = tmp_path / 'diverged.pt'
        save_checkpoint(path, model)
        with pytest.raises(ValueError, match=f"parameter '{name}' holds "
                           f"non-finite values"):
            load(path)


def test_a_checkpoint_with_a_bit_flipped_is_refused_or_unchanged(tmp_path):
    # 300 single bits flipped at seeded places: each file is refused
    # whole, or its weights and configuration load exactly as saved
    path = tmp_path / 'model.pt'
    save_checkpoint(path, make_gaussian())
    expected = load_checkpoint(path)
    refused, loaded = loads_after_bit_flips(path, load_checkpoint, 300, 8)
    for place, state in loaded:
        assert states_equal(state['model'], expected['model']), place
        assert state['config'] == expected['config'], place
    assert refused > 200


def test_checkpoint_with_other_k_is_refused(tmp_path):
    path = tmp_path / 'model.pt'
    save_checkpoint(path, make_model(num_particles=16))
    with pytest.raises(ValueError) as info:
        nebp_from_checkpoint(path, num_particles=40)
    assert '16' in str(info.value) and '40' in str(info.value)


def test_equivariant_checkpoint_round_trips_and_runs_at_any_k(tmp_path):
    model = make_model(5, num_particles=16, variant='equivariant',
                       particle_dim=6)
    train(model, tiny_data(1), epochs=1, batch_size=1, lr=1e-2)
    path = tmp_path / 'model.pt'
    save_checkpoint(path, model)
    state = load_checkpoint(path)
    assert state['config']['variant'] == 'equivariant'
    assert state['config']['particle_dim'] == 6
    rebuilt = nebp_from_checkpoint(path)
    assert rebuilt.config() == model.config()
    assert states_equal(rebuilt.state_dict(), model.state_dict())
    data = tiny_data(1, steps=3, offset=10)[0]
    with torch.no_grad():
        a, b = model(data, gen(7)), rebuilt(data, gen(7))
    assert torch.equal(a.mean, b.mean) and torch.equal(a.cov, b.cov)
    # the same weights at another K
    wider = nebp_from_checkpoint(path, num_particles=40)
    assert wider.num_particles == 40
    assert states_equal(wider.state_dict(), model.state_dict())
    with torch.no_grad():
        out = wider(data, gen(7))
    assert bool(torch.isfinite(out.mean).all())


def test_version_2_checkpoints_are_the_paper_variant(tmp_path):
    model = make_model(6)
    path = tmp_path / 'model.pt'
    save_checkpoint(path, model)
    state = torch.load(path, weights_only=True)
    state['version'] = 2
    del state['config']['variant']
    torch.save(state, path)
    rebuilt = nebp_from_checkpoint(path)
    assert rebuilt.variant == 'paper'
    assert states_equal(rebuilt.state_dict(), model.state_dict())


def test_checkpoint_with_wrong_version_is_refused(tmp_path):
    path = tmp_path / 'model.pt'
    save_checkpoint(path, make_model())
    state = torch.load(path, weights_only=True)
    for version in (CHECKPOINT_VERSION + 1, 1, 0, None):
        state['version'] = version
        torch.save(state, path)
        with pytest.raises(ValueError, match='version'):
            load_checkpoint(path)
        with pytest.raises(ValueError, match='version'):
            nebp_from_checkpoint(path)


def test_checkpoint_with_foreign_weights_is_refused(tmp_path):
    path = tmp_path / 'model.pt'
    save_checkpoint(path, make_model(num_particles=16))
    state = torch.load(path, weights_only=True)
    state['model'] = {k: torch.zeros(1) for k in state['model']}
    torch.save(state, path)
    with pytest.raises(ValueError):
        nebp_from_checkpoint(path)
    del state['model']
    torch.save(state, path)
    with pytest.raises(ValueError, match='model'):
        load_checkpoint(path)


def _foreign_files(tmp_path):
    random_bytes = bytes(torch.randint(0, 256, (512, ), generator=gen(0),
                                       dtype=torch.uint8).tolist())
    (tmp_path / 'random.pt').write_bytes(random_bytes)
    (tmp_path / 'config.json').write_text(json.dumps({'format': 'x'}))
    torch.save({'model': {'w': torch.zeros(2)}, 'version': 1},
               tmp_path / 'plain.pt')
    torch.save([1, 2, 3], tmp_path / 'list.pt')
    (tmp_path / 'empty.pt').write_bytes(b'')
    good = tmp_path / 'good.pt'
    save_checkpoint(good, make_model())
    (tmp_path / 'truncated.pt').write_bytes(good.read_bytes()[:300])
    # a complete checkpoint but for its format key: absent, then foreign
    state = torch.load(good, weights_only=True)
    del state['format']
    torch.save(state, tmp_path / 'no_format.pt')
    state['format'] = 'someone.else'
    torch.save(state, tmp_path / 'other_format.pt')
    return ['random.pt', 'config.json', 'plain.pt', 'list.pt', 'empty.pt',
            'truncated.pt', 'missing.pt', 'no_format.pt', 'other_format.pt']


def test_foreign_files_are_refused(tmp_path):
    for name in _foreign_files(tmp_path):
        with pytest.raises(ValueError):
            load_checkpoint(tmp_path / name)
        with pytest.raises(ValueError):
            nebp_from_checkpoint(tmp_path / name)


@pytest.mark.parametrize('payload', [
    b'\x80\x02t.',  # TUPLE without MARK: IndexError
    b'\x80\x02h\x05.',  # BINGET of a missing memo entry: KeyError
])
def test_malformed_pickle_streams_are_refused(tmp_path, payload):
    path = tmp_path / 'bad.pt'
    path.write_bytes(payload)
    with pytest.raises(ValueError):
        load_checkpoint(path)


def test_checkpoint_with_incomplete_config_is_refused(tmp_path):
    path = tmp_path / 'model.pt'
    save_checkpoint(path, make_model())
    state = torch.load(path, weights_only=True)
    del state['config']['motion']
    torch.save(state, path)
    with pytest.raises(ValueError):
        nebp_from_checkpoint(path)


class Exploit:
    r"""Runs a shell command when unpickled."""
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f'touch {shlex.quote(self.marker)}', ))


@pytest.mark.parametrize('writer', ['torch.save', 'pickle.dump',
                                    'inside a checkpoint'])
def test_code_executing_pickle_is_refused(tmp_path, writer):
    marker = tmp_path / 'MARKER'
    path = tmp_path / 'evil.pt'
    if writer == 'torch.save':
        torch.save(Exploit(marker), path)
    elif writer == 'pickle.dump':
        with open(path, 'wb') as f:
            pickle.dump(Exploit(marker), f, protocol=2)
    else:  # a genuine checkpoint with one malicious entry
        save_checkpoint(path, make_model())
        state = torch.load(path, weights_only=True)
        state['progress'] = {'history': Exploit(marker)}
        torch.save(state, path)
    with pytest.raises(ValueError) as info:
        load_checkpoint(path)
    # one line, without torch's colour codes and its advice to load the
    # file unsafely
    message = str(info.value)
    assert '\n' not in message and '\x1b' not in message
    assert 'weights_only=False' not in message and 'refused' in message
    with pytest.raises(ValueError):
        nebp_from_checkpoint(path)
    with pytest.raises(ValueError):
        train(make_model(), tiny_data(1), epochs=1, checkpoint=path,
              resume=True)
    assert not marker.exists()
    # the payload is real: an unsafe load would have run it
    if writer == 'pickle.dump':
        with open(path, 'rb') as f:
            pickle.load(f)
    else:
        torch.load(path, weights_only=False)
    assert marker.exists()


def test_save_is_atomic_and_leaves_no_temporary(tmp_path):
    path = tmp_path / 'sub' / 'model.pt'
    save_checkpoint(path, make_model())
    assert sorted(p.name for p in path.parent.iterdir()) == ['model.pt']

    class Boom(NEBP):
        def config(self):
            raise RuntimeError('boom')

    before = path.read_bytes()
    torch.manual_seed(0)
    with pytest.raises(RuntimeError):
        save_checkpoint(path, Boom(num_particles=16, **SMALL))
    assert path.read_bytes() == before
    assert sorted(p.name for p in path.parent.iterdir()) == ['model.pt']


# --------------------------------------------------------------------------
# 3. resume
# --------------------------------------------------------------------------

def test_resume_equals_uninterrupted_run(tmp_path):
    data = tiny_data(3, steps=2)
    val = tiny_data(1, steps=2, offset=50)
    kwargs = dict(batch_size=2, lr=1e-2, seed=11)
    full = make_model(5)
    initial = copy.deepcopy(full.state_dict())
    history = train(full, data, val, epochs=2,
                    checkpoint=tmp_path / 'full.pt', **kwargs)

    first = make_model(99)  # other init: loaded from the initial state
    first.load_state_dict(initial)
    part = train(first, data, val, epochs=1,
                 checkpoint=tmp_path / 'part.pt', **kwargs)
    after_one = copy.deepcopy(first.state_dict())
    assert part == history[:1]

    resumed = make_model(123)  # fresh, differently initialized
    resumed_history = train(resumed, data, val, epochs=2,
                            checkpoint=tmp_path / 'part.pt', resume=True,
                            **kwargs)
    assert states_equal(resumed.state_dict(), full.state_dict())
    assert resumed_history == history
    assert not states_equal(after_one, full.state_dict())  # epoch 2 trained
    assert not states_equal(initial, after_one)
    # the two final checkpoints agree, optimizer state included
    a = load_checkpoint(tmp_path / 'full.pt')
    b = load_checkpoint(tmp_path / 'part.pt')
    assert states_equal(a['model'], b['model'])
    for key, sa in a['optimizer']['state'].items():
        sb = b['optimizer']['state'][key]
        assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert a['progress']['history'] == b['progress']['history']


def test_resume_of_finished_run_changes_nothing(tmp_path):
    data = tiny_data(2)
    model = make_model(6)
    history = train(model, data, data[:1], epochs=1, batch_size=2,
                    lr=1e-2, checkpoint=tmp_path / 'm.pt')
    again = make_model(7)
    assert train(again, data, data[:1], epochs=1, batch_size=2, lr=1e-2,
                 checkpoint=tmp_path / 'm.pt', resume=True) == history
    assert states_equal(again.state_dict(), model.state_dict())


def test_resume_with_other_config_is_refused(tmp_path):
    data = tiny_data(1)
    path = tmp_path / 'm.pt'
    train(make_model(8), data, epochs=1, checkpoint=path)
    for other in (make_model(8, hidden_dim=8),
                  make_model(8, correct_anchor_edges=True),
                  make_model(8, num_particles=12),
                  make_model(8, resampler='systematic')):
        with pytest.raises(ValueError, match='configuration'):
            train(other, data, epochs=2, checkpoint=path, resume=True)


def test_resume_without_checkpoint_is_refused(tmp_path):
    data = tiny_data(1)
    with pytest.raises(ValueError):
        train(make_model(), data, epochs=1, resume=True)
    with pytest.raises(ValueError):
        train(make_model(), data, epochs=1, resume=True,
              checkpoint=tmp_path / 'absent.pt')
    assert not (tmp_path / 'absent.pt').exists()


@pytest.mark.parametrize('change', [dict(seed=5), dict(batch_size=1),
                                    dict(lr=1e-3)])
def test_resume_with_other_run_settings_is_refused(tmp_path, change):
    data = tiny_data(2)
    settings = dict(epochs=2, batch_size=2, lr=1e-4, seed=0)
    path = tmp_path / 'run.pt'
    train(make_model(), data, epochs=1, batch_size=2, lr=1e-4, seed=0,
          checkpoint=path)
    with pytest.raises(ValueError, match=next(iter(change))):
        train(make_model(), data, checkpoint=path, resume=True,
              **{**settings, **change})


def test_checkpoint_of_other_shapes_is_refused_on_one_line(tmp_path):
    path = mixed_k_checkpoint(tmp_path / 'mixed.pt')
    with pytest.raises(ValueError, match=r"does not match the NEBP model: "
                       r".*size mismatch") as info:
        nebp_from_checkpoint(path)
    assert '\n' not in str(info.value) and '\t' not in str(info.value)


def test_optimizer_and_loss_can_be_replaced():
    data = tiny_data(2)
    calls = []

    def counted_loss(step, batch):
        calls.append(step.t)
        return step_loss(step, batch)

    # a zero learning rate leaves the parameters where they are
    model = make_model()
    before = copy.deepcopy(model.state_dict())
    train(model, data, epochs=1, batch_size=1,
          optimizer=lambda p: torch.optim.SGD(p, lr=0.0), loss=counted_loss)
    assert states_equal(model.state_dict(), before)
    assert calls == [0, 1, 0, 1]  # one loss per time step of every batch
    # the default is the paper's Adam with 'lr' on step_loss
    a, b = make_model(), make_model()
    train(a, data, epochs=1, batch_size=1, lr=1e-3)
    train(b, data, epochs=1, batch_size=1, optimizer=adam(1e-3),
          loss=step_loss)
    assert states_equal(a.state_dict(), b.state_dict())


@pytest.mark.parametrize('drop', ['variant', 'position_dim'])
def test_older_checkpoints_resume_as_what_they_meant(tmp_path, drop):
    # version 2 lacks the variant (the paper's), checkpoints from before
    # 3-D lack position_dim (2-D): both resume, to the uninterrupted run
    data = tiny_data(2)
    path = tmp_path / 'm.pt'
    whole = make_model(6)
    history = train(whole, data, data[:1], epochs=2, batch_size=2, lr=1e-2,
                    checkpoint=tmp_path / 'whole.pt')
    train(make_model(6), data, data[:1], epochs=1, batch_size=2, lr=1e-2,
          checkpoint=path)
    state = torch.load(path, weights_only=True)
    del state['config'][drop]
    if drop == 'variant':
        state['version'] = 2
    torch.save(state, path)
    resumed = make_model(7)
    assert train(resumed, data, data[:1], epochs=2, batch_size=2, lr=1e-2,
                 checkpoint=path, resume=True) == history
    assert states_equal(resumed.state_dict(), whole.state_dict())


@pytest.mark.parametrize('damage, message', [
    (lambda h: h[0].pop('val_loss'), "no number 'val_loss'"),
    (lambda h: h[0].update(train_loss='low'), "no number 'train_loss'"),
    (lambda h: h.__setitem__(0, 'epoch 0'), "no number 'epoch'"),
    (lambda h: h[0].update(epoch=3), 'is epoch 3'),
])
def test_a_damaged_history_is_one_clear_error(tmp_path, damage, message):
    data = tiny_data(2)
    path = tmp_path / 'm.pt'
    train(make_model(6), data, data[:1], epochs=1, batch_size=2, lr=1e-2,
          checkpoint=path)
    state = torch.load(path, weights_only=True)
    damage(state['progress']['history'])
    torch.save(state, path)
    with pytest.raises(ValueError, match=f"m.pt': .*{message}"):
        train(make_model(6), data, data[:1], epochs=2, batch_size=2,
              lr=1e-2, checkpoint=path, resume=True)


def test_a_checkpoint_without_optimizer_state_is_not_resumed(tmp_path):
    data = tiny_data(2)
    path = tmp_path / 'm.pt'
    model = make_model(6)
    save_checkpoint(path, model, progress=dict(seed=0, batch_size=2,
                                               lr=1e-2, history=[]))
    with pytest.raises(ValueError, match='can be evaluated, not resumed'):
        train(make_model(6), data, epochs=1, batch_size=2, lr=1e-2,
              checkpoint=path, resume=True)


# --------------------------------------------------------------------------
# Gaussian NEBP: its loss, checkpoints of either base, resume
# --------------------------------------------------------------------------

def make_gaussian(seed=0, **kwargs):
    torch.manual_seed(seed)
    return GaussianNEBP(**{'hidden_dim': 8, 'num_iterations': 5, **kwargs})


def test_gaussian_step_loss_is_the_negative_log_likelihood_plus_error():
    g = gen(3)
    count = 5
    mean = torch.randn(count, 4, generator=g, dtype=torch.float64)
    root = torch.randn(count, 4, 4, generator=g, dtype=torch.float64)
    cov = root @ root.transpose(-1, -2) + 0.1 * torch.eye(4)
    states = torch.randn(count, 3, 4, generator=g, dtype=torch.float64)
    anchor = torch.tensor([False, True, False, False, True])
    batch = Batch(anchor=anchor, states=states)
    expected = 0.0
    for i in range(count):
        if bool(anchor[i]):
            continue
        normal = torch.distributions.MultivariateNormal(mean[i, :2],
                                                        cov[i, :2, :2])
        # log N without its constant log(2 pi)
        expected += -float(normal.log_prob(states[i, 1, :2])) - math.log(
            2 * math.pi)
        expected += float((mean[i, :2] - states[i, 1, :2]).square().sum())
    step = StepOutput(1, mean, cov)
    assert math.isclose(float(gaussian_step_loss(step, batch)), expected,
                        rel_tol=1e-12)


def test_gaussian_training_lowers_the_loss_and_resumes_exactly(tmp_path):
    data = tiny_data(4, steps=3)
    val = tiny_data(2, steps=3, offset=50)
    kwargs = dict(batch_size=2, lr=3e-3, seed=2, loss=gaussian_step_loss)
    full = make_gaussian(1)
    initial = copy.deepcopy(full.state_dict())
    history = train(full, data, val, epochs=3, checkpoint=tmp_path / 'a.pt',
                    **kwargs)
    assert history[-1]['val_loss'] < history[0]['val_loss']
    first = make_gaussian(9)
    first.load_state_dict(initial)
    train(first, data, val, epochs=1, checkpoint=tmp_path / 'b.pt', **kwargs)
    resumed = make_gaussian(17)
    resumed_history = train(resumed, data, val, epochs=3,
                            checkpoint=tmp_path / 'b.pt', resume=True,
                            **kwargs)
    assert states_equal(resumed.state_dict(), full.state_dict())
    assert resumed_history == history
    assert not states_equal(initial, full.state_dict())
    # a checkpoint of another configuration does not resume
    with pytest.raises(ValueError, match='configuration'):
        train(make_gaussian(1, hidden_dim=4), data, val, epochs=4,
              checkpoint=tmp_path / 'b.pt', resume=True, **kwargs)


def test_gaussian_checkpoint_round_trip_and_refusals(tmp_path):
    model = make_gaussian(2)
    train(model, tiny_data(1), epochs=1, batch_size=1, lr=1e-2,
          loss=gaussian_step_loss)
    path = tmp_path / 'gaussian.pt'
    save_checkpoint(path, model)
    rebuilt = gaussian_nebp_from_checkpoint(path)
    assert rebuilt.config() == model.config()
    assert states_equal(rebuilt.state_dict(), model.state_dict())
    assert isinstance(tracker_from_checkpoint(path), GaussianNEBP)
    data = tiny_data(1, steps=3, offset=10)[0]
    with torch.no_grad():
        assert torch.equal(model(data).mean, rebuilt(data).mean)
    # run-time options replace the iterations and the tolerance only; the
    # iteration feature keeps the scale the network was trained with
    longer = gaussian_nebp_from_checkpoint(path, tolerance=None,
                                           num_iterations=12)
    assert (longer.tolerance, longer.num_iterations) == (None, 12)
    assert longer.conv.num_iterations == model.num_iterations == 5
    for option in (dict(position_dim=3), dict(hidden_dim=4)):
        with pytest.raises(ValueError, match=f"'{next(iter(option))}' is "
                           f"fixed by the checkpoint"):
            gaussian_nebp_from_checkpoint(path, **option)
    # a configuration from before the iteration scale was recorded means
    # the iterations it was trained with
    old = dict(model.config())
    del old['iteration_scale']
    assert GaussianNEBP.from_config(old).config() == model.config()
    # the other base is refused by name, both ways
    with pytest.raises(ValueError, match=r"holds a gaussian NEBP, not a "
                       r"particle one: evaluate it with --method gnebp"):
        nebp_from_checkpoint(path)
    particle = tmp_path / 'particle.pt'
    save_checkpoint(particle, make_model())
    with pytest.raises(ValueError, match=r"holds a particle NEBP, not a "
                       r"gaussian one: evaluate it with --method nebp"):
        gaussian_nebp_from_checkpoint(particle)
    assert isinstance(tracker_from_checkpoint(particle), NEBP)
    # and so is a realization of another dimension
    with pytest.raises(ValueError, match=r'built for 2-D positions'):
        rebuilt(embed_in_3d(data))
    # an unknown base is named
    state = load_checkpoint(path)
    state['config']['base'] = 'kalman'
    torch.save(state, tmp_path / 'unknown.pt')
    with pytest.raises(ValueError, match=r"unknown base 'kalman'"):
        tracker_from_checkpoint(tmp_path / 'unknown.pt')
    with pytest.raises(ValueError, match=r"unknown base 'kalman'"):
        checkpoint_base(tmp_path / 'unknown.pt')
    assert (checkpoint_base(path), checkpoint_base(particle)) == (
        'gaussian', 'particle')


@pytest.mark.parametrize('name', PRETRAINED)
def test_pretrained_checkpoints_load_by_name_with_their_command(name):
    path = checkpoint_path(name)
    assert path.is_file() and path.parent.name == 'pretrained'
    tracker = gaussian_nebp_from_checkpoint(name)
    windowed = name.startswith('window')
    assert isinstance(tracker, (FixedLagGaussianNEBP if windowed else
                                GaussianNEBP))
    # trained: not the identity correction of an untrained one
    assert float(tracker.correction.weight_head.weight.detach().abs().sum(
    )) > 0
    readme = (path.parent / 'README.md').read_text()
    assert f'`{name}.pt`' in readme and 'tg-nebp train --base gaussian' \
        in readme
    # a file path is a path, not a name
    assert checkpoint_path(f'./{name}') == Path(f'./{name}')


@pytest.mark.parametrize('field, value', [('lag', 0), ('lag', -1),
                                          ('hidden_dim', 0)])
def test_a_stored_configuration_out_of_range_names_the_checkpoint(
        tmp_path, field, value):
    # a window checkpoint whose stored lag or width is out of range was
    # refused as the user's own flag ("'lag' must be positive") without
    # naming the file
    path = tmp_path / 'window.pt'
    save_checkpoint(path, FixedLagGaussianNEBP.recommended(lag=3,
                                                           hidden_dim=8))
    state = load_checkpoint(path)
    state['config'][field] = value
    torch.save(state, path)
    with pytest.raises(ValueError, match=rf"checkpoint '{path}' cannot be "
                       rf"rebuilt as a FixedLagGaussianNEBP .*'{field}'"):
        gaussian_nebp_from_checkpoint(path)
