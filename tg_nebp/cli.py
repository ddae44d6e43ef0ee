r"""The :obj:`tg-nebp` command line: :obj:`evaluate` and :obj:`bench`."""
import argparse
import sys
import time
from pathlib import Path
from typing import List, Optional

import torch
from tqdm import tqdm

from tg_nebp.datasets import CooperativeLocalizationDataset
from tg_nebp.evaluation import summarize, track_dataset
from tg_nebp.filters import ParticleBP
from tg_nebp.io import read_json, write_json

__all__ = ['main']


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f'must be at least 1, got {value}')
    return value


def _non_negative(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f'must be at least 0, got {value}')
    return value


def _device(name: str) -> str:
    if name not in ('cpu', 'cuda') and not name.startswith('cuda:'):
        raise argparse.ArgumentTypeError(f"must be 'cpu' or 'cuda', got "
                                         f"'{name}'")
    if name.startswith('cuda') and not torch.cuda.is_available():
        raise argparse.ArgumentTypeError('CUDA is not available here')
    return name


def _add_common(parser: argparse.ArgumentParser):
    parser.add_argument('--device', type=_device, default='cpu',
                        help="'cpu' (default) or 'cuda'")
    parser.add_argument('--root', default='datasets',
                        help='dataset root (default: datasets)')


def _evaluate(args) -> int:
    dataset = CooperativeLocalizationDataset(
        args.root, scenario=args.scenario,
        num_realizations=args.realizations, seed=args.seed, log=False)
    tracker = ParticleBP(args.particles, args.iterations,
                         motion=dataset.scenario.motion(),
                         measurement=dataset.scenario.measurement(),
                         resampler=args.resampler).to(args.device)
    total = len(dataset) * dataset.scenario.num_steps
    start = time.perf_counter()
    with tqdm(total=total, desc=f'{args.method} K={args.particles}',
              unit='step', disable=args.quiet) as bar:
        result = track_dataset(tracker, dataset, args.batch_size,
                               args.device, args.seed, progress=bar.update)
    seconds = time.perf_counter() - start
    entry = summarize(result['errors'], result['nees'])
    entry.update(particles=args.particles, realizations=len(dataset),
                 seconds=round(seconds, 3), device=args.device,
                 seed=args.seed, iterations=args.iterations,
                 scenario=dataset.scenario.name)
    path = Path(args.out) / 'metrics.json'
    # keep the other methods' entries: BP and NEBP share one file
    everything = read_json(path) if path.exists() else {}
    everything[args.method] = entry
    write_json(path, everything)
    print(f"{args.method}: RMSE {entry['rmse']:.3f} m, outage "
          f"{entry['outage']}, P(accept) {entry['accept']}, "
          f"{seconds:.1f} s -> {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='tg-nebp',
        description='Particle BP and Neural Enhanced BP for cooperative '
        'localization.')
    sub = parser.add_subparsers(dest='command', required=True)

    ev = sub.add_parser('evaluate', help='run a tracker on the test network '
                        'and write DIR/metrics.json')
    ev.add_argument('--method', choices=['bp'], default='bp')
    ev.add_argument('--particles', type=_positive, default=1000,
                    help='particles K per agent (default: 1000)')
    ev.add_argument('--realizations', type=_positive, default=10,
                    help='test realizations R (default: 10)')
    ev.add_argument('--seed', type=_non_negative, default=0,
                    help='seed of data and particles (default: 0)')
    ev.add_argument('--iterations', type=_positive, default=1,
                    help='message passing iterations per step (default: 1)')
    ev.add_argument('--batch-size', type=_positive, default=1,
                    help='realizations tracked together (default: 1)')
    ev.add_argument('--resampler', choices=['multinomial', 'systematic'],
                    default='multinomial')
    ev.add_argument('--scenario', default='paper_test',
                    help='scenario name or JSON file (default: paper_test)')
    ev.add_argument('--out', default='results/evaluate',
                    help='output folder (default: results/evaluate)')
    ev.add_argument('--quiet', action='store_true', help='no progress bar')
    _add_common(ev)
    ev.set_defaults(run=_evaluate)

    from tg_nebp.bench import add_arguments, run_bench
    bench = sub.add_parser('bench', help='benchmark ParticleBPConv and the '
                           'tracker on the test network')
    add_arguments(bench)
    _add_common(bench)
    bench.set_defaults(run=run_bench)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except ValueError as e:  # bad input: a clear message, no traceback
        print(f'tg-nebp: error: {e}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
