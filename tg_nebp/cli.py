r"""The :obj:`tg-nebp` command line: :obj:`evaluate`, :obj:`train`,
:obj:`reproduce`, :obj:`frontier`, :obj:`compare`, :obj:`bench`, and the
live path: :obj:`track`, :obj:`record` and :obj:`score`. Here the parser
and the handling of errors; what each command runs and prints is in
:mod:`tg_nebp.cli_commands`."""
import argparse
import contextlib
import logging
import math
import os
import re
import sys
from pathlib import Path
from typing import Callable, List, NoReturn, Optional

from tg_nebp.cli_commands import (run_compare, run_evaluate, run_fit,
                                  run_frontier, run_record, run_reproduce,
                                  run_score, run_track, run_train)
from tg_nebp.datasets.mrclam import FIT_HORIZON
from tg_nebp.datasets.uwb import UWB_FIT_HORIZON
from tg_nebp.experiments.bench import BenchFailed, add_arguments, run_bench
from tg_nebp.experiments.options import METHODS, WHOLE_SEQUENCE
from tg_nebp.experiments.reproduce import PRESET_NAMES
from tg_nebp.experiments.track import LIVE_METHODS
from tg_nebp.filters.particle.nebp import VARIANTS
from tg_nebp.filters.particle.particle_bp import MAX_BANDWIDTH
from tg_nebp.filters.particle.resampling import RESAMPLERS
from tg_nebp.io import check_writable_folder, one_line
from tg_nebp.live import ON_ERROR, WINDOW_LINES
from tg_nebp.models import MODELS
from tg_nebp.threads import threads_in_force
from tg_nebp.training import MAX_LR, PRETRAINED
from tg_nebp.utils import check_device

__all__ = ['main']


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f'must be a finite number, got '
                                         f'{text}')
    return value


def _lag(text: str):
    # a smoother's window: a positive number of steps, or the whole sequence
    if text == WHOLE_SEQUENCE:
        return text
    return _at_least(1)(text)


def _at_least(minimum, kind: Callable = int) -> Callable:
    # the argparse type of a number (kind: int, or _number) of at least
    # 'minimum'
    def parse(text: str):
        value = kind(text)
        if value < minimum:
            raise argparse.ArgumentTypeError(f'must be at least {minimum}, '
                                             f'got {text}')
        return value

    return parse


_positive, _non_negative = _at_least(1), _at_least(0)


def _samples(text: str):
    if text == 'all':
        return text
    return _positive(text)


def _within(low: float, high: float) -> Callable:
    # the argparse type of a finite number in (low, high]
    def parse(text: str) -> float:
        value = _number(text)
        if not low < value <= high:
            raise argparse.ArgumentTypeError(f'must lie in ({low:g}, '
                                             f'{high:g}], got {text}')
        return value

    return parse


_learning_rate = _within(0.0, MAX_LR)


def _bandwidth(text: str):
    if text == 'silverman':
        return text
    try:
        float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number or 'silverman', "
                                         f"got '{text}'") from None
    return _within(0.0, MAX_BANDWIDTH)(text)


def _grid_bandwidth(text: str):
    # a grid value of --regularize: also 'none', plain resampling
    return None if text == 'none' else _bandwidth(text)


def _grid_threshold(text: str):
    return None if text == 'none' else _fraction(text)


def _fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f'must lie in (0, 1], got {text}')
    return value


def _add_resampling(parser: argparse.ArgumentParser):
    parser.add_argument('--regularize', type=_bandwidth, nargs='?',
                        const='silverman', default=None, metavar='H',
                        help='regularized resampling: Gaussian jitter with '
                        'H^2 times the particle covariance (H from '
                        "Silverman's rule without a value)")
    parser.add_argument('--ess-threshold', type=_fraction, default=None,
                        metavar='T', help='resample a node only when its '
                        'effective sample size is below T * K (default: '
                        'every step, as the paper)')


def _add_samples(parser: argparse.ArgumentParser, default):
    parser.add_argument('--samples', type=_samples, default=default,
                        metavar='M', help='sender particles per receiver '
                        "particle in every BP message: 1 is the paper's "
                        "pairing, 'all' the exact message (default: "
                        f"{default if default is not None else 1})")


_REAL_SCENARIOS = ('; mrclam-N with options, e.g. mrclam-6 or '
                   'mrclam-6-range-no-odometry: a UTIAS MRCLAM sequence '
                   'read from --root (the folder holding MRCLAM_DatasetN.zip '
                   'or MRCLAM_DatasetN/; downloaded there where absent); '
                   'tiers-uwb-testN with options (ros1, raw, all-nodes: '
                   'n_8 tracked without truth, first-half, second-half), '
                   'e.g. tiers-uwb-test3-second-half: a run of the TIERS '
                   'UWB dataset\'s case 4 read from --root (the folder '
                   'holding case_4/); miluv-EXPERIMENT with options '
                   '(no-height, first-half, second-half), e.g. '
                   'miluv-cirObstacles_1_random3_0: a MILUV experiment read '
                   'from --root (the folder holding config/ and data/); or a '
                   'scenario file naming a ROS bag and its topics')


def _add_test_data(parser: argparse.ArgumentParser, realizations: int,
                   real: bool = False):
    # the realizations a tracker is evaluated on, and their batching; a
    # real sequence's (real) are its windows, all of them by default
    parser.add_argument('--realizations', type=_positive,
                        default=None if real else realizations,
                        help=f'test realizations R (default: '
                        f'{realizations}' + ('; every window of a real '
                                             'sequence)' if real else ')'))
    parser.add_argument('--seed', type=_non_negative, default=0,
                        help='seed of data and particles (default: 0)')
    parser.add_argument('--batch-size', type=_positive, default=1,
                        help='realizations tracked together (default: 1)')
    parser.add_argument('--scenario', default='paper_test',
                        help='scenario name or JSON file (default: '
                        'paper_test)' + (_REAL_SCENARIOS if real else ''))


def _device(name: str) -> str:
    try:
        return check_device(name)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _threads(text: str):
    return 'auto' if text == 'auto' else _positive(text)


def _add_common(parser: argparse.ArgumentParser, root: bool = True):
    # --device, --threads and (for the commands that read datasets)
    # --root
    parser.add_argument('--device', type=_device, default='cpu',
                        help="'cpu' (default), 'cuda' or 'cuda:N'")
    parser.add_argument('--threads', type=_threads, default=None,
                        metavar='N|auto',
                        help="torch's CPU threads: a number, or 'auto' (as "
                        'many as the cores that other processes leave free, '
                        'checked after every time step; for particle BP, '
                        'Gaussian BP, the IEKF and the bound, whose results '
                        'do not depend on the thread count) (default: '
                        "'auto' for those, torch's default for NEBP and "
                        'the Gaussian NEBP)')
    if root:
        parser.add_argument('--root', default='datasets',
                            help='dataset root (default: datasets)')


def _add_compile(parser: argparse.ArgumentParser, who: str = ''):
    # not common: compare runs its rows as they are configured
    parser.add_argument('--compile', action='store_true',
                        help=f'{who}fuse the per-edge work with '
                        'torch.compile (the first steps compile)')


def _add_measurement(parser, who: str):
    parser.add_argument(
        '--measurement', choices=sorted(MODELS['measurement']),
        default=None, help=f"{who}'s likelihood (default: the scenario's); "
        "it keeps the scenario's sigma and max_range, so 'gaussian' on NLOS "
        "data shows the cost of mismatch")


def _add_method_options(parser: argparse.ArgumentParser):
    # the options of method_tracker (MethodOptions), for evaluate and track
    add = parser.add_argument
    add('--no-control', action='store_true',
        help='ignore the known inputs (odometry) of the data: every step '
        'is the motion model\'s input-free prediction (what odometry is '
        'worth)')
    add('--lag', type=_lag, default=None, metavar='L',
        help='smooth over a window of L steps, the newest counted (gbp: '
        'fixed-lag Gaussian BP; hybrid: over it, its filtered estimates; '
        'iekf: the centralized smoother; pcrb: the '
        'smoothing bound at lag L), or over the whole sequence with '
        "'all' (iekf, pcrb); a smoother writes its filtered entry and its "
        "smoothed one (KEY-smoothed)")
    add('--incremental', action='store_true',
        help="iekf with --lag all: the incremental smoother of the whole "
        "sequence (as iSAM2: each step relinearizes only the past states "
        "that moved; its filtered entry is each step's newest states with "
        "the past relinearized, iekf-incremental)")
    add('--escape', action='store_true',
        help="iekf with --lag all: the full smoother started from the "
        "incremental smoother's last step and from fixed-lag Gaussian BP's "
        "smoothed estimates (lag 10, TrajectorySearch), the optimum of "
        "lower cost kept, connected groups of agents taken from the other "
        "where that costs less (GroupExchange), groups that range to no "
        "anchor flipped across their outside neighbours' line where that "
        "costs less (GroupFlip), every agent's trajectory then searched "
        "for a better basin by a conditional particle filter "
        "(ParticleTrajectorySearch; iekf-smoother-escape)")
    add('--marginal', action='store_true',
        help='iekf: keep only every agent\'s marginal between steps (the '
        'ideal of a distributed filter)')
    add('--inflation', type=_at_least(1, _number), default=None,
        metavar='K', help='gbp, hybrid: multiply every belief covariance by '
        'K before the next prediction (default: 1.5; 1 with '
        '--report-inflation 1 is plain Gaussian BP)')
    add('--report-inflation', type=_at_least(1, _number), default=None,
        metavar='K', help='bp, and gbp and hybrid without --lag: report '
        'every covariance inflated by K, no further than the step\'s '
        'prediction (default: gbp and hybrid 2.5, bp 1 as the paper; 1 '
        'reports the belief itself)')
    add('--adapt-noise', action='store_true',
        help='gbp and hybrid without --lag: estimate every agent\'s '
        'measurement noise scale (at least 1) from its links\' innovations '
        'and temper its messages by it: a model whose noise is too small '
        'for the data is corrected without ground truth')
    add('--tolerance', type=_at_least(0, _number), default=None,
        metavar='T', help='gbp, gnebp, hybrid: stop a step\'s iterations '
        'once no belief mean moves by more than T (default: 0.01; 0 runs '
        'every iteration)')
    add('--ends', choices=['both', 'receiver'], default=None,
        help="bp, gbp: which ends of a link its range informs: 'both' (a "
        "pair of nodes' two ranges one factor that informs both, extrinsic "
        "messages) or 'receiver' (the paper's convention) (default: "
        "receiver for bp, both for gbp)")
    add('--checkpoint', default=None,
        help='NEBP checkpoint (with --method nebp), Gaussian NEBP '
        'checkpoint (with --method gnebp, or hybrid: hybrid BP over it): '
        f"a path, or one shipped: {', '.join(PRETRAINED)}")
    add('--particles', type=_positive, default=None,
        help="particles K per agent (default: 1000 for BP, the checkpoint's "
        'K for NEBP, any K for an equivariant checkpoint; 50 for hybrid)')
    add('--iterations', type=_positive, default=None,
        help='message passing iterations per step (bp, default: 1; gbp, at '
        'most, default: 20) or Gauss-Newton iterations per step (iekf, '
        'default: 5)')
    add('--resampler', choices=sorted(RESAMPLERS), default=None,
        help='bp: how to draw the particles of the next step (default: '
        'multinomial)')
    _add_measurement(parser, 'BP\'s or the IEKF')
    _add_compile(parser, 'bp, nebp, gbp: ')
    _add_samples(parser, None)
    _add_resampling(parser)


def _evaluate_command(sub) -> None:
    # the 'evaluate' command and its options
    ev = sub.add_parser(
        'evaluate', help='run a tracker (or the bound) on the test network '
        'and write DIR/metrics.json', description='Runs a method on the test '
        'realizations and merges its entry into DIR/metrics.json: particle '
        'BP (bp), NEBP from a checkpoint (nebp), Gaussian BP (gbp), '
        'Gaussian NEBP from a checkpoint (gnebp; shipped ones by name: '
        f"{', '.join(PRETRAINED)}), hybrid BP (hybrid: Gaussian BP between "
        'the agents, particles within each, lost agents relocated), the '
        'centralized iterated EKF (iekf; iekf-marginal with --marginal) or '
        'the posterior Cramer-Rao bound of the same realizations (pcrb: its '
        'RMSE is the floor, its outage that of an efficient estimator); an '
        'option that the method does not take is an error. Sharded over N '
        'processes: '
        '"torchrun --nproc_per_node=N -m tg_nebp evaluate ..." (gloo on the '
        'CPU; NCCL with --device cuda, one GPU per process): rank r tracks '
        'realizations r, r + N, ..., rank 0 gathers the errors, prints and '
        'writes; the metrics equal one process\'s.')
    ev.add_argument('--method', choices=list(METHODS), default='bp',
                    help=f"{', '.join(METHODS)} (default: bp)")
    _add_test_data(ev, realizations=10, real=True)
    ev.add_argument('--out', default='results/evaluate',
                    help='output folder (default: results/evaluate)')
    ev.add_argument('--quiet', action='store_true', help='no progress bar')
    _add_common(ev)
    _add_method_options(ev)
    ev.set_defaults(run=run_evaluate)


def _train_command(sub) -> None:
    # the 'train' command and its options
    tr = sub.add_parser(
        'train', help='train NEBP (default: on the paper\'s training '
        'network); writes DIR/nebp.pt', description='Trains NEBP on a '
        'scenario (default: the paper\'s training network) and writes '
        'DIR/nebp.pt. Data-parallel on N processes: '
        '"torchrun --nproc_per_node=N -m tg_nebp train ..." (gloo on the '
        'CPU; NCCL with --device cuda, one GPU per process); the same result '
        'as one process up to float rounding. Rank 0 generates the data, '
        'writes the checkpoint and prints; the others are quiet.')
    tr.add_argument('--base', choices=('particle', 'gaussian'),
                    default='particle',
                    help="what the GNN corrects: 'particle' (NEBP, the "
                    "paper's) or 'gaussian' (GaussianNEBP: Gaussian BP's "
                    "messages and inflation, trained on the negative "
                    "log-likelihood plus the squared error) (default: "
                    "particle)")
    tr.add_argument('--hidden-dim', type=_positive, default=32,
                    help='embedding size of the Gaussian base (default: 32)')
    tr.add_argument('--lag', type=_positive, default=None,
                    help='the Gaussian base inside the window of fixed-lag '
                    'Gaussian BP of this many steps (FixedLagGaussianNEBP, '
                    'trained on the loss of every window step; default: '
                    'no window)')
    tr.add_argument('--particles', type=_positive, default=None,
                    help='particles K (default: 1000; the paper: 50000)')
    tr.add_argument('--variant', choices=sorted(VARIANTS), default='paper',
                    help="the NEBP layer: 'paper' (NEBPConv, sized by K) or "
                    "'equivariant' (EquivariantNEBPConv: evaluate it at any "
                    "K) (default: paper)")
    tr.add_argument('--scenario', nargs='+', default=['paper_train'],
                    help='scenario name or JSON file of the training and '
                    'validation data; several: a mix, --realizations of '
                    'each (default: paper_train)' + _REAL_SCENARIOS)
    _add_measurement(tr, 'NEBP')
    tr.add_argument('--val-scenario', nargs='+', default=None,
                    metavar='NAME|FILE', help='scenarios of the validation '
                    'data (default: those of --scenario, drawn from seed + '
                    '1); a real sequence\'s training windows need other '
                    'ones' + _REAL_SCENARIOS)
    tr.add_argument('--realizations', type=_positive, default=None,
                    help='training realizations (default: 100; every '
                    'window of a real sequence)')
    tr.add_argument('--val-realizations', type=_positive, default=None,
                    help='validation realizations (default: 10; every '
                    'window of a real sequence)')
    tr.add_argument('--epochs', type=_positive, default=10)
    tr.add_argument('--batch-size', type=_positive, default=2,
                    help='realizations per batch, over all processes; under '
                    'torchrun a multiple of N dividing --realizations '
                    '(default: 2)')
    tr.add_argument('--lr', type=_learning_rate, default=1e-4,
                    help=f'Adam learning rate, in (0, {MAX_LR:g}] '
                    f'(default: 1e-4)')
    tr.add_argument('--iterations', type=_positive, default=None,
                    help='NEBP iterations per step (default: 1; the '
                    'Gaussian base: 20, at most)')
    tr.add_argument('--seed', type=_non_negative, default=1,
                    help='seed of data (validation: seed + 1), shuffling '
                    'and particles (default: 1)')
    tr.add_argument('--out', default='results/train')
    tr.add_argument('--resume', action='store_true',
                    help='continue from DIR/nebp.pt')
    tr.add_argument('--log-dir', default=None, metavar='LOG',
                    help='write the loss of every step (LOG/steps.csv) and '
                    'epoch (LOG/epochs.csv), TensorBoard event files if '
                    'tensorboard is installed, and LOG/history.png at the '
                    'end (default: no log)')
    tr.add_argument('--quiet', action='store_true')
    _add_common(tr)
    _add_compile(tr)
    _add_samples(tr, 1)
    _add_resampling(tr)
    tr.set_defaults(run=run_train)


def _reproduce_command(sub) -> None:
    # the 'reproduce' command and its options
    rp = sub.add_parser('reproduce', help='the paper\'s experiment: data, '
                        'training, BP and NEBP evaluation, report, figures')
    rp.add_argument('--preset', choices=PRESET_NAMES, default='quick')
    rp.add_argument('--out', default=None,
                    help='output folder (default: results/reproduce, '
                    'results/beyond with --preset beyond)')
    rp.add_argument('--quiet', action='store_true')
    _add_common(rp)
    _add_compile(rp)
    _add_samples(rp, 1)
    rp.set_defaults(run=run_reproduce)


def _frontier_command(sub) -> None:
    # the 'frontier' command and its options
    fr = sub.add_parser(
        'frontier', help='BP\'s accuracy against its cost over a grid of '
        'K, M and resampling options; writes DIR/frontier.json, '
        'DIR/frontier.md and DIR/frontier.png',
        description='Runs particle BP for every combination of the options '
        'on the same test realizations (same prior particle draws) and '
        'writes P_out, P(accept H0), RMSE and seconds per realization of '
        'each to DIR/frontier.json after every point, then the table '
        'DIR/frontier.md and DIR/frontier.png with the Pareto fronts and '
        'the paper\'s rows. Run again with more options to add points: '
        'those already in the file are skipped.')
    fr.add_argument('--particles', type=_positive, nargs='+',
                    default=[500, 1000, 2000], metavar='K',
                    help='particle counts (default: 500 1000 2000)')
    fr.add_argument('--samples', type=_samples, nargs='+', default=[1, 4, 16],
                    metavar='M', help="sender particles per receiver "
                    "particle; 'all' is the exact message (default: 1 4 16)")
    fr.add_argument('--resampler', choices=sorted(RESAMPLERS), nargs='+',
                    default=['multinomial'], help='resamplers (default: '
                    'multinomial)')
    fr.add_argument('--regularize', type=_grid_bandwidth, nargs='+',
                    default=[None, 'silverman'], metavar='H',
                    help="regularized resampling bandwidths: 'none', "
                    "'silverman' or a number (default: none silverman)")
    fr.add_argument('--ess-threshold', type=_grid_threshold, nargs='+',
                    default=[None], metavar='T', help="ESS-adaptive "
                    "resampling thresholds: 'none' (every step) or a "
                    "fraction in (0, 1] (default: none)")
    _add_test_data(fr, realizations=20)
    fr.add_argument('--out', default='results/frontier',
                    help='output folder (default: results/frontier)')
    fr.add_argument('--quiet', action='store_true', help='no progress bar')
    _add_common(fr)
    _add_compile(fr)
    fr.set_defaults(run=run_frontier)


def _compare_command(sub) -> None:
    # the 'compare' command and its options
    cp = sub.add_parser(
        'compare', help='one table of every method against the bound; '
        'writes DIR/compare.json, DIR/compare.md and DIR/compare.png',
        description='Runs the posterior Cramer-Rao bound, the centralized '
        'IEKF (Gaussian, Student-t and the scenario\'s likelihood; joint '
        'and marginals-only), Gaussian BP (recommended and without '
        'inflation, with the same likelihoods), particle BP (the paper\'s '
        'configuration and the recommended one) and NEBP from every '
        '--checkpoint on the same '
        'realizations and prior particle draws of every scenario, and '
        'writes DIR/compare.json after every method, then the table '
        'DIR/compare.md and DIR/compare.png, its tables in the order of '
        'the scenarios and of the rows. Run again to resume or to add '
        'checkpoints: rows already in the file are skipped; a file made '
        'with other realizations, seed, device or scenario contents is an '
        'error, as is a damaged one. The rows run as they are configured '
        '(no --compile).')
    cp.add_argument('--scenario', nargs='+', default=['paper_test',
                                                      'paper_test_nlos'],
                    metavar='NAME|FILE', help='scenarios, of distinct '
                    'names (default: paper_test paper_test_nlos)'
                    + _REAL_SCENARIOS)
    cp.add_argument('--realizations', type=_positive, default=None,
                    help='realizations per scenario (default: 20; every '
                    'window of a real sequence)')
    cp.add_argument('--seed', type=_non_negative, default=0,
                    help='seed of data and particles (default: 0)')
    cp.add_argument('--batch-size', type=_positive, default=1,
                    help='realizations tracked together (default: 1)')
    cp.add_argument('--checkpoint', nargs='+', default=[], metavar='PATH',
                    help='NEBP checkpoints, one row each (which --methods '
                    'must select)')
    cp.add_argument('--methods', nargs='+', default=None, metavar='PREFIX',
                    help='run only the rows whose key starts with one of '
                    'these (pcrb, iekf, iekf-marginal, gbp, gbp-plain, '
                    'bp-paper, bp-recommended, nebp; default: all); a '
                    'prefix that selects no row is an error')
    cp.add_argument('--lag', type=_at_least(2), default=None, metavar='L',
                    help='add the smoothers over a window of L steps: their '
                    'filtered and smoothed rows (gbp-lagL, iekf-lagL, and '
                    'the full smoother iekf-smoother), each beside its '
                    'bound (pcrb, pcrb-lagL, pcrb-smoother)')
    cp.add_argument('--out', default='results/compare',
                    help='output folder (default: results/compare)')
    cp.add_argument('--quiet', action='store_true', help='no progress bar')
    _add_common(cp)
    cp.set_defaults(run=run_compare)


def _track_command(sub) -> None:
    # the 'track' command and its options
    tk = sub.add_parser(
        'track', help='track live: JSON lines of measurements in, one line '
        'of estimates per step out', description='Runs a tracker live, one '
        'time step per input line (JSON: "dt" or "time", "join": [{"id", '
        '"mean", "cov"} or {"id", "anchor"}], "leave": [ids], "links": '
        '[[from, to, range], ...]), and writes each step\'s line of '
        'estimates ({"t", "time", "estimates": [{"id", "mean", "cov"}]}) '
        'as soon as it is processed. The models are the scenario\'s. A bad '
        'link is reported (line and position) and left out, the step going '
        'on with the others; a bad line is reported with its line number '
        'and skipped, or ends the run (--on-error); the session is never '
        'half-updated by it. Ctrl-C ends it with one line saying where.')
    tk.add_argument('--method', choices=list(LIVE_METHODS), default='gbp',
                    help=f"{', '.join(LIVE_METHODS)} (default: gbp)")
    tk.add_argument('--input', default='-', metavar='FILE|-',
                    help='measurement lines (default: -, standard input)')
    tk.add_argument('--output', default='-', metavar='FILE|-',
                    help='estimate lines (default: -, standard output)')
    tk.add_argument('--on-error', choices=list(ON_ERROR), default='stop',
                    help='a bad line: report it and go on (skip), or end '
                    'the run with exit status 2 (stop) (default: stop)')
    tk.add_argument('--save-state', default=None, metavar='FILE',
                    help='save the session after every line (atomically)')
    tk.add_argument('--resume', default=None, metavar='FILE',
                    help='continue a saved session: the lines it had read '
                    'are skipped (feed the same input: another one is '
                    'refused, naming where it differs), an --output file '
                    'keeps the lines of the saved steps')
    tk.add_argument('--scenario', default='paper_test',
                    help='scenario name or JSON file whose motion and '
                    'measurement models the tracker uses (default: '
                    'paper_test; mrclam-N: the models fitted on a UTIAS '
                    'MRCLAM sequence)')
    tk.add_argument('--seed', type=_non_negative, default=0,
                    help='seed of the session\'s draws (default: 0)')
    tk.add_argument('--window', choices=list(WINDOW_LINES), default=None,
                    help='gbp and hybrid with --lag L > 1 (or a window '
                    'checkpoint): what a line holds of the window: every '
                    'earlier step revised (all), the step that leaves the '
                    'full window at the next step (final: a line that does '
                    'not grow with the lag) or none (default: all); refused '
                    'by a tracker whose lines carry no window')
    _add_method_options(tk)
    _add_common(tk, root=False)
    tk.set_defaults(run=run_track)


def _record_command(sub) -> None:
    # the 'record' command and its options
    rc = sub.add_parser(
        'record', help='write a test realization as measurement lines for '
        'track, its truth apart', description='Writes realization INDEX '
        'of the test data (the ones evaluate tracks with the same --seed) '
        'as the measurement lines of tg-nebp track (measurements only) and '
        'its true states to another file, for a replay through the live '
        'path and tg-nebp score.')
    rc.add_argument('--scenario', default='paper_test',
                    help='scenario name or JSON file (default: paper_test)'
                    + _REAL_SCENARIOS)
    rc.add_argument('--seed', type=_non_negative, default=0,
                    help='seed of the test data (default: 0)')
    rc.add_argument('--realization', type=_non_negative, default=0,
                    metavar='INDEX', help='which realization (default: 0)')
    rc.add_argument('--measurements', required=True, metavar='FILE',
                    help='where the measurement lines go')
    rc.add_argument('--truth', required=True, metavar='FILE',
                    help='where the true states go')
    rc.add_argument('--root', default='datasets',
                    help='dataset root (default: datasets)')
    rc.set_defaults(run=run_record, threads=None, device='cpu')


def _fit_command(sub) -> None:
    # the 'fit' command and its options
    ft = sub.add_parser(
        'fit', help='fit the noise models of a real recording (a UTIAS '
        'MRCLAM sequence, a UWB recording) and write them as a scenario',
        description='MRCLAM (--sequence N): fits the range and bearing '
        'noise (robust scales, the Student-t tail, the range bias against '
        'the distance) and the odometry noise on the ground truth of a '
        'sequence\'s test protocol (600 s from the first time all five '
        'robots have ground truth and odometry, steps of 0.5 s); every '
        'mrclam-N name uses the ones fitted on sequence 6. A UWB recording '
        '(--scenario tiers-uwb-testN with options, or a scenario file naming '
        'a bag): fits each pair\'s range bias, the range noise (a robust '
        'Student-t, its long-run spread) and the constant-velocity motion '
        'noise on the truth of the scenario\'s part (for example '
        'tiers-uwb-test3-first-half, or the static run tiers-uwb-test1); '
        'every tiers-uwb name uses the ones fitted on the first half of '
        'test3. Writes the scenario file that evaluate, compare, train, '
        'track and record read (--scenario FILE).')
    ft.add_argument('--sequence', type=int, choices=range(1, 10), default=6,
                    metavar='N', help='the MRCLAM sequence, 1 to 9 '
                    '(default: 6)')
    ft.add_argument('--scenario', default=None, metavar='NAME|FILE',
                    help='a UWB recording\'s scenario instead of an MRCLAM '
                    'sequence: tiers-uwb-testN with options, or a scenario '
                    'file with a "recording"')
    ft.add_argument('--root', default='datasets',
                    help='the folder holding MRCLAM_DatasetN.zip or '
                    'MRCLAM_DatasetN/ (downloaded there where absent), or '
                    'the UWB dataset\'s folder (for TIERS the one holding '
                    'case_4/) (default: datasets)')
    ft.add_argument('--horizon', type=_positive, default=None,
                    metavar='H', help='steps over which the long-run noise '
                    'variances are fitted (1: the one-step variances; '
                    f'default: {FIT_HORIZON}, 20 s, for MRCLAM; '
                    f'{UWB_FIT_HORIZON}, 5 s, for a UWB recording)')
    ft.add_argument('--output', required=True, metavar='FILE.json',
                    help='the scenario file written')
    ft.set_defaults(run=run_fit, threads=None, device='cpu')


def _score_command(sub) -> None:
    # the 'score' command and its options
    sc = sub.add_parser(
        'score', help='the accuracy of track\'s estimates against record\'s '
        'truth', description='Prints the RMSE, outage and P(accept) of '
        'estimate lines against true states, computed as evaluate computes '
        'them.')
    sc.add_argument('--estimates', required=True, metavar='FILE')
    sc.add_argument('--truth', required=True, metavar='FILE')
    sc.set_defaults(run=run_score, threads=None, device='cpu')


def _bench_command(sub) -> None:
    # the 'bench' command and its options
    bench = sub.add_parser('bench', help='benchmark ParticleBPConv and the '
                           'tracker on the test network')
    add_arguments(bench)
    _add_common(bench)
    _add_compile(bench)
    bench.set_defaults(run=run_bench)


#: Every command, in the order of the help, each adding its own parser
#: and options (a new command is one more function here).
_COMMANDS = (_evaluate_command, _train_command, _reproduce_command,
             _frontier_command, _compare_command, _track_command,
             _record_command, _fit_command, _score_command, _bench_command)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog='tg-nebp',
        description='Particle BP and Neural Enhanced BP for cooperative '
        'localization.')
    sub = parser.add_subparsers(dest='command', required=True)
    for add in _COMMANDS:
        add(sub)
    return parser


class _Parser(argparse.ArgumentParser):
    r"""argparse with the CLI's one-line errors (no usage block)."""
    def error(self, message: str) -> NoReturn:
        _print_error(f'{message} (see {self.prog} --help)')
        sys.exit(2)


def _print_error(message) -> int:
    # one write of the whole line: the ranks of a torchrun share a stream,
    # and print's separate write of the newline lets their lines interleave
    sys.stderr.write(f'error: {one_line(message)}\n')
    sys.stderr.flush()
    return 2


def _check_paths(args):
    # before any work: a run must not fail at its end, after minutes of
    # work, because its output cannot be written
    root = getattr(args, 'root', None)
    if root is not None and Path(root).exists() and not Path(root).is_dir():
        raise ValueError(f"--root '{root}' is a file, not a folder")
    if getattr(args, 'out', None) is not None:
        check_writable_folder(args.out, '--out')
    if getattr(args, 'log_dir', None) is not None:
        check_writable_folder(args.log_dir, '--log-dir')


#: The methods of :obj:`tg-nebp evaluate` whose results are bit-identical
#: for any thread count (tested at 1 and 2): the learned ones round by it.
THREAD_INVARIANT = ('bp', 'gbp', 'iekf', 'pcrb')


def _thread_invariant(args) -> bool:
    # bench measures speed only and passes the setting on to its
    # measurement processes
    return (args.command in ('frontier', 'bench') or
            (args.command == 'evaluate' and
             args.method in THREAD_INVARIANT))


@contextlib.contextmanager
def _threads_in_force(args):
    r"""--threads for the run: a count, or (:obj:`auto`, the default of BP
    runs) a governor that the progress bars of :func:`progress_bars` update."""
    threads = args.threads
    if threads is None:
        threads = 'auto' if _thread_invariant(args) else None
    elif threads == 'auto' and not _thread_invariant(args):
        raise ValueError("--threads auto is for BP runs (evaluate --method "
                         "bp, gbp, iekf or pcrb, frontier, bench): the "
                         "learned methods' results depend on the thread "
                         "count; give a number")
    if args.command == 'bench':  # its measurement processes set it
        args.threads, args.governor = threads, None
        yield
        return
    with threads_in_force(threads, args.device) as governor:
        args.governor = governor
        yield


def main(argv: Optional[List[str]] = None) -> int:
    r"""The :obj:`tg-nebp` entry point. A user error (bad flag, missing or
    malformed file, unwritable output) prints one line starting with
    :obj:`error:` and exits with status 2, without a traceback."""
    args = build_parser().parse_args(argv)
    with _library_reports() as reports:
        status = _main(args)
    # a failed run prints its one error line alone; under torchrun rank 0
    # speaks for all (each rank read the same data)
    if status == 0 and int(os.environ.get('RANK', '0')) == 0:
        for line in dict.fromkeys(reports):
            sys.stderr.write(line + '\n')
        sys.stderr.flush()
    return status


class _Collected(logging.Handler):
    # the records' messages, in order
    def __init__(self):
        super().__init__(logging.INFO)
        self.lines = []

    def emit(self, record):
        self.lines.append(record.getMessage())


@contextlib.contextmanager
def _library_reports():
    # what the library reports while a command runs (the reading of a real
    # sequence: what it kept and dropped), printed on standard error once
    # the command has succeeded
    handler, logger = _Collected(), logging.getLogger('tg_nebp')
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield handler.lines
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def _out_of_memory(error: RuntimeError) -> bool:
    # CUDA's OutOfMemoryError, or the CPU allocator's failure
    return type(error).__name__ == 'OutOfMemoryError' or \
        "can't allocate memory" in str(error)


def _main(args) -> int:
    if args.command == 'reproduce' and args.out is None:
        args.out = ('results/beyond' if args.preset == 'beyond' else
                    'results/reproduce')
    try:
        _check_paths(args)
        with _threads_in_force(args):
            return args.run(args)
    except ValueError as e:  # bad input: a clear message, no traceback
        return _print_error(e)
    except KeyboardInterrupt as e:  # Ctrl-C: where it stopped, one line
        sys.stderr.write(f"interrupted: {one_line(str(e) or 'by the user')}"
                         f"\n")
        sys.stderr.flush()
        return 130
    except BenchFailed as e:  # measurements that failed, each in the table
        _print_error(e)
        return 1
    except RuntimeError as e:
        # an allocation the machine cannot make (particles, realizations or
        # a network too large for its memory) is a choice of the user's:
        # one line that says what to make smaller; any other RuntimeError
        # is a bug and keeps its traceback
        if not _out_of_memory(e):
            raise
        bytes_ = re.search(r'allocate (\d+) bytes', str(e))
        size = (f' ({int(bytes_.group(1)) / 2**30:.3g} GiB in one tensor)'
                if bytes_ else '')
        return _print_error(
            f"out of memory{size}: fewer --particles, a smaller "
            f"--batch-size or a smaller network")
    except OSError as e:  # a file or folder that cannot be read or written
        where = f" '{e.filename}'" if e.filename else ''
        return _print_error(f'{e.strerror or e}{where}')


if __name__ == '__main__':
    sys.exit(main())
