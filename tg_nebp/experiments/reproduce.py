r"""The paper's experiment end to end: generate data, train NEBP, evaluate
BP and NEBP on the same test realizations with the same prior particle
draws, and write :obj:`metrics.json`, :obj:`report.md` and the figures
:obj:`tracks.png`, :obj:`outage.png`, :obj:`consistency.png`. The preset
:obj:`"beyond"` runs the experiments beyond the paper instead
(:mod:`tg_nebp.experiments.equivariant_nebp`)."""
import time
from pathlib import Path
from typing import Callable, Optional, Union

from tg_nebp.datasets import Scenario, load_datasets
from tg_nebp.evaluation import evaluate_method
from tg_nebp.experiments.equivariant_nebp import reproduce_beyond
from tg_nebp.experiments.train import train_scenario
from tg_nebp.filters import ParticleBP
from tg_nebp.io import claim_folder, read_json, write_text
from tg_nebp.reference import PAPER_TABLE
from tg_nebp.utils import check_device

__all__ = ['PRESETS', 'PRESET_NAMES', 'reproduce']

# Seeds of the three disjoint data sets (train_scenario draws the validation
# data from the training seed + 1); evaluation draws particles from the test
# seed so that BP and NEBP see the same prior particles.
TRAIN_SEED, VAL_SEED, TEST_SEED = 1, 2, 0

#: The sizes of the paper's experiment by preset name.
PRESETS = {
    # 2 CPU cores, well under 15 minutes; a shorter training budget than the
    # paper's, so a larger (fixed, not tuned on test data) learning rate
    'quick': dict(particles=1000, train_realizations=40, val_realizations=5,
                  epochs=4, batch_size=2, lr=1e-3, test_realizations=20,
                  eval_batch_size=5),
    # the paper's configuration (K from the authors' code)
    'paper': dict(particles=50_000, train_realizations=100,
                  val_realizations=10, epochs=10, batch_size=2, lr=1e-4,
                  test_realizations=400, eval_batch_size=4),
    # the paper's K on a GPU in about a minute (benchmarks/gpu_check.sh):
    # the whole path at the paper's size, with a short training
    'paper-short': dict(particles=50_000, train_realizations=20,
                        val_realizations=4, epochs=2, batch_size=2,
                        lr=1e-4, test_realizations=8, eval_batch_size=4),
}
#: The names of the presets, the paper's experiment at the sizes above and
#: 'beyond' (the equivariant NEBP at several K, on marginalized BP and
#: under NLOS mismatch; tg_nebp.experiments.equivariant_nebp, its sizes
#: in BEYOND by device).
PRESET_NAMES = sorted([*PRESETS, 'beyond'])


def _report(metrics: dict, preset: str, config: dict, device: str,
            seconds: float, history: list) -> str:
    lines = [
        f'# tg_nebp reproduce: preset `{preset}` on `{device}`', '',
        f'Wall time {seconds / 60:.1f} min. Configuration: '
        + ', '.join(f'{k}={v}' for k, v in config.items()) + '.', '',
        '| method | source | P_out(0.5 m) | P_out(1 m) | P_out(2 m) | '
        'P(accept) 0.50 | 0.95 | 0.99 | RMSE [m] |',
        '| --- | --- | --- | --- | --- | --- | --- | --- | --- |'
    ]
    for method in ('bp', 'nebp'):
        for source, entry in ((f'this run (K={config["particles"]}, '
                               f'{config["test_realizations"]} real.)',
                               metrics.get(method)),
                              ('paper, Fig. 2 (400 real.)',
                               PAPER_TABLE[method])):
            if entry is None:
                continue
            o, a = entry['outage'], entry['accept']
            rmse = f"{entry['rmse']:.3f}" if 'rmse' in entry else ''
            lines.append(f"| {method.upper()} | {source} | {o['0.5']:.3f} | "
                         f"{o['1.0']:.3f} | {o['2.0']:.3f} | "
                         f"{a['0.50']:.3f} | {a['0.95']:.3f} | "
                         f"{a['0.99']:.3f} | {rmse} |")
    lines += ['', '| epoch | train loss | validation loss |',
              '| --- | --- | --- |']
    lines += [f"| {h['epoch']} | {h['train_loss']:.4f} | "
              f"{h['val_loss']:.4f} |" for h in history]
    lines += ['', 'Losses are per agent and time step (m^2). Figures: '
              '`tracks.png`, `outage.png`, `consistency.png` (the paper\'s '
              'curves dashed), `history.png` (the training losses; '
              '`steps.csv`, `epochs.csv`).', '']
    return '\n'.join(lines)


def reproduce(preset: str, device: str = 'cpu', out: str = 'results',
              root: str = 'datasets', log: Callable = print,
              progress_factory: Optional[Callable] = None,
              compile: bool = False, num_samples: Union[int, str] = 1
              ) -> dict:
    r"""Runs the whole experiment of :obj:`preset` (see :obj:`PRESETS`;
    :obj:`"beyond"` runs
    :func:`~tg_nebp.experiments.equivariant_nebp.reproduce_beyond`) and
    writes its results to :obj:`out`; returns :obj:`metrics.json`'s
    content. :obj:`num_samples` is both trackers' number of sender samples
    per BP message (see :class:`~tg_nebp.filters.ParticleBP`).
    :obj:`compile` fuses the trackers' per-edge work with
    :func:`torch.compile` (see :class:`~tg_nebp.nn.conv.NEBPConv`)."""
    from tg_nebp.plot import plot_consistency, plot_outage, plot_tracks

    if preset not in PRESET_NAMES:
        raise ValueError(f"'preset' must be one of {PRESET_NAMES}, got "
                         f"'{preset}'")
    check_device(device)
    if preset == 'beyond':
        if compile or num_samples != 1:
            raise ValueError("the preset 'beyond' sets its own samples and "
                             "does not compile: leave --samples and "
                             "--compile out")
        return reproduce_beyond(device, out, root, log, progress_factory)
    config = PRESETS[preset]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = ('paper_train', 'paper_test')
    claim_folder(out, dict(preset=preset, config=config, device=str(device),
                           compile=compile, num_samples=num_samples,
                           fingerprints={n: Scenario.load(n).fingerprint()
                                         for n in names}))
    start = time.perf_counter()
    k = config['particles']

    log(f"training NEBP (K={k}, {config['train_realizations']} "
        f"realizations, {config['epochs']} epochs)")
    nebp, history, _, _ = train_scenario(
        'paper_train', out, particles=k,
        realizations=config['train_realizations'],
        val_realizations=config['val_realizations'],
        epochs=config['epochs'], batch_size=config['batch_size'],
        lr=config['lr'], seed=TRAIN_SEED, samples=num_samples, log_dir=out,
        root=root, device=device, compile=compile,
        progress_factory=progress_factory)
    test_set, = load_datasets(
        root, ('paper_test', config['test_realizations'], TEST_SEED))
    scenario = test_set.scenario
    models = dict(motion=scenario.motion_model,
                  measurement=scenario.measurement_model, compile=compile,
                  num_samples=num_samples)
    for h in history:
        log(f"  epoch {h['epoch']}: train {h['train_loss']:.4f}, "
            f"validation {h['val_loss']:.4f}")

    results = {}
    for method, tracker in (('bp', ParticleBP(k, **models)), ('nebp', nebp)):
        bar = progress_factory(len(test_set) * scenario.num_steps,
                               method) if progress_factory else None
        results[method] = evaluate_method(
            method, tracker.to(device).eval(), test_set,
            config['eval_batch_size'], device, TEST_SEED, out,
            progress=bar.update if bar else None)
        if bar:
            bar.close()
        log(f"  {method}: {results[method]['entry']}")

    first = results['bp']
    plot_tracks(first['first_states'],
                {m: r['first_mean'] for m, r in results.items()},
                first['first_anchor'], out / 'tracks.png')
    plot_outage({m: r['errors'] for m, r in results.items()},
                out / 'outage.png')
    plot_consistency({m: r['nees'] for m, r in results.items()},
                     out / 'consistency.png')
    metrics = read_json(out / 'metrics.json')
    write_text(out / 'report.md',
               _report(metrics, preset, config, device,
                       time.perf_counter() - start, history))
    return metrics
