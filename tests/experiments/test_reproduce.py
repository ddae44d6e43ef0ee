r"""Tests of :mod:`tg_nebp.experiments.reproduce`: the paper's experiment
end to end at a tiny size (the preset's numbers are patched, its code path
is not)."""
import tg_nebp.experiments.reproduce as reproduce_module
from tg_nebp.evaluation import summarize, track_dataset
from tg_nebp.datasets import CooperativeLocalizationDataset
from tg_nebp.filters import ParticleBP
from tg_nebp.io import read_json
from tg_nebp.training import load_checkpoint, nebp_from_checkpoint
from tg_nebp.training_log import read_training_log


def test_tiny_preset_writes_everything(tmp_path, monkeypatch):
    tiny = dict(particles=8, train_realizations=2, val_realizations=1,
                epochs=2, batch_size=2, lr=1e-3, test_realizations=2,
                eval_batch_size=2)
    monkeypatch.setitem(reproduce_module.PRESETS, 'quick', tiny)
    out, root = tmp_path / 'out', str(tmp_path / 'data')
    metrics = reproduce_module.reproduce('quick', out=str(out), root=root,
                                         log=lambda *a: None)
    assert metrics == read_json(out / 'metrics.json')
    for name in ('report.md', 'tracks.png', 'outage.png', 'consistency.png',
                 'history.png', 'steps.csv', 'epochs.csv', 'nebp.pt'):
        assert (out / name).stat().st_size > 0, name
    history = load_checkpoint(out / 'nebp.pt')['progress']['history']
    log = read_training_log(out)
    assert log['epochs'] == [{k: h[k] for k in ('epoch', 'train_loss',
                                                'val_loss')}
                             for h in history]
    assert len(log['steps']) == 2 * 50  # epochs x (1 batch x 50 steps)
    # both rows equal an independent run of the same trackers and data
    test = CooperativeLocalizationDataset(root, 'paper_test', 2,
                                          reproduce_module.TEST_SEED)
    for method, tracker in (('bp', ParticleBP(8)),
                            ('nebp', nebp_from_checkpoint(out / 'nebp.pt'))):
        result = track_dataset(tracker.eval(), test, 1, 'cpu',
                               reproduce_module.TEST_SEED)
        want = summarize(result['errors'], result['nees'])
        for key in ('outage', 'accept'):  # repr: NaN (K = 8) equals NaN
            assert repr(metrics[method][key]) == repr(want[key]), method
