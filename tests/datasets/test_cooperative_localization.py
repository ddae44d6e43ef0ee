import math
import os
import random

import numpy as np
import pytest
import torch
from scipy.stats import kstest

from tg_nebp.data import Realization
from tg_nebp.datasets import CooperativeLocalizationDataset, Scenario
from tg_nebp.models import GaussianRange

T = 5
FIELDS = ('states', 'edge_index', 'edge_attr', 'edge_time', 'anchor',
          'prior_mean', 'prior_cov')


def small():
    return Scenario.load('paper_train').replace(num_steps=T)


def make(root, scenario=None, num_realizations=3, seed=0, **kwargs):
    return CooperativeLocalizationDataset(
        str(root), scenario=scenario or small(),
        num_realizations=num_realizations, seed=seed, log=False, **kwargs)


def same_data(a, b):
    return all(torch.equal(a[k], b[k]) for k in FIELDS) and \
        int(a.num_steps) == int(b.num_steps)


@pytest.fixture(scope='module')
def dataset(tmp_path_factory):
    return make(tmp_path_factory.mktemp('data'), num_realizations=4, seed=3)


def test_items_are_realizations(dataset):
    assert len(dataset) == 4
    for data in dataset:
        assert isinstance(data, Realization)
        assert data.num_nodes == 30 and data.num_time_steps == T
        assert data.states.shape == (30, T, 4)
    assert 'paper_train' in repr(dataset)


def test_processed_file_name(dataset, tmp_path):
    name = os.path.basename(dataset.processed_paths[0])
    assert name.startswith('paper_train_')
    assert '_r4_' in name and '_seed3_' in name and f'_t{T}_' in name
    assert small().fingerprint() in name
    assert os.path.isfile(dataset.processed_paths[0])
    assert os.path.dirname(dataset.processed_paths[0]).startswith(
        os.path.join(str(dataset.root)))
    other = make(tmp_path, num_realizations=2, seed=11)
    name = os.path.basename(other.processed_paths[0])
    assert '_r2_' in name and '_seed11_' in name
    assert os.path.join(str(tmp_path), 'paper_train') == other.root


def test_same_seed_identical_across_roots(tmp_path):
    a = make(tmp_path / 'a', seed=7)
    b = make(tmp_path / 'b', seed=7)
    assert a.processed_paths[0] != b.processed_paths[0]
    for x, y in zip(a, b):
        assert same_data(x, y)
    c = make(tmp_path / 'c', seed=8)
    for x, y in zip(a, c):
        assert not torch.equal(x.states, y.states)
    # realizations within one dataset differ from each other
    assert not torch.equal(a[0].states, a[1].states)


def test_more_realizations_new_file_extending_the_shorter(tmp_path):
    short = make(tmp_path, num_realizations=2, seed=1)
    long = make(tmp_path, num_realizations=3, seed=1)
    assert short.processed_paths[0] != long.processed_paths[0]
    assert os.path.isfile(short.processed_paths[0])
    assert len(short) == 2 and len(long) == 3
    for i in range(2):
        assert same_data(short[i], long[i])


def test_changed_parameter_regenerates(tmp_path, monkeypatch):
    calls = []
    original = CooperativeLocalizationDataset.process

    def counting(self):
        calls.append(self.scenario.measurement_model.sigma)
        original(self)

    monkeypatch.setattr(CooperativeLocalizationDataset, 'process', counting)
    base = make(tmp_path, num_realizations=2)
    noisy = make(tmp_path, scenario=small().replace(
        measurement=GaussianRange(sigma=3.0)),
                 num_realizations=2)
    assert calls == [1.0, 3.0]  # never reuses the other file
    assert base.processed_paths[0] != noisy.processed_paths[0]
    assert os.path.isfile(base.processed_paths[0])

    def residual_std(ds):
        res = []
        for d in ds:
            t, (j, i) = d.edge_time, d.edge_index
            dist = (d.states[j, t, :2] - d.states[i, t, :2]).norm(dim=-1)
            far = dist > 15.0
            res.append((d.edge_attr[:, 0] - dist)[far])
        return float(torch.cat(res).std())

    assert abs(residual_std(base) - 1.0) < 0.15
    assert abs(residual_std(noisy) - 3.0) < 0.45
    # loading again reuses the matching file without processing
    again = make(tmp_path, num_realizations=2)
    assert calls == [1.0, 3.0]
    assert same_data(again[1], base[1])


def test_force_reload_regenerates(tmp_path, monkeypatch):
    calls = []
    original = CooperativeLocalizationDataset.process

    def counting(self):
        calls.append(1)
        original(self)

    monkeypatch.setattr(CooperativeLocalizationDataset, 'process', counting)
    first = make(tmp_path, num_realizations=2)
    path = first.processed_paths[0]
    # a stale, unrelated file under the final name: force_reload overwrites
    torch.save('stale', path)
    reloaded = make(tmp_path, num_realizations=2, force_reload=True)
    assert len(calls) == 2
    # the content, not the mtime: file times tick coarser than a fast write
    assert torch.load(path, weights_only=True) != 'stale'
    assert same_data(reloaded[0], first[0])
    make(tmp_path, num_realizations=2)
    assert len(calls) == 2


def test_killed_write_leaves_no_final_file(tmp_path, monkeypatch):
    def dying_save(state, path):
        with open(path, 'wb') as f:  # half a file, then the process dies
            f.write(b'partial')
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, 'save', dying_save)
    with pytest.raises(KeyboardInterrupt):
        make(tmp_path, num_realizations=2)
    folder = tmp_path / 'paper_train' / 'processed'
    names = os.listdir(folder)
    assert not [n for n in names if 'paper_train' in n], names
    monkeypatch.undo()
    # the next run generates the data from scratch
    ds = make(tmp_path, num_realizations=2)
    assert os.path.isfile(ds.processed_paths[0]) and len(ds) == 2


def test_torch_save_failure_leaves_no_final_file(tmp_path, monkeypatch):
    def failing(*args, **kwargs):
        raise OSError('disk full')

    monkeypatch.setattr(torch, 'save', failing)
    with pytest.raises(OSError, match='disk full'):
        make(tmp_path, num_realizations=2, seed=4)
    folder = tmp_path / 'paper_train' / 'processed'
    assert not [n for n in os.listdir(folder) if 'paper_train' in n]


@pytest.mark.parametrize('kwargs,match', [
    (dict(num_realizations=0), 'num_realizations'),
    (dict(seed=-1), 'seed'),
])
def test_bad_arguments(tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        make(tmp_path, **kwargs)


def test_scenario_by_name(tmp_path):
    ds = CooperativeLocalizationDataset(str(tmp_path), 'paper_train',
                                        num_realizations=1, log=False)
    assert ds.scenario == Scenario.load('paper_train')
    assert ds[0].num_time_steps == 50 and ds[0].num_nodes == 30


# ---- statistics of the generated data ---------------------------------------

def test_ranges_are_distance_plus_gaussian_noise(dataset):
    res = []
    for d in dataset:
        t, (j, i) = d.edge_time, d.edge_index
        dist = (d.states[j, t, :2] - d.states[i, t, :2]).norm(dim=-1)
        assert bool((d.edge_attr >= 0).all())
        far = dist > 5.0  # the negative-range redraw never matters here
        res.append((d.edge_attr[:, 0] - dist)[far].double())
    res = torch.cat(res).numpy()
    n = res.size
    assert n > 3000
    assert abs(res.mean()) < 5 / math.sqrt(n)
    assert abs(res.std() - 1.0) < 5 / math.sqrt(2 * n)
    assert kstest(res, 'norm').pvalue > 1e-4


def test_edges_within_range_and_never_into_anchors(dataset):
    for d in dataset:
        t, (j, i) = d.edge_time, d.edge_index
        dist = (d.states[j, t, :2] - d.states[i, t, :2]).norm(dim=-1)
        assert bool((dist <= 20.0 + 1e-4).all())
        assert not bool(d.anchor[i].any())
        assert bool((j != i).all())
        # agents measure each other both ways
        pairs = set(zip(t.tolist(), j.tolist(), i.tolist()))
        for tt, jj, ii in pairs:
            if not d.anchor[jj]:
                assert (tt, ii, jj) in pairs


def test_anchor_states_static(dataset):
    anchors = torch.tensor(small().anchor_positions)
    for d in dataset:
        a = d.states[d.anchor]
        assert torch.equal(a[:, :, :2],
                           anchors.view(-1, 1, 2).expand(-1, T, 2))
        assert bool((a[:, :, 2:] == 0).all())
        assert torch.equal(d.prior_mean[d.anchor, :2], anchors)
        assert bool((d.prior_cov[d.anchor] == 0).all())


def test_prior_statistics(tmp_path):
    # prior_mean ~ N(x_0, diag(10, 10, .01, .01)), x_0 not stored: compare
    # with x_1 = F x_0 + W(-c v|v| + a), which adds var(v0 + a/2) ~ 0.0106
    # to the position and var(a) = 0.0025 to the velocity
    ds = make(tmp_path, scenario=small().replace(num_steps=1),
              num_realizations=150, seed=2)
    diffs = []
    for d in ds:
        agents = ~d.anchor
        diffs.append((d.prior_mean[agents] - d.states[agents, 0]).double())
    diffs = torch.cat(diffs).numpy()
    n = diffs.shape[0]
    pos = diffs[:, :2].reshape(-1)
    var_pos = 10.0 + 0.01 + 0.05**2 / 4
    assert abs(pos.mean()) < 5 * math.sqrt(var_pos / pos.size)
    assert abs(pos.var() / var_pos - 1) < 5 * math.sqrt(2 / pos.size)
    vel = diffs[:, 2:].reshape(-1)
    var_vel = 0.01 + 0.05**2
    assert abs(vel.mean()) < 5 * math.sqrt(var_vel / vel.size)
    assert abs(vel.var() / var_vel - 1) < 5 * math.sqrt(2 / vel.size)
    # the position and velocity prior errors are independent
    corr = np.corrcoef(diffs[:, 0], diffs[:, 1])[0, 1]
    assert abs(corr) < 5 / math.sqrt(n)


# --- files on disk: nothing in them runs, damage heals or is named ----------

class Exploit:
    r"""Unpickling this creates :obj:`marker`: proof that code ran."""
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, 'w'))


def test_crafted_processed_file_does_not_run(tmp_path):
    path = make(tmp_path, num_realizations=2).processed_paths[0]
    marker = tmp_path / 'ran'
    torch.save({'format': 'tg_nebp.dataset', 'payload': Exploit(marker)},
               path)
    with pytest.raises(ValueError, match=r"processed file '.*\.pt' holds "
                       r"objects other than tensors and primitives"):
        make(tmp_path, num_realizations=2)
    assert not marker.exists()
    # the payload is real: an unsafe load would have run it (PyG's
    # fs.torch_load falls back to weights_only=False)
    torch.load(path, weights_only=False)
    assert marker.exists()


def test_crafted_pre_transform_record_is_never_read(tmp_path):
    # PyG reads processed/pre_transform.pt with weights_only=False
    ds = make(tmp_path, num_realizations=2)
    marker = tmp_path / 'ran'
    folder = os.path.dirname(ds.processed_paths[0])
    for name in ('pre_transform.pt', 'pre_filter.pt'):
        torch.save(Exploit(marker), os.path.join(folder, name))
    again = make(tmp_path, num_realizations=2)
    make(tmp_path, num_realizations=3)  # generating writes no record
    assert not marker.exists() and same_data(again[0], ds[0])
    assert sorted(os.listdir(folder)) == sorted(
        [os.path.basename(ds.processed_paths[0]), 'pre_transform.pt',
         'pre_filter.pt', os.path.basename(
             make(tmp_path, num_realizations=3).processed_paths[0])])


@pytest.mark.parametrize('damage', ['cut in half', 'empty', 'garbage 0',
                                    'garbage 1', 'garbage 2', 'garbage 3'])
def test_damaged_processed_file_is_generated_again(tmp_path, damage):
    ds = make(tmp_path, num_realizations=2)
    path = ds.processed_paths[0]
    content = open(path, 'rb').read()
    if damage.startswith('garbage'):  # random bytes fail in many ways
        damaged = random.Random(int(damage[-1])).randbytes(1000)
    else:
        damaged = {'cut in half': content[:len(content) // 2],
                   'empty': b''}[damage]
    with open(path, 'wb') as f:
        f.write(damaged)
    with pytest.warns(UserWarning, match=r"processed file '.*\.pt' is "
                      r"(cut short or )?corrupt.*generating it again"):
        healed = make(tmp_path, num_realizations=2)
    assert same_data(healed[1], ds[1])
    assert open(path, 'rb').read() != damaged


def test_foreign_processed_file_is_refused(tmp_path):
    path = make(tmp_path, num_realizations=2).processed_paths[0]
    torch.save({'weights': torch.zeros(3)}, path)
    with pytest.raises(ValueError, match=r"processed file '.*\.pt' is not a "
                       r"tg_nebp dataset"):
        make(tmp_path, num_realizations=2)


def test_other_pre_transform_warns(tmp_path):
    make(tmp_path, num_realizations=2)
    with pytest.warns(UserWarning, match='pre_transform'):
        make(tmp_path, num_realizations=2, pre_transform=lambda d: d)


def test_root_that_is_a_file(tmp_path):
    root = tmp_path / 'file'
    root.write_text('x')
    with pytest.raises(ValueError, match=r"'root' = '.*file' is not a "
                       r"folder"):
        make(root)
