r"""Running a tracker over a dataset and summarizing its accuracy and
consistency, shared by the CLI, the notebooks and the benchmarks."""
import time
from pathlib import Path
from typing import Callable, Dict, Iterable, Optional, Sequence

import torch
from torch_geometric.loader import DataLoader

from tg_nebp import metrics
from tg_nebp.filters import ParticleBP
from tg_nebp.io import read_json, write_json
from tg_nebp.utils import derive_seed

__all__ = ['track_dataset', 'summarize', 'evaluate_method',
           'OUTAGE_THRESHOLDS', 'CONFIDENCE']

#: The error thresholds in metres of the reported outage
#: probabilities.
OUTAGE_THRESHOLDS = (0.5, 1.0, 2.0)
#: The confidence levels of the reported P(accept H0).
CONFIDENCE = (0.50, 0.95, 0.99)


def track_dataset(tracker: ParticleBP, dataset: Iterable,
                  batch_size: int = 1, device: str = 'cpu', seed: int = 0,
                  progress: Optional[Callable] = None) -> Dict[str, torch.Tensor]:
    r"""Tracks every realization of :obj:`dataset` and returns the agents'
    position errors and NEES values, flattened over agents, time steps and
    realizations (:obj:`"errors"`, :obj:`"nees"`), the index of the
    realization each value belongs to (:obj:`"realization"`), plus the
    estimates of the first realization (:obj:`"first_mean"`,
    :obj:`"first_states"`, :obj:`"first_anchor"`) for plots.

    Realization :math:`r` draws its particles from its own generator,
    seeded with :obj:`derive_seed(seed, r)`, so two trackers run with the
    same :obj:`seed` see the same prior particle draws, and the result does
    not depend on :obj:`batch_size`.

    Args:
        tracker (ParticleBP): The tracker (BP or NEBP).
        dataset (iterable): Realizations with true :obj:`states`.
        batch_size (int, optional): Realizations tracked together as one
            disjoint graph. (default: :obj:`1`)
        device (str, optional): Device. (default: :obj:`"cpu"`)
        seed (int, optional): Seed of the particle draws. (default: :obj:`0`)
        progress (callable, optional): Called after each time step with
            the number of realization-steps it did (the batch's
            realizations), so a bar of :obj:`len(dataset) * T` ends full
            for any :obj:`batch_size`. (default: :obj:`None`)
    """
    errors, nees, owner, first = [], [], [], {}
    with torch.no_grad():
        for b, batch in enumerate(DataLoader(dataset, batch_size=batch_size)):
            batch = batch.to(device)
            offset = b * batch_size  # the batch's first realization
            generator = [
                torch.Generator(device).manual_seed(derive_seed(seed, r))
                for r in range(offset, offset + batch.num_graphs)]
            agents = ~batch.anchor
            realization = (batch.batch + offset)[agents]
            means = []
            for step in tracker.steps(batch, generator):
                truth = batch.states[:, step.t, :2]
                est = step.mean[:, :2]
                errors.append(metrics.position_errors(est, truth)[agents])
                nees.append(
                    metrics.nees(est, step.cov[:, :2, :2], truth)[agents])
                owner.append(realization)
                if b == 0:
                    means.append(step.mean)
                if progress is not None:  # realization-steps
                    progress(batch.num_graphs)
            if b == 0:
                ptr = batch.ptr
                first = {
                    'first_mean': torch.stack(means, 1)[:ptr[1]].cpu(),
                    'first_states': batch.states[:ptr[1]].cpu(),
                    'first_anchor': batch.anchor[:ptr[1]].cpu(),
                }
    return dict(errors=torch.cat(errors).cpu(), nees=torch.cat(nees).cpu(),
                realization=torch.cat(owner).cpu(), **first)


def summarize(errors: torch.Tensor, nees: torch.Tensor,
              thresholds: Sequence[float] = OUTAGE_THRESHOLDS,
              confidence: Sequence[float] = CONFIDENCE) -> dict:
    r"""The :obj:`metrics.json` entry of a method: RMSE, outage
    probabilities keyed by threshold (:obj:`"0.5"`, ...) and
    :math:`\mathbb{P}(\text{accept } H_0)` keyed by confidence level
    (:obj:`"0.95"`, ...)."""
    outage = metrics.outage_from_errors(errors, thresholds)
    accept = metrics.consistency_curve(nees, confidence)
    return {
        'rmse': metrics.rmse_from_errors(errors),
        'outage': {f'{t:.1f}': float(p) for t, p in zip(thresholds, outage)},
        'accept': {f'{c:.2f}': float(p) for c, p in zip(confidence, accept)},
    }


def evaluate_method(method: str, tracker: ParticleBP, dataset,
                    batch_size: int, device: str, seed: int, out: Path,
                    progress: Optional[Callable] = None) -> dict:
    r"""Tracks :obj:`dataset`, merges the :obj:`method`'s entry into
    :obj:`out/metrics.json` and returns the raw errors and NEES."""
    start = time.perf_counter()
    result = track_dataset(tracker, dataset, batch_size, device, seed,
                           progress=progress)
    entry = summarize(result['errors'], result['nees'])
    entry.update(particles=tracker.num_particles, realizations=len(dataset),
                 seconds=round(time.perf_counter() - start, 3),
                 device=device, seed=seed,
                 iterations=tracker.num_iterations,
                 measurement=tracker.measurement.config(),
                 samples=tracker.num_samples,
                 regularize=tracker.regularize,
                 ess_threshold=tracker.ess_threshold,
                 scenario=getattr(getattr(dataset, 'scenario', None), 'name',
                                  None))
    path = out / 'metrics.json'
    everything = read_json(path) if path.exists() else {}
    everything[method] = entry  # BP and NEBP share one file
    write_json(path, everything)
    result['entry'] = entry
    return result
