r"""The bound's outage with today's :func:`tg_nebp.metrics.gaussian_outage`
and with that of an earlier revision, on the same posterior CRB
covariances of the same realizations: the before/after table of issue 27
(a direction quadrature, wrong for elongated covariances, replaced by a
recursion over the eigenvalues). Every scenario is a name or a JSON file.

    python benchmarks/bound_outage_before_after.py --rev 9af1e56 \
        --scenario paper_test:20 paper_test_nlos:20 box3d_test:4
"""
import argparse
import importlib.util
import subprocess
import tempfile
from pathlib import Path

import torch

from tg_nebp import metrics
from tg_nebp.bounds import PosteriorCRB
from tg_nebp.datasets import load_datasets

THRESHOLDS = [0.5, 1.0, 2.0]


def metrics_at(rev: str):
    # the metrics module of revision 'rev' of this repository, imported
    # from a temporary file (it imports only numpy, scipy and torch)
    root = Path(__file__).resolve().parents[1]
    text = subprocess.run(['git', 'show', f'{rev}:tg_nebp/metrics.py'],
                          cwd=root, capture_output=True, text=True,
                          check=True).stdout
    folder = tempfile.mkdtemp()
    path = Path(folder) / 'metrics_before.py'
    path.write_text(text)
    spec = importlib.util.spec_from_file_location('metrics_before', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def compare(before, name: str, realizations: int, root: str, seed: int):
    dataset, = load_datasets(root, (name, realizations, seed))
    scenario = dataset.scenario
    bound = PosteriorCRB(scenario.motion_model, scenario.measurement_model)
    dim = scenario.position_dim
    new, old, condition = [], [], []
    for r in range(len(dataset)):
        data = dataset[r]
        cov = bound(data)[~data.anchor][..., :dim, :dim].reshape(-1, dim,
                                                                 dim)
        eig = torch.linalg.eigvalsh(cov)
        condition.append(eig[:, -1] / eig[:, 0])
        new.append(metrics.gaussian_outage(cov, THRESHOLDS))
        try:
            old.append(before.gaussian_outage(cov, THRESHOLDS))
        except ValueError:  # the old function refused singular ones
            old.append(torch.full_like(new[-1], float('nan')))
    new, old, condition = (torch.cat(new), torch.cat(old),
                           torch.cat(condition))
    rounded = [[round(float(p), 5) for p in x.mean(0)] for x in (old, new)]
    print(f'{scenario.name}: {realizations} realizations (seed {seed}), '
          f'{new.size(0)} agent-steps, condition number max '
          f'{float(condition.max()):.3g}; P_out at {THRESHOLDS} m before '
          f'{rounded[0]}, after {rounded[1]}; largest change of one '
          f'agent-step {float((new - old).abs().max()):.3g}')


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--rev', default='9af1e56',
                        help='the earlier revision (default: 9af1e56)')
    parser.add_argument('--scenario', nargs='+', metavar='NAME:R',
                        default=['paper_test:20', 'paper_test_nlos:20'],
                        help='scenarios and their realization counts')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--root', default='datasets')
    args = parser.parse_args()
    before = metrics_at(args.rev)
    for spec in args.scenario:
        name, _, count = spec.rpartition(':')
        compare(before, name, int(count), args.root, args.seed)


if __name__ == '__main__':
    main()
