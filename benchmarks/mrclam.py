r"""Every Gaussian method and particle BP on a UTIAS MRCLAM sequence under
the test protocol (tg_nebp.datasets.mrclam_realization), in three
information settings (range only; range and odometry; range, bearing and
odometry), with the noise models fitted on sequence 6
(tg_nebp.datasets.fit_models). Prints one row per method and setting:
RMSE, median, P_out at 0.5 and 1 m, the largest error, P(accept 0.95),
the heading's RMSE and the seconds per step.

    python benchmarks/mrclam.py --sequence PATH_TO_MRCLAM_DatasetN.zip
"""
import argparse
import time

import torch

from tg_nebp.datasets import fit_models, mrclam_realization, read_mrclam
from tg_nebp.filters import CentralizedIEKF, GaussianBP, ParticleBP
from tg_nebp.metrics import angle_errors, consistency_curve, nees
from tg_nebp.models import model_like

SEQUENCE_6 = '../shared/data/mrclam/MRCLAM_Dataset6.zip'


def settings(sequence, fitted):
    motion, measurement = fitted
    both, _ = mrclam_realization(sequence)
    ranges, _ = mrclam_realization(sequence, features=('range', ))
    blind, _ = mrclam_realization(sequence, features=('range', ),
                                  odometry=False)
    range_only = model_like('student-t', 'measurement', measurement)
    return {'range only': (blind, motion, range_only),
            'range, odometry': (ranges, motion, range_only),
            'range, bearing, odometry': (both, motion, measurement)}


def methods(motion, measurement):
    return {
        'IEKF': CentralizedIEKF(motion=motion, measurement=measurement),
        'Gaussian BP (inflation 1.1)': GaussianBP.recommended(
            inflation=1.1, motion=motion, measurement=measurement),
        'Gaussian BP (no inflation)': GaussianBP.recommended(
            inflation=1.0, motion=motion, measurement=measurement),
        'particle BP (K = 500, M = 32)': ParticleBP.recommended(
            motion=motion, measurement=measurement),
    }


def row(data, out, seconds):
    agents = ~data.anchor
    truth = data.states[agents].double()
    mean, cov = out.mean[agents].double(), out.cov[agents].double()
    error = (mean[..., :2] - truth[..., :2]).norm(dim=-1).flatten()
    accept = consistency_curve(nees(mean[..., :2], cov[..., :2, :2],
                                    truth[..., :2]).flatten(), [0.95])
    heading = angle_errors(mean[..., 2], truth[..., 2])
    return (f"RMSE {float(error.square().mean().sqrt()):.3f} m, median "
            f"{float(error.median()):.3f} m, P_out(0.5, 1 m) "
            f"{float((error > 0.5).double().mean()):.4f}, "
            f"{float((error > 1.0).double().mean()):.4f}, max "
            f"{float(error.max()):.2f} m, P(accept 0.95) "
            f"{float(accept[0]):.3f}, heading "
            f"{float(heading.square().mean().sqrt()):.3f} rad, "
            f"{1000 * seconds / int(data.num_steps):.1f} ms per step")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--sequence', default=SEQUENCE_6)
    parser.add_argument('--fit', default=SEQUENCE_6,
                        help='the sequence the noise is fitted on')
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args()
    fitted_on, _ = mrclam_realization(read_mrclam(args.fit))
    motion, measurement, report = fit_models(fitted_on)
    print(f'fitted: {motion}\n        {measurement}\n        {report}')
    sequence = read_mrclam(args.sequence)
    for setting, (data, motion, likelihood) in settings(
            sequence, (motion, measurement)).items():
        for name, tracker in methods(motion, likelihood).items():
            start = time.perf_counter()
            try:
                with torch.no_grad():
                    out = tracker(data, torch.Generator().manual_seed(
                        args.seed))
            except ValueError as e:
                print(f'{setting} | {name}: failed: {e}', flush=True)
                continue
            print(f'{setting} | {name}: '
                  f'{row(data, out, time.perf_counter() - start)}',
                  flush=True)


if __name__ == '__main__':
    main()
