r"""What each sub-command of :obj:`tg-nebp` runs on its parsed arguments
(:mod:`tg_nebp.cli` builds the parser and handles errors), and what it
prints."""
import sys
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from tg_nebp.datasets import (FIT_HORIZON, UWB_FIT_HORIZON,
                              RecordingScenario, fitted_recording_scenario,
                              fitted_scenario, load_scenario)
from tg_nebp.datasets.mrclam_dataset import sequence_source
from tg_nebp.experiments.compare import compare
from tg_nebp.experiments.evaluate import evaluate_scenario
from tg_nebp.experiments.frontier import frontier
from tg_nebp.experiments.options import MethodOptions
from tg_nebp.experiments.reproduce import reproduce
from tg_nebp.experiments.track import (record_realization, score_files,
                                       track_stream)
from tg_nebp.experiments.train import train_scenario
from tg_nebp.utils import joined_process_group, process_group

__all__ = ['progress_bars', 'run_evaluate', 'run_train', 'run_track',
           'run_record', 'run_fit', 'run_score', 'run_frontier',
           'run_compare', 'run_reproduce']


class _Bar(tqdm):
    r"""The progress bar of a command; its :obj:`update` after every time
    step also lets the thread governor take its reading."""
    governor = None

    def update(self, n=1):
        super().update(n)
        if self.governor is not None:
            self.governor.update()


def progress_bars(args) -> Callable:
    # the progress_factory of the library's commands: rank 0's bar, unless
    # --quiet
    def bar(total, desc):
        # shown after a second: a run refused at its start (a checked
        # argument) prints its one error line and no empty bar
        made = _Bar(total=total, desc=desc, unit='step', delay=1.0,
                    disable=args.quiet or process_group()[1] > 0)
        made.governor = args.governor
        return made

    return bar


def run_evaluate(args) -> int:
    # one record of the method's options, checked by method_tracker
    options = MethodOptions.of(args)
    with joined_process_group(args.device) as device:
        result = evaluate_scenario(
            args.method, args.scenario, args.realizations, args.seed,
            args.root, args.out, args.batch_size, device, progress_bars(args),
            options)
        if process_group()[1] > 0:
            return 0
    for key, entry in result['entries']:
        what = 'RMSE floor' if key.startswith('pcrb') else 'RMSE'
        heading = (f", heading {entry['heading_rmse']:.4f} rad"
                   if 'heading_rmse' in entry else '')
        largest = (f", median {entry['median_error']:.3f} m, max "
                   f"{entry['max_error']:.2f} m" if 'max_error' in entry
                   else '')
        print(f"{key}: {what} {entry['rmse']:.3f} m{largest}{heading}, "
              f"outage {entry['outage']}, P(accept) {entry['accept']}, "
              f"{entry['seconds']:.1f} s -> "
              f"{Path(args.out) / 'metrics.json'}")
    if 'tracks' in result:
        print(f"tracks, filtered and smoothed -> {result['tracks']}")
    return 0


def run_train(args) -> int:
    with joined_process_group(args.device) as device:
        scenario = (args.scenario[0] if len(args.scenario) == 1 else
                    args.scenario)
        trained = train_scenario(
            scenario, args.out, args.variant, args.particles,
            args.iterations, args.realizations, args.val_realizations,
            args.epochs, args.batch_size, args.lr, args.seed,
            args.measurement, args.samples, args.regularize,
            args.ess_threshold, args.resume, args.log_dir, args.root,
            device, args.compile, progress_bars(args), base=args.base,
            hidden_dim=args.hidden_dim, val_scenario=args.val_scenario,
            lag=args.lag)
        if process_group()[1] > 0:
            return 0
    for h in trained.history:
        unit = ('m^2 per agent-step' if args.base == 'particle' else
                'negative log-likelihood plus m^2, per agent-step')
        print(f"epoch {h['epoch']}: train loss {h['train_loss']:.4f}, "
              f"validation loss {h['val_loss']:.4f} ({unit})")
    print(f'checkpoint -> {trained.checkpoint}')
    if trained.log is not None:
        events = ', TensorBoard events' if trained.log.tensorboard else ''
        print(f'log -> {trained.log.log_dir} (steps.csv, epochs.csv, '
              f'history.png{events})')
    return 0


def run_track(args) -> int:
    # one record of the method's options, checked by method_tracker
    counts = track_stream(args.method, args.input, args.output,
                          args.scenario, args.on_error, args.save_state,
                          args.resume, args.seed, args.device,
                          options=MethodOptions.of(args),
                          window=args.window)
    if counts['skipped']:
        sys.stderr.write(f"{counts['skipped']} bad line(s) skipped\n")
    return 0


def run_record(args) -> int:
    record_realization(args.measurements, args.truth, args.scenario,
                       args.realization, args.seed, args.root)
    print(f"realization {args.realization} -> {args.measurements} "
          f"(measurements), {args.truth} (truth)")
    return 0


def run_fit(args) -> int:
    # the output checked before the fit's work (and its own refusals)
    if Path(args.output).is_dir():
        raise ValueError(f"--output '{args.output}' is a folder, not a file")
    if args.scenario is not None:
        # a recording (tiers-uwb-testN, a scenario file naming a bag): its
        # models and range calibration fitted on its own part
        recorded = load_scenario(args.scenario)
        if not isinstance(recorded, RecordingScenario):
            raise ValueError(f"--scenario '{args.scenario}' is not a "
                             f"recording (tiers-uwb-testN or a scenario file "
                             f"with a 'recording'); MRCLAM sequences are "
                             f"fitted with --sequence N")
        horizon = (UWB_FIT_HORIZON if args.horizon is None
                   else args.horizon)
        scenario, report = fitted_recording_scenario(
            recorded, args.root, name=Path(args.output).stem,
            horizon=horizon)
    else:
        source = sequence_source(args.root, args.sequence)
        scenario, report = fitted_scenario(
            source, args.sequence, horizon=(FIT_HORIZON if args.horizon is
                                            None else args.horizon))
    scenario.save(args.output)
    print(f"motion: {scenario.motion_model}\nmeasurement: "
          f"{scenario.measurement_model}\nfit: {report}\n-> {args.output} "
          f"(--scenario {args.output} --root {args.root})")
    return 0


def run_score(args) -> int:
    entry = score_files(args.estimates, args.truth)
    print(f"RMSE {entry['rmse']:.3f} m, outage {entry['outage']}, "
          f"P(accept) {entry['accept']}, {entry['steps']} steps, "
          f"{entry['estimates']} estimates; not estimated: "
          f"{entry['unscored_steps']} truth steps, "
          f"{entry['unscored_states']} true states"
          + (f"; {entry['without_truth']} estimates of agents without "
             f"truth, not scored" if entry['without_truth'] else ''))
    return 0


def run_frontier(args) -> int:
    out = Path(args.out)
    result = frontier(args.particles, args.samples, args.resampler,
                      args.regularize, args.ess_threshold, args.scenario,
                      args.realizations, args.seed, out, args.root,
                      args.device, args.batch_size, args.compile,
                      progress_bars(args))
    print(f"{len(result['points'])} points -> {out / 'frontier.json'}, "
          f"{out / 'frontier.md'}, {out / 'frontier.png'}")
    return 0


def run_compare(args) -> int:
    out = Path(args.out)
    result = compare(out, progress_bars(args), root=args.root,
                     scenarios=args.scenario,
                     realizations=args.realizations, seed=args.seed,
                     checkpoints=args.checkpoint, device=args.device,
                     batch_size=args.batch_size, methods=args.methods,
                     lag=args.lag)
    print(f"{sum(map(len, result['results'].values()))} rows -> "
          f"{out / 'compare.json'}, {out / 'compare.md'}, "
          f"{out / 'compare.png'}")
    return 0


def run_reproduce(args) -> int:
    metrics = reproduce(args.preset, args.device, args.out, args.root,
                        progress_factory=progress_bars(args),
                        compile=args.compile, num_samples=args.samples)
    print(f"report -> {Path(args.out) / 'report.md'}")
    for method, entry in metrics.items():
        print(f"{method}: outage {entry['outage']}, P(accept) "
              f"{entry['accept']}")
    return 0
