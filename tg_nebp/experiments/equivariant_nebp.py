r"""The experiments beyond the paper (:obj:`tg-nebp reproduce --preset
beyond`): the particle-equivariant NEBP
(:class:`~tg_nebp.nn.conv.EquivariantNEBPConv`) trained at one particle
count and run at several, on the paper's paired BP and on marginalized,
regularized BP, against BP at the same :math:`K`; and the same correction
under range model mismatch (NLOS ranges, a Gaussian likelihood inside)
against BP with the mismatched and with the matched likelihood.

Every method runs on the same test realizations with the same prior
particle draws. The run is resumable: trained models are checkpoints and
every evaluated method keeps its raw errors, so a second run with the same
settings skips what is done (and another setting is an error naming it)."""
import time
from pathlib import Path
from typing import Callable, Dict, Optional

import torch

from tg_nebp.datasets import Scenario, load_datasets
from tg_nebp.evaluation import evaluate_method, spread
from tg_nebp.experiments.train import train_scenario
from tg_nebp.filters import ParticleBP
from tg_nebp.io import (atomic_write, claim_folder, read_json, write_json,
                        write_text)
from tg_nebp.models import model_like
from tg_nebp.reference import PAPER_TABLE
from tg_nebp.training import checkpoint_history, nebp_from_checkpoint

__all__ = ['BEYOND', 'reproduce_beyond']

# seeds of the disjoint data sets, as in the paper's experiment
TRAIN_SEED, VAL_SEED, TEST_SEED = 1, 2, 0
PAPER_PARTICLES = 50_000  # the paper's K (from the authors' code)
# training and test scenarios, line-of-sight and NLOS (names or JSON files)
SCENARIOS = dict(train='paper_train', test='paper_test',
                 nlos_train='paper_train_nlos', nlos_test='paper_test_nlos')

#: The sizes of :obj:`tg-nebp reproduce --preset beyond` by device.
BEYOND = {
    # 2 CPU cores: each model trains in under 30 minutes; fixed before any
    # test result was seen
    'cpu': dict(train_particles=1000, test_particles=[1000, 5000],
                train_realizations=40, val_realizations=5, epochs=5,
                batch_size=2, lr=1e-3, test_realizations=20,
                eval_batch_size=5,
                # marginalized BP: trained with 4 samples (the cost of the
                # backward pass), run with the recommended 16
                train_samples=4, samples=16, regularize='silverman',
                marginalized_epochs=3, scenarios=SCENARIOS),
    # one GPU: the paper's data sizes and its K
    'cuda': dict(train_particles=5000,
                 test_particles=[1000, 5000, PAPER_PARTICLES],
                 train_realizations=100, val_realizations=10, epochs=10,
                 batch_size=2, lr=1e-3, test_realizations=400,
                 eval_batch_size=4, train_samples=4, samples=16,
                 regularize='silverman', marginalized_epochs=10,
                 scenarios=SCENARIOS),
}


def _arms(config: dict) -> Dict[str, dict]:
    # the trained models: name -> training scenario, epochs, tracker
    # options (train_scenario's)
    names = config['scenarios']
    return {
        'paired': dict(scenario=names['train'], epochs=config['epochs'],
                       options=dict(samples=1)),
        'marginalized': dict(
            scenario=names['train'], epochs=config['marginalized_epochs'],
            options=dict(samples=config['train_samples'],
                         regularize=config['regularize'])),
        # the Gaussian likelihood with the NLOS data's sigma and range
        'nlos': dict(scenario=names['nlos_train'], epochs=config['epochs'],
                     options=dict(samples=1, measurement='gaussian')),
    }


def _train_arm(name: str, arm: dict, config: dict, root: str, device: str,
               out: Path, log: Callable,
               progress_factory: Optional[Callable]) -> list:
    checkpoint = out / name / 'nebp.pt'
    checkpoint.parent.mkdir(parents=True, exist_ok=True)
    done = len(checkpoint_history(checkpoint)) if checkpoint.exists() else 0
    log(f"training the equivariant NEBP '{name}' (K="
        f"{config['train_particles']}, {config['train_realizations']} "
        f"realizations of {Scenario.load(arm['scenario']).name}, "
        f"{arm['epochs']} epochs, {done} done)")
    start = time.perf_counter()
    # the folder of the checkpoint holds its training log; a checkpoint
    # there is resumed
    history = train_scenario(
        arm['scenario'], checkpoint.parent, 'equivariant',
        config['train_particles'], realizations=config['train_realizations'],
        val_realizations=config['val_realizations'], epochs=arm['epochs'],
        batch_size=config['batch_size'], lr=config['lr'], seed=TRAIN_SEED,
        resume=checkpoint.exists(), log_dir=checkpoint.parent, root=root,
        device=device, progress_factory=progress_factory,
        description=f'train {name}', **arm['options']).history
    if done < arm['epochs']:
        log(f'  trained in {(time.perf_counter() - start) / 60:.1f} min')
    for h in history:
        log(f"  epoch {h['epoch']}: train {h['train_loss']:.4f}, "
            f"validation {h['val_loss']:.4f}")
    return history


def _evaluations(config: dict, scenarios: dict, out: Path) -> Dict[str,
                                                                   tuple]:
    # method -> (test scenario, tracker factory); NEBP methods are the
    # trained checkpoints run at the test K (and M)
    models = {}
    for key, scenario in scenarios.items():
        models[key] = dict(motion=scenario.motion_model,
                           measurement=scenario.measurement_model)
    marginal = dict(num_samples=config['samples'],
                    regularize=config['regularize'])
    methods = {}
    for k in config['test_particles']:
        methods[f'bp K={k}'] = ('los', lambda k=k: ParticleBP(
            k, **models['los']))
        methods[f'nebp K={k}'] = ('los', lambda k=k: nebp_from_checkpoint(
            out / 'paired' / 'nebp.pt', k))
        methods[f'bp marginalized K={k}'] = ('los', lambda k=k: ParticleBP(
            k, **models['los'], **marginal))
        methods[f'nebp marginalized K={k}'] = (
            'los', lambda k=k: nebp_from_checkpoint(
                out / 'marginalized' / 'nebp.pt', k,
                num_samples=config['samples']))
    k = config['train_particles']
    gaussian = model_like('gaussian', 'measurement',
                          models['nlos']['measurement'])
    methods[f'nlos: bp gaussian (mismatched) K={k}'] = (
        'nlos', lambda: ParticleBP(k, motion=models['nlos']['motion'],
                                   measurement=gaussian))
    methods[f'nlos: bp nlos (matched) K={k}'] = (
        'nlos', lambda: ParticleBP(k, **models['nlos']))
    methods[f'nlos: nebp gaussian K={k}'] = (
        'nlos', lambda: nebp_from_checkpoint(out / 'nlos' / 'nebp.pt', k))
    return methods


def _report(metrics: dict, histories: dict, config: dict, device: str,
            seconds: float) -> str:
    lines = [
        f'# tg_nebp reproduce: preset `beyond` on `{device}`', '',
        f'Wall time {seconds / 60:.1f} min (this run; parts resumed from an '
        f'earlier run are not counted). Configuration: '
        + ', '.join(f'{k}={v}' for k, v in config.items()) + '.', '',
        'NEBP is the particle-equivariant layer (`--variant equivariant`), '
        f"trained once at K={config['train_particles']} and run at every K. "
        f"Marginalized: M={config['samples']} sender samples per message and "
        f"{config['regularize']}-regularized resampling (NEBP trained with "
        f"M={config['train_samples']}). Per-realization spread: mean ± "
        'sample std over the realizations.', '',
        '| method | scenario | K | R | P_out(0.5 m) | P_out(1 m) | '
        'P_out(2 m) | P(accept) 0.50 | 0.95 | 0.99 | RMSE [m] | '
        'P_out(1 m) per real. | P(accept 0.95) per real. | s / real. |',
        '| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- '
        '| --- | --- | --- |']
    for method, e in metrics.items():
        o, a, s = e['outage'], e['accept'], e['spread']
        lines.append(
            f"| {method} | {e['scenario']} | {e['particles']} | "
            f"{e['realizations']} | {o['0.5']:.3f} | {o['1.0']:.3f} | "
            f"{o['2.0']:.3f} | {a['0.50']:.3f} | {a['0.95']:.3f} | "
            f"{a['0.99']:.3f} | {e['rmse']:.3f} | "
            f"{s['outage_1m']['mean']:.3f} ± {s['outage_1m']['std']:.3f} | "
            f"{s['accept_0.95']['mean']:.3f} ± "
            f"{s['accept_0.95']['std']:.3f} | "
            f"{e['seconds'] / e['realizations']:.2f} |")
    for method, e in PAPER_TABLE.items():
        o, a = e['outage'], e['accept']
        lines.append(
            f"| {method.upper()}, paper Fig. 2 | paper_test | "
            f"{PAPER_PARTICLES} | 400 | {o['0.5']:.3f} | {o['1.0']:.3f} | "
            f"{o['2.0']:.3f} | {a['0.50']:.3f} | {a['0.95']:.3f} | "
            f"{a['0.99']:.3f} | | | | |")
    lines += ['', '| model | epoch | train loss | validation loss |',
              '| --- | --- | --- | --- |']
    for name, history in histories.items():
        lines += [f"| {name} | {h['epoch']} | {h['train_loss']:.4f} | "
                  f"{h['val_loss']:.4f} |" for h in history]
    lines += ['', 'Losses are per agent and time step (m^2), on the '
              'training scenario. Figures: `outage.png`, `consistency.png` '
              '(every method on the line-of-sight test network; the '
              "paper's curves dashed), `nlos_outage.png`, "
              '`nlos_consistency.png`, `particles.png` (P_out(1 m) and '
              'P(accept) against K), and each model\'s `<model>/history.png` '
              '(its training losses; `steps.csv`, `epochs.csv`).', '']
    return '\n'.join(lines)


def reproduce_beyond(device: str = 'cpu', out: str = 'results/beyond',
                     root: str = 'datasets', log: Callable = print,
                     progress_factory: Optional[Callable] = None) -> dict:
    r"""Runs the experiments of :obj:`BEYOND[device]` (:obj:`"cpu"` or
    :obj:`"cuda"`) and writes :obj:`metrics.json` (every method's entry and
    its per-realization spread), :obj:`report.md` and the figures to
    :obj:`out`; returns the metrics."""
    from tg_nebp.plot import (plot_consistency, plot_outage,
                              plot_outage_against_particles)

    config = BEYOND['cuda' if str(device).startswith('cuda') else 'cpu']
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # a scenario is its fingerprint: a file changed under the same name is
    # another run
    settings = dict(config=config, device=str(device), seed=TEST_SEED,
                    fingerprints={name: Scenario.load(name).fingerprint()
                                  for name in config['scenarios'].values()})
    claim_folder(out, settings)
    start = time.perf_counter()
    names = config['scenarios']
    los, nlos = load_datasets(
        root, (names['test'], config['test_realizations'], TEST_SEED),
        (names['nlos_test'], config['test_realizations'], TEST_SEED))
    tests = {'los': los, 'nlos': nlos}
    scenarios = {key: data.scenario for key, data in tests.items()}

    histories = {name: _train_arm(name, arm, config, root, device, out, log,
                                  progress_factory)
                 for name, arm in _arms(config).items()}

    raw = out / 'raw'
    raw.mkdir(exist_ok=True)
    results = {}
    for method, (key, build) in _evaluations(config, scenarios,
                                             out).items():
        path = raw / (method.replace(' ', '_').replace(':', '').replace(
            '(', '').replace(')', '').replace('=', '') + '.pt')
        if path.exists():  # tensors only: loading runs no code
            results[method] = torch.load(path, weights_only=True)
            continue
        tracker = build().to(device).eval()
        data = tests[key]
        bar = progress_factory(len(data) * data.scenario.num_steps,
                               method) if progress_factory else None
        result = evaluate_method(method, tracker, data,
                                 config['eval_batch_size'], device,
                                 TEST_SEED, out,
                                 progress=bar.update if bar else None)
        if bar:
            bar.close()
        log(f"  {method}: P_out(1 m) {result['entry']['outage']['1.0']:.3f}"
            f", P(accept 0.95) {result['entry']['accept']['0.95']:.3f}, "
            f"{result['entry']['seconds']:.0f} s")
        kept = {k: result[k] for k in ('errors', 'nees', 'realization')}
        atomic_write(path, lambda tmp: torch.save(kept, tmp))
        results[method] = kept

    metrics = read_json(out / 'metrics.json')
    for method, result in results.items():
        metrics[method]['spread'] = spread(result)
    metrics = {method: metrics[method] for method in results}
    write_json(out / 'metrics.json', metrics)

    def pick(prefix):
        return {m: r for m, r in results.items() if m.startswith(prefix)}

    plot_outage({m: r['errors'] for m, r in results.items()
                 if not m.startswith('nlos')}, out / 'outage.png')
    plot_consistency({m: r['nees'] for m, r in results.items()
                      if not m.startswith('nlos')}, out / 'consistency.png')
    plot_outage({m: r['errors'] for m, r in pick('nlos').items()},
                out / 'nlos_outage.png')
    plot_consistency({m: r['nees'] for m, r in pick('nlos').items()},
                     out / 'nlos_consistency.png')
    by_k = {}
    for method, entry in metrics.items():
        if not method.startswith('nlos'):
            name = method.rsplit(' K=', 1)[0]
            by_k.setdefault(name, {})[entry['particles']] = entry
    plot_outage_against_particles(
        by_k, out / 'particles.png',
        paper={f'{m.upper()} (paper)': dict(e, particles=PAPER_PARTICLES)
               for m, e in PAPER_TABLE.items()})
    write_text(out / 'report.md',
               _report(metrics, histories, config, str(device),
                       time.perf_counter() - start))
    return metrics
